"""Thin adapter: rule scan -> stex.stages.scan.write_scan."""
from stex.logs import setup_logging
from stex.stages.scan import write_scan

setup_logging(snakemake.log[0])
write_scan(snakemake.params.template, snakemake.params.source, snakemake.params.masks, snakemake.output[0])
