"""Thin adapter: rule evaluate -> stex.stages.evaluation.write_evaluation over the blocks' records
(+ the stage timings)."""
from stex.logs import setup_logging
from stex.reporting import stage_timings
from stex.stages.evaluation import EvaluationInputs, write_evaluation

setup_logging(snakemake.log[0])
i = snakemake.input
inputs = EvaluationInputs(
    scene=i.scene, frames=list(i.frames), masks=list(i.masks), template=i.template, tracking=i.tracking,
    projection=i.projection, labels=i.labels, volume=list(i.volume), corrected=list(i.corrected),
    global_texture=i.global_texture, truth=list(i.truth) or None, coords=i.coords,
    observations=i.observations, data_term=list(i.data_term), records=list(i.records),
    sampling=i.sampling[0] if i.sampling else None)
write_evaluation(inputs, snakemake.output[0], snakemake.params.evaluation,
                 timing=stage_timings(snakemake.params.benchmarks, len(i.corrected)))
