# Ingest: the source (synthetic scene, folder dataset or Azure Kinect .mkv) into zarr stores.
# The dataset files each job reads are its inputs: a file changed after a run re-runs that job.


rule ingest_scene:
    input:
        scene_source_files,
    output:
        directory(f"{RESULTS}/scene.zarr"),
    log:
        f"{RESULTS}/logs/ingest_scene.log",
    benchmark:
        f"{RESULTS}/benchmarks/ingest_scene.tsv"
    priority: TEXTURE_PRIORITY
    conda:
        ENV
    params:
        **({} if SYNTHETIC else {"frame_ids": id_ranges(_SOURCE.frame_ids)}),
        source=SOURCE,
        frame_block=config["frame_block"],
        # a dataset's frames are found on disk, not set: their ids are a parameter, so frames
        # added to (or removed from) its folder after a run re-write the scene store's frame list
        # (a synthetic scene's frames follow from its settings; no new parameter re-runs it)
    script:
        "../scripts/ingest_scene.py"


if SYNTHETIC:

    rule ingest_block:
        input:
            block_source_files,
        output:
            frames=directory(f"{RESULTS}/frames/block_{{block}}.zarr"),
            truth=directory(f"{RESULTS}/truth/block_{{block}}.zarr"),
        log:
            f"{RESULTS}/logs/ingest_block_{{block}}.log",
        benchmark:
            f"{RESULTS}/benchmarks/ingest_block_{{block}}.tsv"
        priority: TEXTURE_PRIORITY
        conda:
            ENV
        params:
            source=SOURCE,
            frames=block_range,
        script:
            "../scripts/ingest_block.py"

else:

    rule ingest_block:
        input:
            block_source_files,
        output:
            frames=directory(f"{RESULTS}/frames/block_{{block}}.zarr"),
        log:
            f"{RESULTS}/logs/ingest_block_{{block}}.log",
        benchmark:
            f"{RESULTS}/benchmarks/ingest_block_{{block}}.tsv"
        priority: TEXTURE_PRIORITY
        conda:
            ENV
        params:
            source=SOURCE,
            frames=block_range,
        script:
            "../scripts/ingest_block.py"
