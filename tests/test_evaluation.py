"""Evaluation stage (stex.evaluation) on the tiny synthetic pipeline."""
import csv
import json
import shutil

import numpy as np
import pytest
import zarr

from stex import metrics as ev
from stex.camera import Calibration, transform_points
from stex.evaluation import (Atlas, coverage_scores, dynamism_regions, image_scores, score_frame,
                             score_methods, truth_views, vertex_motion)
from stex.stages.global_texture import write_global_texture
from stex.io import FrameSequence, StoreError, open_store
from stex.reporting import METHODS, rst_tables
from stex.stages.evaluation import EvaluationInputs, TextureSlices, score_frames, write_evaluation
from conftest import results_folder


def _inputs(P, **stores):
    """EvaluationInputs of the pipeline ``P`` (its global_texture store), with ``stores``
    (truth, observations, data_term, records, ...) as given."""
    return EvaluationInputs(scene=P["scene"], frames=P["frames"], masks=P["masks"], template=P["template"],
                            tracking=P["tracking"], projection=P["projection"], labels=P["labels"],
                            volume=P["volume"], corrected=P["corrected"], global_texture=P["global_texture"],
                            **stores)


def _evaluate(P, out, params=None, frames=None, timing=None, threads=1, others=None, **stores):
    """write_evaluation of the pipeline ``P`` (its global_texture store) into ``out``."""
    return write_evaluation(_inputs(P, **stores), out, params, frames=frames, timing=timing,
                            threads=threads, others=others)


@pytest.fixture(scope="module")
def evaluation(tiny_pipeline, tmp_path_factory):
    out = tmp_path_factory.mktemp("eval")
    res = _evaluate(tiny_pipeline, out, truth=tiny_pipeline["truth"],
                    observations=tiny_pipeline["observations"], data_term=tiny_pipeline["data_term"],
                    timing={"labeling": 90.0, "volume": 30.0})
    return out, res


@pytest.fixture(scope="module")
def frame(tiny_pipeline):
    """Frame 2 of the tiny scene: photo, mask, calibration, our mesh/atlas/texture, the truth."""
    scene = open_store(tiny_pipeline["scene"], "scene")
    template = open_store(tiny_pipeline["template"], "template")
    t = 2
    return {
        "cal": Calibration.from_dict(scene.attrs["calibration"]),
        "image": FrameSequence(tiny_pipeline["frames"], "frames").read("color", t),
        "mask": FrameSequence(tiny_pipeline["masks"], "masks").read("mask", t),
        "V": open_store(tiny_pipeline["tracking"], "tracking")["vertices"][t],
        "atlas": Atlas(template["faces"][...], template["texcoords"][...], template["texcoord_faces"][...]),
        "ours": FrameSequence(tiny_pipeline["corrected"], "corrected").read("texture", t),
        "visible": open_store(tiny_pipeline["projection"], "projection")["face_visible"][t],
        "true_V": scene["truth/vertices"][t],
        "true_atlas": Atlas(scene["template/faces"][...], scene["template/texcoords"][...],
                            scene["template/texcoord_faces"][...]),
        "appearance": FrameSequence(tiny_pipeline["truth"], "truth").read("appearance", t),
    }


def test_input_against_itself_is_perfect(frame):
    s = image_scores(frame["image"], frame["image"], frame["mask"])
    assert s["psnr"] == ev.PSNR_CAP and s["psnr_plain"] == ev.PSNR_CAP
    assert s["ssim"] == pytest.approx(1.0, abs=1e-12)
    assert s["blur"] == s["blur_input"] and 0 < s["blur"] < 1
    assert s["blur_interior"] == s["blur_input_interior"] and 0 < s["blur_interior"] < 1
    assert s["blur_interior"] != s["blur"]                  # a band was left out
    narrow = image_scores(frame["image"], frame["image"], frame["mask"], blur_interior_px=0)
    assert narrow["blur_interior"] == narrow["blur"]
    assert s["n_patches"] > 0 and s["mean_shift_px"] == 0


def test_truth_scored_by_the_ground_truth_path_is_perfect(frame):
    tv = truth_views(frame["true_V"], frame["true_atlas"], frame["appearance"], frame["cal"])
    K, w, h = frame["cal"].color.K, frame["cal"].color.width, frame["cal"].color.height
    vis = ev.input_view_visibility(transform_points(frame["cal"].depth_to_color, frame["true_V"]),
                                   frame["true_atlas"].faces, K, w, h)
    s = score_frame(frame["appearance"], frame["true_V"], frame["true_atlas"], frame["image"],
                    frame["mask"], frame["cal"], truth=tv, face_visible=vis)
    for view in ("novel", "input"):
        assert s[f"gt_{view}_psnr_all"] == ev.PSNR_CAP
        assert s[f"gt_{view}_ssim_all"] == pytest.approx(1.0, abs=1e-9)
        assert s[f"gt_{view}_iou"] == 1.0
    # the truth rendered as the method: the reference blur is the method's own blur
    assert s["blur_truth"] == pytest.approx(s["blur"], abs=1e-9)
    assert s["blur_truth_interior"] == pytest.approx(s["blur_interior"], abs=1e-9)
    # the far side is unseen, the input view mostly seen
    assert s["gt_novel_n_seen"] < 0.02 * s["gt_novel_n_unseen"]
    assert s["gt_input_n_seen"] > 5 * s["gt_input_n_unseen"]
    # the true texture rendered through depth_to_color matches the photo (sensor noise only) ...
    assert s["psnr"] > 38 and s["ssim"] > 0.9 and s["mask_iou"] > 0.99
    # ... and the colour camera is not the depth camera (32 mm baseline)
    cal0 = Calibration(frame["cal"].color, frame["cal"].depth, np.eye(4))
    s0 = score_frame(frame["appearance"], frame["true_V"], frame["true_atlas"], frame["image"],
                     frame["mask"], cal0)
    assert s0["psnr_plain"] < s["psnr_plain"] - 10 and s0["mask_iou"] < 0.9


def test_ours_beats_a_black_texture(frame):
    tv = truth_views(frame["true_V"], frame["true_atlas"], frame["appearance"], frame["cal"])
    kw = dict(truth=tv, face_visible=frame["visible"])
    ours = score_frame(frame["ours"], frame["V"], frame["atlas"], frame["image"], frame["mask"],
                       frame["cal"], **kw)
    black = score_frame(np.zeros_like(frame["ours"]), frame["V"], frame["atlas"], frame["image"],
                        frame["mask"], frame["cal"], **kw)
    assert ours["psnr"] > black["psnr"] + 15
    assert ours["ssim"] > black["ssim"] + 0.3
    assert ours["gt_novel_psnr_unseen"] > black["gt_novel_psnr_unseen"] + 5
    assert ours["gt_input_psnr_all"] > 28


def test_unseen_region_splits_into_borrowed_and_never_seen(frame):
    """The novel view's pixels unseen at t split into surface some frame saw and surface none saw."""
    tv = truth_views(frame["true_V"], frame["true_atlas"], frame["appearance"], frame["cal"])
    F = len(frame["atlas"].faces)
    seen_faces = frame["visible"] | (np.arange(F) % 2 == 0)    # half the far side "seen" elsewhere
    kw = dict(truth=tv, face_visible=frame["visible"], seen_faces=seen_faces)
    ours = score_frame(frame["ours"], frame["V"], frame["atlas"], frame["image"], frame["mask"],
                       frame["cal"], **kw)
    assert ours["gt_novel_n_borrowed"] > 0 and ours["gt_novel_n_never_seen"] > 0
    assert ours["gt_novel_n_borrowed"] + ours["gt_novel_n_never_seen"] == ours["gt_novel_n_unseen"]
    black = score_frame(np.zeros_like(frame["ours"]), frame["V"], frame["atlas"], frame["image"],
                        frame["mask"], frame["cal"], **kw)
    assert ours["gt_novel_psnr_borrowed"] > black["gt_novel_psnr_borrowed"] + 5
    # without seen_faces there is no split
    assert "gt_novel_psnr_borrowed" not in score_frame(
        frame["ours"], frame["V"], frame["atlas"], frame["image"], frame["mask"], frame["cal"],
        truth=tv, face_visible=frame["visible"])


