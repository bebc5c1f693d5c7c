"""Thin adapter: rule template -> stex.template.write_template."""
from stex.logs import setup_logging
from stex.template import write_template

setup_logging(snakemake.log[0])
write_template(snakemake.input.scene, snakemake.params.template, snakemake.output[0])
