# Masks: GrabCut at colour resolution seeded from depth, one job per frame block.


rule masks:
    input:
        scene=f"{RESULTS}/scene.zarr",
        frames=f"{RESULTS}/frames/block_{{block}}.zarr",
    output:
        directory(f"{RESULTS}/masks/block_{{block}}.zarr"),
    log:
        f"{RESULTS}/logs/masks_{{block}}.log",
    benchmark:
        f"{RESULTS}/benchmarks/masks_{{block}}.tsv"
    priority: TEXTURE_PRIORITY
    conda:
        ENV
    params:
        masks=config["masks"],
    script:
        "../scripts/masks.py"


rule masks_preview:
    input:
        scene=f"{RESULTS}/scene.zarr",
        frames=expand(f"{RESULTS}/frames/block_{{block}}.zarr", block=BLOCK_IDS),
        masks=expand(f"{RESULTS}/masks/block_{{block}}.zarr", block=BLOCK_IDS),
        truth=expand(f"{RESULTS}/truth/block_{{block}}.zarr", block=BLOCK_IDS) if SYNTHETIC else [],
    output:
        report(
            f"{RESULTS}/previews/masks.png",
            caption="../report/masks.rst",
            category="Masks",
            subcategory=config["scene"],
        ),
    log:
        f"{RESULTS}/logs/masks_preview.log",
    benchmark:
        f"{RESULTS}/benchmarks/masks_preview.tsv"
    conda:
        ENV
    script:
        "../scripts/masks_preview.py"
