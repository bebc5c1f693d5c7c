# Texture volume: one atlas slice per frame from the labelled source frames, per frame block.


rule volume:
    input:
        template=f"{RESULTS}/template.zarr",
        labels=f"{RESULTS}/labels.zarr",
        coords=COORDS,
        projection=f"{RESULTS}/projection.zarr",
        frames=expand(f"{RESULTS}/frames/block_{{block}}.zarr", block=BLOCK_IDS),
    output:
        directory(f"{RESULTS}/volume/block_{{block}}.zarr"),
    log:
        f"{RESULTS}/logs/volume_{{block}}.log",
    benchmark:
        f"{RESULTS}/benchmarks/volume_{{block}}.tsv"
    priority: TEXTURE_PRIORITY
    conda:
        ENV
    params:
        volume=config["volume"],
        positions=block_range,
    script:
        "../scripts/volume.py"
