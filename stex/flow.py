"""The tracker's colour terms: optical flow from an appearance model to the current image.

The appearance model (:class:`AppearanceModel`) lives in the template's atlas: texels captured
from earlier frames, rendered at the predicted pose. DIS optical flow over the object's box from
that rendering to the current image gives each visible vertex a target pixel
(:func:`flow_constraints`, forward-backward consistent only). Ours: the flow runs on grey and on
two chromaticity channels, each its own flow (:func:`flow_image`), so shading that comes and goes,
as wrinkles do, does not draw the targets off.
"""


from __future__ import annotations

import cv2
import numpy as np

from stex.atlas import texel_map
from stex.camera import project_points, transform_points
from stex.render import face_visibility, rasterize, render_textured, sample_bilinear, vertex_visibility


FLOW_CHANNELS = ("grey", "chroma", "grey+chroma")
CHROMA_DARK = 30.0   # grey levels added to R + G + B: a dark pixel's chromaticity is mostly noise


def flow_image(image: np.ndarray, channels: str = "grey+chroma") -> np.ndarray:
    """The images the flow term tracks, (Hc, Wc, C) uint8, from a colour image.

    Args:
        image: (Hc, Wc, 3) uint8 RGB, or (Hc, Wc) grey (then the one grey channel, whatever
            ``channels`` says).
        channels: "grey" (luma), "chroma" (two chromaticity channels, (R - G) / S and
            (R + G - 2 B) / S with S = R + G + B + CHROMA_DARK, mapped around 128), or both.

    Why chromaticity: shading that darkens the three channels alike (a wrinkle, a shadow, the
    camera's exposure) leaves it unchanged, while it moves grey; the flow against an appearance
    model captured frames earlier then still finds the surface (on the demo the wrinkles' stripes
    drew grey flow targets 1-2 px off, chroma 0.1-0.2 px: docs/tracking.md).
    """
    if channels not in FLOW_CHANNELS:
        raise ValueError(f"flow channels must be one of {FLOW_CHANNELS}, got {channels!r}")
    img = np.asarray(image)
    if img.ndim == 2:
        return img.astype(np.uint8)[..., None]
    if img.ndim != 3 or img.shape[2] != 3:
        raise ValueError(f"the flow term needs an (H, W, 3) RGB or (H, W) grey image, got shape {img.shape}")

    out = []
    if channels in ("grey", "grey+chroma"):
        out.append(cv2.cvtColor(np.ascontiguousarray(img, np.uint8), cv2.COLOR_RGB2GRAY))
    if channels in ("chroma", "grey+chroma"):
        f = img.astype(np.float32)
        S = f.sum(2) + CHROMA_DARK
        out.append((128 + 400 * (f[..., 0] - f[..., 1]) / S).clip(0, 255).astype(np.uint8))
        out.append((128 + 200 * (f[..., 0] + f[..., 1] - 2 * f[..., 2]) / S).clip(0, 255).astype(np.uint8))
    return np.stack(out, -1)


def _colour_view(vertices, faces, calibration):
    """Vertices in the colour camera, their raster, visibility/cos and pixel positions."""
    c = calibration.color
    Vc = transform_points(calibration.depth_to_color, vertices)
    raster = rasterize(Vc, faces, c.K, c.width, c.height)
    vis, cos = vertex_visibility(Vc, faces, c.K, raster.depth)
    uv, _ = project_points(Vc, c.K)
    return Vc, raster, vis, cos, uv


