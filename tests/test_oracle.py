"""The oracle bound (stex.oracle) on tiny arrays, and the test / dev dataset files."""

from pathlib import Path

import numpy as np
import pytest
import yaml

from stex.config import dataset_scene_configs
from stex.oracle import oracle_labels, truth_samples

REPO = Path(__file__).resolve().parents[1]


def _truth(values):
    """(T, F, S=2, 3) true colours from a (T, F) array of grey values."""
    v = np.asarray(values, np.float32)
    return np.repeat(np.repeat(v[:, :, None, None], 2, axis=2), 3, axis=3)


def test_oracle_takes_the_source_frame_whose_truth_is_closest():
    # 4 frames, 2 faces. Face 0 is seen at frames 0 and 2 (true grey 10, 50), unseen at 1 and 3
    # (true grey 48 and 12): the oracle borrows frame 2 at t=1 and frame 0 at t=3.
    truth = _truth([[10, 5], [48, 5], [50, 5], [12, 5]])
    vis = np.array([[1, 1], [0, 1], [1, 0], [0, 0]], bool)
    ours = np.array([[0, 0], [0, 1], [2, 1], [2, 1]], np.int16)
    got = oracle_labels(truth, vis, np.ones(4, bool), ours)
    assert got[:, 0].tolist() == [0, 2, 2, 0]
    # face 1 is static: where unseen (t = 2, 3) the nearest seen frame in time wins the tie
    assert got[:, 1].tolist() == [0, 1, 1, 1]
    assert got.dtype == np.int16


def test_oracle_keeps_seen_faces_and_respects_sources_and_candidates():
    truth = _truth([[10], [48], [50], [49]])
    vis = np.array([[1], [0], [1], [1]], bool)
    ours = np.array([[0], [0], [2], [3]], np.int16)
    # frame 2 is held out (not a source): at t = 1 the closest source is 3 (49), and t = 2, which
    # sees the face but may not texture it, borrows too
    src = np.array([True, True, False, True])
    got = oracle_labels(truth, vis, src, ours)
    assert got[:, 0].tolist() == [0, 3, 3, 3]
    # among the data term's candidates only: at t = 1 only frame 0 is a candidate
    cand = np.full((4, 1, 2), -1, np.int16)
    cand[1, 0] = [0, -1]
    cand[2, 0] = [0, 3]
    got = oracle_labels(truth, vis, src, ours, candidates=cand)
    assert got[:, 0].tolist() == [0, 0, 3, 3]
    # a face no source saw keeps its label (-1: never seen)
    none = oracle_labels(truth, np.zeros((4, 1), bool), src, np.full((4, 1), -1, np.int16))
    assert (none == -1).all()


def test_oracle_refuses_mismatched_shapes():
    with pytest.raises(ValueError, match="do not agree"):
        oracle_labels(_truth([[1, 2]]), np.ones((1, 3), bool), np.ones(1, bool), np.zeros((1, 3)))


def test_truth_samples_read_the_texture_at_the_points():
    app = np.zeros((4, 4, 3), np.uint8)
    app[1, 2] = (200, 100, 50)                    # texel row 1 (v), column 2 (u)
    uv = np.array([[[2.5 / 4, 1.5 / 4], [0.5 / 4, 0.5 / 4]]])
    got = truth_samples(app, uv)
    assert got.shape == (1, 2, 3)
    assert got[0, 0].tolist() == [200, 100, 50] and got[0, 1].tolist() == [0, 0, 0]


@pytest.mark.parametrize("name", ["test_set.yaml", "dev_set.yaml"])
def test_dataset_files_parse_and_name_existing_scene_files(name, monkeypatch):
    path = REPO / "config" / "datasets" / name
    dataset = yaml.safe_load(path.read_text())
    files = [f for e in dataset["scene_files"] for f in ([e] if isinstance(e, str) else e)]
    missing = [f for f in files if not (REPO / f).is_file()]
    assert not missing, f"{name} names scene files that do not exist: {missing}"
    monkeypatch.chdir(REPO)
    scenes = dataset_scene_configs(dataset, where=name)
    assert len(scenes) == len(dataset["scene_files"])
    if name == "test_set.yaml":
        assert len(scenes) >= 5
        # never a dev scene, never a default-tuning scene
        assert not set(scenes) & {"demo", "demo_heldout", "fox", "fox_heldout", "dev_body", "dev_body_twist",
                                  "biped", "biped_turning", "fox_run"}
        assert any(c["tracking"]["mode"] == "track" for c in scenes.values())
        assert all("oracle" in c["evaluation"]["references"] for c in scenes.values())
