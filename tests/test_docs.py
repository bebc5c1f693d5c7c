"""The documentation that is generated or bounded: the schema's descriptions, config/README.md,
README.md's length, docs/results.md."""
import re

import pytest
import yaml

from conftest import REPO, load_benchmark
from stex import config_doc
from stex.config import SCHEMA_PATH, load_schema, validate_config

# a commit hash as the old descriptions quoted them: 7-40 hex digits with a letter and a digit
COMMIT = re.compile(r"\b(?=[0-9a-f]*[a-f])(?=[0-9a-f]*[0-9])[0-9a-f]{7,40}\b")


def _descriptions(node, path=""):
    if isinstance(node, dict):
        if isinstance(node.get("description"), str):
            yield path or "(the schema)", node["description"]
        for key, value in node.items():
            yield from _descriptions(value, f"{path}.{key}" if path else key)
    elif isinstance(node, list):
        for i, value in enumerate(node):
            yield from _descriptions(value, f"{path}[{i}]")


def test_schema_descriptions_are_short_and_carry_no_commit_hashes():
    """One or two sentences a setting: the measurements behind a default live in
    docs/decisions/config-<section>.md, where they are history, not in the schema."""
    found = list(_descriptions(yaml.safe_load(SCHEMA_PATH.read_text())))
    assert len(found) > 150  # every setting, the sections and the schema itself
    long = [(p, len(" ".join(d.split()))) for p, d in found if len(" ".join(d.split())) > 300]
    assert not long, long
    hashes = [(p, COMMIT.findall(d)) for p, d in found if COMMIT.search(d)]
    assert not hashes, hashes


def test_the_commit_pattern_finds_the_hashes_the_old_schema_quoted():
    assert COMMIT.findall("before commit 2b4e30e its inputs; now (ea37a35, from above)") == ["2b4e30e", "ea37a35"]
    # words and numbers of hex letters are not commits
    assert not COMMIT.findall("decade, 4096 texels, 0.0015 m, facade, 2048x2048, TEXCOORD_0")


def test_every_decision_file_the_schema_names_exists():
    text = SCHEMA_PATH.read_text()
    named = set(re.findall(r"docs/decisions/[\w.-]+\.md", text))
    assert named
    assert not [n for n in named if not (REPO / n).is_file()], named


def test_settings_have_a_valid_tier_and_both_tiers_are_used():
    rows = list(config_doc.settings(load_schema()))
    tiers = {path: tier for path, _, tier in rows}
    assert len(tiers) == len(rows) > 150
    # what a user sets for their own capture is in the user tier, a kernel's weight is not
    for path in ("scene", "frame_block", "source.kind", "source.mkv.path", "source.folder.path",
                 "masks.depth_far_m", "template.from_depth", "template.uv", "template.atlas_size",
                 "tracking.mode", "evaluation.stride"):
        assert tiers[path] == "user", path
    for path in ("tracking.w_rot", "texcoords.gauge", "labeling.omega_s", "correction.boundary_gradient",
                 "source.synthetic.degradations.motion_blur.enabled"):
        assert tiers[path] == "research", path
    with pytest.raises(ValueError, match="masks.iterations.*tier 'expert'"):
        list(config_doc.settings({"properties": {"masks": {"properties": {
            "iterations": {"type": "integer", "tier": "expert"}}}}}))


def test_the_tier_keyword_leaves_validation_and_defaults_alone():
    """JSON Schema ignores keywords it does not know: the schema without ``tier`` gives the same
    config, so marking a setting cannot change a run."""
    def strip(node):
        if isinstance(node, dict):
            return {k: strip(v) for k, v in node.items() if k != "tier"}
        if isinstance(node, list):
            return [strip(v) for v in node]
        return node
    schema = load_schema()
    assert "tier" in str(schema)
    assert validate_config({}, schema) == validate_config({}, strip(schema))
    cfg = {"tracking": {"mode": "given"}, "template": {"atlas_size": 256}}
    assert validate_config(dict(cfg), schema) == validate_config(dict(cfg), strip(schema))


def test_config_readme_is_generated_from_the_schema():
    """config/README.md is `python -m stex.config_doc > config/README.md`: regenerate it after
    changing stex/schema.yaml."""
    text = (REPO / "config" / "README.md").read_text()
    assert text == config_doc.markdown(), "config/README.md is stale: python -m stex.config_doc > config/README.md"
    user, research = text.split("## Research and ablation switches")
    assert "| `tracking.mode` |" in user and "| `tracking.w_rot` |" in research
    assert "| `tracking.mode` |" not in research


