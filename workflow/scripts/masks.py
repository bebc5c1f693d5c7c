"""Thin adapter: rule masks -> stex.stages.masks.write_masks_block."""
from stex.logs import setup_logging
from stex.stages.masks import write_masks_block

setup_logging(snakemake.log[0])
write_masks_block(snakemake.input.scene, snakemake.input.frames, snakemake.params.masks, snakemake.output[0])
