import os
from pathlib import Path

import pytest
import yaml

from stex.config import load_config

REPO = Path(__file__).resolve().parents[1]


def load_benchmark(name: str):
    """benchmarks/<name>.py as a module (benchmarks/ is a folder of scripts, not a package)."""
    import importlib.util

    spec = importlib.util.spec_from_file_location(name, REPO / "benchmarks" / f"{name}.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def data_samples() -> Path:
    """The shared third-party samples (../shared/data_samples or $STEX_DATA_SAMPLES)."""
    env = os.environ.get("STEX_DATA_SAMPLES")
    return Path(env) if env else REPO.parent / "shared" / "data_samples"


def real_tracking_pairs(samples: Path) -> list[tuple[str, "np.ndarray", list, list]]:
    """The real depth frame pairs of the tracking checks, from the shared samples: (name, depth K
    (3, 3), depths [2 x (H, W) float64 metres], object masks [2 x (H, W) bool]). KillingFusion's
    Snoopy, frames 50 and 51, with its own masks; DeepDeform seq017, frames 300 and 600, masked to
    the largest connected region of depth within 2.05 m."""
    import cv2
    import numpy as np
    from scipy import ndimage

    sd = samples / "killingfusion_snoopy" / "frames_000050_000051"
    Ks = np.array([[517.0, 0, 320], [0, 517.0, 240], [0, 0, 1]])
    pairs = [("KillingFusion Snoopy, frames 50 -> 51", Ks,
              [cv2.imread(str(sd / f"snoopy_depth_0000{i}.png"), -1) / 1000.0 for i in (50, 51)],
              [cv2.imread(str(sd / f"snoopy_omask_0000{i}.png"), 0) > 0 for i in (50, 51)])]
    dd = samples / "deepdeform_neuraltracking" / "example_data" / "test" / "seq017"
    Kd = np.loadtxt(dd / "intrinsics.txt")[:3, :3]
    ds = [cv2.imread(str(dd / "depth" / f"000{i}.png"), -1) / 1000.0 for i in (300, 600)]

    def largest(m):
        lab, n = ndimage.label(m)
        return lab == (np.argmax(np.bincount(lab.ravel())[1:]) + 1)
    pairs.append(("DeepDeform seq017, frames 300 -> 600", Kd, ds, [largest((d > 0) & (d < 2.05)) for d in ds]))
    return pairs


def real_pair_fits(samples: Path, **params) -> list[tuple[str, float, float, float]]:
    """For each of :func:`real_tracking_pairs`: a template from the first frame's depth (stride 2)
    tracked to the second without flow (``gn_iterations`` 8 unless ``params`` say otherwise), and
    the mean clipped depth difference (m) at the second frame over the pixels mesh and depth both
    cover: (name, template as it is, rigid fit (``rigid_only``), tracked)."""
    from stex.template import template_from_depth
    from stex.frame_fit import depth_residual
    from stex.tracking import Observation, TrackParams, depth_target, track_sequence

    out = []
    for name, K, depths, masks in real_tracking_pairs(samples):
        V, F = template_from_depth(depths[0], K, masks[0], stride=2)
        targets = [depth_target(d, K, m) for d, m in zip(depths, masks)]
        fits = []
        for rigid_only in (True, False):
            p = TrackParams(**{"gn_iterations": 8, **params, "rigid_only": rigid_only, "w_flow": 0.0})
            *_, (_, Vb, _) = track_sequence(V, F, [Observation(t) for t in targets], p, progress=False)
            fits.append(depth_residual(Vb, F, targets[1], union=False))
        out.append((name, depth_residual(V, F, targets[1], union=False), *fits))
    return out


# the tiny scene's source.synthetic settings, in a file so that benchmarks read them without pytest
TINY_SYNTHETIC = yaml.safe_load((REPO / "tests" / "tiny_synthetic.yaml").read_text())


def tiny_workflow_config(results) -> dict:
    """A config file's content for the whole workflow on the tiny scene in one frame block, with
    given meshes and texture coordinates at Φ (every stage, each job a few seconds), into
    ``results``."""
    return {"scene": "tiny", "results": str(results), "frame_block": 6,
            "source": {"kind": "synthetic", "synthetic": TINY_SYNTHETIC},
            "template": {"atlas_size": 256}, "tracking": {"mode": "given"},
            "observations": {"coordinates": "projected"}}


def pytest_terminal_summary(terminalreporter):
    """What tests recorded with ``record_property("summary", text)`` (e.g. the jobs a real SLURM
    cluster saw, tests/test_slurm_real.py), printed at the end of the run also under -q and from
    xdist workers, so that a CI log shows it."""
    lines = [value for report in terminalreporter.stats.get("passed", [])
             for name, value in getattr(report, "user_properties", ()) if name == "summary"]
    if lines:
        terminalreporter.write_sep("-", "recorded by the tests")
        for text in lines:
            terminalreporter.write_line(text)


def grid_atlas(n: int = 9):
    """A flat n x n vertex grid covering [0.05, 0.95]^2 of an atlas whose texcoords are the
    vertices: (texcoords (n², 2) float64, faces (2 (n-1)², 3) int32)."""
    import numpy as np

    g = np.linspace(0.05, 0.95, n)
    u, v = np.meshgrid(g, g)
    tc = np.stack([u.ravel(), v.ravel()], 1)
    faces = []
    for r in range(n - 1):
        for c in range(n - 1):
            a = r * n + c
            faces += [[a, a + 1, a + n + 1], [a, a + n + 1, a + n]]
    return tc, np.array(faces, np.int32)


@pytest.fixture(scope="session")
def demo_config() -> dict:
    """The embedded default scene's validated config."""
    return load_config(REPO / "config" / "config.yaml")


def tiny_scene_config(**sections) -> dict:
    """The validated config of the tiny synthetic scene (fast to render; blocks of 4 frames),
    schema defaults elsewhere; ``sections`` override whole config keys (e.g. template=...)."""
    return load_config(overrides={"scene": "tiny", "frame_block": 4,
                                  "source": {"kind": "synthetic", "synthetic": TINY_SYNTHETIC},
                                  **sections})


@pytest.fixture
def tiny_config() -> dict:
    """A tiny synthetic scene (fast to render) with schema defaults."""
    return tiny_scene_config()


def run_stages(cfg: dict, d) -> dict:
    """Run ingest, masks, template, 'given' tracking and projection of ``cfg`` into folder ``d``
    through the real stage writers (what the workflow runs, without Snakemake). Returns the
    store paths: scene, frames, truth, masks (lists per block), template, tracking, projection."""
    from stex.stages.ingest import write_frames_block, write_scene
    from stex.io import open_store
    from stex.stages.masks import write_masks_block
    from stex.stages.projection import write_projection
    from stex.stages.template import write_template
    from stex.stages.tracking import write_tracking

    write_scene(cfg["source"], cfg["frame_block"], d / "scene.zarr")
    scene = open_store(d / "scene.zarr", "scene")
    frames, truth, masks = [], [], []
    for b, (start, stop) in enumerate(scene.attrs["frame_blocks"]):
        frames.append(d / f"frames_{b}.zarr")
        truth.append(d / f"truth_{b}.zarr")
        masks.append(d / f"masks_{b}.zarr")
        write_frames_block(cfg["source"], start, stop, frames[-1], truth[-1])
        write_masks_block(d / "scene.zarr", frames[-1], cfg["masks"], masks[-1])
    write_template(d / "scene.zarr", cfg["template"], d / "template.zarr")
    write_tracking(d / "scene.zarr", d / "template.zarr", frames, masks,
                   dict(cfg["tracking"], mode="given"), d / "tracking.zarr")
    write_projection(d / "tracking.zarr", d / "template.zarr", d / "scene.zarr", masks,
                     cfg["projection"], d / "projection.zarr")
    return {"scene": d / "scene.zarr", "frames": frames, "truth": truth, "masks": masks,
            "template": d / "template.zarr", "tracking": d / "tracking.zarr", "projection": d / "projection.zarr"}


@pytest.fixture(scope="session")
def tiny_pipeline(tmp_path_factory) -> dict:
    """:func:`run_pipeline` of the tiny scene with a 256² atlas, once per test process; tests
    read its stores and write their own into their own folders."""
    return run_pipeline(tiny_scene_config(template={"atlas_size": 256}), tmp_path_factory.mktemp("tiny"))


def run_pipeline(cfg: dict, d) -> dict:
    """:func:`run_stages` then poses, observations (at Φ), tables, labeling, volume, correction
    and the global texture (at Φ, the tables' source_stride) through the real stage writers.
    Returns the store paths of :func:`run_stages` plus poses, observations, tables, labels,
    volume and corrected (lists per block) and global_texture."""
    from stex.stages.global_texture import write_global_texture
    from stex.stages.correction import write_corrected
    from stex.io import open_store
    from stex.stages.labeling import write_labels
    from stex.stages.observations import write_observations
    from stex.stages.poses import write_pose_table
    from stex.stages.data_term import write_data_term
    from stex.stages.volume import write_volume

    P = run_stages(cfg, d)
    P["poses"] = d / "poses.zarr"
    write_pose_table(P["tracking"], P["poses"], cfg["poses"], array="vertices", faces=P["template"],
                     visibility=P["projection"], source_stride=cfg["data_term"]["source_stride"])
    P["observations"] = d / "observations.zarr"
    write_observations(P["template"], P["tracking"], P["projection"], P["projection"], P["frames"],
                       cfg["observations"], P["observations"])
    blocks = open_store(P["scene"], "scene").attrs["frame_blocks"]
    P["data_term"] = [d / f"data_term_{b}.zarr" for b in range(len(blocks))]
    for path, (start, stop) in zip(P["data_term"], blocks):
        write_data_term(P["scene"], P["template"], P["tracking"], P["poses"], P["observations"],
                     [start, stop], cfg["data_term"], path)
    P["labels"] = d / "labels.zarr"
    write_labels(P["observations"], P["data_term"], P["template"], cfg["labeling"], P["labels"],
                 projection_path=P["projection"])
    P["volume"] = [d / f"volume_{b}.zarr" for b in range(len(blocks))]
    P["corrected"] = [d / f"corrected_{b}.zarr" for b in range(len(blocks))]
    for b, (start, stop) in enumerate(blocks):
        write_volume(P["template"], P["labels"], P["projection"], P["frames"], [start, stop],
                     cfg["volume"], P["volume"][b])
        write_corrected(P["template"], P["volume"][b], cfg["correction"], P["corrected"][b])
    P["global_texture"] = d / "global_texture.zarr"
    write_global_texture(P["scene"], P["frames"], P["template"], P["projection"], P["projection"],
                         P["global_texture"],
                         dict(cfg["global_texture"], source_stride=cfg["data_term"]["source_stride"]))
    return P


def results_folder(P: dict, root) -> "Path":
    """The stores of :func:`run_pipeline` (``P``) laid out as a workflow run's
    ``results/<scene>`` (symlinks), as ``stex export``, ``stex view`` and the evaluation read it."""
    root = Path(root)
    root.mkdir(parents=True)
    for name in ("scene", "template", "tracking", "projection", "labels", "observations",
                 "global_texture"):
        (root / f"{name}.zarr").symlink_to(P[name])
    for kind in ("frames", "masks", "truth", "data_term", "volume", "corrected"):
        (root / kind).mkdir()
        for b, path in enumerate(P[kind]):
            (root / kind / f"block_{b:04d}.zarr").symlink_to(path)
    return root
