# Reference methods scored beside ours (evaluation.references): the oracle bound of the labeling
# (synthetic scenes: labels chosen with the truth, stex.oracle), the same among the data term's
# candidates, and ours without the temporal term. Each gets ours' volume and correction, in
# references/<name>/; the evaluation scores references/<name>/corrected as the method <name>.


wildcard_constraints:
    reference="oracle|oracle_candidates|no_temporal",


rule reference_oracle_labels:
    input:
        scene=f"{RESULTS}/scene.zarr",
        template=f"{RESULTS}/template.zarr",
        truth=expand(f"{RESULTS}/truth/block_{{block}}.zarr", block=BLOCK_IDS),
        observations=f"{RESULTS}/observations.zarr",
        labels=f"{RESULTS}/labels.zarr",
        data_term=expand(f"{RESULTS}/data_term/block_{{block}}.zarr", block=BLOCK_IDS),
    output:
        directory(f"{RESULTS}/references/{{oracle}}/labels.zarr"),
    log:
        f"{RESULTS}/logs/reference_labels_{{oracle}}.log",
    benchmark:
        f"{RESULTS}/benchmarks/reference_labels_{{oracle}}.tsv"
    wildcard_constraints:
        oracle="oracle|oracle_candidates",
    conda:
        ENV
    script:
        "../scripts/oracle_labels.py"


rule reference_no_temporal_labels:
    input:
        template=f"{RESULTS}/template.zarr",
        observations=f"{RESULTS}/observations.zarr",
        projection=f"{RESULTS}/projection.zarr",
        data_term=expand(f"{RESULTS}/data_term/block_{{block}}.zarr", block=BLOCK_IDS),
    output:
        directory(f"{RESULTS}/references/no_temporal/labels.zarr"),
    log:
        f"{RESULTS}/logs/reference_labels_no_temporal.log",
    benchmark:
        f"{RESULTS}/benchmarks/reference_labels_no_temporal.tsv"
    conda:
        ENV
    threads: 2
    params:
        labeling=dict(config["labeling"], temporal="off"),
    script:
        "../scripts/labeling.py"


rule reference_volume:
    input:
        template=f"{RESULTS}/template.zarr",
        labels=f"{RESULTS}/references/{{reference}}/labels.zarr",
        coords=COORDS,
        projection=f"{RESULTS}/projection.zarr",
        frames=expand(f"{RESULTS}/frames/block_{{block}}.zarr", block=BLOCK_IDS),
    output:
        directory(f"{RESULTS}/references/{{reference}}/volume/block_{{block}}.zarr"),
    log:
        f"{RESULTS}/logs/reference_volume_{{reference}}_{{block}}.log",
    benchmark:
        f"{RESULTS}/benchmarks/reference_volume_{{reference}}_{{block}}.tsv"
    conda:
        ENV
    params:
        volume=config["volume"],
        positions=block_range,
    script:
        "../scripts/volume.py"


rule reference_correction:
    input:
        template=f"{RESULTS}/template.zarr",
        volume=f"{RESULTS}/references/{{reference}}/volume/block_{{block}}.zarr",
        previous=previous_reference_corrected,
    output:
        directory(f"{RESULTS}/references/{{reference}}/corrected/block_{{block}}.zarr"),
    log:
        f"{RESULTS}/logs/reference_correction_{{reference}}_{{block}}.log",
    benchmark:
        f"{RESULTS}/benchmarks/reference_correction_{{reference}}_{{block}}.tsv"
    conda:
        ENV
    params:
        correction=config["correction"],
    script:
        "../scripts/correction.py"
