"""Thin adapter: rule evaluate_frames -> stex.evaluation.score_frames (one frame block)."""
from stex.evaluation import score_frames
from stex.logs import setup_logging

setup_logging(snakemake.log[0])
i = snakemake.input
score_frames(i.scene, list(i.frames), list(i.masks), i.template, i.tracking, i.projection, i.labels,
             list(i.volume), list(i.corrected), snakemake.output[0], snakemake.params.evaluation,
             global_texture_path=i.global_texture, truth_paths=list(i.truth) or None,
             coords_path=i.coords, data_term_paths=list(i.data_term), block=snakemake.params.positions,
             threads=snakemake.threads)