def test_texture_on_the_true_surface(frame, tiny_pipeline):
    """gt_truegeom: the same texture rendered on the true surface (the truth carried onto the
    template). With the tracked mesh in its place the scores are the gt_novel ones; with the
    tracked mesh moved 1 cm sideways, gt_novel drops and gt_truegeom does not see the move."""
    from stex.mesh import transfer_vertices
    template = open_store(tiny_pipeline["template"], "template")
    tvv = transfer_vertices(frame["true_V"], frame["true_atlas"].faces, template["embedding/face"][...],
                            template["embedding/bary"][...])
    tv = truth_views(frame["true_V"], frame["true_atlas"], frame["appearance"], frame["cal"],
                     template_vertices=tvv)
    F = len(frame["atlas"].faces)
    kw = dict(truth=tv, face_visible=frame["visible"], seen_faces=frame["visible"] | (np.arange(F) % 2 == 0))
    same = score_frame(frame["ours"], tvv, frame["atlas"], frame["image"], frame["mask"], frame["cal"], **kw)
    for k in ("psnr_unseen", "psnr_borrowed", "psnr_never_seen", "ssim_unseen"):
        assert same[f"gt_truegeom_{k}"] == pytest.approx(same[f"gt_novel_{k}"], abs=1e-9)
    for k in ("psnr_all", "psnr_seen", "psnr_unseen", "ssim_all", "n_seen", "iou"):
        assert same[f"gt_truegeom_input_{k}"] == pytest.approx(same[f"gt_input_{k}"], abs=1e-9, nan_ok=True)
    assert same["gt_truegeom_input_n_seen"] > 1000
    moved = score_frame(frame["ours"], tvv + np.array([0.01, 0.0, 0.0]), frame["atlas"], frame["image"],
                        frame["mask"], frame["cal"], **kw)
    for k in ("psnr_unseen", "input_psnr_all", "input_psnr_seen", "input_iou"):
        assert moved[f"gt_truegeom_{k}"] == pytest.approx(same[f"gt_truegeom_{k}"], abs=1e-9)
    # the true surface's borrowed / never-seen split (novel-view pixels on surface some source frame
    # saw) is the true surface's own: the moved tracked mesh changes gt_novel's split, not it
    for k in ("psnr_borrowed", "n_borrowed", "psnr_never_seen", "n_never_seen"):
        assert moved[f"gt_truegeom_{k}"] == same[f"gt_novel_{k}"], k
    assert moved["gt_novel_n_borrowed"] != same["gt_novel_n_borrowed"]
    print("same / moved: gt_novel iou", same["gt_novel_iou"], moved["gt_novel_iou"],
          "gt_input psnr", same["gt_input_psnr_all"], moved["gt_input_psnr_all"])
    assert moved["gt_novel_iou"] < same["gt_novel_iou"] - 0.05
    assert abs(moved["gt_novel_psnr_unseen"] - same["gt_novel_psnr_unseen"]) > 0.01
    assert moved["gt_input_iou"] < same["gt_input_iou"] - 0.05
    assert moved["gt_input_psnr_all"] < same["gt_input_psnr_all"] - 1.0
    # no template vertices in the truth: no such keys
    plain = truth_views(frame["true_V"], frame["true_atlas"], frame["appearance"], frame["cal"])
    assert "gt_truegeom_psnr_unseen" not in score_frame(
        frame["ours"], frame["V"], frame["atlas"], frame["image"], frame["mask"], frame["cal"],
        truth=plain, face_visible=frame["visible"])


def test_methods_scored_together_score_as_each_alone(frame, tiny_pipeline):
    """score_methods shares the rasterised mesh and the photo's and the truth's blur between
    textures: every score equals score_frame's for that texture alone, with the true surface
    apart from the tracked mesh (its own rasters) and with it in the same place (reused)."""
    from stex.mesh import transfer_vertices
    template = open_store(tiny_pipeline["template"], "template")
    surface = transfer_vertices(frame["true_V"], frame["true_atlas"].faces,
                                template["embedding/face"][...], template["embedding/bary"][...])
    F = len(frame["atlas"].faces)
    textures = {"ours": frame["ours"], "flipped": np.ascontiguousarray(frame["ours"][::-1]),
                "grey": np.full_like(frame["ours"], 128)}
    has = {"ours": np.ones(F, bool), "flipped": frame["visible"], "grey": np.arange(F) % 3 == 0}
    for V in (frame["V"], surface):
        tv = truth_views(frame["true_V"], frame["true_atlas"], frame["appearance"], frame["cal"],
                         template_vertices=surface)
        kw = dict(truth=tv, face_visible=frame["visible"], seen_faces=frame["visible"] | (np.arange(F) % 2 == 0))
        together = score_methods(textures, V, frame["atlas"], frame["image"], frame["mask"],
                                 frame["cal"], face_has_texture=has, **kw)
        assert list(together) == list(textures)
        for name, tex in textures.items():
            alone = score_frame(tex, V, frame["atlas"], frame["image"], frame["mask"], frame["cal"],
                                face_has_texture=has[name], **kw)
            assert list(together[name]) == list(alone)
            np.testing.assert_equal(together[name], alone)
            # and as rendered and scored one by one from the metric functions
            cal = frame["cal"]
            K, w, h = cal.color.K, cal.color.width, cal.color.height
            a = frame["atlas"]
            Vc = transform_points(cal.depth_to_color, np.asarray(V, np.float64))
            rec, rmask = ev.render_texture(Vc, a.faces, a.texcoords, a.texcoord_faces, tex, K, w, h)
            direct = image_scores(frame["image"], rec, frame["mask"] & rmask)
            assert {k: together[name][k] for k in direct} == direct
            Vn = transform_points(tv["novel_transform"], Vc)
            nov, nmask = ev.render_texture(Vn, a.faces, a.texcoords, a.texcoord_faces, tex, K, w, h)
            seen = ev.seen_mask_in_view(Vn, a.faces, frame["visible"], K, w, h)
            r = ev.region_psnr(*tv["novel"][:1], nov, tv["novel"][1] & nmask, seen, ssim=True)
            assert r["n_unseen"] > 0
            for k in ("psnr_seen", "psnr_unseen", "ssim_seen", "ssim_unseen"):
                np.testing.assert_equal(together[name][f"gt_novel_{k}"], r[k])
        assert together["grey"]["psnr"] != together["ours"]["psnr"]
        assert together["grey"]["blur_input"] == together["ours"]["blur_input"]
    with pytest.raises(ValueError, match="face_has_texture names"):
        score_methods(textures, frame["V"], frame["atlas"], frame["image"], frame["mask"],
                      frame["cal"], face_has_texture={"ours": has["ours"]})


def test_coverage(evaluation):
    _, res = evaluation
    for rec in res["frames"]:
        m = rec["methods"]
        assert m["projection"]["coverage_faces"] < m["ours"]["coverage_faces"]
        assert m["ours"]["coverage_seen"] == 1.0 and m["ours_uncorrected"]["coverage_seen"] == 1.0
        assert m["projection"]["coverage_seen"] < 1.0
        assert 0 < m["ours"]["coverage_area"] <= 1


def test_coverage_scores_checks_shapes():
    s = coverage_scores([True, False, True, False], [1.0, 1.0, 2.0, 0.0], [True, True, True, False])
    assert s["coverage_faces"] == 0.5 and s["coverage_area"] == 0.75
    assert s["coverage_seen"] == pytest.approx(2 / 3)
    with pytest.raises(ValueError, match="face_area"):
        coverage_scores([True, False], [1.0])


def test_outputs_are_written(evaluation):
    out, res = evaluation
    saved = json.loads((out / "evaluation.json").read_text())
    assert saved["scored_frames"] == list(range(6)) and len(saved["frames"]) == 6
    assert set(saved["frames"][0]["methods"]) == set(METHODS)
    assert saved["has_truth"] and saved["summary"]["n_held_out"] == 0
    assert saved["summary"]["all"]["ours"]["psnr"]["n"] == 6
    # flicker needs the previous frame: frames 1..5
    assert saved["summary"]["all"]["ours"]["flicker"]["n"] == 5
    with open(out / "per_frame.csv") as f:
        rows = list(csv.DictReader(f))
    assert len(rows) == 6 * len(METHODS) and float(rows[0]["psnr"]) > 20
    for name in ("psnr_per_frame", "blur_vs_motion", "side_by_side", "label_map", "dynamism"):
        data = (out / f"{name}.png").read_bytes()
        assert data[:8] == b"\x89PNG\r\n\x1a\n" and len(data) > 2000, name
    rst = (out / "tables.rst").read_text()
    assert "Kim et al. 2019 (global)" in rst and "Blurriness" in rst and "+====" in rst
    # the inputs' noise beside the blur (the tiny scene: schema default σ 2 per channel)
    assert "Noise, grey levels (Immerkær)" in rst
    assert "Blurriness, object interior (mask eroded by 3 px)" in rst
    assert saved["summary"]["all"]["ours"]["blur_input_interior"]["n"] == 6
    assert 0.8 < saved["summary"]["all"]["ours"]["noise_input"]["mean"] < 2.5
    assert "<" not in rst                                   # no HTML
    assert "1.50" in rst                                    # labeling 90 s = 1.50 min
    with open(out / "table_reconstruction.csv") as f:
        table = list(csv.reader(f))
    assert table[0][:2] == ["Metric", "Method"] and len(table) > 8


