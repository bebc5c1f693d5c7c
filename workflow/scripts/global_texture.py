"""Thin adapter: rule global_texture -> stex.stages.global_texture.write_global_texture."""
from stex.stages.global_texture import write_global_texture
from stex.logs import setup_logging

setup_logging(snakemake.log[0])
i = snakemake.input
write_global_texture(i.scene, list(i.frames), i.template, i.projection, i.coords,
                     snakemake.output[0],
                     dict(snakemake.params.global_texture, source_stride=snakemake.params.source_stride))
