# Tracking: per-frame vertices of the template (ED + L0 through the depth stream, or given meshes).


rule tracking:
    input:
        scene=f"{RESULTS}/scene.zarr",
        template=f"{RESULTS}/template.zarr",
        frames=expand(f"{RESULTS}/frames/block_{{block}}.zarr", block=BLOCK_IDS),
        masks=expand(f"{RESULTS}/masks/block_{{block}}.zarr", block=BLOCK_IDS),
    output:
        directory(f"{RESULTS}/tracking.zarr"),
    log:
        f"{RESULTS}/logs/tracking.log",
    benchmark:
        f"{RESULTS}/benchmarks/tracking.tsv"
    priority: TEXTURE_PRIORITY
    conda:
        ENV
    resources:
        runtime=SEQUENCE_RUNTIME_MIN,
    params:
        tracking=config["tracking"],
    script:
        "../scripts/tracking.py"


rule tracking_preview:
    input:
        f"{RESULTS}/tracking.zarr",
    output:
        report(
            f"{RESULTS}/previews/tracking_fit.png",
            caption="../report/tracking.rst",
            category="Tracking",
            subcategory=config["scene"],
        ),
    log:
        f"{RESULTS}/logs/tracking_preview.log",
    benchmark:
        f"{RESULTS}/benchmarks/tracking_preview.tsv"
    conda:
        ENV
    script:
        "../scripts/tracking_preview.py"