def test_threads_score_exactly_as_one(tiny_pipeline, evaluation, tmp_path):
    """Runs of frames in 3 threads (the flicker of a run's first frame re-renders its
    predecessor): every score equals the single-thread evaluation's."""
    _, res = evaluation
    par = _evaluate(tiny_pipeline, tmp_path / "eval3", truth=tiny_pipeline["truth"],
                    observations=tiny_pipeline["observations"], data_term=tiny_pipeline["data_term"], threads=3)
    assert [r["frame"] for r in par["frames"]] == list(range(6))
    assert par["frames"] == res["frames"] and par["summary"] == res["summary"]


def _block_stores(P, blocks):
    """The pipeline ``P`` with its frame-block stores cut to ``blocks`` (indices)."""
    return {**P, **{k: [P[k][b] for b in blocks] for k in ("frames", "masks", "truth", "volume", "corrected")}}


def test_blocks_scored_apart_merge_into_the_same_evaluation(tiny_pipeline, evaluation, tmp_path):
    """Each frame block scored from its own stores (and its predecessor block's, for the
    flicker of its first frame), then merged: the same records, summary and tables."""
    _, res = evaluation
    blocks = open_store(tiny_pipeline["scene"], "scene").attrs["frame_blocks"]
    assert len(blocks) == 2
    paths = []
    for b, block in enumerate(blocks):
        P = _block_stores(tiny_pipeline, [b - 1, b] if b else [b])
        paths.append(tmp_path / f"block_{b}.json")
        doc = score_frames(_inputs(P, truth=P["truth"], data_term=P["data_term"]), paths[-1], block=block)
        assert doc["scored_frames"] == list(range(*block))
        assert not list(tmp_path.glob(f"block_{b}.json.partial*"))
    # the second block alone lacks frame 3, its first frame's predecessor
    with pytest.raises(ValueError, match=r"frames \[3\] are needed"):
        P = _block_stores(tiny_pipeline, [1])
        score_frames(_inputs(P, truth=P["truth"]), tmp_path / "bad.json", block=blocks[1])
    assert not (tmp_path / "bad.json").exists()
    merged = _evaluate(tiny_pipeline, tmp_path / "merged", truth=tiny_pipeline["truth"],
                       observations=tiny_pipeline["observations"], data_term=tiny_pipeline["data_term"],
                       records=paths[::-1])
    assert merged["frames"] == res["frames"] and merged["summary"] == res["summary"]
    assert merged["tables"] == res["tables"]
    assert (tmp_path / "merged" / "side_by_side.png").exists()

    # records that do not make up the evaluation are refused, naming what is wrong
    with pytest.raises(ValueError, match=r"\[4, 5\] missing"):
        _evaluate(tiny_pipeline, tmp_path / "m1", truth=tiny_pipeline["truth"], records=paths[:1])
    with pytest.raises(ValueError, match="twice"):
        _evaluate(tiny_pipeline, tmp_path / "m2", truth=tiny_pipeline["truth"],
                  records=paths + paths[1:])
    with pytest.raises(ValueError, match="other evaluation settings .*radius"):
        _evaluate(tiny_pipeline, tmp_path / "m3", params={"radius": 2}, truth=tiny_pipeline["truth"],
                  records=paths)
    # the figures' settings are the merge's own: other ones re-draw from the same records
    fig = _evaluate(tiny_pipeline, tmp_path / "m5", params={"figure_frame": 1, "dynamism_regions": 2},
                    truth=tiny_pipeline["truth"], observations=tiny_pipeline["observations"],
                    data_term=tiny_pipeline["data_term"], records=paths)
    assert fig["frames"] == res["frames"] and fig["summary"] == res["summary"]
    (tmp_path / "junk.json").write_text("{not json")
    with pytest.raises(StoreError, match="junk.json"):
        _evaluate(tiny_pipeline, tmp_path / "m4", truth=tiny_pipeline["truth"],
                  records=[tmp_path / "junk.json"])
    assert not any((tmp_path / f"m{k}").exists() for k in range(1, 5))
    assert not list(tmp_path.glob("m*.partial*"))


def test_other_methods_score_beside_ours(tiny_pipeline, evaluation, tmp_path):
    """Other methods' slices (PNG files as `stex export` writes them, or a texture store) are
    scored by the same code as ours: ours exported to PNG and ours_uncorrected's own stores score
    exactly as ours and ours_uncorrected, and appear in the tables under their names; bad
    sources are refused naming what is wrong."""
    from PIL import Image

    from stex.cli import main
    from stex.stages.evaluation import evaluate_results
    from stex.export import write_png_slices

    _, res = evaluation
    ours = FrameSequence(tiny_pipeline["corrected"], "corrected")
    ids = ours.frame_ids
    write_png_slices((ours.read("texture", i) for i in ids), ids, tmp_path / "mine")
    R = results_folder(tiny_pipeline, tmp_path / "results" / "tiny")
    # the run's sampling table (texcoords_sampling.json) goes into the new folder's tables too
    steps = [{"step": 1, "keyframes": 6, "energy": 2.0, "seconds": 4.0, "error_ratio": 1.0, "speedup": 1.0},
             {"step": 2, "keyframes": 3, "energy": 2.5, "seconds": 2.0, "error_ratio": 1.25, "speedup": 2.0}]
    (R / "texcoords_sampling.json").write_text(json.dumps({"steps": steps, "params": {}}))
    got = evaluate_results(R, tmp_path / "eval", {"mine": tmp_path / "mine", "unc": R / "volume"})
    assert got["methods"] == list(METHODS) + ["mine", "unc"]
    html = (tmp_path / "eval" / "tables.html").read_text()  # as the workflow's evaluation folder
    assert "mine" in html and "1.25" in html and (tmp_path / "eval" / "table_sampling.csv").is_file()
    assert [f["frame"] for f in got["frames"]] == [f["frame"] for f in res["frames"]]
    keys = ("psnr", "psnr_plain", "ssim", "blur", "blur_interior", "gt_novel_psnr_unseen",
            "gt_input_psnr_all", "flicker", "coverage_faces")
    for f, before in zip(got["frames"], res["frames"]):
        for other, same in (("mine", "ours"), ("unc", "ours_uncorrected")):
            np.testing.assert_equal({k: f["methods"][other].get(k) for k in keys},
                                    {k: f["methods"][same].get(k) for k in keys})
        np.testing.assert_equal(f["methods"]["ours"], before["methods"]["ours"])
    assert any("flicker" in f["methods"]["mine"] for f in got["frames"])
    rows = [r[1] for r in got["tables"]["reconstruction"]]
    assert rows.count("mine") >= 5 and "unc" in rows
    assert "mine" in (tmp_path / "eval" / "tables.rst").read_text()

    # a frame's slice missing, a slice of the wrong size, a reserved name: refused
    (tmp_path / "mine" / "texture_00004.png").unlink()
    with pytest.raises(ValueError, match=r"'mine'.*no slices for frames \[4\]$"):
        evaluate_results(R, tmp_path / "e1", {"mine": tmp_path / "mine"})
    # frames 5: scored alone, but its flicker reads frame 4 too: the message says why
    with pytest.raises(ValueError, match=r"no slices for frames \[4\]; the frame before each scored frame"):
        evaluate_results(R, tmp_path / "e1", {"mine": tmp_path / "mine"}, frames=[5])
    small = tmp_path / "small"
    write_png_slices((np.zeros((8, 8, 3), np.uint8) for _ in ids), ids, small)
    with pytest.raises(ValueError, match=r"slices are \(8, 8, 3\)"):
        evaluate_results(R, tmp_path / "e2", {"small": small})
    with pytest.raises(ValueError, match=r"other_methods: \['ours'\] name methods the evaluation scores itself"):
        evaluate_results(R, tmp_path / "e3", {"ours": small})
    with pytest.raises(ValueError, match="other_methods: 'Bad-Name' does not match"):
        evaluate_results(R, tmp_path / "e3", {"Bad-Name": small})
    with pytest.raises(StoreError, match="no texture_<frame>.png"):
        evaluate_results(R, tmp_path / "e4", {"x": tmp_path})
    Image.fromarray(np.zeros((8, 8), np.uint8)).save(small / "texture_00000.png")
    with pytest.raises(StoreError, match="8-bit RGB"):
        TextureSlices(small).read(0)
    cut = small / "texture_00001.png"
    cut.write_bytes(cut.read_bytes()[:60])
    with pytest.raises(StoreError, match=r"texture_00001\.png: cannot read the image"):
        TextureSlices(small).read(1)
    with pytest.raises(ValueError, match="own evaluation folder"):
        evaluate_results(R, R / "evaluation", {})
    assert not any((tmp_path / f"e{k}").exists() for k in range(1, 5))

    # the command: every 2nd frame of 2:6, a black method (no texture anywhere)
    black = tmp_path / "black"
    write_png_slices((np.zeros_like(ours.read("texture", i)) for i in ids), ids, black)
    assert main(["evaluate", str(R), "--texture", f"black={black}", "--frames", "2:6",
                 "--stride", "2", "--out", str(tmp_path / "cli")]) == 0
    doc = json.loads((tmp_path / "cli" / "evaluation.json").read_text())
    assert doc["scored_frames"] == [2, 4] and doc["methods"][-1] == "black"
    assert all(f["methods"]["black"]["coverage_faces"] == 0.0 for f in doc["frames"])
    assert all(f["methods"]["black"]["psnr"] < f["methods"]["ours"]["psnr"] - 10 for f in doc["frames"])
    assert main(["evaluate", str(R), "--texture", "black", "--out", str(tmp_path / "cli2")]) == 1
    assert not (tmp_path / "cli2").exists()


