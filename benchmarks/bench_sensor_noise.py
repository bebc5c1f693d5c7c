"""Calibrate the synthetic colour noise against real RGB-D colour frames (issue 7's blur criterion).

The Crete blur metric reads fine-scale noise as sharpness, so the inputs' blur depends on how much
noise the synthetic camera adds. This measures, with one estimator (``stex.metrics.noise_sigma``:
Immerkær 1996 on the 30 % flattest pixels) and at 640 px width:

- the real colour frames in ``../shared/data_samples`` (an Azure Kinect MJPG recording, DeepDeform
  and KillingFusion "Snoopy" frames; the Azure frame is resized to 640 px wide, INTER_AREA);
- renders of a synthetic scene (``--scene demo`` or ``fox``: config/config.yaml plus the scene
  file) at each ``--sigma`` of its Gaussian sensor noise, on ``--frames``.

    python benchmarks/bench_sensor_noise.py [--scene demo] [--sigma 0 0.5 1 2] [--frames 0 30 60]
"""

from __future__ import annotations

import argparse
import copy
import sys
from pathlib import Path

import cv2
import numpy as np

try:
    import stex  # noqa: F401
except ImportError:  # run from a source checkout without installing the package
    sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from stex.config import load_config
from stex.metrics import noise_sigma
from stex.synth.scene import SyntheticScene

REPO = Path(__file__).resolve().parents[1]
SAMPLES = REPO.parent / "shared" / "data_samples"
SCENES = {"demo": [], "fox": ["config/scenes/fox.yaml"]}


def real_frames():
    """(name, RGB uint8 image at 640 px width) of the shared real colour frames that exist."""
    mkv = SAMPLES / "azure_kinect_pyk4a" / "recording.mkv"
    if mkv.exists():
        import av

        with av.open(str(mkv)) as container:
            frame = next(container.decode(video=0)).to_ndarray(format="rgb24")
        h = int(round(frame.shape[0] * 640 / frame.shape[1]))
        yield "Azure Kinect MJPG 720p (resized)", cv2.resize(frame, (640, h), interpolation=cv2.INTER_AREA)
    for pattern, name in (("deepdeform_neuraltracking/**/color/*.jpg", "DeepDeform"),
                          ("killingfusion_snoopy/**/color_*.png", "KillingFusion Snoopy")):
        for f in sorted(SAMPLES.glob(pattern)):
            yield f"{name} {f.name}", cv2.imread(str(f))[..., ::-1]


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scene", choices=sorted(SCENES), default="demo")
    ap.add_argument("--sigma", type=float, nargs="+", default=[0.0, 0.25, 0.5, 0.6, 0.75, 1.0, 2.0])
    ap.add_argument("--frames", type=int, nargs="+", default=[0, 20, 39])
    a = ap.parse_args()
    print("real colour frames (640 px wide):")
    real = []
    for name, img in real_frames():
        real.append(noise_sigma(img)["sigma"])
        print(f"  {name:44s} {img.shape[1]}x{img.shape[0]}  {real[-1]:.2f}")
    if real:
        print(f"  median {np.median(real):.2f}, range {min(real):.2f}-{max(real):.2f} ({len(real)} frames)")
    else:
        print(f"  none found under {SAMPLES}")
    cfg = load_config(REPO / "config" / "config.yaml", *[REPO / f for f in SCENES[a.scene]])
    syn = cfg["source"]["synthetic"]
    print(f"synthetic '{a.scene}' ({syn['color']['width']} px wide; motion blur "
          f"{'on' if syn['degradations']['motion_blur']['enabled'] else 'off'}; scene file sigma "
          f"{syn['degradations']['sensor_noise']['sigma'] if syn['degradations']['sensor_noise']['enabled'] else 0}), "
          f"frames {a.frames}:")
    for sigma in a.sigma:
        s = copy.deepcopy(syn)
        s["degradations"]["sensor_noise"] = {"enabled": sigma > 0, "sigma": sigma}
        scene = SyntheticScene(s)
        vals = [noise_sigma(scene.render_frame(t).color)["sigma"] for t in a.frames]
        print(f"  sensor_noise sigma {sigma:4.2f}: {np.mean(vals):.2f}  (per frame {', '.join(f'{v:.2f}' for v in vals)})")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
