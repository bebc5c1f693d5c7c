"""benchmarks/bench_blur_resample.py's round trip: photo -> texels -> pixels."""

import numpy as np
import pytest
from scipy.ndimage import gaussian_filter

from conftest import load_benchmark
from stex import metrics as ev


def _bench():
    return load_benchmark("bench_blur_resample")


def _photo():
    rng = np.random.default_rng(5)
    g = gaussian_filter(rng.uniform(0, 255, (60, 80)), 1.0)
    return np.repeat(g[..., None], 3, axis=2).astype(np.float32)


def test_roundtrip_keeps_the_size_and_softens_less_with_denser_texels_and_a_sharper_kernel():
    b, photo = _bench(), _photo()
    out = {(k, s): b.texture_roundtrip(photo, s, k, seed=1) for k in ("bilinear", "bicubic") for s in (1.0, 3.0)}
    assert all(r.shape == photo.shape for r in out.values())
    blur = {k: ev.blur(r, None)["blur"] for k, r in out.items()}
    assert blur[("bicubic", 3.0)] < blur[("bicubic", 1.0)]
    assert blur[("bicubic", 1.0)] < blur[("bilinear", 1.0)]
    err = {k: np.abs(r - photo)[5:-5, 5:-5].mean() for k, r in out.items()}
    assert err[("bicubic", 3.0)] < err[("bilinear", 1.0)]


def test_roundtrip_refuses_an_unknown_kernel_and_a_density_of_zero():
    b, photo = _bench(), _photo()
    with pytest.raises(ValueError, match="kernel"):
        b.texture_roundtrip(photo, 2.0, "nearest")
    with pytest.raises(ValueError, match="density"):
        b.texture_roundtrip(photo, 0.0, "bicubic")
