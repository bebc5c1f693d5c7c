"""A dataset of captures in one run (workflow/dataset.smk): the workflow once per scene file."""
import json
import re
import subprocess
import sys

import pytest
import yaml

from conftest import REPO, TINY_SYNTHETIC
from stex.config import dataset_scene_configs
from stex.io import open_store


def _write(path, data):
    path.write_text(yaml.safe_dump(data))
    return str(path)


def test_scene_configs_merge_base_common_and_scene_file(tmp_path):
    base = _write(tmp_path / "base.yaml", {"scene": "demo", "frame_block": 16, "masks": {"depth_far_m": 3.0}})
    a = _write(tmp_path / "a.yaml", {"scene": "a"})
    b = _write(tmp_path / "b.yaml", {"scene": "b", "masks": {"depth_far_m": 1.2}})
    configs = dataset_scene_configs({"scene_files": [a, b], "common": {"masks": {"depth_far_m": 1.5}}}, base)
    assert list(configs) == ["a", "b"]
    assert configs["a"]["frame_block"] == 16  # from the base
    assert configs["a"]["masks"]["depth_far_m"] == 1.5  # common over the base
    assert configs["b"]["masks"]["depth_far_m"] == 1.2  # the scene file over common
    assert configs["a"]["masks"]["depth_near_m"] > 0  # the schema's defaults filled in
    # an entry of several files merges them in order, as several --configfile files
    c = _write(tmp_path / "c.yaml", {"scene": "c", "frame_block": 3})
    merged = dataset_scene_configs({"scene_files": [[b, c]]}, base)
    assert list(merged) == ["c"] and merged["c"]["frame_block"] == 3 and merged["c"]["masks"]["depth_far_m"] == 1.2
    # no base file: the schema's defaults, as Snakemake skips a configfile: that is not there
    assert dataset_scene_configs({"scene_files": [a]}, tmp_path / "none.yaml")["a"]["frame_block"] != 16


def test_scenes_picks_scenes_in_the_datasets_order_and_names_unknown_ones(tmp_path):
    """``scenes`` (a dataset key, or --config scenes=...: a string, a list, or an int for a
    numeric name) returns the chosen scenes in the dataset's order; a name the dataset lacks is
    refused naming it and the dataset's scenes."""
    files = [_write(tmp_path / f"{n}.yaml", {"scene": n}) for n in ("b", "a", "2024")]
    pick = lambda chosen: list(dataset_scene_configs({"scene_files": files, "scenes": chosen}, None))
    assert pick(None) == ["b", "a", "2024"]
    assert pick(["a", "b"]) == ["b", "a"]
    assert pick("a") == ["a"] and pick(2024) == ["2024"] and pick([2024]) == ["2024"]
    with pytest.raises(ValueError, match=r"my\.yaml: scenes must name scenes of the dataset \(b, a, 2024\), "
                                         r"got \['a', 'c'\]: 'c' is not one"):
        dataset_scene_configs({"scene_files": files, "scenes": ["a", "c"]}, None, where="my.yaml")
    with pytest.raises(ValueError, match=r"scenes must name scenes of the dataset \(b, a, 2024\), got \[\]"):
        pick([])


def test_the_shipped_datasets_resolve(monkeypatch):
    """config/datasets/*.yaml name existing scene files and distinct scenes (run from the checkout)."""
    monkeypatch.chdir(REPO)
    names = {}
    for dataset in sorted((REPO / "config" / "datasets").glob("*.yaml")):
        names[dataset.name] = list(dataset_scene_configs(yaml.safe_load(dataset.read_text()), where=dataset.name))
    assert names["demo_and_fox.yaml"] == ["demo", "demo_heldout", "fox", "fox_heldout"]


