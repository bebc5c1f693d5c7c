# Evaluation: every method scored by the same code (input views, ground truth on synthetic
# scenes), tables and figures for the report.


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
        tables=expand(f"{RESULTS}/tables/block_{{block}}.zarr", block=BLOCK_IDS),
        labels=f"{RESULTS}/labels.zarr",
        volume=expand(f"{RESULTS}/volume/block_{{block}}.zarr", block=BLOCK_IDS),
        corrected=expand(f"{RESULTS}/corrected/block_{{block}}.zarr", block=BLOCK_IDS),
        global_texture=f"{RESULTS}/global_texture.zarr",
    output:
        report(
            directory(f"{RESULTS}/evaluation"),
            patterns=["{name}.png", "{name}.html"],
            caption="../report/evaluation.rst",
            category="Evaluation",
        ),
    threads: 2
    params:
        evaluation=config["evaluation"],
        benchmarks=lambda wildcards: f"{RESULTS}/benchmarks",
    log:
        f"{RESULTS}/logs/evaluate.log",
    conda:
        ENV
    script:
        "../scripts/evaluate.py"
