"""Thin adapter: rule evaluate_frames -> stex.stages.evaluation.score_frames (one frame block)."""
from stex.logs import setup_logging
from stex.stages.evaluation import EvaluationInputs, score_frames

setup_logging(snakemake.log[0])
i = snakemake.input
inputs = EvaluationInputs(
    scene=i.scene, frames=list(i.frames), masks=list(i.masks), template=i.template, tracking=i.tracking,
    projection=i.projection, labels=i.labels, volume=list(i.volume), corrected=list(i.corrected),
    global_texture=i.global_texture, truth=list(i.truth) or None, coords=i.coords,
    data_term=list(i.data_term))
score_frames(inputs, snakemake.output[0], snakemake.params.evaluation, block=snakemake.params.positions,
             threads=snakemake.threads)