def test_bad_datasets_name_the_file_and_the_cause(tmp_path):
    a = _write(tmp_path / "a.yaml", {"scene": "a"})
    also_a = _write(tmp_path / "also_a.yaml", {"scene": "a", "frame_block": 4})
    with pytest.raises(ValueError, match=r"scene files .*a\.yaml and .*also_a\.yaml both name scene 'a'"):
        dataset_scene_configs({"scene_files": [a, also_a]}, None)
    with pytest.raises(FileNotFoundError, match=r"my\.yaml: scene file .*missing\.yaml not found"):
        dataset_scene_configs({"scene_files": [a, str(tmp_path / "missing.yaml")]}, None, where="my.yaml")
    bad = _write(tmp_path / "bad.yaml", {"scene": "bad", "masks": {"depth_far_m": -1}})
    with pytest.raises(ValueError, match=r"scene file .*bad\.yaml: config error at masks/depth_far_m"):
        dataset_scene_configs({"scene_files": [a, bad]}, None)
    with pytest.raises(ValueError, match=r"unknown key\(s\) \['scene'\]"):
        dataset_scene_configs({"scene_files": [a], "scene": "a"}, None)
    with pytest.raises(ValueError, match="scene_files must be a non-empty list"):
        dataset_scene_configs({"scene_files": []}, None)
    with pytest.raises(ValueError, match="scene_files must be a non-empty list"):
        dataset_scene_configs({"scene_files": [a, []]}, None)
    with pytest.raises(ValueError, match=r"scene files .*a\.yaml and .*a\.yaml \+ .*also_a\.yaml both name scene 'a'"):
        dataset_scene_configs({"scene_files": [a, [a, also_a]]}, None)
    with pytest.raises(ValueError, match="common must be a mapping"):
        dataset_scene_configs({"scene_files": [a], "common": [1]}, None)
    empty = tmp_path / "empty.yaml"
    empty.write_text("")
    with pytest.raises(ValueError, match=r"scene file .*empty\.yaml is empty"):   # it ran the demo scene
        dataset_scene_configs({"scene_files": [a, str(empty)]}, None)
    # a scene file without a name ran as the base's scene, into its results folder
    nameless = _write(tmp_path / "monday.yaml", {"frame_block": 4})
    base = _write(tmp_path / "base.yaml", {"scene": "demo"})
    with pytest.raises(ValueError, match=r"monday\.yaml sets no `scene:`.*run as 'demo'"):
        dataset_scene_configs({"scene_files": [a, nameless]}, base)
    # a typo in common is common's, not the first scene file's
    with pytest.raises(ValueError, match=r"^dataset: common: config error at masks"):
        dataset_scene_configs({"scene_files": [a], "common": {"masks": {"depth_far": 1.5}}}, base)
    # YAML syntax errors name the file and the line, in one line
    broken = tmp_path / "broken.yaml"
    broken.write_text("scene: broken\nmasks: {depth_far_m: 1.5\n")
    with pytest.raises(ValueError, match=r"scene file .*broken\.yaml is not valid YAML at line 3"):
        dataset_scene_configs({"scene_files": [a, str(broken)]}, None)
    with pytest.raises(FileNotFoundError, match="relative paths are read from the working directory"):
        dataset_scene_configs({"scene_files": ["captures/nowhere.yaml"]}, None)


def _capture_with_a_corrupt_frame(folder):
    """A folder capture (stex layout) of the tiny scene's first two frames, the second colour
    image cut short: the workflow lists it at parse time, its ingest job cannot decode it."""
    import cv2
    import trimesh

    from stex.config import load_config
    from stex.synth.scene import SyntheticScene

    synthetic = SyntheticScene(load_config(overrides={"source": {"synthetic": TINY_SYNTHETIC}})["source"]["synthetic"])
    for sub in ("color", "depth", "meshes"):
        (folder / sub).mkdir(parents=True)
    (folder / "calibration.json").write_text(json.dumps(synthetic.calibration.to_dict()))
    for i in range(2):
        frame = synthetic.render_frame(i)
        assert cv2.imwrite(str(folder / "color" / f"{i:06d}.png"), frame.color[..., ::-1])
        assert cv2.imwrite(str(folder / "depth" / f"{i:06d}.png"), frame.depth_mm)
        trimesh.Trimesh(synthetic.given_vertices(i), synthetic.faces, process=False).export(
            folder / "meshes" / f"{i:06d}.obj")
    corrupt = folder / "color" / "000001.png"
    corrupt.write_bytes(corrupt.read_bytes()[:2000])
    return folder


