"""Thin adapter: rule tracking_preview -> stex.stages.tracking.plot_tracking_fit."""
from stex.logs import setup_logging
from stex.stages.tracking import plot_tracking_fit

setup_logging(snakemake.log[0])
plot_tracking_fit(snakemake.input[0], snakemake.output[0])
