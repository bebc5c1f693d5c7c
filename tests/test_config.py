"""Configuration: the schema's checks, the rules between settings it cannot state, and the
errors a mistyped config gives (one line naming the key)."""
import subprocess
import sys

import pytest
import yaml

from conftest import REPO
from stex.config import load_config, section_params, validate_config


def test_unknown_key_and_wrong_type_name_the_key():
    with pytest.raises(ValueError, match=r"config error at masks: .*'depth_far' was unexpected"):
        validate_config({"masks": {"depth_far": 1.5}})
    with pytest.raises(ValueError, match=r"config error at masks/depth_far_m: '1.5m' is not of type 'number'"):
        section_params("masks", {"depth_far_m": "1.5m"})


def test_depth_range_must_be_ordered():
    with pytest.raises(ValueError, match=r"masks: depth_near_m \(2 m\) must be below depth_far_m \(1.6 m\)"):
        load_config(overrides={"masks": {"depth_near_m": 2.0}})
    with pytest.raises(ValueError, match="must be below depth_far_m"):
        section_params("masks", {"depth_near_m": 1.0, "depth_far_m": 1.0})
    assert section_params("masks", {"depth_near_m": 1.0, "depth_far_m": 1.2})["depth_far_m"] == 1.2


def test_the_workflow_refuses_an_unordered_depth_range_before_any_job(tmp_path):
    (tmp_path / "bad.yaml").write_text(yaml.safe_dump({"results": str(tmp_path / "results"),
                                                       "masks": {"depth_near_m": 2.0, "depth_far_m": 1.0}}))
    run = subprocess.run([sys.executable, "-m", "snakemake", "--snakefile", str(REPO / "Snakefile"), "-n",
                          "--directory", str(tmp_path), "--configfile", str(REPO / "config" / "config.yaml"),
                          str(tmp_path / "bad.yaml")], capture_output=True, text=True, timeout=300)
    assert run.returncode != 0
    assert "depth_near_m (2 m) must be below depth_far_m (1 m)" in run.stdout + run.stderr
    assert not (tmp_path / "results").exists()


def test_settings_that_only_a_late_stage_needed_are_checked_with_the_config():
    from stex.config import validate_config

    for overrides, message in [
            ({"correction": {"solve_size": 100}, "template": {"atlas_size": 512}}, r"correction/solve_size: .* 512 .*factor 5"),
            ({"sampling_table": {"steps": [2, 3]}}, r"sampling_table/steps: \[2, 3\] needs 1"),
            ({"template": {"from_depth": True, "uv": "mesh"}}, r"template: uv: mesh .* from_depth"),
            ({"template": {"from_depth": True}, "tracking": {"mode": "given"}}, r"tracking/mode: given"),
            ({"evaluation": {"other_methods": {"global": "x"}}}, r"other_methods: \['global'\]"),
            ({"scene": ".."}, r"config error at scene"),
            ({"results": ""}, r"config error at results"),
            # YAML 1.1: an unquoted off is false, 1e-4 is text; the message says so
            ({"labeling": {"temporal": False}}, r"quote it, e.g. 'off'"),
            ({"labeling": {"rel_tol": "1e-4"}}, r"write it with a decimal point"),
            ({"trackng": {}}, r"'trackng' was unexpected\); allowed: correction, .*tracking, volume$"),
            # an integer in quotes: not the decimal-point advice of a number
            ({"frame_block": "8"}, r"frame_block: '8' .* give the number without quotes, e\.g\. 8\)$"),
            # NaN passes every minimum; numpy then failed with a ZeroDivisionError
            ({"poses": {"icp_threshold_m": float("nan")}}, r"poses/icp_threshold_m: nan is not a finite number"),
            ({"masks": {"depth_far_m": float("inf")}}, r"masks/depth_far_m: inf is not a finite number"),
            ({"poses": {"seed": -1}}, r"poses/seed: -1 is less than the minimum of 0"),
            ({"template": {"gutter_px": 1021}}, r"template/gutter_px: 1021 .* give at most 1020"),
            ({"template": {"atlas_size": 40960}}, r"template/atlas_size: 40960 is greater than the maximum"),
            ({"sampling_table": {"steps": [1, 1, 2]}}, r"sampling_table/steps: .*non-unique"),
            # an entry of two forms: the error of the form it was meant as, not "none of the schemas"
            ({"evaluation": {"other_methods": {"foo": {"slices": "a", "uvmesh": "b"}}}},
             r"evaluation/other_methods/foo: .*'uvmesh' was unexpected\); allowed: slices, uv_mesh"),
            ({"evaluation": {"other_methods": {"foo": 3}}}, r"foo: 3 is none of the allowed kinds")]:
        with pytest.raises(ValueError, match=message):
            validate_config(overrides)
    validate_config({"correction": {"solve_size": 1024}, "template": {"atlas_size": 4096}})
    # JSON Schema counts 8.0 as an integer, numpy and range() do not: made an int
    cfg = validate_config({"frame_block": 8.0, "poses": {"ransac_iterations": 500.0, "icp_threshold_m": 0.01}})
    assert type(cfg["frame_block"]) is int and type(cfg["poses"]["ransac_iterations"]) is int
    assert cfg["poses"]["icp_threshold_m"] == 0.01
    assert type(section_params("poses", {"ransac_iterations": 50.0})["ransac_iterations"]) is int
    from stex.config import RESERVED_METHOD_NAMES
    from stex.reporting import METHODS

    assert set(RESERVED_METHOD_NAMES) == set(METHODS) | {"input", "truth"}


