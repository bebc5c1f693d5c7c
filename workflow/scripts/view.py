"""Thin adapter: rule view -> stex.viewer.write_view."""
from stex.logs import setup_logging
from stex.viewer import write_view

setup_logging(snakemake.log[0])
write_view(snakemake.params.results, snakemake.output[0], source="corrected")
