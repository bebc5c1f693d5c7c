# Template: clean + decimate the template mesh, UV atlas, face adjacency, texel map (one job).
# template.from_scan: rule scan fuses the scan capture into a closed mesh first.

_T = config["template"]


rule scan:
    input:
        # the scan's files, so a replaced recording re-runs the fusion (the synthetic turntable reads none)
        [_T["scan"]["path"]] if _T["from_scan"] and _T["scan"]["kind"] != "synthetic" else [],
    output:
        directory(f"{RESULTS}/scan.zarr"),
    log:
        f"{RESULTS}/logs/scan.log",
    benchmark:
        f"{RESULTS}/benchmarks/scan.tsv"
    priority: TEXTURE_PRIORITY
    conda:
        ENV
    params:
        template=_T,
        source=SOURCE,
        masks=config["masks"],
    script:
        "../scripts/scan.py"


rule template:
    input:
        scene=f"{RESULTS}/scene.zarr",
        # template.from_depth, align, from_scan: the first frame's depth and mask
        first=(
            [f"{RESULTS}/frames/block_{BLOCK_IDS[0]}.zarr", f"{RESULTS}/masks/block_{BLOCK_IDS[0]}.zarr"]
            if _T["from_depth"] or _T["align"] or _T["from_scan"]
            else []
        ),
        scan=[f"{RESULTS}/scan.zarr"] if _T["from_scan"] else [],
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
        template=_T,
        # the masks' settings only where the template is aligned: otherwise a changed mask
        # setting would re-run the template, which does not read the masks
        masks=config["masks"] if _T["align"] or _T["from_scan"] else {},
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
