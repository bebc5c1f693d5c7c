"""Thin adapter: rule projection_preview -> stex.stages.projection.preview_projection."""
from stex.logs import setup_logging
from stex.stages.projection import preview_projection

setup_logging(snakemake.log[0])
preview_projection(list(snakemake.input.frames), snakemake.input.projection, snakemake.output[0])