def test_other_methods_in_another_uv_layout(tiny_pipeline, tmp_path, capsys):
    """Slices in another UV layout (here the scene's own mesh and atlas) are carried into the
    run's atlas through that mesh: ours carried out into it and scored from there score like
    ours. A mesh elsewhere is refused naming it, and so are such slices read as the run's atlas."""
    from PIL import Image

    from stex.cli import main
    from stex.stages.evaluation import evaluate_results
    from stex.export import write_png_slices
    from stex.readers.meshes import Mesh, load_mesh, write_obj
    from stex.resample import atlas_transfer
    from stex.atlas import texel_map

    scene = open_store(tiny_pipeline["scene"], "scene")
    template = open_store(tiny_pipeline["template"], "template")
    V0, F0, T0, TF0 = (np.asarray(scene[f"template/{k}"][...]) for k in
                       ("vertices", "faces", "texcoords", "texcoord_faces"))
    out_of_ours = atlas_transfer(*texel_map(T0, TF0, 512), V0, F0, template["vertices"][...],
                                 template["faces"][...], template["texcoords"][...],
                                 template["texcoord_faces"][...], gutter_px=4)
    ours = FrameSequence(tiny_pipeline["corrected"], "corrected")
    ids = ours.frame_ids
    theirs = tmp_path / "theirs"
    write_png_slices((out_of_ours.apply(ours.read("texture", i)) for i in ids), ids, theirs)
    write_obj(tmp_path / "theirs.obj", Mesh(V0, F0, T0, TF0))
    # the same slices carried back by hand (through the mesh as the file holds it: 1 µm
    # rounding), as PNG files in the run's atlas
    mesh = load_mesh(tmp_path / "theirs.obj")
    back = atlas_transfer(template["texel/face_id"][...], template["texel/bary"][...],
                          template["vertices"][...], template["faces"][...], mesh.vertices,
                          mesh.faces, mesh.texcoords, mesh.texcoord_faces,
                          gutter_px=int(template.attrs["gutter_px"]))
    by_hand = tmp_path / "by_hand"
    write_png_slices((back.apply(np.asarray(Image.open(theirs / f"texture_{i:05d}.png"))) for i in ids),
                     ids, by_hand)
    R = results_folder(tiny_pipeline, tmp_path / "results" / "tiny")
    got = evaluate_results(R, tmp_path / "eval", {"theirs": {"slices": str(theirs),
                                                            "uv_mesh": str(tmp_path / "theirs.obj")},
                                                 "by_hand": by_hand})
    assert got["methods"][-2:] == ["theirs", "by_hand"]
    assert got["params"]["other_methods"]["theirs"]["uv_mesh"] == str(tmp_path / "theirs.obj")
    for f in got["frames"]:
        m = f["methods"]
        assert m["theirs"] == m["by_hand"]
        # two bilinear resamplings (256 -> 512 -> 256 texels) from ours
        assert abs(m["theirs"]["psnr"] - m["ours"]["psnr"]) < 1.0
        assert abs(m["theirs"]["gt_input_psnr_all"] - m["ours"]["gt_input_psnr_all"]) < 1.0
        assert m["theirs"]["coverage_faces"] == m["ours"]["coverage_faces"]

    # the authors' file names (their texture volume folder): Smooth_ preferred over Frame_
    authors = tmp_path / "authors_video"
    authors.mkdir()
    for i in ids:
        shutil.copy(theirs / f"texture_{i:05d}.png", authors / f"Smooth_{i:06d}.png")
        Image.fromarray(np.zeros((8, 8, 3), np.uint8)).save(authors / f"Frame_{i:06d}.png")
    src = TextureSlices(authors)
    assert src.frame_ids == list(ids)
    np.testing.assert_array_equal(src.read(ids[1]), np.asarray(Image.open(theirs / f"texture_{ids[1]:05d}.png")))

    # the same slices read as if in the run's atlas: refused by their size
    with pytest.raises(ValueError, match=r"slices are \(512, 512, 3\)"):
        evaluate_results(R, tmp_path / "e1", {"theirs": theirs})
    # a mesh 5 cm away from the template: refused, naming it
    write_obj(tmp_path / "moved.obj", Mesh(V0 + [0.05, 0.0, 0.0], F0, T0, TF0))
    with pytest.raises(ValueError, match="moved.obj"):
        evaluate_results(R, tmp_path / "e2", {"theirs": {"slices": str(theirs),
                                                          "uv_mesh": str(tmp_path / "moved.obj")}})
    assert not (tmp_path / "e1").exists() and not (tmp_path / "e2").exists()
    # the command
    assert main(["evaluate", str(R), "--texture", f"theirs={theirs}", "--uv-mesh",
                 f"theirs={tmp_path / 'theirs.obj'}", "--frames", "2:4", "--out", str(tmp_path / "cli")]) == 0
    doc = json.loads((tmp_path / "cli" / "evaluation.json").read_text())
    assert doc["methods"][-1] == "theirs" and doc["scored_frames"] == [2, 3]
    assert main(["evaluate", str(R), "--texture", f"theirs={theirs}", "--uv-mesh",
                 f"nobody={tmp_path / 'theirs.obj'}", "--out", str(tmp_path / "cli2")]) == 1
    twice = ["--uv-mesh", f"theirs={tmp_path / 'theirs.obj'}"] * 2
    capsys.readouterr()
    assert main(["evaluate", str(R), "--texture", f"theirs={theirs}", *twice, "--out", str(tmp_path / "cli2")]) == 1
    assert "error: --uv-mesh: method name 'theirs' given twice" in capsys.readouterr().err
    assert not (tmp_path / "cli2").exists()


