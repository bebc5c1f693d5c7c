"""The Snakemake workflow end to end on a tiny scene: outputs, no-op re-run, params tracking, lint."""
import re
import shutil
import subprocess
import sys

import numpy as np
import pytest
import yaml

from conftest import REPO, TINY_SYNTHETIC
from stex.io import FrameSequence, open_store


def snakemake(workdir, *args, configfiles=("tiny.yaml",)):
    cmd = [sys.executable, "-m", "snakemake", "--snakefile", str(REPO / "Snakefile"),
           "--directory", str(workdir), "--configfile", *[str(workdir / c) for c in configfiles], *args]
    return subprocess.run(cmd, capture_output=True, text=True, timeout=600)


@pytest.fixture(scope="module")
def tiny_run(tmp_path_factory):
    work = tmp_path_factory.mktemp("wf")
    cfg = {"scene": "tiny", "results": str(work / "results"), "frame_block": 4,
           "source": {"kind": "synthetic", "synthetic": TINY_SYNTHETIC},
           "template": {"atlas_size": 256},
           "texcoords": {"levels": 2, "iterations": 10, "refine_iterations": 10},
           "observations": {"coordinates": "optimised"}}
    (work / "tiny.yaml").write_text(yaml.safe_dump(cfg))
    run = snakemake(work, "--cores", "2")
    assert run.returncode == 0, run.stderr[-3000:]
    return work


def test_outputs_exist_and_are_complete(tiny_run):
    res = tiny_run / "results" / "tiny"
    scene = open_store(res / "scene.zarr", "scene")
    assert scene.attrs["frame_blocks"] == [[0, 4], [4, 6]]
    frames = FrameSequence(sorted((res / "frames").glob("block_*.zarr")), "frames")
    masks = FrameSequence(sorted((res / "masks").glob("block_*.zarr")), "masks")
    truth = FrameSequence(sorted((res / "truth").glob("block_*.zarr")), "truth")
    assert frames.frame_ids == masks.frame_ids == truth.frame_ids == list(range(6))
    assert frames.read("color", 5).shape == (150, 200, 3)
    assert np.array_equal(scene["given/vertices"][3], scene["truth/vertices"][3])
    assert (res / "previews" / "masks.png").stat().st_size > 1000
    # the tiny scene is tracked (mode track): the mesh covers the mask at every frame
    assert (res / "previews" / "tracking_fit.png").stat().st_size > 1000
    tracking = open_store(res / "tracking.zarr", "tracking")
    assert tracking.attrs["poorly_fitted_frames"] == []
    assert (tracking["silhouette_iou"][...] > 0.85).all()
    from stex.synth.scene import SyntheticScene
    from stex.config import load_config
    s = SyntheticScene(load_config(overrides={"source": {"synthetic": TINY_SYNTHETIC}})["source"]["synthetic"])
    r = s.render_frame(5)  # block jobs give the same bytes as rendering the frame alone
    assert np.array_equal(frames.read("color", 5), r.color)
    assert np.array_equal(truth.read("appearance", 5), r.appearance)


def test_scheduling_rounds_follow_the_jobs_that_finish(tmp_path):
    """A local run has a scheduling round when it starts and when a job ends, and no more:
    workflow/rules/scheduling.smk turns Snakemake's job rate limiter off. With it (--no-hooks
    skips that onstart), every job that ends while others wait for a core adds a round a second.
    Ingest and masks of the tiny scene in one-frame blocks (13 jobs, most of them block jobs
    ready together on 2 cores), both ways: 12 rounds against 38-64 when measured."""
    cfg = {"scene": "tiny", "results": str(tmp_path / "results"), "frame_block": 1,
           "source": {"kind": "synthetic", "synthetic": TINY_SYNTHETIC}}
    (tmp_path / "tiny.yaml").write_text(yaml.safe_dump(cfg))

    def rounds_and_jobs(*hooks):
        for old in ("results", ".snakemake"):
            shutil.rmtree(tmp_path / old, ignore_errors=True)
        run = snakemake(tmp_path, "--cores", "2", "--verbose", "--until", "masks", *hooks)
        log = run.stdout + run.stderr
        assert run.returncode == 0, log[-3000:]
        return log.count("Resources before job selection"), len(re.findall(r"^Finished jobid", log, flags=re.M))

    rounds, finished = rounds_and_jobs()
    assert finished == 13 and 1 <= rounds <= finished + 1, (rounds, finished)
    limited, finished = rounds_and_jobs("--no-hooks")
    assert finished == 13 and limited > finished + 1, (limited, finished)


