"""Thin adapter: rule preview_video -> stex.export.preview_results."""
from stex.export import preview_results
from stex.logs import setup_logging

setup_logging(snakemake.log[0])
preview_results(snakemake.params.results, snakemake.output[0], source="corrected")
