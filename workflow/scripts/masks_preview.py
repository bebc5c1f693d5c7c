"""Thin adapter: rule masks_preview -> stex.stages.masks.preview_masks."""
from stex.logs import setup_logging
from stex.stages.masks import preview_masks

setup_logging(snakemake.log[0])
preview_masks(list(snakemake.input.frames), list(snakemake.input.masks),
              list(snakemake.input.truth) or None, snakemake.output[0], scene_path=snakemake.input.scene)
