"""Thin adapter: rule poses -> stex.stages.poses.write_pose_table."""
from stex.logs import setup_logging
from stex.stages.poses import write_pose_table

setup_logging(snakemake.log[0])
write_pose_table(snakemake.input.tracking, snakemake.output[0], snakemake.params.poses,
                 array="vertices", faces=snakemake.input.template, threads=snakemake.threads,
                 visibility=snakemake.input.projection, source_stride=snakemake.params.source_stride)
