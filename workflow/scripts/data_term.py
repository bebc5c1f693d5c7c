"""Thin adapter: rule data_term -> stex.stages.data_term.write_data_term."""
from stex.logs import setup_logging
from stex.stages.data_term import write_data_term

setup_logging(snakemake.log[0])
write_data_term(snakemake.input.scene, snakemake.input.template, snakemake.input.tracking,
             snakemake.input.poses, snakemake.input.observations, snakemake.params.positions,
             snakemake.params.data_term, snakemake.output[0])
