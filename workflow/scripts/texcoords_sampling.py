"""Thin adapter: rule texcoords_sampling -> stex.stages.texcoords.write_sampling_table."""
from stex.logs import setup_logging
from stex.stages.texcoords import write_sampling_table

setup_logging(snakemake.log[0])
i = snakemake.input
write_sampling_table(i.scene, i.template, i.projection, list(i.frames), list(i.masks),
                     snakemake.params.texcoords, snakemake.params.steps, snakemake.output[0])
