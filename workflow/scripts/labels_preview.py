"""Thin adapter: rule labels_preview -> stex.stages.labeling.preview_labels."""
from stex.stages.labeling import preview_labels
from stex.logs import setup_logging

setup_logging(snakemake.log[0])
preview_labels(list(snakemake.input.volume), list(snakemake.input.corrected),
               snakemake.input.observations, snakemake.input.template, snakemake.output[0],
               theta_omega=snakemake.params.theta_omega)
