"""A procedural deforming object with a shape-tied, time-varying appearance (no external files).

The object is a closed, lumpy body of revolution with a protruding "nose" (so it hides parts of
itself), parameterised by (s, h): s in [0, 1) around the vertical axis, h in [0, 1] from bottom
to top. Its lower half is a rigid core; above the waist (h = 0.5) it bends, twists, squashes
and breathes (a bulge on the back), all closed-form functions of time, so any frame (or
sub-frame, for motion blur) can be generated independently and deterministically.

Its appearance is a high-frequency base texture (colour noise, random strokes, dots) modulated by
the shape, because the paper's premise is "similar shape, similar texture":

- wrinkle shading: dark horizontal stripes whose strength follows the local vertical compression
  of the surface (the concave side of the bend);
- a pose-dependent patch whose colour follows the bend parameter (red when bent one way, blue the
  other).

Object frame: metres, +y up, the body centred at the origin. Texture coordinates follow stex's
convention (u right, v down): u = s, v = 1 - h.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np
from scipy import ndimage


@dataclass(frozen=True)
class ProceduralParams:
    """Shape and motion of the procedural body (lengths in metres, angles in radians, times in s)."""

    height: float = 0.5
    radius: float = 0.15
    n_around: int = 96
    n_rings: int = 48
    bend: float = 0.5          # total bend angle amplitude
    bend_period: float = 6.0
    twist: float = 0.35        # total twist amplitude, top relative to bottom
    twist_period: float = 7.0
    squash: float = 0.06       # relative height change amplitude
    squash_period: float = 5.0
    bulge: float = 0.15        # breathing bulge amplitude, relative to radius
    bulge_period: float = 4.0
    wrinkle_depth: float = 0.6       # darkening of the stripes where the compression is full
    wrinkle_stripes: float = 28.0    # stripes from bottom to top
    patch_strength: float = 0.85     # opacity of the pose patch at full bend
    patch_size: float = 1.0          # scale of the pose patch's extent
    stretch_tint: float = 0.0        # opacity of a green tint where the surface is stretched
    seed: int = 0


def _wrap(d):
    return (d + 0.5) % 1.0 - 0.5


class ProceduralBody:
    """The deforming body: topology, texcoords, per-time vertices and true appearance."""

    def __init__(self, params: ProceduralParams = ProceduralParams()):
        self.p = params
        na, nr = params.n_around, params.n_rings
        if na < 8 or nr < 4:
            raise ValueError(f"procedural body needs n_around >= 8 and n_rings >= 4, got {na}, {nr}")
        # Vertex parameters: rings j = 1..nr-1, then the bottom and top poles.
        s = np.tile(np.arange(na) / na, nr - 1)
        h = np.repeat(np.arange(1, nr) / nr, na)
        self.vertex_s = np.concatenate([s, [0.0, 0.0]])
        self.vertex_h = np.concatenate([h, [0.0, 1.0]])
        bottom, top = (nr - 1) * na, (nr - 1) * na + 1

        # Texcoord grid has na+1 columns so the seam at s=1 gets its own column.
        def vid(j, i):  # ring j (0-based, 0..nr-2), column i (wraps)
            return j * na + (i % na)

        def tid(j, i):
            return j * (na + 1) + i

        j, i = np.meshgrid(np.arange(nr - 2), np.arange(na), indexing="ij")
        j, i = j.ravel(), i.ravel()
        # Rings go up in h; quads (j,i),(j,i+1),(j+1,i+1),(j+1,i). Outward normals need this order
        # because s increases counter-clockwise seen from +y... verified by the volume sign test.
        quad_a = np.stack([vid(j, i), vid(j + 1, i), vid(j + 1, i + 1)], 1)
        quad_b = np.stack([vid(j, i), vid(j + 1, i + 1), vid(j, i + 1)], 1)
        tq_a = np.stack([tid(j, i), tid(j + 1, i), tid(j + 1, i + 1)], 1)
        tq_b = np.stack([tid(j, i), tid(j + 1, i + 1), tid(j, i + 1)], 1)
        i = np.arange(na)
        n_grid = (nr - 1) * (na + 1)
        cap_bottom = np.stack([np.full(na, bottom), vid(0, i), vid(0, i + 1)], 1)
        cap_top = np.stack([np.full(na, top), vid(nr - 2, i + 1), vid(nr - 2, i)], 1)
        t_bottom = np.stack([n_grid + i, tid(0, i), tid(0, i + 1)], 1)
        t_top = np.stack([n_grid + na + i, tid(nr - 2, i + 1), tid(nr - 2, i)], 1)
        self.faces = np.concatenate([quad_a, quad_b, cap_bottom, cap_top]).astype(np.int32)
        self.texcoord_faces = np.concatenate([tq_a, tq_b, t_bottom, t_top]).astype(np.int32)

        gs = np.tile(np.arange(na + 1) / na, nr - 1)
        gh = np.repeat(np.arange(1, nr) / nr, na + 1)
        pole_s = (np.arange(na) + 0.5) / na
        ts = np.concatenate([gs, pole_s, pole_s])
        th = np.concatenate([gh, np.zeros(na), np.ones(na)])
        self.texcoords = np.stack([ts, 1.0 - th], 1)
        self.rest_vertices = self.surface(self.vertex_s, self.vertex_h, None)

    # -- shape ---------------------------------------------------------------------------------
    def state(self, time_s: float | None) -> dict:
        """Deformation parameters at ``time_s`` (None = rest shape)."""
        p = self.p
        if time_s is None:
            return {"bend": 0.0, "twist": 0.0, "squash": 0.0, "bulge": 0.0}
        t = float(time_s)
        return {
            "bend": p.bend * np.sin(2 * np.pi * t / p.bend_period),
            "twist": p.twist * np.sin(2 * np.pi * t / p.twist_period + 0.7),
            "squash": p.squash * np.sin(2 * np.pi * t / p.squash_period + 1.3),
            "bulge": p.bulge * 0.5 * (1 + np.sin(2 * np.pi * t / p.bulge_period + 2.1)),
        }

    def pose_parameter(self, time_s: float | None) -> float:
        """The bend, normalised to [-1, 1]; drives the pose-dependent patch colour."""
        return float(self.state(time_s)["bend"] / self.p.bend) if self.p.bend else 0.0

    def surface(self, s: np.ndarray, h: np.ndarray, time_s: float | None) -> np.ndarray:
        """Points of the surface at parameters (s, h), shape (..., 3), object frame, metres."""
        p = self.p
        st = self.state(time_s)
        s = np.asarray(s, dtype=np.float64)
        h = np.asarray(h, dtype=np.float64)
        prof = np.sqrt(np.clip(np.sin(np.pi * h), 0, None)) * (1 + 0.2 * np.sin(2 * np.pi * h + 0.5))
        lumps = 1 + 0.10 * np.sin(2 * np.pi * 3 * s) * np.sin(np.pi * h)
        nose = 0.6 * np.exp(-(_wrap(s - 0.25) ** 2 / 0.05**2 + (h - 0.62) ** 2 / 0.07**2))
        belly = st["bulge"] * np.exp(-(_wrap(s - 0.75) ** 2 / 0.08**2 + (h - 0.7) ** 2 / 0.1**2))
        r = p.radius * prof * (lumps + nose + belly)
        # The lower half is a rigid core (like legs and hips); the upper half twists, squashes
        # and bends above the waist at h = 0.5, so the object has a well-defined rigid part.
        up = np.clip(h - 0.5, 0, None)
        ang = 2 * np.pi * s + st["twist"] * 2 * up
        sq = 1 + st["squash"]
        w = np.clip(up / 0.15, 0, 1)  # squash fades in above the waist
        thin = 1 + w * (1 / np.sqrt(sq) - 1)
        x = r * np.cos(ang) * thin
        z = r * np.sin(ang) * thin
        y = p.height * (np.minimum(h, 0.5) - 0.5 + up * sq)
        kappa = st["bend"] / (0.5 * p.height)
        if abs(kappa) > 1e-9:
            yy = np.clip(y, 0, None)
            rho = 1.0 / kappa - x
            theta = kappa * yy
            x = np.where(y > 0, 1.0 / kappa - rho * np.cos(theta), x)
            y = np.where(y > 0, rho * np.sin(theta), y)
        return np.stack([x, y, z], axis=-1)

    def vertices(self, time_s: float | None) -> np.ndarray:
        """(V, 3) float64 vertices at ``time_s`` in the object frame."""
        return self.surface(self.vertex_s, self.vertex_h, time_s)

    # -- appearance ----------------------------------------------------------------------------
    def base_texture(self, size: int) -> np.ndarray:
        """(size, size, 3) float32 base albedo in [0, 1]: seeded colour noise, random strokes, dots."""
        rng = np.random.default_rng(self.p.seed)
        tex = np.zeros((size, size, 3), np.float32)
        for scale, amp in ((size / 8, 0.5), (size / 32, 0.3)):
            # Smooth noise is generated coarse (about 4 samples per sigma) and upsampled: the
            # same look at any size without a huge blur kernel.
            n = max(8, int(round(4 * size / scale)))
            noise = rng.standard_normal((n, n, 3)).astype(np.float32)
            noise = ndimage.gaussian_filter(noise, (scale * n / size, scale * n / size, 0), mode="wrap")
            # Pad periodically before upsampling so the texture stays seamless across u = 0/1.
            f = size / n
            big = cv2.resize(np.pad(noise, ((2, 2), (2, 2), (0, 0)), mode="wrap"),
                             (round((n + 4) * f),) * 2, interpolation=cv2.INTER_CUBIC)
            o = round(2 * f)
            noise = big[o:o + size, o:o + size]
            noise /= noise.std() + 1e-9
            tex += amp * noise
        tex = 0.55 + 0.18 * tex
        img = (tex * 255).clip(0, 255).astype(np.uint8)
        # Irregular high-frequency detail (random strokes and dots) rather than a regular grid:
        # periodic patterns alias under motion and defeat optical flow and texture alignment.
        n_strokes = max(100, size * size // 600)
        p0 = rng.uniform(0, size, (n_strokes, 2))
        ang = rng.uniform(0, np.pi, n_strokes)
        length = rng.uniform(size / 200, size / 40, n_strokes)
        p1 = p0 + length[:, None] * np.stack([np.cos(ang), np.sin(ang)], 1)
        shade = rng.uniform(0.0, 0.35, n_strokes)
        width = max(1, size // 512)
        for a, b, g in zip(p0.astype(int), p1.astype(int), shade):  # drawn once per scene
            cv2.line(img, (int(a[0]), int(a[1])), (int(b[0]), int(b[1])), (float(g) * 255,) * 3, width, cv2.LINE_AA)
        n_dots = max(50, size * size // 1500)
        cx, cy = rng.uniform(0, size, n_dots), rng.uniform(0, size, n_dots)
        rad = rng.uniform(size / 400, size / 120, n_dots)
        col = rng.uniform(0.05, 0.95, (n_dots, 3))
        for x, y, r, c in zip(cx, cy, rad, col):
            cv2.circle(img, (int(x), int(y)), max(1, int(r)), tuple(float(v) * 255 for v in c), -1, cv2.LINE_AA)
        return img.astype(np.float32) / 255.0

    def compression(self, s: np.ndarray, h: np.ndarray, time_s: float | None, signed: bool = False) -> np.ndarray:
        """Relative vertical compression (0 = none, 0.2 = 20 % shorter) of the surface at (s, h);
        ``signed``: not clipped at 0, so a stretched surface is negative (-0.1 = 10 % longer)."""
        dh = 1e-3
        def dlen(t):
            return np.linalg.norm(self.surface(s, h + dh, t) - self.surface(s, h - dh, t), axis=-1)
        rest = dlen(None)
        c = 1.0 - dlen(time_s) / np.maximum(rest, 1e-12)
        return np.clip(c, -1.0, 1.0) if signed else np.clip(c, 0.0, 1.0)

    def appearance(self, time_s: float | None, size: int, base: np.ndarray | None = None) -> np.ndarray:
        """(size, size, 3) uint8 true texture at ``time_s`` in this body's texcoords."""
        if base is None:
            base = self.base_texture(size)
        c = (np.arange(size) + 0.5) / size
        s, v = np.meshgrid(c, c)
        h = 1.0 - v
        # The compression field is smooth: evaluated on at most 512^2 texel centres and
        # upsampled (cv2 aligns texel centres), which makes a large slice much cheaper.
        n = min(size, 512)
        cc = (np.arange(n) + 0.5) / n
        cs, cv_ = np.meshgrid(cc, cc)
        p = self.p
        signed = self.compression(cs, 1.0 - cv_, time_s, signed=True).astype(np.float32)
        comp, stretch = np.clip(signed, 0, 1), np.clip(-signed, 0, 1)
        if n != size:
            comp = cv2.resize(comp, (size, size), interpolation=cv2.INTER_LINEAR)
            stretch = cv2.resize(stretch, (size, size), interpolation=cv2.INTER_LINEAR)
        wrinkle = np.clip(comp / 0.15, 0, 1) * (0.5 + 0.5 * np.cos(2 * np.pi * p.wrinkle_stripes * h))
        tex = base * (1 - p.wrinkle_depth * wrinkle)[..., None]
        if p.stretch_tint > 0:
            # the convex side of a bend: a tint that grows with the stretch
            k = (p.stretch_tint * np.clip(stretch / 0.15, 0, 1))[..., None]
            tex = tex * (1 - k) + np.array([0.2, 0.85, 0.3], np.float32) * k
        pose = self.pose_parameter(time_s)
        ps = p.patch_size
        patch = np.exp(-(_wrap(s - 0.02) ** 2 / (0.06 * ps) ** 2 + (h - 0.33) ** 2 / (0.07 * ps) ** 2))
        tint = np.array([0.92, 0.18, 0.15] if pose >= 0 else [0.15, 0.3, 0.92], np.float32)
        k = (p.patch_strength * abs(pose) * patch)[..., None]
        tex = tex * (1 - k) + tint * k
        return (tex * 255 + 0.5).clip(0, 255).astype(np.uint8)
