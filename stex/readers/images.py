"""Image checks shared by the readers: JPEG decoding that refuses damaged data, and the
plausibility of a source's object mask."""

from __future__ import annotations

import contextlib
import os
import sys
import tempfile
import threading

import cv2
import numpy as np

# libjpeg's warnings that mean the pixels are not what was encoded (jerror.h: JWRN_HIT_MARKER,
# JWRN_EXTRANEOUS_DATA, JWRN_HUFF_BAD_CODE, JWRN_ARITH_BAD_CODE, JWRN_MUST_RESYNC, JWRN_JPEG_EOF,
# JWRN_BOGUS_PROGRESSION). libjpeg decodes on after them, so the image looks whole.
_DAMAGE = ("Corrupt JPEG data", "Premature end of JPEG file", "Inconsistent progression sequence")
_HARMLESS = ("Corrupt JPEG data: bad ICC marker",)  # the colour profile only, never read here

# cv2.imdecode has no way to report libjpeg's warnings: they go to the process's stderr (fd 2),
# which is redirected while libjpeg runs. One decode at a time, so that the text is its own.
_STDERR_LOCK = threading.Lock()


@contextlib.contextmanager
def _stderr_into(file):
    """Point fd 2 at ``file`` inside the block (C code's stderr included), then back."""
    with contextlib.suppress(Exception):
        sys.stderr.flush()  # Python's pending text goes out first, where it belongs
    try:
        saved = os.dup(2)
    except OSError:  # fd 2 closed: closed again afterwards
        saved = None
    os.dup2(file.fileno(), 2)
    try:
        yield
    finally:
        if saved is None:
            os.close(2)
        else:
            os.dup2(saved, 2)
            os.close(saved)


def decode_jpeg(buf, flags: int, what: str) -> np.ndarray | None:
    """Decode JPEG bytes with ``cv2.imdecode(buf, flags)``, refusing data libjpeg reports damaged.

    libjpeg decodes a JPEG whose entropy-coded data is damaged (bytes zeroed or changed on disk or
    in transfer, the end marker intact) to a full-size image, wrong from the damage on, and only
    prints "Corrupt JPEG data: ..." on stderr, which OpenCV does not pass on. Here its stderr
    is captured while it runs: a warning that the data is damaged (:data:`_DAMAGE`) raises, any
    other text is written to stderr as before. A JPEG cut short is caught earlier by its missing
    end marker (:func:`stex.readers.kinect_mkv.jpeg_ends`); this check finds damage inside.

    Args:
        buf: the JPEG file's bytes (bytes, bytearray, memoryview or a uint8 array).
        flags: ``cv2.IMREAD_*`` flags, as for ``cv2.imdecode``.
        what: the file or frame, named in the error.

    Returns:
        The image as ``cv2.imdecode`` returns it (BGR for colour flags), or None when libjpeg
        cannot decode it at all (as ``cv2.imdecode``; the caller reports that or falls back).

    Raises:
        ValueError: naming ``what`` and quoting libjpeg, when it reports damaged data.

    Thread safety: fd 2 is the process's, so decodes are serialised here, and text that other
    threads write to stderr during one (a decode takes milliseconds) reaches it after the decode.
    """
    a = np.frombuffer(buf, np.uint8) if not isinstance(buf, np.ndarray) else buf
    if a.size == 0:
        return None
    with _STDERR_LOCK, tempfile.TemporaryFile() as log:
        with _stderr_into(log):
            img = cv2.imdecode(a, flags)
        log.seek(0)
        text = log.read().decode("utf-8", "replace")
    lines = text.splitlines()
    damage = [s.strip() for s in lines if s.strip().startswith(_DAMAGE) and not s.strip().startswith(_HARMLESS)]
    rest = [s for s in lines if s.strip() not in damage]
    if rest:
        os.write(2, ("\n".join(rest) + "\n").encode())
    if damage and img is not None:
        raise ValueError(f"{what}: the JPEG's data is damaged (libjpeg: {damage[0]!r}): it decodes to a "
                         f"full-size image that is wrong from the damage on")
    return img


# The border of the image: an object filmed by one camera leaves most of it to the background
# (foreground on 0 % of the border in each of the 4 real masks of the shared samples, KillingFusion
# Snoopy frames 0, 1, 50, 51), while an inverted mask (object 0, background >= 1) covers all of it
# but where the object touches it. A half separates a mask from its inverse: of the two, at most
# one has more than half of the border as foreground.
MAX_MASK_BORDER_FOREGROUND = 0.5


def border_foreground(mask: np.ndarray) -> float:
    """Fraction of the image's outermost pixels (first and last row and column) that are
    foreground in the (H, W) bool ``mask``."""
    m = np.asarray(mask, bool)
    ring = np.concatenate([m[0], m[-1], m[1:-1, 0], m[1:-1, -1]])
    return float(ring.mean())


def check_mask(mask: np.ndarray, what: str) -> None:
    """Refuse a source's (H, W) bool object mask that is empty, all foreground, or whose
    foreground covers more than :data:`MAX_MASK_BORDER_FOREGROUND` of the image border (an
    inverted mask); ValueError naming ``what`` (the file or frame)."""
    if not mask.any():
        raise ValueError(f"{what}: the mask is empty (no pixel >= 1)")
    if mask.all():
        raise ValueError(f"{what}: the mask is all foreground (every pixel >= 1): a mask marks the object's "
                         f"pixels >= 1 and the background 0")
    border = border_foreground(mask)
    if border > MAX_MASK_BORDER_FOREGROUND:
        raise ValueError(
            f"{what}: the mask's foreground covers {100 * border:.0f} % of the image border (more than "
            f"{100 * MAX_MASK_BORDER_FOREGROUND:.0f} %) and {100 * float(mask.mean()):.0f} % of the image: an "
            f"object filmed by one camera leaves most of the border to the background. Is the mask inverted "
            f"(the object 0, the background >= 1)? The object's pixels must be >= 1, the background 0")
