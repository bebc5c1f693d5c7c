"""Thin adapter: rule texcoords -> stex.stages.texcoords.write_texcoords."""
from stex.logs import setup_logging
from stex.stages.texcoords import write_texcoords

setup_logging(snakemake.log[0])
write_texcoords(snakemake.input.scene, snakemake.input.template, snakemake.input.projection,
                list(snakemake.input.frames), list(snakemake.input.masks),
                snakemake.params.texcoords, snakemake.output[0])
