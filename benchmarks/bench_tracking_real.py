"""The tracker on real depth frame pairs: how well a template built from the first frame's depth
fits the second frame, left where it is, rigidly tracked (``tracking.rigid_only``) and tracked
with the deformation graph (mean clipped depth difference over the pixels mesh and depth both
cover, mm; no optical flow). The pairs (KillingFusion's Snoopy, DeepDeform seq017) come from the
shared samples; ``tests/test_tracking.py::test_real_pairs_fit_better_than_rigid`` asserts the order.

    python benchmarks/bench_tracking_real.py [--samples ../shared/data_samples] [--params JSON]
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO / "tests"))   # the pairs and the fit are the test's own (conftest)
try:
    import stex  # noqa: F401
except ImportError:  # run from a source checkout without installing the package
    sys.path.insert(0, str(REPO))

from conftest import data_samples, real_pair_fits  # noqa: E402


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--samples", type=Path, default=data_samples())
    ap.add_argument("--params", default="{}", help="JSON overrides of the tracking settings (TrackParams fields)")
    args = ap.parse_args()
    if not (args.samples / "killingfusion_snoopy").is_dir():
        raise SystemExit(f"no shared samples at {args.samples} (--samples)")
    print("| pair | template as it is | rigid fit | tracked |\n|---|---|---|---|")
    for name, before, rigid, tracked in real_pair_fits(args.samples, **json.loads(args.params)):
        print(f"| {name} | {1000 * before:.2f} mm | {1000 * rigid:.2f} mm | {1000 * tracked:.2f} mm |")
    return 0


if __name__ == "__main__":
    sys.exit(main())
