# Tables: E_glo rows, E_loc of prefiltered frames, E_qual and the candidate source frames of
# every face, one job per block of target frames.


rule tables:
    input:
        scene=f"{RESULTS}/scene.zarr",
        template=f"{RESULTS}/template.zarr",
        tracking=f"{RESULTS}/tracking.zarr",
        poses=f"{RESULTS}/poses.zarr",
        observations=f"{RESULTS}/observations.zarr",
    output:
        directory(f"{RESULTS}/tables/block_{{block}}.zarr"),
    params:
        tables=config["tables"],
        positions=block_range,
    log:
        f"{RESULTS}/logs/tables_{{block}}.log",
    benchmark:
        f"{RESULTS}/benchmarks/tables_{{block}}.tsv",
    conda:
        ENV
    script:
        "../scripts/tables.py"