def test_other_methods_from_the_settings_scored_in_blocks(tiny_pipeline, tmp_path):
    """evaluation.other_methods (the workflow's way): block jobs score them too, and their
    merge equals the in-process evaluation with the same methods given as ``others``."""
    from stex.export import write_png_slices

    ours = FrameSequence(tiny_pipeline["volume"], "volume")
    write_png_slices((ours.read("texture", i) for i in ours.frame_ids), ours.frame_ids, tmp_path / "unc")
    params = {"other_methods": {"unc": str(tmp_path / "unc")}}
    blocks = open_store(tiny_pipeline["scene"], "scene").attrs["frame_blocks"]
    paths = []
    for b, block in enumerate(blocks):
        P = _block_stores(tiny_pipeline, [b - 1, b] if b else [b])
        paths.append(tmp_path / f"block_{b}.json")
        score_frames(_inputs(P, truth=P["truth"], data_term=P["data_term"]), paths[-1], params, block=block)
    merged = _evaluate(tiny_pipeline, tmp_path / "merged", params=params, truth=tiny_pipeline["truth"],
                       data_term=tiny_pipeline["data_term"], records=paths)
    direct = _evaluate(tiny_pipeline, tmp_path / "direct", truth=tiny_pipeline["truth"],
                       data_term=tiny_pipeline["data_term"], others={"unc": tmp_path / "unc"})
    assert merged["methods"] == direct["methods"] == list(METHODS) + ["unc"]
    assert merged["params"]["other_methods"] == direct["params"]["other_methods"]
    assert merged["frames"] == direct["frames"] and merged["tables"] == direct["tables"]
    for f in merged["frames"]:
        assert f["methods"]["unc"]["psnr"] == f["methods"]["ours_uncorrected"]["psnr"]
    # records scored without the other method do not make up this evaluation
    with pytest.raises(ValueError, match="other evaluation settings .*other_methods"):
        _evaluate(tiny_pipeline, tmp_path / "m", truth=tiny_pipeline["truth"],
                  data_term=tiny_pipeline["data_term"],
                  records=paths, others={"x": tmp_path / "unc"})


def test_blocks_score_every_stride_th_frame_of_the_scene(tiny_pipeline, tmp_path):
    """With evaluation.stride the frames to score are every k-th of the whole scene, whichever
    block holds them; a block with none of them writes an empty record list."""
    blocks = open_store(tiny_pipeline["scene"], "scene").attrs["frame_blocks"]
    docs = [score_frames(_inputs(tiny_pipeline), tmp_path / f"b{b}.json", {"stride": 5}, block=block)
            for b, block in enumerate(blocks)]
    assert [d["scored_frames"] for d in docs] == [[0], [5]]
    assert [[r["frame"] for r in d["frames"]] for d in docs] == [[0], [5]]
    empty = score_frames(_inputs(tiny_pipeline), tmp_path / "none.json", {"stride": 5}, block=[1, 4])
    assert empty["frames"] == [] and json.loads((tmp_path / "none.json").read_text())["frames"] == []
    res = _evaluate(tiny_pipeline, tmp_path / "eval", params={"stride": 5},
                    records=[tmp_path / "b0.json", tmp_path / "none.json", tmp_path / "b1.json"])
    assert res["scored_frames"] == [0, 5] and [r["frame"] for r in res["frames"]] == [0, 5]
    with pytest.raises(ValueError, match="outside the scene"):
        score_frames(_inputs(tiny_pipeline), tmp_path / "x.json", block=[4, 9])


def test_held_out_frames_are_labelled_and_summarised_apart(tiny_pipeline, tmp_path):
    tables = []
    for k, p in enumerate(tiny_pipeline["data_term"]):
        q = tmp_path / f"tables_{k}.zarr"
        shutil.copytree(p, q)
        zarr.open_group(str(q), mode="r+").attrs.update(source_frames=[0, 2, 4])
        tables.append(q)
    # the global baseline of the same source frames (what the workflow builds with stride 2)
    glob2 = tmp_path / "global_2.zarr"
    P = tiny_pipeline
    write_global_texture(P["scene"], P["frames"], P["template"], P["projection"], P["projection"], glob2,
                         {"source_stride": 2})
    with pytest.raises(ValueError, match="source_stride"):   # stride-1 global vs stride-2 tables
        _evaluate(tiny_pipeline, tmp_path / "bad", data_term=tables, frames=[1, 2])
    assert not (tmp_path / "bad").exists()
    res = _evaluate({**tiny_pipeline, "global_texture": glob2}, tmp_path / "eval",
                    data_term=tables, frames=[1, 2])
    assert [r["held_out"] for r in res["frames"]] == [True, False]
    assert res["source_frames"] == [0, 2, 4]
    assert res["seconds"]["global_texture"] == open_store(glob2, "global_texture").attrs["seconds"]
    s = res["summary"]
    assert s["n_held_out"] == 1 and "projection" not in s["held_out"]
    assert s["held_out"]["ours"]["psnr"]["n"] == 1 and s["source"]["global"]["psnr"]["n"] == 1
    # 'seen by some frame' means by some source frame (0, 2, 4): the projection of held-out
    # frame 1 textures the faces it sees, of which coverage_seen counts those sources saw
    vis = open_store(P["projection"], "projection")["face_visible"][...].astype(bool)
    seen = vis[0] | vis[2] | vis[4]
    assert (vis[1] & ~seen).any()
    assert res["frames"][0]["methods"]["projection"]["coverage_seen"] == pytest.approx(vis[1][seen].mean(), abs=1e-12)
    assert not res["has_truth"] and "gt_novel_psnr_all" not in res["frames"][0]["methods"]["ours"]
    assert any("held-out" in r[0] for r in res["tables"]["reconstruction"])


def test_bad_input_names_the_store(tiny_pipeline, tmp_path):
    with pytest.raises(ValueError, match="volume"):          # mismatched frame counts
        _evaluate({**tiny_pipeline, "volume": tiny_pipeline["volume"][:1]}, tmp_path / "a")
    with pytest.raises(StoreError, match="nothing.zarr"):   # missing store
        _evaluate({**tiny_pipeline, "labels": tmp_path / "nothing.zarr"}, tmp_path / "b")
    with pytest.raises(ValueError, match="frames to score"):
        _evaluate(tiny_pipeline, tmp_path / "c", frames=[99])
    with pytest.raises(ValueError, match="strides"):
        _evaluate(tiny_pipeline, tmp_path / "d", params={"strides": 2})
    with pytest.raises(ValueError, match="global_min_weight"):   # moved to global_texture.min_weight
        _evaluate(tiny_pipeline, tmp_path / "e", params={"global_min_weight": 0.3})
    with pytest.raises(StoreError, match="global_texture"):      # another kind of store
        _evaluate({**tiny_pipeline, "global_texture": tiny_pipeline["labels"]}, tmp_path / "f")
    assert not (tmp_path / "a").exists()


def test_textures_of_another_atlas_of_the_same_side_are_refused(tiny_pipeline, tmp_path):
    """The texture stores record their template's atlas; a store of another atlas of the same
    side (which would score as noise in this one) is refused, naming it, wherever it is read:
    as another method, as the run's own slices, by the correction and by the export."""
    import shutil

    import zarr

    from stex.atlas import atlas_digest
    from stex.stages.correction import write_corrected
    from stex.stages.evaluation import evaluate_results
    from stex.stages.export import RunResults
    from stex.stages.template import template_atlas_digest

    template = open_store(tiny_pipeline["template"], "template")
    mine = template_atlas_digest(template)
    for kind in ("volume", "corrected"):
        assert {open_store(b, kind).attrs["atlas_digest"] for b in tiny_pipeline[kind]} == {mine}
    assert open_store(tiny_pipeline["global_texture"], "global_texture").attrs["atlas_digest"] == mine
    # another layout of the same side: the scene's own mesh and atlas
    scene = open_store(tiny_pipeline["scene"], "scene")
    W = int(template.attrs["atlas_size"])
    other = atlas_digest(scene["template/texcoords"][...], scene["template/texcoord_faces"][...], W)
    assert other != mine
    assert atlas_digest(template["texcoords"][...].astype(np.float64), template["texcoord_faces"][...], W) == mine
    assert atlas_digest(template["texcoords"][...], template["texcoord_faces"][...], W * 2) != mine

    R = results_folder(tiny_pipeline, tmp_path / "results" / "tiny")
    moved = tmp_path / "moved"
    moved.mkdir()
    for b, path in enumerate(tiny_pipeline["corrected"]):
        shutil.copytree(path, moved / f"block_{b:04d}.zarr")
        zarr.open_group(str(moved / f"block_{b:04d}.zarr"), mode="r+").attrs["atlas_digest"] = other
    with pytest.raises(ValueError, match=r"moved/block_0000\.zarr holds textures of another UV atlas .*--uv-mesh"):
        evaluate_results(R, tmp_path / "e1", {"mine": moved})
    with pytest.raises(ValueError, match=r"moved/block_0000\.zarr holds textures of another UV atlas than the template"):
        _evaluate({**tiny_pipeline, "corrected": sorted(moved.glob("block_*.zarr"))}, tmp_path / "e2")
    with pytest.raises(ValueError, match=r"moved/block_0000\.zarr holds textures of another UV atlas"):
        write_corrected(tiny_pipeline["template"], tiny_pipeline["volume"][1], {"temporal": True}, tmp_path / "c.zarr",
                        previous_path=moved / "block_0000.zarr")
    (R / "corrected").rename(R / "corrected_ours")
    (R / "corrected").symlink_to(moved)
    with pytest.raises(ValueError, match="another UV atlas"):
        RunResults(R)
    assert not any((tmp_path / x).exists() for x in ("e1", "e2", "c.zarr"))
    # stores written before the attr existed are read as before
    for b in range(len(tiny_pipeline["corrected"])):
        del zarr.open_group(str(moved / f"block_{b:04d}.zarr"), mode="r+").attrs["atlas_digest"]
    assert RunResults(R).frame_ids == FrameSequence(tiny_pipeline["corrected"], "corrected").frame_ids


