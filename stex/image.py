"""Grey levels of colour images (BT.601 weights, as OpenCV): 0.299 R + 0.587 G + 0.114 B.

Two functions, because the stages that use them were tuned with two different computations that
do not give the same float64 values: :func:`grey` (a matrix product in float64, for the SSIM of
the dynamism) and :func:`grey_float32` (channel by channel in float64, rounded to float32, for the
observations' samples). Both agree once rounded to float32, but the float64 values differ in the
last bits for some colours, and the SSIM is computed from the float64 ones.
"""

from __future__ import annotations

import numpy as np

__all__ = ["grey", "grey_float32"]

_GREY = np.array([0.299, 0.587, 0.114], np.float64)


def grey(image) -> np.ndarray:
    """(H, W) float64 grey levels of an (H, W, 3) RGB or (H, W) image, in the input's units
    (0..255 for uint8, unchanged scale for float): 0.299 R + 0.587 G + 0.114 B."""
    a = np.asarray(image)
    if a.ndim == 2:
        return a.astype(np.float64)
    if a.ndim != 3 or a.shape[2] != 3:
        raise ValueError(f"image must be (H, W, 3) RGB or (H, W) grey, got {a.shape}")
    return a.astype(np.float64) @ _GREY


def grey_float32(image: np.ndarray) -> np.ndarray:
    """(H, W) float32 luma (ITU-R 601 weights, 0..255) of an (H, W, 3) uint8 RGB image."""
    img = np.asarray(image)
    if img.ndim != 3 or img.shape[2] != 3:
        raise ValueError(f"image must be (H, W, 3) RGB, got shape {img.shape}")
    return (0.299 * img[..., 0] + 0.587 * img[..., 1] + 0.114 * img[..., 2]).astype(np.float32)