def test_the_schema_has_no_description_cut_by_a_comma():
    """An unquoted comma in a flow mapping ends the description and makes a key of the rest."""
    import yaml

    from stex.config import SCHEMA_PATH

    def walk(node, path):
        if isinstance(node, dict):
            assert not [k for k, v in node.items() if v is None and k != "default"], path
            for k, v in node.items():
                walk(v, path + [k])

    walk(yaml.safe_load(SCHEMA_PATH.read_text()), [])


def test_explicit_defaults_give_the_same_parameters_as_left_out_ones():
    # Snakemake compares jobs' parameters by repr, keys in order
    defaults = validate_config({})
    explicit = validate_config({"masks": {"depth_far_m": defaults["masks"]["depth_far_m"]},
                                "correction": {"temporal": defaults["correction"]["temporal"]},
                                "source": {"synthetic": {"degradations": {"motion_blur": {"exposure": 0.5}}}}})
    assert repr(explicit["masks"]) == repr(defaults["masks"])
    assert repr(explicit["correction"]) == repr(defaults["correction"])
    assert list(explicit) == list(defaults)
    assert repr(section_params("masks", {"depth_far_m": defaults["masks"]["depth_far_m"]})) == repr(defaults["masks"])
    # free-form names (method names) keep the order they were given in
    cfg = validate_config({"evaluation": {"other_methods": {"zeta": "a", "alpha": "b"}}})
    assert list(cfg["evaluation"]["other_methods"]) == ["zeta", "alpha"]


def test_scoring_settings_leave_out_only_the_figures():
    from stex.config import FIGURE_SETTINGS, scoring_settings
    ev = section_params("evaluation")
    assert set(FIGURE_SETTINGS) <= set(ev)
    assert set(scoring_settings(ev)) == set(ev) - set(FIGURE_SETTINGS)


def test_a_missing_source_names_its_scene(tmp_path):
    # in a dataset run, the message alone did not say which capture's folder is missing
    (tmp_path / "monday.yaml").write_text(yaml.safe_dump({
        "scene": "monday", "source": {"kind": "folder", "folder": {"path": "data/monday"}}}))
    run = subprocess.run([sys.executable, "-m", "snakemake", "--snakefile", str(REPO / "Snakefile"), "-n",
                          "--directory", str(tmp_path), "--configfile", str(tmp_path / "monday.yaml")],
                         capture_output=True, text=True, timeout=300)
    assert run.returncode != 0
    assert "scene 'monday': dataset folder not found: data/monday" in run.stdout + run.stderr


def test_a_decimation_target_below_min_faces_is_refused_naming_both_keys():
    """Decimated meshes end at target_faces, smaller ones are split up to min_faces: with the target
    below min_faces, a mesh just over the target ended with fewer faces than one just under it
    (target 1000, min_faces 4000: 1020 faces -> 1000, 980 -> 3920)."""
    for check in (lambda t: validate_config({"template": t})["template"], lambda t: section_params("template", t)):
        with pytest.raises(ValueError, match=r"template/target_faces: .* target_faces 1000, below template\.min_faces "
                                             r"4000, .* give target_faces >= min_faces"):
            check({"target_faces": 1000})  # min_faces' default 4000
        assert check({"target_faces": 1000, "min_faces": 1000})["target_faces"] == 1000
        assert check({"target_faces": 1000, "min_faces": 0})["min_faces"] == 0
        # without decimation the target is not used: nothing to contradict
        assert check({"target_faces": 1000, "decimate": False})["min_faces"] == 4000