class AppearanceModel:
    """A texture of the template in a UV atlas (the flow's ``channels``: :func:`flow_image`), each
    texel filled when first seen well.

    The tracker's flow term compares the current image with this model rendered at the
    predicted pose, so flow errors do not accumulate from frame to frame: a surface point's
    appearance is fixed the first time it is seen at a good angle, and replaced only when it is
    later seen much more squarely (``refresh_margin`` of :meth:`capture`). A texel captured at
    a grazing angle, just after it came into view, is captured where the mesh is least held
    (no texel there yet to give it flow) and carries that mesh's drift into every later frame.
    """

    def __init__(self, texcoords, texcoord_faces, faces, size: int = 1024, channels: int = 1):
        self.texcoords = np.asarray(texcoords, np.float64)
        self.texcoord_faces = np.asarray(texcoord_faces, np.int64)
        self.faces = np.asarray(faces, np.int64)
        face_id, bary = texel_map(self.texcoords, self.texcoord_faces, size)
        self.texels = np.flatnonzero(face_id.ravel() >= 0)
        self.texel_face = face_id.ravel()[self.texels]
        self.texel_bary = bary.reshape(-1, 3)[self.texels].astype(np.float64)
        self.channels = channels
        self.texture = np.zeros((size, size, channels + 1), np.float32)  # the channels, then filled
        self.captured_at = np.full(size * size, -1, np.int32)  # frame position of each texel's capture
        self.captured_cos = np.zeros(size * size, np.float32)   # its face's viewing cosine then
        self.size = size
        # one texcoord per vertex (any corner's): where a vertex sits in the atlas
        self.vertex_texel = np.zeros(int(self.faces.max()) + 1, np.int64)
        px = np.clip((self.texcoords[self.texcoord_faces.ravel()] * size).astype(np.int64), 0, size - 1)
        self.vertex_texel[self.faces.ravel()] = px[:, 1] * size + px[:, 0]

    def capture(self, vertices, image, calibration, min_cos: float = 0.5, frame: int = 0,
                refresh_margin: float | None = None) -> tuple[int, int]:
        """Fill still-empty texels of faces seen at cos > ``min_cos`` from ``image``, and with
        ``refresh_margin`` also capture again the filled texels whose face is now seen at a
        cosine more than ``refresh_margin`` above the one of their capture.

        Args:
            vertices: (V, 3) float mesh in the depth camera (m).
            image: (Hc, Wc, channels) (or (Hc, Wc) with one channel) the flow's image.
            calibration: the rig (:class:`stex.camera.Calibration`).
            min_cos: least viewing cosine of a captured face.
            frame: frame position, recorded per texel (``captured_at``).
            refresh_margin: cosine margin of a re-capture (None: a texel is never replaced).

        Returns:
            (texels filled for the first time, texels captured again).
        """
        c = calibration.color
        Vc = transform_points(calibration.depth_to_color, vertices)
        depth = rasterize(Vc, self.faces, c.K, c.width, c.height).depth
        vis, cos = face_visibility(Vc, self.faces, c.K, depth, min_cos=min_cos)
        flat = self.texture.reshape(-1, self.channels + 1)
        seen = vis[self.texel_face]
        filled = flat[self.texels, -1] > 0
        new = seen & ~filled
        todo = new.copy()
        if refresh_margin is not None:
            texel_cos = cos[self.texel_face]
            todo |= seen & filled & (texel_cos > self.captured_cos[self.texels] + refresh_margin)
        if not todo.any():
            return 0, 0
        f = self.faces[self.texel_face[todo]]
        X = (self.texel_bary[todo][:, :, None] * Vc[f]).sum(1)
        uv, _ = project_points(X, c.K)
        idx = self.texels[todo]
        flat[idx, :-1] = sample_bilinear(image, uv).reshape(len(idx), self.channels)
        flat[idx, -1] = 1.0
        self.captured_at[idx] = frame
        self.captured_cos[idx] = cos[self.texel_face[todo]]
        n_new = int(new.sum())
        return n_new, int(todo.sum()) - n_new

    def render(self, vertices, calibration):
        """The model at ``vertices`` in the colour camera: (image (Hc, Wc, channels) float32, valid
        (Hc, Wc) bool)."""
        c = calibration.color
        Vc = transform_points(calibration.depth_to_color, vertices)
        img, mask = render_textured(Vc, self.faces, self.texcoords, self.texcoord_faces, self.texture,
                                    c.K, c.width, c.height)
        return img[..., :-1], mask & (img[..., -1] > 0.999)