def test_a_dataset_run_is_the_runs_each_scene_file_makes_alone_and_a_failed_scene_is_left_out(tmp_path):
    """Two scenes are reconstructed and evaluated, with their own sources; the cluster wall time
    of the sequence-long jobs holds for the prefixed rules; and each scene's results are what the
    main workflow would make from its scene file: run alone afterwards, it has nothing to do.
    A third scene fails in a job (a corrupt colour frame): --keep-going finishes the others,
    --report on the whole dataset names the incomplete scene and how to report the rest, and
    --config scenes=[...] is the report of the finished scenes."""
    # one frame block and the given meshes: every job is a process of its own, so their count
    # (and the tracking's work) is most of the test's time; one run serves both halves
    common = {"results": str(tmp_path / "results"), "frame_block": 6, "template": {"atlas_size": 256},
              "tracking": {"mode": "given"},
              "texcoords": {"levels": 2, "iterations": 10, "refine_iterations": 10},
              "sampling_table": {"steps": []}}
    capture = _capture_with_a_corrupt_frame(tmp_path / "capture")
    files = [_write(tmp_path / "tiny_a.yaml", {"scene": "tiny-a", "source": {
                 "kind": "synthetic", "synthetic": TINY_SYNTHETIC}}),
             _write(tmp_path / "tiny_b.yaml", {"scene": "tiny_b", "source": {
                 "kind": "synthetic", "synthetic": {**TINY_SYNTHETIC, "seed": 1}}}),
             _write(tmp_path / "broken.yaml", {"scene": "broken", "source": {
                 "kind": "folder", "folder": {"path": str(capture), "layout": "stex"}}})]
    dataset = _write(tmp_path / "dataset.yaml", {"scene_files": files, "common": common})
    common_file = _write(tmp_path / "common.yaml", common)
    # the working directory's config/config.yaml is under every scene, as under a run of ../Snakefile;
    # its keys come after the scene files' (Snakemake's order; another order re-ran the Fox)
    (tmp_path / "config").mkdir()
    # (the scenes' wall stands at 2.2 m: a far end beyond it would make the background the object)
    _write(tmp_path / "config" / "config.yaml", {"source": {"synthetic": {"fps": 25.0}}, "masks": {"depth_far_m": 1.8}})

    def snakemake(snakefile, configfiles, *args, ok=True):
        run = subprocess.run([sys.executable, "-m", "snakemake", "--snakefile", str(snakefile),
                              "--directory", str(tmp_path), "--configfile", *configfiles, "--cores", "2", *args],
                             capture_output=True, text=True, timeout=900)
        assert (run.returncode == 0) == ok, (run.stdout + run.stderr)[-3000:]
        return run.stdout + run.stderr

    log = snakemake(REPO / "workflow" / "dataset.smk", [dataset], "--keep-going", ok=False)
    assert "Error in rule broken_ingest_block" in log, log[-3000:]
    assert "cannot decode image" in (tmp_path / "results" / "broken" / "logs" / "ingest_block_0000.log").read_text()
    jobs = re.split(r"\n(?=\[[A-Z][a-z]{2} |rule \w+:)", log)  # one block per job (a time stamp, or its rule line)
    tracking_jobs = [j for j in jobs if "rule tiny_a_tracking:" in j or "rule tiny_b_tracking:" in j]
    assert len(tracking_jobs) == 2 and all("runtime=240" in j for j in tracking_jobs), tracking_jobs
    scores = {}
    for scene in ("tiny-a", "tiny_b"):
        evaluation = tmp_path / "results" / scene / "evaluation" / "evaluation.json"
        scores[scene] = json.loads(evaluation.read_text())
    assert scores["tiny-a"] != scores["tiny_b"]  # two seeds: two different scenes
    scene = open_store(tmp_path / "results" / "tiny-a" / "scene.zarr", "scene")
    assert scene.attrs["params"]["source"]["synthetic"]["fps"] == 25.0  # the base was read

    # the report of the whole dataset names the failed scene and how to report the others
    report = tmp_path / "report.html"
    log = snakemake(REPO / "workflow" / "dataset.smk", [dataset], "--report", str(report), ok=False)
    assert not report.exists()
    assert re.search(r"scene 'broken' is incomplete: .*results/broken/\S+ and \d+ more of its results are missing", log), log
    assert "Report the complete scenes with --config scenes=[tiny-a,tiny_b]" in log and "'tiny-a' is" not in log, log
    log = snakemake(REPO / "workflow" / "dataset.smk", [dataset], "--config", "scenes=[tiny_a]", "-n", ok=False)
    assert "scenes must name scenes of the dataset (tiny-a, tiny_b, broken), got ['tiny_a']: " \
           "'tiny_a' is not one" in log, log[-2000:]  # the rules' spelling, not the scene's

    # one report over the finished scenes: every category holds a group per scene
    snakemake(REPO / "workflow" / "dataset.smk", [dataset], "--config", "scenes=[tiny-a,tiny_b]", "--report", str(report))
    html = report.read_text()
    categories = json.loads(re.search(r"var categories = (\{.*?\});?\n", html)[1])
    assert {"Masks", "Tracking", "Evaluation"} <= set(categories)
    for groups in categories.values():
        assert set(groups) == {"tiny-a", "tiny_b"}, groups
    assert "stex over a dataset of captures" in html and "tiny_b.yaml" in html  # its description
    assert "tiny_a_tracking" in html and "broken_" not in html  # their rules, none of the failed one's
    for scene_file in files[:2]:
        assert "Nothing to be done" in snakemake(REPO / "Snakefile", [common_file, scene_file], "-n")
