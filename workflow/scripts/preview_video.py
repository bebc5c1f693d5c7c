"""Thin adapter: rule preview_video -> stex.stages.export.preview_results."""
from stex.logs import setup_logging
from stex.stages.export import preview_results

setup_logging(snakemake.log[0])
preview_results(snakemake.params.results, snakemake.output[0], source="corrected")
