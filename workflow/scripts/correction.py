"""Thin adapter: rule correction -> stex.stages.correction.write_corrected."""
from stex.stages.correction import write_corrected
from stex.logs import setup_logging

setup_logging(snakemake.log[0])
previous = snakemake.input.previous[0] if snakemake.input.previous else None
write_corrected(snakemake.input.template, snakemake.input.volume, snakemake.params.correction,
                snakemake.output[0], previous_path=previous)
