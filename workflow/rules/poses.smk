# Rigid pose tables K_{t->t'} between all frame pairs, from the tracked vertices.


rule poses:
    input:
        tracking=f"{RESULTS}/tracking.zarr",
        template=f"{RESULTS}/template.zarr",
    output:
        directory(f"{RESULTS}/poses.zarr"),
    params:
        poses=config["poses"],
    threads: 2
    log:
        f"{RESULTS}/logs/poses.log",
    benchmark:
        f"{RESULTS}/benchmarks/poses.tsv",
    priority: TEXTURE_PRIORITY
    conda:
        ENV
    script:
        "../scripts/poses.py"
