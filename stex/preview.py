"""Pictures for people: small montages written beside the artifacts (and into the report)."""

from __future__ import annotations

import cv2
import numpy as np


def label_image(img: np.ndarray, text: str) -> np.ndarray:
    """A copy of the (H, W, 3) uint8 RGB ``img`` with ``text`` in white on a black band along
    its top (22 px)."""
    out = img.copy()
    cv2.rectangle(out, (0, 0), (out.shape[1], 22), (0, 0, 0), -1)
    cv2.putText(out, text, (4, 16), cv2.FONT_HERSHEY_SIMPLEX, 0.5, (255, 255, 255), 1, cv2.LINE_AA)
    return out


def mask_overlay(color: np.ndarray, mask: np.ndarray, title: str = "") -> np.ndarray:
    """(H, W, 3) uint8 RGB: the image, background dimmed, mask outline in green."""
    out = color.astype(np.float32)
    out[~mask] *= 0.45
    out = out.astype(np.uint8)
    contours, _ = cv2.findContours(mask.astype(np.uint8), cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_NONE)
    cv2.drawContours(out, contours, -1, (0, 255, 0), 2)
    return label_image(out, title) if title else out


def montage(images: list[np.ndarray], columns: int = 3, width: int = 960) -> np.ndarray:
    """Tile equally-sized (H, W, 3) uint8 images into one image ``width`` pixels wide."""
    if not images:
        raise ValueError("montage needs at least one image")
    h, w = images[0].shape[:2]
    columns = min(columns, len(images))
    rows = -(-len(images) // columns)
    grid = np.zeros((rows * h, columns * w, 3), np.uint8)
    for k, im in enumerate(images):
        r, c = divmod(k, columns)
        grid[r * h:(r + 1) * h, c * w:(c + 1) * w] = im
    scale = width / grid.shape[1]
    return cv2.resize(grid, (width, max(1, round(grid.shape[0] * scale))), interpolation=cv2.INTER_AREA)


def pyplot():
    """matplotlib.pyplot on the file-only Agg backend (imported on first use: figures only)."""
    import matplotlib  # loaded on first use: only the figures need it, and it loads slowly

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt  # after use("Agg"), so no display backend is tried

    return plt


def write_png(path, rgb: np.ndarray) -> None:
    """Write the (H, W, 3) uint8 RGB ``rgb`` as a PNG at ``path`` (OSError when it cannot)."""
    if not cv2.imwrite(str(path), np.ascontiguousarray(rgb[..., ::-1])):
        raise OSError(f"cannot write image {path}")
