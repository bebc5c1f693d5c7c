# Rigid pose tables K_{t->t'} between all frame pairs, from the tracked vertices.


rule poses:
    input:
        tracking=f"{RESULTS}/tracking.zarr",
        template=f"{RESULTS}/template.zarr",
    output:
        directory(f"{RESULTS}/poses.zarr"),
    log:
        f"{RESULTS}/logs/poses.log",
    benchmark:
        f"{RESULTS}/benchmarks/poses.tsv"
    priority: TEXTURE_PRIORITY
    conda:
        ENV
    threads: 2
    params:
        poses=config["poses"],
    script:
        "../scripts/poses.py"
