# Data term: E_glo rows, E_loc of prefiltered frames, E_qual and the candidate source frames of
# every face, one job per block of target frames.


rule data_term:
    input:
        scene=f"{RESULTS}/scene.zarr",
        template=f"{RESULTS}/template.zarr",
        tracking=f"{RESULTS}/tracking.zarr",
        poses=f"{RESULTS}/poses.zarr",
        observations=f"{RESULTS}/observations.zarr",
    output:
        directory(f"{RESULTS}/data_term/block_{{block}}.zarr"),
    log:
        f"{RESULTS}/logs/data_term_{{block}}.log",
    benchmark:
        f"{RESULTS}/benchmarks/data_term_{{block}}.tsv"
    priority: TEXTURE_PRIORITY
    conda:
        ENV
    params:
        data_term=config["data_term"],
        positions=block_range,
    script:
        "../scripts/data_term.py"
