# Projection: Φ (tracked vertices in every colour image) and visibility/cos per (frame, vertex/face).


rule projection:
    input:
        scene=f"{RESULTS}/scene.zarr",
        template=f"{RESULTS}/template.zarr",
        tracking=f"{RESULTS}/tracking.zarr",
        masks=(
            expand(f"{RESULTS}/masks/block_{{block}}.zarr", block=BLOCK_IDS)
            if config["projection"]["use_mask"]
            else []
        ),
    output:
        directory(f"{RESULTS}/projection.zarr"),
    log:
        f"{RESULTS}/logs/projection.log",
    benchmark:
        f"{RESULTS}/benchmarks/projection.tsv"
    priority: TEXTURE_PRIORITY
    conda:
        ENV
    params:
        projection=config["projection"],
    script:
        "../scripts/projection.py"


rule projection_preview:
    input:
        frames=expand(f"{RESULTS}/frames/block_{{block}}.zarr", block=BLOCK_IDS),
        projection=f"{RESULTS}/projection.zarr",
    output:
        report(
            f"{RESULTS}/previews/projection.png",
            caption="../report/projection.rst",
            category="Projection",
            subcategory=config["scene"],
        ),
    log:
        f"{RESULTS}/logs/projection_preview.log",
    benchmark:
        f"{RESULTS}/benchmarks/projection_preview.tsv"
    conda:
        ENV
    script:
        "../scripts/projection_preview.py"
