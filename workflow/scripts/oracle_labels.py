"""Thin adapter: rule reference_oracle_labels -> stex.stages.oracle.write_oracle_labels."""
from stex.logs import setup_logging
from stex.stages.oracle import write_oracle_labels

setup_logging(snakemake.log[0])
write_oracle_labels(snakemake.input.scene, snakemake.input.template, list(snakemake.input.truth),
                    snakemake.input.observations, snakemake.input.labels, list(snakemake.input.data_term),
                    snakemake.output[0], among_candidates=snakemake.wildcards.oracle == "oracle_candidates")