TEXTURE_RULES = {"ingest_scene", "ingest_block", "masks", "template", "tracking", "poses", "projection",
                 "texcoords", "observations", "data_term", "labeling", "volume", "correction"}
EXTRA_RULES = {"masks_preview", "template_preview", "tracking_preview", "projection_preview", "texcoords_preview",
               "texcoords_sampling", "global_texture", "labels_preview", "preview_video", "view",
               "evaluate_frames", "evaluate"}


def test_the_jobs_that_make_the_texture_go_before_the_extras(tmp_path):
    """Every job of a run with the paper's recipe (so the sampling table too), as the dry run
    lists it with its Snakemake priority: each texture job's is above every extra's, so a
    labeling and a sampling table ready together on a busy machine start in that order. A rule
    in neither list fails here: a new rule is put on one side or the other."""
    cfg = {"scene": "tiny", "results": str(tmp_path / "results"), "frame_block": 4,
           "source": {"kind": "synthetic", "synthetic": TINY_SYNTHETIC},
           "observations": {"coordinates": "optimised"}}
    (tmp_path / "tiny.yaml").write_text(yaml.safe_dump(cfg))
    shutil.copy(REPO / "config" / "recipes" / "paper_tables.yaml", tmp_path / "paper_tables.yaml")
    run = snakemake(tmp_path, "-n", configfiles=("tiny.yaml", "paper_tables.yaml"))
    out = run.stdout + run.stderr
    assert run.returncode == 0, out[-3000:]
    priorities = {}
    for job in re.split(r"^(?=(?:local)?rule \w+:)", out, flags=re.M)[1:]:
        name = re.match(r"(?:local)?rule (\w+):", job).group(1)
        found = re.search(r"^\s+priority: (-?\d+)", job, flags=re.M)
        priorities.setdefault(name, set()).add(int(found.group(1)) if found else 0)
    priorities.pop("all")
    assert set(priorities) == TEXTURE_RULES | EXTRA_RULES, sorted(set(priorities) ^ (TEXTURE_RULES | EXTRA_RULES))
    lowest_texture = min(min(priorities[r]) for r in TEXTURE_RULES)
    highest_extra = max(max(priorities[r]) for r in EXTRA_RULES)
    assert lowest_texture > highest_extra, priorities


def test_rerun_does_nothing(tiny_run):
    run = snakemake(tiny_run, "--cores", "2", "-n")
    assert run.returncode == 0
    assert "Nothing to be done" in run.stdout + run.stderr


def test_changing_a_masks_parameter_reruns_only_masks(tiny_run):
    (tiny_run / "masks3.yaml").write_text(yaml.safe_dump({"masks": {"iterations": 3}}))
    run = snakemake(tiny_run, "--cores", "2", "-n", configfiles=("tiny.yaml", "masks3.yaml"))
    out = run.stdout + run.stderr
    assert run.returncode == 0, out[-2000:]
    jobs = set(re.findall(r"^rule (\w+):", out, flags=re.M))
    # masks and what is downstream of them re-run; nothing upstream (ingest) or beside them (template)
    downstream = {"tracking", "tracking_preview", "poses", "projection", "projection_preview", "texcoords", "observations",
                  "data_term", "labeling", "volume", "correction", "labels_preview", "preview_video", "view",
                  "evaluate_frames", "evaluate", "texcoords_preview", "global_texture"}
    assert jobs == {"all", "masks", "masks_preview"} | downstream, out
    assert "Params have changed since last execution" in out


