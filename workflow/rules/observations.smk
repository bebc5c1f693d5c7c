# Observations: what every frame shows of every face (grey samples, E_qual flags, SSIM
# dynamism, SHOT descriptors), one pass over the colour frames.


rule observations:
    input:
        template=f"{RESULTS}/template.zarr",
        tracking=f"{RESULTS}/tracking.zarr",
        projection=f"{RESULTS}/projection.zarr",
        coords=COORDS,
        frames=expand(f"{RESULTS}/frames/block_{{block}}.zarr", block=BLOCK_IDS),
    output:
        directory(f"{RESULTS}/observations.zarr"),
    log:
        f"{RESULTS}/logs/observations.log",
    benchmark:
        f"{RESULTS}/benchmarks/observations.tsv"
    priority: TEXTURE_PRIORITY
    conda:
        ENV
    params:
        observations=config["observations"],
    script:
        "../scripts/observations.py"
