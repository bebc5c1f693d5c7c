"""Thin adapter: rule tracking -> stex.stages.tracking.write_tracking."""
from stex.logs import setup_logging
from stex.stages.tracking import write_tracking

setup_logging(snakemake.log[0])
write_tracking(snakemake.input.scene, snakemake.input.template, list(snakemake.input.frames),
               list(snakemake.input.masks), snakemake.params.tracking, snakemake.output[0])
