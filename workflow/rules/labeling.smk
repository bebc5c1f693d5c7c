# Labeling: the spatiotemporal MRF (Eq. 2), α-expansion per frame, even/odd block coordinate
# descent; and the label-map pictures.


rule labeling:
    input:
        template=f"{RESULTS}/template.zarr",
        observations=f"{RESULTS}/observations.zarr",
        projection=f"{RESULTS}/projection.zarr",
        data_term=expand(f"{RESULTS}/data_term/block_{{block}}.zarr", block=BLOCK_IDS),
    output:
        directory(f"{RESULTS}/labels.zarr"),
    log:
        f"{RESULTS}/logs/labeling.log",
    benchmark:
        f"{RESULTS}/benchmarks/labeling.tsv"
    priority: TEXTURE_PRIORITY
    conda:
        ENV
    threads: 2
    resources:
        runtime=SEQUENCE_RUNTIME_MIN,
    params:
        labeling=config["labeling"],
    script:
        "../scripts/labeling.py"
