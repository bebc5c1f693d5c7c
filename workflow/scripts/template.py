"""Thin adapter: rule template -> stex.stages.template.write_template."""
from stex.logs import setup_logging
from stex.stages.template import write_template

setup_logging(snakemake.log[0])
first = list(snakemake.input.first) or [None, None]  # template.from_depth: frames and masks of block 0
write_template(snakemake.input.scene, snakemake.params.template, snakemake.output[0], *first)
