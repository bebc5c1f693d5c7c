# Texture-coordinate optimisation: ξ (Φ refined so that all frames agree with proxy colours, Eq. 1).


rule texcoords:
    input:
        scene=f"{RESULTS}/scene.zarr",
        template=f"{RESULTS}/template.zarr",
        projection=f"{RESULTS}/projection.zarr",
        frames=expand(f"{RESULTS}/frames/block_{{block}}.zarr", block=BLOCK_IDS),
        masks=expand(f"{RESULTS}/masks/block_{{block}}.zarr", block=BLOCK_IDS),
    output:
        directory(f"{RESULTS}/texcoords.zarr"),
    log:
        f"{RESULTS}/logs/texcoords.log",
    benchmark:
        f"{RESULTS}/benchmarks/texcoords.tsv"
    priority: TEXTURE_PRIORITY
    conda:
        ENV
    threads: 2
    resources:
        runtime=SEQUENCE_RUNTIME_MIN,
    params:
        texcoords=config["texcoords"],
    script:
        "../scripts/texcoords.py"


rule texcoords_preview:
    input:
        frames=expand(f"{RESULTS}/frames/block_{{block}}.zarr", block=BLOCK_IDS),
        projection=f"{RESULTS}/projection.zarr",
        texcoords=f"{RESULTS}/texcoords.zarr",
    output:
        report(
            f"{RESULTS}/previews/texcoords.png",
            caption="../report/texcoords.rst",
            category="Texture coordinates",
            subcategory=config["scene"],
        ),
    log:
        f"{RESULTS}/logs/texcoords_preview.log",
    benchmark:
        f"{RESULTS}/benchmarks/texcoords_preview.tsv"
    conda:
        ENV
    script:
        "../scripts/texcoords_preview.py"


rule texcoords_sampling:
    input:
        scene=f"{RESULTS}/scene.zarr",
        template=f"{RESULTS}/template.zarr",
        projection=f"{RESULTS}/projection.zarr",
        frames=expand(f"{RESULTS}/frames/block_{{block}}.zarr", block=BLOCK_IDS),
        masks=expand(f"{RESULTS}/masks/block_{{block}}.zarr", block=BLOCK_IDS),
    output:
        f"{RESULTS}/texcoords_sampling.json",
    log:
        f"{RESULTS}/logs/texcoords_sampling.log",
    benchmark:
        f"{RESULTS}/benchmarks/texcoords_sampling.tsv"
    conda:
        ENV
    threads: 2
    resources:
        runtime=SEQUENCE_RUNTIME_MIN,
    params:
        texcoords=config["texcoords"],
        steps=config["sampling_table"]["steps"],
    script:
        "../scripts/texcoords_sampling.py"
