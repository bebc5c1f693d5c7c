# Colour correction: gradient-domain stitching of every slice, per frame block (in sequence
# when the temporal coupling is on).


rule correction:
    input:
        template=f"{RESULTS}/template.zarr",
        volume=f"{RESULTS}/volume/block_{{block}}.zarr",
        previous=previous_corrected,
    output:
        directory(f"{RESULTS}/corrected/block_{{block}}.zarr"),
    log:
        f"{RESULTS}/logs/correction_{{block}}.log",
    benchmark:
        f"{RESULTS}/benchmarks/correction_{{block}}.tsv"
    priority: TEXTURE_PRIORITY
    conda:
        ENV
    params:
        correction=config["correction"],
    script:
        "../scripts/correction.py"


rule labels_preview:
    input:
        volume=expand(f"{RESULTS}/volume/block_{{block}}.zarr", block=BLOCK_IDS),
        corrected=expand(f"{RESULTS}/corrected/block_{{block}}.zarr", block=BLOCK_IDS),
        observations=f"{RESULTS}/observations.zarr",
        template=f"{RESULTS}/template.zarr",
    output:
        report(
            f"{RESULTS}/previews/labels.png",
            caption="../report/labels.rst",
            category="Labeling",
            subcategory=config["scene"],
        ),
    log:
        f"{RESULTS}/logs/labels_preview.log",
    benchmark:
        f"{RESULTS}/benchmarks/labels_preview.tsv"
    conda:
        ENV
    params:
        theta_omega=config["labeling"]["theta_omega"],
    script:
        "../scripts/labels_preview.py"


rule preview_video:
    input:
        scene=f"{RESULTS}/scene.zarr",
        template=f"{RESULTS}/template.zarr",
        tracking=f"{RESULTS}/tracking.zarr",
        frames=expand(f"{RESULTS}/frames/block_{{block}}.zarr", block=BLOCK_IDS),
        corrected=expand(f"{RESULTS}/corrected/block_{{block}}.zarr", block=BLOCK_IDS),
    output:
        report(
            f"{RESULTS}/previews/preview.mp4",
            caption="../report/preview.rst",
            category="Result",
            subcategory=config["scene"],
        ),
    log:
        f"{RESULTS}/logs/preview_video.log",
    benchmark:
        f"{RESULTS}/benchmarks/preview_video.tsv"
    conda:
        ENV
    params:
        results=lambda wildcards: RESULTS,
    script:
        "../scripts/preview_video.py"
