"""Thin adapter: rule projection -> stex.stages.projection.write_projection."""
from stex.logs import setup_logging
from stex.stages.projection import write_projection

setup_logging(snakemake.log[0])
write_projection(snakemake.input.tracking, snakemake.input.template, snakemake.input.scene,
                 list(snakemake.input.masks), snakemake.params.projection, snakemake.output[0])