def test_writing_out_default_values_reruns_nothing(tiny_run):
    # explicit keys come before the filled-in defaults unless the config is put in schema order,
    # and Snakemake compares the jobs' parameters with their keys in order
    from stex.config import section_params
    (tiny_run / "defaults.yaml").write_text(yaml.safe_dump({
        "masks": {"depth_far_m": section_params("masks")["depth_far_m"]},
        "labeling": {"temporal": section_params("labeling")["temporal"]}}))
    run = snakemake(tiny_run, "--cores", "2", "-n", configfiles=("tiny.yaml", "defaults.yaml"))
    assert run.returncode == 0, (run.stdout + run.stderr)[-2000:]
    assert "Nothing to be done" in run.stdout + run.stderr, (run.stdout + run.stderr)[-3000:]


def test_changing_a_figure_setting_redraws_without_rescoring(tiny_run):
    (tiny_run / "figure.yaml").write_text(yaml.safe_dump({"evaluation": {"figure_frame": 1}}))
    run = snakemake(tiny_run, "--cores", "2", "-n", configfiles=("tiny.yaml", "figure.yaml"))
    out = run.stdout + run.stderr
    assert run.returncode == 0, out[-2000:]
    assert set(re.findall(r"^rule (\w+):", out, flags=re.M)) == {"all", "evaluate"}, out


def test_lint_has_no_findings(tiny_run):
    run = snakemake(tiny_run, "--lint")
    out = run.stdout + run.stderr
    assert run.returncode == 0 and "Congratulations" in out, out[-3000:]


def test_texture_outputs(tiny_run):
    """The texture stages ran: every face seen by some frame has a label at every frame, the
    volume and corrected slices exist for every frame, the previews and the evaluation are there."""
    res = tiny_run / "results" / "tiny"
    labels = open_store(res / "labels.zarr", "labels")
    L = labels["labels"][...]
    never = labels["never_seen"][...]
    assert L.shape == (6, len(never)) and (L[:, ~never] >= 0).all() and (L[:, never] == -1).all()
    glimpse = labels["glimpse_source"][...]
    assert not (never & (glimpse >= 0)).any() and (L[:, glimpse >= 0] == glimpse[glimpse >= 0]).all()
    assert np.all(np.diff(labels["energy"][...]) <= 1e-9)
    corrected = FrameSequence(sorted((res / "corrected").glob("block_*.zarr")), "corrected")
    assert corrected.frame_ids == list(range(6))
    assert corrected.read("texture", 3).shape == (256, 256, 3)
    assert (res / "previews" / "labels.png").stat().st_size > 1000
    assert (res / "previews" / "preview.mp4").stat().st_size > 1000
    # every frame block scored in its own job, the records merged into the evaluation
    import json

    blocks = sorted((res / "evaluation_frames").glob("block_*.json"))
    scored = [r["frame"] for b in blocks for r in json.loads(b.read_text())["frames"]]
    evaluation = json.loads((res / "evaluation" / "evaluation.json").read_text())
    assert len(blocks) == 2 and scored == [r["frame"] for r in evaluation["frames"]] == list(range(6))
    assert (res / "benchmarks" / "labeling.tsv").exists()
    assert (res / "benchmarks" / "evaluate_frames_0001.tsv").exists()
    assert "evaluate_frames" in (res / "evaluation" / "tables.rst").read_text()   # timing table
    # the paper's sampling table runs only when asked for (config/recipes/paper_tables.yaml)
    assert not (res / "texcoords_sampling.json").exists() and evaluation["sampling"] is None
    assert not (res / "evaluation" / "table_sampling.csv").exists()