def test_readme_is_a_page_a_newcomer_reads():
    readme = (REPO / "README.md").read_text()
    assert len(readme.splitlines()) <= 150
    for doc in re.findall(r"\]\(((?:docs|config)/[^)#]+)", readme):  # every linked doc exists
        assert (REPO / doc).exists(), doc


def _results_page():
    return load_benchmark("results_page")


def test_results_page_is_generated_from_the_recorded_runs():
    """docs/results.md is what `python benchmarks/results_page.py` builds from docs/runs/*.json:
    the figures it shows are the recorded runs', not typed in."""
    rp = _results_page()
    records = rp.load_records()
    assert records, "no run recorded in docs/runs/"
    assert (REPO / "docs" / "results.md").read_text() == rp.page(records), \
        "docs/results.md is stale: python benchmarks/results_page.py"
    demo = next(r for r in records if r["scene"] == "demo")
    assert demo["summary"]["all"]["ours"]["psnr"]["mean"] > 0 and demo["stage_seconds"]["labeling"] > 0


def _fake_run(root, psnr_ours=31.25):
    """A run folder as the workflow leaves it, reduced to what a record reads: one frame block."""
    run = root / "results" / "tiny"
    (run / "evaluation").mkdir(parents=True)
    (run / "benchmarks").mkdir()
    (run / "scene.zarr").mkdir()
    (run / "scene.zarr" / "zarr.json").write_text('{"attributes": {"frame_blocks": [[0, 6]]}}')
    stat = {"mean": psnr_ours, "median": 31.0, "min": 30.0, "max": 33.0, "n": 6, "n_total": 6}
    summary = {"all": {"ours": {"psnr": stat, "blur": dict(stat, mean=None, n=0)},
                       "global": {"psnr": dict(stat, mean=28.5)}},
               "source": {}, "held_out": {}, "n_frames": 6, "n_held_out": 0,
               "held_out_label": "", "blur_interior_px": 3}
    (run / "evaluation" / "evaluation.json").write_text(
        '{"scene": "tiny", "summary": %s, "sampling": null, "libraries": {"numpy": "2.4.6"}}'
        % __import__("json").dumps(summary))
    head = "s\th:m:s\tmax_rss\tmax_vms\n"
    (run / "benchmarks" / "masks_0000.tsv").write_text(head + "2.5\t0:00:02\t120.0\t900\n")
    (run / "benchmarks" / "masks_0001.tsv").write_text(head + "99.0\t0:01:39\t999.0\t900\n")  # an older, longer run's block
    (run / "benchmarks" / "labeling.tsv").write_text(head + "60.0\t0:01:00\t-\t900\n")
    return run


def test_a_record_holds_the_runs_scores_and_times(tmp_path):
    rp = _results_page()
    run = _fake_run(tmp_path)
    rec = rp.record(run, machine="test machine", commit="abc")
    assert rec["scene"] == "tiny" and rec["commit"] == "abc" and rec["machine"] == "test machine"
    assert rec["summary"]["all"]["ours"]["psnr"] == {"mean": 31.25, "n": 6, "n_total": 6}  # means only
    # the block the scene store does not list is left out
    assert rec["stage_seconds"] == {"labeling": 60.0, "masks": 2.5}
    assert rec["stage_jobs"] == {"labeling": {"jobs": 1, "max_rss_mb": None}, "masks": {"jobs": 1, "max_rss_mb": 120.0}}
    text = rp.page([rec])
    assert "| tiny | " in text and "31.25" in text and "28.50" in text and "| numpy | 2.4.6 |" in text
    assert "1.00" in text  # labeling's minute in the timing table

    # --add writes the record and the page; --check then passes, and fails once a score changes
    runs, out = tmp_path / "runs", tmp_path / "results.md"
    args = ["--runs", str(runs), "--out", str(out), "--machine", "m", "--commit", "c"]
    assert rp.main(["--add", str(run), *args]) == 0
    assert (runs / "tiny.json").is_file() and "31.25" in out.read_text()
    assert rp.main(["--check", *args]) == 0
    _fake_run(tmp_path / "again", psnr_ours=20.0)
    assert rp.main(["--add", str(tmp_path / "again" / "results" / "tiny"), *args, "--out", str(tmp_path / "x.md")]) == 0
    assert rp.main(["--check", *args]) == 1


def test_a_run_without_an_evaluation_is_refused_by_name(tmp_path):
    rp = _results_page()
    with pytest.raises(FileNotFoundError, match="evaluation.json: no evaluation"):
        rp.record(tmp_path)
