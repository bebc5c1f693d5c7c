"""Thin adapter: rule ingest_scene -> stex.stages.ingest.write_scene."""
from stex.stages.ingest import write_scene
from stex.logs import setup_logging

setup_logging(snakemake.log[0])
write_scene(snakemake.params.source, snakemake.params.frame_block, snakemake.output[0])