def test_vertex_motion_and_dynamism_regions():
    V = np.zeros((3, 3))
    assert vertex_motion(V, V + [0.003, 0.004, 0]) == pytest.approx(5.0)   # mm
    S = np.array([[0.5, 0.9, np.nan], [0.6, 0.99, np.nan], [0.4, 0.98, 0.7]])
    regions = dynamism_regions(S, np.array([0, 1, 2]), np.ones(3), 2)
    assert [c for c, _ in regions] == [0, 1]                 # most dynamic, then most static
    np.testing.assert_allclose(regions[0][1], [0.5, 0.6, 0.4])


def test_rst_tables_over_two_scenes():
    def summary(p):
        return {"all": {"ours": {"psnr": {"mean": p}}, "global": {"psnr": {"mean": p - 1}}},
                "n_held_out": 0}
    rst = rst_tables({"demo": summary(30.0), "fox": summary(25.5)}, timing={"demo": {"labels": 120}})
    lines = rst.splitlines()
    assert any("demo" in l and "fox" in l for l in lines)
    row = next(l for l in lines if "| Ours " in l)
    assert "30.00" in row and "25.50" in row
    assert "2.00" in rst and "Coverage" in rst and "Ground truth" not in rst


def test_pipeline_tables_rank_with_the_observed_strain(tiny_pipeline):
    """The observations stage stores the tracked meshes' strain once (E_str), and every tables
    block ranks with it: the stored e_str of each kept candidate is E_str(t, f, l) of that strain."""
    from stex.similarity import face_strain, strain_similarity

    obs = open_store(tiny_pipeline["observations"], "observations")
    template = open_store(tiny_pipeline["template"], "template")
    strain = np.asarray(obs["strain"][...])
    expected = face_strain(open_store(tiny_pipeline["tracking"], "tracking")["vertices"][...],
                           template["vertices"][...], template["faces"][...],
                           obs.attrs["params"]["strain_rings"])
    np.testing.assert_allclose(strain, expected, atol=1e-6)
    tables = open_store(tiny_pipeline["data_term"][0], "data_term")
    assert tables.attrs["params"]["omega_str"] > 0
    t = 0
    cand = np.asarray(tables["candidates"][t], np.int64)
    ok = cand >= 0
    # the tolerance is for the faces frame t does not see
    tol = np.where(np.asarray(obs["face_visible"][t], bool), 0.0, tables.attrs["str_tolerance"])
    E = strain_similarity(strain, t, tables.attrs["params"]["str_clip"], tolerance=tol)
    f = np.nonzero(ok)[0]
    np.testing.assert_allclose(tables["e_str"][t][ok], E[cand[ok], f], atol=1e-6)


def test_labeling_reads_the_tables_a_frame_at_a_time(tiny_pipeline):
    """The labeling reads each frame's candidates and data term from the tables blocks when it
    solves that frame (TableRows), instead of holding every frame's (T, F, K) rows; the rows and
    the labels are those of the whole arrays read at once."""
    from stex.labeling import TableRows, label_sequence
    from stex.stages.labeling import labeling_inputs
    from stex.data_term import unary_terms

    args = labeling_inputs(tiny_pipeline["observations"], tiny_pipeline["data_term"], tiny_pipeline["template"], {})
    args.pop("frame_ids"), args.pop("never_seen")
    assert isinstance(args["cand"], TableRows) and isinstance(args["unary"], TableRows)
    blocks = [open_store(p, "data_term") for p in tiny_pipeline["data_term"]]
    tp = blocks[0].attrs["params"]
    cand = np.concatenate([b["candidates"][...] for b in blocks])
    unary = np.concatenate([unary_terms(b["e_qual"][...], b["e_glo"][...], b["e_loc"][...],
                                        tp["omega_g"], tp["similarity"], b["e_str"][...],
                                        tp["omega_str"]) for b in blocks]).astype(np.float32)
    assert args["cand"].shape == cand.shape and len(blocks) > 1
    for t in range(len(cand)):
        assert np.array_equal(args["cand"][t], cand[t])
        assert np.array_equal(args["unary"][t], unary[t])
    with pytest.raises(IndexError):
        args["cand"][len(cand)]
    lazy = label_sequence(**args, threads=2)
    whole = label_sequence(**dict(args, cand=cand, unary=unary), threads=2)
    assert np.array_equal(lazy["labels"], whole["labels"])
    assert np.array_equal(lazy["energy"], whole["energy"])
    stored = open_store(tiny_pipeline["labels"], "labels")["labels"][...]
    glimpsed = open_store(tiny_pipeline["labels"], "labels")["glimpse_source"][...] >= 0
    assert np.array_equal(stored[:, ~glimpsed], lazy["labels"][:, ~glimpsed])


def test_ground_truth_table_says_over_how_many_frames_a_rare_region_was_scored():
    """A region that exists at few frames (the surface seen at t, in a view from behind) is
    averaged over those frames only; the table says how many, so 32 dB over 9 pixels of 5 frames
    is not read as a whole-sequence figure."""
    import math

    from stex.evaluation import summarise_frames
    from stex.reporting import table_rows

    records = [{"frame": t, "position": t, "held_out": False,
                "methods": {"ours": {"psnr": 30.0, "gt_novel_psnr_all": 20.0,
                                     "gt_novel_psnr_seen": 32.0 if t == 1 else math.nan}}}
               for t in range(4)]
    summary = summarise_frames(records, methods=("ours",))
    rows = {(r[0], r[1]): r[2] for r in table_rows({"s": summary})["ground_truth"][1:]}
    assert rows[("PSNR, dB, seen at t", "Ours")] == "32.00 (1 of 4 frames)"
    assert rows[("PSNR, dB, whole object", "Ours")] == "20.00"


def test_evaluation_records_the_library_versions_and_tables_name_differences(evaluation, tmp_path):
    """evaluation.json holds the versions it was scored with; `stex tables` over two evaluations
    whose scipy differs says so under the tables (a newer scipy or numba moves figures a little),
    and says nothing when they agree."""
    import json
    import shutil

    from stex.io import library_versions
    from stex.reporting import runs_tables

    out, res = evaluation
    assert res["libraries"] == library_versions() and "numpy" in res["libraries"]
    a, b = tmp_path / "a", tmp_path / "b"
    shutil.copytree(out, a)
    shutil.copytree(out, b)
    assert "different library versions" not in runs_tables([a, b])
    doc = json.loads((b / "evaluation.json").read_text())
    doc["libraries"]["scipy"] = "0.0.1"
    (b / "evaluation.json").write_text(json.dumps(doc))
    note = runs_tables([a, b]).splitlines()[-1]
    assert note.startswith("The runs were scored with different library versions")
    assert f"scipy {library_versions()['scipy']} (a), 0.0.1 (b)" in note


def test_image_scores_look_only_inside_the_mask():
    """A render equal to the photo inside the mask and black outside scores as the photo itself:
    PSNR 100 dB (the cap), SSIM 1 (outside the mask the render is replaced by the photo, so
    every window compares the photo with itself), n_pixels = the mask's 40 x 50 = 2000 pixels.
    The same render brightened by 10 grey levels inside the mask: plain PSNR
    10 log10(255² / 10²) = 28.1308 dB, whatever lies outside the mask."""
    rng = np.random.default_rng(0)
    photo = rng.integers(0, 200, (96, 96, 3)).astype(np.uint8)
    mask = np.zeros((96, 96), bool)
    mask[20:60, 10:60] = True
    render = np.where(mask[..., None], photo, 0).astype(np.float32)
    s = image_scores(photo, render, mask)
    assert s["n_pixels"] == 2000
    assert s["psnr_plain"] == ev.PSNR_CAP and s["psnr"] == ev.PSNR_CAP
    assert s["ssim"] == pytest.approx(1.0, abs=1e-12)
    brighter = image_scores(photo, render + 10 * mask[..., None], mask)
    assert brighter["psnr_plain"] == pytest.approx(28.1308, abs=1e-4)


