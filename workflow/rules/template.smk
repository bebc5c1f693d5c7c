# Template: clean + decimate the template mesh, UV atlas, face adjacency, texel map (one job).


rule template:
    input:
        scene=f"{RESULTS}/scene.zarr",
        # template.from_depth: the first frame's depth and mask
        first=(
            [f"{RESULTS}/frames/block_{BLOCK_IDS[0]}.zarr", f"{RESULTS}/masks/block_{BLOCK_IDS[0]}.zarr"]
            if config["template"]["from_depth"]
            else []
        ),
    output:
        directory(f"{RESULTS}/template.zarr"),
    log:
        f"{RESULTS}/logs/template.log",
    benchmark:
        f"{RESULTS}/benchmarks/template.tsv"
    priority: TEXTURE_PRIORITY
    conda:
        ENV
    params:
        template=config["template"],
    script:
        "../scripts/template.py"


rule template_preview:
    input:
        f"{RESULTS}/template.zarr",
    output:
        report(
            f"{RESULTS}/previews/template_atlas.png",
            caption="../report/template.rst",
            category="Template",
            subcategory=config["scene"],
        ),
    log:
        f"{RESULTS}/logs/template_preview.log",
    benchmark:
        f"{RESULTS}/benchmarks/template_preview.tsv"
    conda:
        ENV
    script:
        "../scripts/template_preview.py"
