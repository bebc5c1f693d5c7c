# Global texture: the comparison baseline of Kim et al. 2019, one texture for the whole sequence
# blended from the source frames (the data term's source_stride), read by the evaluation.


rule global_texture:
    input:
        scene=f"{RESULTS}/scene.zarr",
        frames=expand(f"{RESULTS}/frames/block_{{block}}.zarr", block=BLOCK_IDS),
        template=f"{RESULTS}/template.zarr",
        projection=f"{RESULTS}/projection.zarr",
        coords=COORDS,
    output:
        directory(f"{RESULTS}/global_texture.zarr"),
    log:
        f"{RESULTS}/logs/global_texture.log",
    benchmark:
        f"{RESULTS}/benchmarks/global_texture.tsv"
    conda:
        ENV
    params:
        global_texture=config["global_texture"],
        source_stride=config["data_term"]["source_stride"],
    script:
        "../scripts/global_texture.py"