def test_novel_view_at_zero_degrees_is_the_input_view(frame):
    """truth_views' novel view turns the true mesh by ``novel_angle_deg`` about the vertical axis
    through its centre: at 0 degrees the transform is the identity and the novel render is the
    input render."""
    tv = truth_views(frame["true_V"], frame["true_atlas"], frame["appearance"], frame["cal"],
                     novel_angle_deg=0.0)
    np.testing.assert_allclose(tv["novel_transform"], np.eye(4), atol=1e-12)
    np.testing.assert_array_equal(tv["novel"][1], tv["input"][1])
    np.testing.assert_allclose(tv["novel"][0], tv["input"][0], atol=1e-3)


def _bands(rows, shape=(30, 30)):
    """(H, W) bool mask of the listed rows (all columns)."""
    m = np.zeros(shape, bool)
    m[list(rows)] = True
    return m


def test_truth_region_scores_by_hand():
    """Ground-truth region scores of hand-made 30 x 30 images. True silhouette rows 0-19, ours
    rows 5-24: scored pixels rows 5-19 (450 px), IoU 450 / 750 (rows 0-24) = 0.6. Ours is the
    truth + 10 grey levels there (PSNR 10 log10(255² / 100) = 28.1308 dB) and + 100 where only
    the truth covers (rows 0-4, not scored). A seen region of 99 px is below MIN_REGION_PX
    (100): NaN; one of 100 px is scored; without a seen mask every scored pixel is unseen."""
    from stex.evaluation import MIN_REGION_PX, _truth_region_scores

    assert MIN_REGION_PX == 100
    truth = np.zeros((30, 30, 3))
    t_mask, r_mask = _bands(range(0, 20)), _bands(range(5, 25))
    rec = truth + 10.0
    rec[:5] += 90.0
    p10 = 10 * np.log10(255.0 ** 2 / 100.0)                    # 28.1308 dB
    seen99 = _bands(range(5, 8))                                # 90 px ...
    seen99[8, :9] = True                                        # ... + 9 = 99 px
    s = _truth_region_scores("x", truth, t_mask, rec, r_mask, seen99)
    assert s["x_iou"] == pytest.approx(0.6)
    assert (s["x_n_seen"], s["x_n_unseen"]) == (99, 351)
    assert s["x_psnr_all"] == pytest.approx(p10) and s["x_psnr_unseen"] == pytest.approx(p10)
    assert np.isnan(s["x_psnr_seen"]) and np.isnan(s["x_ssim_seen"])
    seen100 = seen99.copy()
    seen100[8, 9] = True
    s = _truth_region_scores("x", truth, t_mask, rec, r_mask, seen100)
    assert s["x_n_seen"] == 100 and s["x_psnr_seen"] == pytest.approx(p10)
    s = _truth_region_scores("x", truth, t_mask, rec, r_mask, None)
    assert (s["x_n_seen"], s["x_n_unseen"]) == (0, 450)
    assert s["x_psnr_unseen"] == pytest.approx(p10) and np.isnan(s["x_psnr_seen"])


def test_novel_scores_split_the_unseen_region_by_hand():
    """The novel view's unseen-at-t pixels split into borrowed (seen by some source frame) and
    never seen, on hand-made 30 x 30 images, everything inside both silhouettes: seen at t rows
    0-9 (ours exact), borrowed rows 10-19 (ours + 5: 10 log10(255² / 25) = 34.1514 dB), never
    seen rows 20-29 (ours + 20: 10 log10(255² / 400) = 22.1102 dB), 300 px each. With only 50
    borrowed pixels (row 10 and 20 pixels of row 11) that region is below MIN_REGION_PX: NaN,
    and the other 600 - 50 = 550 unseen pixels are never seen."""
    from stex.evaluation import _novel_scores

    truth_img = np.zeros((30, 30, 3))
    full = np.ones((30, 30), bool)
    rec = truth_img.copy()
    rec[10:20] += 5.0
    rec[20:30] += 20.0
    seen_t = _bands(range(0, 10))
    truth = {"novel": (truth_img, full)}
    views = {"novel": (rec, full), "novel_seen": seen_t}
    s = _novel_scores("g", truth, views, _bands(range(0, 20)))
    assert (s["g_n_borrowed"], s["g_n_never_seen"]) == (300, 300)
    assert s["g_psnr_borrowed"] == pytest.approx(10 * np.log10(255.0 ** 2 / 25.0))
    assert s["g_psnr_never_seen"] == pytest.approx(10 * np.log10(255.0 ** 2 / 400.0))
    ever = _bands(range(0, 11))
    ever[11, :20] = True
    s = _novel_scores("g", truth, views, ever)
    assert (s["g_n_borrowed"], s["g_n_never_seen"]) == (50, 550)
    assert np.isnan(s["g_psnr_borrowed"]) and np.isfinite(s["g_psnr_never_seen"])


def test_vertex_motion_is_the_mean_displacement():
    """Two vertices, one moved by (3, 4, 0) mm, one still: mean displacement (5 + 0) / 2 = 2.5 mm."""
    V = np.zeros((2, 3))
    assert vertex_motion(V, V + [[0.003, 0.004, 0.0], [0.0, 0.0, 0.0]]) == pytest.approx(2.5)


def test_dynamism_regions_by_hand():
    """Charts: 0 = faces 0 (area 1, S 0.2) and 1 (area 3, S 0.6), area-weighted mean
    (0.2 + 1.8) / 4 = 0.5 in every frame; 1 = face 2, S 0.9 in 2 of 4 frames (at least half:
    kept); 2 = face 3, S 0.7. Two regions: the most dynamic (chart 0, 0.5) and the most static
    (chart 1, 0.9)."""
    S = np.array([[0.2, 0.6, 0.9, 0.7], [0.2, 0.6, 0.9, 0.7],
                  [0.2, 0.6, np.nan, 0.7], [0.2, 0.6, np.nan, 0.7]])
    regions = dynamism_regions(S, np.array([0, 0, 1, 2]), np.array([1.0, 3.0, 1.0, 1.0]), 2)
    assert [c for c, _ in regions] == [0, 1]
    np.testing.assert_allclose(regions[0][1], [0.5] * 4)
    np.testing.assert_allclose(regions[1][1], [0.9, 0.9, np.nan, np.nan])
    # three frames: a chart finite in 1 of them is not seen in at least half (1 < 1.5), one in 2 is
    # (before the fix, 3 // 2 = 1 frame let the first in, and it was drawn as the most dynamic)
    S = np.array([[0.9, np.nan, 0.5], [0.9, np.nan, np.nan], [0.9, 0.1, 0.5]])
    assert [c for c, _ in dynamism_regions(S, np.array([0, 1, 2]), np.ones(3), 3)] == [2, 0]


def _records(values: dict, held_out=(False, False, True)):
    """Per-frame records of frames 0, 1, 2 (``held_out`` each) with ``{method: {metric: [v0,
    v1, v2]}}`` (None: the metric is absent from that frame's record)."""
    return [{"frame": t, "position": t, "held_out": h, "motion_mm": float("nan"),
             "methods": {m: {k: v[t] for k, v in metrics.items() if v[t] is not None}
                         for m, metrics in values.items()}}
            for t, h in enumerate(held_out)]


def test_summarise_frames_by_hand():
    """Frames 0 and 1 are sources, frame 2 is held out. ours psnr 30, 33, 21: every frame mean
    28, sources mean 31.5 (n 2), held out 21 (n 1). projection is summarised on every frame and
    the sources, not on the held-out frames (its texture there is the frame's own photo). A
    metric absent from frame 0's record (the flicker, which needs a predecessor) is averaged over
    the frames that have it (values 1.0 and 3.0 -> mean 2.0, n 2) and counted over all 3 (n_total)."""
    from stex.evaluation import summarise_frames

    recs = _records({"ours": {"psnr": [30.0, 33.0, 21.0], "flicker": [None, 1.0, 3.0]},
                     "projection": {"psnr": [40.0, 42.0, 50.0]}})
    s = summarise_frames(recs, methods=("ours", "projection"))
    assert s["all"]["ours"]["psnr"]["mean"] == pytest.approx(28.0)
    assert (s["source"]["ours"]["psnr"]["mean"], s["source"]["ours"]["psnr"]["n"]) == (pytest.approx(31.5), 2)
    assert (s["held_out"]["ours"]["psnr"]["mean"], s["held_out"]["ours"]["psnr"]["n"]) == (21.0, 1)
    assert s["source"]["projection"]["psnr"]["mean"] == pytest.approx(41.0)
    assert "projection" not in s["held_out"]
    fl = s["all"]["ours"]["flicker"]
    assert (fl["mean"], fl["n"], fl["n_total"]) == (pytest.approx(2.0), 2, 3)


