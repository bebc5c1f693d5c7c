"""Thin adapter: rule template_preview -> stex.stages.template.preview_template."""
from stex.logs import setup_logging
from stex.stages.template import preview_template

setup_logging(snakemake.log[0])
preview_template(snakemake.input[0], snakemake.output[0])
