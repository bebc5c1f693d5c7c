# Evaluation: every method scored by the same code (input views, ground truth on synthetic
# scenes), per frame block (each block's frames as soon as its slices exist), then merged into
# the tables and figures of the report.


rule evaluate_frames:
    input:
        scene=f"{RESULTS}/scene.zarr",
        frames=evaluation_blocks("frames"),
        masks=evaluation_blocks("masks"),
        truth=evaluation_blocks("truth") if SYNTHETIC else [],
        template=f"{RESULTS}/template.zarr",
        tracking=f"{RESULTS}/tracking.zarr",
        projection=f"{RESULTS}/projection.zarr",
        coords=COORDS,
        data_term=expand(f"{RESULTS}/data_term/block_{{block}}.zarr", block=BLOCK_IDS),
        labels=f"{RESULTS}/labels.zarr",
        volume=evaluation_blocks("volume"),
        corrected=evaluation_blocks("corrected"),
        global_texture=f"{RESULTS}/global_texture.zarr",
        others=OTHER_METHODS + REFERENCE_BLOCKS,
    output:
        f"{RESULTS}/evaluation_frames/block_{{block}}.json",
    log:
        f"{RESULTS}/logs/evaluate_frames_{{block}}.log",
    benchmark:
        f"{RESULTS}/benchmarks/evaluate_frames_{{block}}.tsv"
    conda:
        ENV
    params:
        # figure_frame and dynamism_regions are the merge's: changing them re-draws, not re-scores
        evaluation=scoring_settings(EVALUATION),
        positions=block_range,
    script:
        "../scripts/evaluate_frames.py"


rule evaluate:
    input:
        scene=f"{RESULTS}/scene.zarr",
        frames=expand(f"{RESULTS}/frames/block_{{block}}.zarr", block=BLOCK_IDS),
        masks=expand(f"{RESULTS}/masks/block_{{block}}.zarr", block=BLOCK_IDS),
        truth=expand(f"{RESULTS}/truth/block_{{block}}.zarr", block=BLOCK_IDS) if SYNTHETIC else [],
        template=f"{RESULTS}/template.zarr",
        tracking=f"{RESULTS}/tracking.zarr",
        projection=f"{RESULTS}/projection.zarr",
        coords=COORDS,
        observations=f"{RESULTS}/observations.zarr",
        data_term=expand(f"{RESULTS}/data_term/block_{{block}}.zarr", block=BLOCK_IDS),
        labels=f"{RESULTS}/labels.zarr",
        volume=expand(f"{RESULTS}/volume/block_{{block}}.zarr", block=BLOCK_IDS),
        corrected=expand(f"{RESULTS}/corrected/block_{{block}}.zarr", block=BLOCK_IDS),
        global_texture=f"{RESULTS}/global_texture.zarr",
        records=expand(f"{RESULTS}/evaluation_frames/block_{{block}}.json", block=BLOCK_IDS),
        sampling=SAMPLING,
        references=REFERENCE_BLOCKS,
    output:
        report(
            directory(f"{RESULTS}/evaluation"),
            patterns=["{name}.png", "{name}.html"],
            caption="../report/evaluation.rst",
            category="Evaluation",
            subcategory=config["scene"],
        ),
    log:
        f"{RESULTS}/logs/evaluate.log",
        # The merge writes the timing table from benchmarks/*.tsv while it runs, so that table
        # cannot hold the merge itself: its own benchmark, written when it ends, is also a log
        # of the job, and Snakemake deletes a job's logs before it starts: a re-run does not
        # report the previous merge's time as its own. `stex tables` over finished runs reads it.
        own_benchmark=f"{RESULTS}/benchmarks/evaluate.tsv",
    benchmark:
        f"{RESULTS}/benchmarks/evaluate.tsv"
    conda:
        ENV
    params:
        evaluation=EVALUATION,
        benchmarks=lambda wildcards: f"{RESULTS}/benchmarks",
    script:
        "../scripts/evaluate.py"
