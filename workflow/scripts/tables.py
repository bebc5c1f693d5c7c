"""Thin adapter: rule tables -> stex.tables.write_tables."""
from stex.logs import setup_logging
from stex.tables import write_tables

setup_logging(snakemake.log[0])
write_tables(snakemake.input.scene, snakemake.input.template, snakemake.input.tracking,
             snakemake.input.poses, snakemake.input.observations, snakemake.params.positions,
             snakemake.params.tables, snakemake.output[0])