def test_table_rows_by_hand():
    """table_rows of hand-made summaries (summarise_frames of frames 0, 1 sources, 2 held out),
    scene "a" with ours and global, scene "b" with ours only: each cell is the mean over the
    frames, formatted by hand. PSNR 30, 33, 21 -> 28.00 (held out: 21.00, labelled '(1/2)');
    plain PSNR 25, 27, 15 -> 22.33; SSIM 0.9, 0.9, 0.6 -> 0.8000; the photo's blur 0.2 and
    ours' 0.3 in their own rows; coverage 0.5, 0.25, 0.125 of the faces -> 29.2 %; global's
    PSNR in "b", which has no global, shows '–'."""
    from stex.evaluation import summarise_frames
    from stex.reporting import table_rows

    ours = {"psnr": [30.0, 33.0, 21.0], "psnr_plain": [25.0, 27.0, 15.0], "ssim": [0.9, 0.9, 0.6],
            "blur": [0.3] * 3, "blur_input": [0.2] * 3, "coverage_faces": [0.5, 0.25, 0.125]}
    summaries = {}
    for scene, methods in (("a", {"ours": ours, "global": {"psnr": [20.0] * 3}}), ("b", {"ours": ours})):
        summaries[scene] = summarise_frames(_records(methods), methods=tuple(methods))
        summaries[scene].update(n_held_out=1, held_out_label="(1/2)", blur_interior_px=3)
    tabs = table_rows(summaries)
    rows = {}
    for name, table in tabs.items():
        label = None
        for r in table[1:]:
            label = r[0] or label
            rows[(name, label, r[1])] = r[2:]
    rec = "reconstruction"
    assert rows[(rec, "PSNR, dB (every frame)", "Ours")] == ["28.00", "28.00"]
    assert rows[(rec, "PSNR, dB (every frame)", "Kim et al. 2019 (global)")] == ["20.00", "–"]
    assert rows[(rec, "PSNR, dB (held-out frames)", "Ours (1/2)")] == ["21.00", "21.00"]
    assert rows[(rec, "Plain PSNR, dB (every frame)", "Ours")] == ["22.33", "22.33"]
    assert rows[(rec, "SSIM (every frame)", "Ours")] == ["0.8000", "0.8000"]
    assert rows[(rec, "Blurriness (Crete et al.)", "Input images")] == ["0.2000", "0.2000"]
    assert rows[(rec, "Blurriness (Crete et al.)", "Ours")] == ["0.3000", "0.3000"]
    assert rows[("coverage", "faces, %", "Ours")] == ["29.2", "29.2"]


def test_per_frame_csv_by_hand(evaluation, tiny_pipeline):
    """per_frame.csv: held_out as 0/1, NaN as an empty cell (frame 0 has no motion and no
    flicker: no predecessor), motion_mm the mean vertex displacement between the tracked meshes
    of frames t-1 and t, in mm (numpy from the tracking store)."""
    out, _ = evaluation
    with open(out / "per_frame.csv") as f:
        rows = list(csv.DictReader(f))
    V = np.asarray(open_store(tiny_pipeline["tracking"], "tracking")["vertices"][...], np.float64)
    assert {r["held_out"] for r in rows} == {"0"}
    for r in rows:
        t = int(r["frame"])
        if t == 0:
            assert r["motion_mm"] == "" and r["flicker"] == ""
        else:
            want = 1000 * np.sqrt(((V[t] - V[t - 1]) ** 2).sum(1)).mean()
            assert float(r["motion_mm"]) == pytest.approx(want, rel=1e-9) and r["flicker"] != ""


def _silhouette(frame, V):
    """(H, W) bool pixels the mesh at ``V`` covers in the colour camera (the renderer's own
    rasteriser, as in test_methods_scored_together_score_as_each_alone)."""
    cal, a = frame["cal"], frame["atlas"]
    Vc = transform_points(cal.depth_to_color, np.asarray(V, np.float64))
    return ev.render_texture(Vc, a.faces, a.texcoords, a.texcoord_faces, frame["ours"], cal.color.K,
                             cal.color.width, cal.color.height)[1]


def test_mask_iou_is_intersection_over_union(frame):
    """mask_iou is |mask & render| / |mask | render| (numpy on the render's silhouette), here with
    the mask cut to the object's lower half so that the render covers much the mask does not:
    about 0.5, where |mask & render| / |mask| would be about 1."""
    r = _silhouette(frame, frame["V"])
    rows = np.flatnonzero(frame["mask"].any(1))
    mask = frame["mask"].copy()
    mask[: (rows[0] + rows[-1]) // 2] = False
    s = score_frame(frame["ours"], frame["V"], frame["atlas"], frame["image"], mask, frame["cal"])
    want = (mask & r).sum() / (mask | r).sum()
    assert 0.3 < want < 0.7
    assert s["mask_iou"] == pytest.approx(want, abs=1e-12)


def test_coverage_area_weights_faces_by_their_area(frame):
    """coverage_area = the textured faces' share of the tracked mesh's area, areas by Heron's
    formula from the edge lengths (not the cross product the code uses); coverage_faces the
    share of faces."""
    V = np.asarray(frame["V"], np.float64)
    F = np.asarray(frame["atlas"].faces)
    has = np.asarray(frame["visible"], bool)
    a, b, c = (np.linalg.norm(V[F[:, i]] - V[F[:, (i + 1) % 3]], axis=1) for i in range(3))
    p = (a + b + c) / 2
    area = np.sqrt(np.clip(p * (p - a) * (p - b) * (p - c), 0, None))
    s = score_frame(frame["ours"], frame["V"], frame["atlas"], frame["image"], frame["mask"], frame["cal"],
                    face_has_texture=has)
    assert s["coverage_faces"] == pytest.approx(has.mean(), abs=1e-12)
    assert s["coverage_area"] == pytest.approx(area[has].sum() / area.sum(), rel=1e-6)
    assert abs(s["coverage_area"] - s["coverage_faces"]) > 1e-3   # the weighting shows here


def test_truth_blur_is_taken_inside_the_true_silhouette_too(frame):
    """blur_truth is the blur of the true render inside mask & our render's silhouette & the true
    silhouette (score_frame's docstring), here with a whole-image mask and our mesh 1 cm to the
    side of the truth, so that the true silhouette cuts the scored pixels; blur_truth_interior
    the same eroded by blur_interior_px (3)."""
    tv = truth_views(frame["true_V"], frame["true_atlas"], frame["appearance"], frame["cal"])
    V = np.asarray(frame["V"]) + [0.01, 0.0, 0.0]
    everywhere = np.ones_like(frame["mask"], bool)
    s = score_frame(frame["ours"], V, frame["atlas"], frame["image"], everywhere, frame["cal"], truth=tv)
    t_img, t_mask = tv["input"]
    r = _silhouette(frame, V)
    sel = r & t_mask
    assert (r & ~t_mask).sum() > 100
    assert s["blur_truth"] == ev.blur(t_img, sel)["blur"]
    assert s["blur_truth_interior"] == ev.blur(t_img, sel, erode_px=3)["blur"]


def test_other_method_texels_with_any_colour_count_as_texture(tiny_pipeline, tmp_path):
    """An other method's face has texture where one of its texels is not black (0, 0, 0): slices
    of pure red (255, 0, 0) in the left half of the atlas and black in the right half texture
    exactly the faces owning a texel in the left half (the template's texel map, numpy)."""
    from stex.export import write_png_slices

    template = open_store(tiny_pipeline["template"], "template")
    W = int(template.attrs["atlas_size"])
    red = np.zeros((W, W, 3), np.uint8)
    red[:, : W // 2, 0] = 255
    write_png_slices((red for _ in range(6)), range(6), tmp_path / "red")
    res = _evaluate(tiny_pipeline, tmp_path / "eval", frames=[0], others={"red": tmp_path / "red"})
    face_id = np.asarray(template["texel/face_id"][...])
    left = face_id[:, : W // 2]
    F = template["faces"].shape[0]
    assert res["frames"][0]["methods"]["red"]["coverage_faces"] == pytest.approx(
        np.unique(left[left >= 0]).size / F, abs=1e-12)