def test_report_holds_the_tables(tiny_run):
    """snakemake --report: the evaluation tables are embedded in the self-contained HTML."""
    import base64

    report = tiny_run / "report.html"
    run = snakemake(tiny_run, "--report", str(report))
    assert run.returncode == 0, (run.stdout + run.stderr)[-3000:]
    html = report.read_text()
    embedded = "".join(base64.b64decode(m).decode("utf-8", "replace")
                       for m in re.findall(r"data:text/html;[^,]*base64,([A-Za-z0-9+/=]+)", html))
    for row in ("PSNR, dB (every frame)", "Kim et al. 2019 (global)", "Blurriness", "Coverage", "evaluate_frames"):
        assert row in embedded, (row, embedded[:2000])
    assert "key-frame sampling" not in embedded  # the default run has no sampling table
    # the tracking-fit plot is in the report, with its caption
    assert "tracking_fit.png" in html and "min_silhouette_iou" in html


def test_the_evaluation_merge_has_a_benchmark_that_its_own_timing_table_leaves_out(tiny_run):
    """The merge writes benchmarks/evaluate.tsv as every job does; `stex tables` over the finished
    run shows it. The timing table the merge writes while it runs cannot time the merge: it has
    no row for it, not even the previous run's (Snakemake deletes that file before the job)."""
    import csv

    from stex.reporting import runs_tables

    res = tiny_run / "results" / "tiny"
    bench = res / "benchmarks" / "evaluate.tsv"

    def stages():
        with open(res / "evaluation" / "table_timing.csv", newline="") as fh:
            return [row[0] for row in csv.reader(fh)][1:]

    def merge_seconds():
        with open(bench, newline="") as fh:
            return float(next(csv.DictReader(fh, delimiter="\t"))["s"])

    assert 0 < merge_seconds() < 999
    assert "evaluate_frames" in stages() and "evaluate" not in stages()
    assert re.search(r"^\| evaluate +\| \d+\.\d\d", runs_tables([res]), re.M)
    bench.write_text("s\th:m:s\n999.0\t0:16:39\n")  # as a previous run's merge left it
    run = snakemake(tiny_run, "--cores", "2", "--forcerun", "evaluate")
    assert run.returncode == 0, (run.stdout + run.stderr)[-3000:]
    assert "evaluate" not in stages() and merge_seconds() < 999


def test_the_paper_tables_recipe_adds_the_sampling_table(tiny_run):
    """config/recipes/paper_tables.yaml given after the scene file: a finished run makes only the
    sampling table and merges the evaluation again (no block is re-scored, no texture stage
    re-runs); the table is in evaluation.json, its CSV and the report."""
    import base64
    import json

    shutil.copy(REPO / "config" / "recipes" / "paper_tables.yaml", tiny_run / "paper_tables.yaml")
    configs = ("tiny.yaml", "paper_tables.yaml")
    dry = snakemake(tiny_run, "--cores", "2", "-n", configfiles=configs)
    out = dry.stdout + dry.stderr
    assert dry.returncode == 0, out[-2000:]
    assert set(re.findall(r"^rule (\w+):", out, flags=re.M)) == {"all", "texcoords_sampling", "evaluate"}, out
    run = snakemake(tiny_run, "--cores", "2", configfiles=configs)
    assert run.returncode == 0, (run.stdout + run.stderr)[-3000:]
    res = tiny_run / "results" / "tiny"
    sampling = json.loads((res / "texcoords_sampling.json").read_text())["steps"]
    evaluation = json.loads((res / "evaluation" / "evaluation.json").read_text())
    assert [r["step"] for r in sampling] == [1, 2, 3, 4, 5] and evaluation["sampling"] == sampling
    assert (res / "evaluation" / "table_sampling.csv").is_file()
    report = tiny_run / "report_paper_tables.html"
    run = snakemake(tiny_run, "--report", str(report), configfiles=configs)
    assert run.returncode == 0, (run.stdout + run.stderr)[-3000:]
    embedded = "".join(base64.b64decode(m).decode("utf-8", "replace") for m in re.findall(
        r"data:text/html;[^,]*base64,([A-Za-z0-9+/=]+)", report.read_text()))
    assert "key-frame sampling" in embedded and "error ratio" in embedded
