"""Thin adapter: rule volume -> stex.stages.volume.write_volume."""
from stex.logs import setup_logging
from stex.stages.volume import write_volume

setup_logging(snakemake.log[0])
write_volume(snakemake.input.template, snakemake.input.labels, snakemake.input.coords,
             list(snakemake.input.frames), snakemake.params.positions, snakemake.params.volume,
             snakemake.output[0], projection_path=snakemake.input.projection)
