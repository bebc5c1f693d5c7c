"""Thin adapter: rule labeling -> stex.stages.labeling.write_labels."""
from stex.stages.labeling import write_labels
from stex.logs import setup_logging

setup_logging(snakemake.log[0])
write_labels(snakemake.input.observations, list(snakemake.input.data_term), snakemake.input.template,
             snakemake.params.labeling, snakemake.output[0], threads=snakemake.threads,
             projection_path=snakemake.input.projection)
