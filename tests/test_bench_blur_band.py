"""benchmarks/bench_blur_band.py's sweep: one mask for every image, each erosion scored alike."""

import numpy as np
from scipy.ndimage import gaussian_filter

from conftest import load_benchmark
from stex import metrics as ev


def _bench():
    return load_benchmark("bench_blur_band")


def _images():
    rng = np.random.default_rng(3)
    sharp = np.kron(rng.integers(0, 2, (12, 16)), np.ones((5, 5))) * 200.0 + 20.0
    soft = gaussian_filter(sharp, 1.5)
    mask = np.zeros(sharp.shape, bool)
    mask[8:52, 10:70] = True
    rgb = {n: np.repeat(im[..., None], 3, axis=2).astype(np.uint8) for n, im in
           (("sharp", sharp), ("soft", soft))}
    return rgb, mask


def test_blur_sweep_scores_every_image_at_every_erosion_in_one_mask():
    images, mask = _images()
    out = _bench().blur_sweep(images, mask, [0, 2, 5], h_size=11)
    assert set(out) == {(e, n) for e in (0, 2, 5) for n in images}
    for e in (0, 2, 5):
        # the soft copy reads blurrier in the same mask, whatever the erosion
        assert out[(e, "soft")] > out[(e, "sharp")] + 0.05
        for n, img in images.items():
            assert out[(e, n)] == ev.blur(img, mask, h_size=11, erode_px=e)["blur"]
    # eroding changes the crop, so the figures are not one number repeated
    assert out[(0, "sharp")] != out[(5, "sharp")]
