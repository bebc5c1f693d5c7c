"""Thin adapter: rule ingest_block -> stex.stages.ingest.write_frames_block."""
from stex.stages.ingest import write_frames_block
from stex.logs import setup_logging

setup_logging(snakemake.log[0])
start, stop = snakemake.params.frames
write_frames_block(snakemake.params.source, start, stop, snakemake.output.frames,
                   snakemake.output.get("truth"))
