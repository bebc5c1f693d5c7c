"""Thin adapter: rule texcoords_sampling -> stex.stages.texcoords.write_sampling_table."""
from stex.logs import setup_logging
from stex.stages.texcoords import write_sampling_table

setup_logging(snakemake.log[0])
if not snakemake.params.steps:  # asked for by name (a target) with the table switched off
    raise ValueError("config error at sampling_table/steps: [] (no sampling table, the default); add "
                     "--configfile config/recipes/paper_tables.yaml (steps [1, 2, 3, 4, 5]) for the paper's table")
i = snakemake.input
write_sampling_table(i.scene, i.template, i.projection, list(i.frames), list(i.masks),
                     snakemake.params.texcoords, snakemake.params.steps, snakemake.output[0])
