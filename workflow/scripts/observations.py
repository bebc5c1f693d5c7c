"""Thin adapter: rule observations -> stex.stages.observations.write_observations."""
from stex.logs import setup_logging
from stex.stages.observations import write_observations

setup_logging(snakemake.log[0])
write_observations(snakemake.input.template, snakemake.input.tracking, snakemake.input.projection, snakemake.input.coords,
                   list(snakemake.input.frames), snakemake.params.observations, snakemake.output[0])
