"""Thin adapter: rule evaluate -> stex.evaluation.write_evaluation over the blocks' records
(+ the stage timings)."""
from stex.evaluation import write_evaluation
from stex.logs import setup_logging
from stex.reporting import stage_timings

setup_logging(snakemake.log[0])
i = snakemake.input
out = snakemake.output[0]
write_evaluation(i.scene, list(i.frames), list(i.masks), i.template, i.tracking, i.projection,
                 i.labels, list(i.volume), list(i.corrected), out, snakemake.params.evaluation,
                 global_texture_path=i.global_texture, truth_paths=list(i.truth) or None,
                 coords_path=i.coords, observations_path=i.observations, data_term_paths=list(i.data_term),
                 records_paths=list(i.records), timing=stage_timings(snakemake.params.benchmarks, len(i.corrected)),
                 sampling_path=i.sampling[0] if i.sampling else None)
