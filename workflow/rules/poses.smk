# Rigid poses K_{t->t'} of the frame pairs candidate pruning keeps (poses.nearest_frames), from
# the tracked vertices; the projection's visibility says which frames can serve each face.


rule poses:
    input:
        tracking=f"{RESULTS}/tracking.zarr",
        template=f"{RESULTS}/template.zarr",
        projection=f"{RESULTS}/projection.zarr",
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
        source_stride=config["data_term"]["source_stride"],
    script:
        "../scripts/poses.py"
