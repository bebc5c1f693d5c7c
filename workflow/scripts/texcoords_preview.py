"""Thin adapter: rule texcoords_preview -> stex.stages.texcoords.preview_texcoords."""
from stex.logs import setup_logging
from stex.stages.texcoords import preview_texcoords

setup_logging(snakemake.log[0])
preview_texcoords(list(snakemake.input.frames), snakemake.input.projection,
                  snakemake.input.texcoords, snakemake.output[0])
