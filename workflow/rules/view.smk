# The 4-D viewer: a static web page (stex view) that plays the tracked mesh with its per-frame
# texture, the input colour frame beside it and the label map as an overlay. Not marked for the
# report: Snakemake embeds a folder only in a .zip report, and `--report report.html` would then
# be refused; the preview's caption points to it instead.


rule view:
    input:
        scene=f"{RESULTS}/scene.zarr",
        template=f"{RESULTS}/template.zarr",
        tracking=f"{RESULTS}/tracking.zarr",
        frames=expand(f"{RESULTS}/frames/block_{{block}}.zarr", block=BLOCK_IDS),
        volume=expand(f"{RESULTS}/volume/block_{{block}}.zarr", block=BLOCK_IDS),
        corrected=expand(f"{RESULTS}/corrected/block_{{block}}.zarr", block=BLOCK_IDS),
    output:
        directory(f"{RESULTS}/view"),
    log:
        f"{RESULTS}/logs/view.log",
    benchmark:
        f"{RESULTS}/benchmarks/view.tsv"
    conda:
        ENV
    params:
        results=lambda wildcards: RESULTS,
    script:
        "../scripts/view.py"