def flow_constraints(pred_vertices, faces, model: AppearanceModel, image, mask, calibration,
                     consistency_px=1.0, min_cos=0.15, erode_px=1, prev_image=None, crop_margin_px=64):
    """Colour-image targets for vertices: optical flow (DIS, forward-backward checked) from the
    appearance model rendered at the predicted pose to the current ``image`` ((Hc, Wc, C) uint8,
    :func:`flow_image`, the model's channels; or (Hc, Wc) with one), each channel on its own.

    Only vertices seen at a good angle, away from the silhouette and from unknown model texels
    (eroded by ``erode_px``), whose flow lands inside the current ``mask``, are used. The flow is
    computed over the box of the model and the mask grown by ``crop_margin_px``.
    Returns (vertex ids (n,), target colour pixels (n, 2)); a vertex appears once per channel
    whose flow passes.
    """
    c = calibration.color
    pred, valid = model.render(pred_vertices, calibration)
    _, _, vis, cos, uv = _colour_view(pred_vertices, faces, calibration)
    kernel = np.ones((2 * erode_px + 1,) * 2, np.uint8)
    core = cv2.erode(valid.astype(np.uint8), kernel) > 0
    ids = np.flatnonzero(vis & (cos > min_cos))
    px = np.rint(uv[ids]).astype(np.int64)
    ok = (px[:, 0] >= 0) & (px[:, 0] < c.width) & (px[:, 1] >= 0) & (px[:, 1] < c.height)
    ids, px = ids[ok], px[ok]
    ids = ids[core[px[:, 1], px[:, 0]]]
    if len(ids) == 0:
        return ids, np.zeros((0, 2))
    # Flow only over the object's box (model and mask, with a margin for the motion and DIS's
    # patches): at colour-camera resolution the whole image costs several times more.
    box = valid if mask is None else (valid | mask)
    rows, cols = np.flatnonzero(box.any(1)), np.flatnonzero(box.any(0))
    y0, y1 = max(rows[0] - crop_margin_px, 0), min(rows[-1] + crop_margin_px + 1, c.height)
    x0, x1 = max(cols[0] - crop_margin_px, 0), min(cols[-1] + crop_margin_px + 1, c.width)
    crop = (slice(y0, y1), slice(x0, x1))
    img = np.atleast_3d(image)[crop]                     # (h, w, C): a grey image is one channel
    # Fill what the model does not know with the previous image (the prediction is the previous
    # pose): it moves like the object does, whereas pasting the current image there would pin the
    # flow to zero around it and make the tracker lag behind the motion.
    fill = img if prev_image is None else np.atleast_3d(prev_image)[crop]
    known = valid[crop]
    pred = np.atleast_3d(pred)[crop]
    offset = np.array([x0, y0], np.float64)
    u0 = uv[ids]
    inside = None if mask is None else cv2.erode(mask.astype(np.uint8), kernel) > 0
    dis = cv2.DISOpticalFlow_create(cv2.DISOPTICAL_FLOW_PRESET_MEDIUM)
    out_ids, out_targets = [], []
    for ch in range(img.shape[2]):
        pred8 = np.where(known, pred[..., ch], fill[..., ch]).clip(0, 255).astype(np.uint8)
        cur8 = np.ascontiguousarray(img[..., ch])
        fw = dis.calc(pred8, cur8, None)
        bw = dis.calc(cur8, pred8, None)
        u1 = u0 + sample_bilinear(fw, u0 - offset)
        back = sample_bilinear(bw, u1 - offset)
        ok = np.linalg.norm(u1 + back - u0, axis=1) < consistency_px
        ok &= (u1[:, 0] >= x0) & (u1[:, 0] <= x1 - 1) & (u1[:, 1] >= y0) & (u1[:, 1] <= y1 - 1)  # box is inside the image
        if inside is not None:
            q = np.rint(u1).astype(np.int64).clip(0, [c.width - 1, c.height - 1])
            ok &= inside[q[:, 1], q[:, 0]]
        out_ids.append(ids[ok])
        out_targets.append(u1[ok])
    return np.concatenate(out_ids), np.concatenate(out_targets)
