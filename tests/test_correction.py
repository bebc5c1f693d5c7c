"""Gradient-domain colour correction (stex.correction): label steps, seams, AMG reuse, temporal."""
import numpy as np
import pytest

import stex.correction as C
from stex.correction import CorrectionSystem, interior_change, label_boundary_step, seam_step
from stex.atlas import texel_map

W = 256


@pytest.fixture(scope="module")
def quad():
    V = np.array([[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0]], float)
    F = np.array([[0, 2, 1], [0, 3, 2]], np.int32)
    tc = np.array([[.05, .05], [.95, .05], [.95, .95], [.05, .95]], np.float32)
    face, _ = texel_map(tc, F, W)
    return V, F, tc, F.copy(), face


def _two_labels(face, offset=20.0):
    cov = face >= 0
    rr, cc = np.mgrid[0:W, 0:W]
    base = 100 + 40 * np.sin(rr / 9.0)[..., None] * np.array([1, .5, .2]) + 30 * np.cos(cc / 13.0)[..., None]
    lm = np.where(cov, (cc >= W // 2).astype(np.int32), -1).astype(np.int32)
    img = base + np.where(lm[..., None] == 1, offset, 0.0)
    img = np.clip(np.round(img), 0, 255).astype(np.uint8)
    img[~cov] = 0
    return img, lm


@pytest.mark.parametrize("factor", [1, 2])
def test_label_step_falls_and_interiors_stay(quad, factor):
    V, F, tc, tf, face = quad
    img, lm = _two_labels(face)
    cs = CorrectionSystem(face, tc, tf, F, factor=factor, screen_length=1 / 16, gutter_px=2)
    out = cs.correct(img, lm)
    before, after = label_boundary_step(img, lm), label_boundary_step(out, lm)
    assert before > 18
    assert after <= 0.4 * before, (before, after)  # falls by >= 60 %
    assert interior_change(img, out, lm, margin=16) <= 2.0
    assert out.dtype == np.uint8 and out.shape == img.shape


@pytest.mark.parametrize("factor", [1, 2])
def test_keep_own_frame_moves_only_the_borrowed_texels(quad, factor):
    V, F, tc, tf, face = quad
    img, lm = _two_labels(face)                 # label 1 is 20 levels brighter than label 0
    cs = CorrectionSystem(face, tc, tf, F, factor=factor, screen_length=1 / 16, gutter_px=2)
    own = lm == 0
    out = cs.correct(img, lm, frame=0)
    np.testing.assert_array_equal(out[own], img[own])           # the observed texels as they were
    before, after = label_boundary_step(img, lm), label_boundary_step(out, lm)
    assert after <= 0.4 * before, (before, after)
    # the whole step went to the borrowed side: next to the boundary it moved by about -20
    h = W // 2
    rows = np.flatnonzero(own[:, h - 1] & (lm[:, h] == 1))
    shift = out[rows, h].astype(float) - img[rows, h]
    assert -22 < shift.mean() < -14, shift.mean()
    # without a frame (or the slice's frame unused) the screened solve of both sides is unchanged
    free = CorrectionSystem(face, tc, tf, F, factor=factor, screen_length=1 / 16, gutter_px=2,
                            keep_own_frame=False)
    np.testing.assert_array_equal(cs.correct(img, lm), free.correct(img, lm))
    np.testing.assert_array_equal(cs.correct(img, lm, frame=5), free.correct(img, lm, frame=5))
    assert np.abs(free.correct(img, lm, frame=0)[own].astype(int) - img[own]).max() > 3


def test_ramp_across_a_label_boundary_keeps_its_slope(quad):
    V, F, tc, tf, face = quad
    cov = face >= 0
    cc = np.mgrid[0:W, 0:W][1]
    lm = np.where(cov, (cc >= W // 2).astype(np.int32), -1).astype(np.int32)
    # a colour ramp of 1 grey level per texel along the columns; source 1 is 20 levels darker
    img = np.clip(np.where(cov, cc - 5.0 - 20.0 * (lm == 1), 0), 0, 255)[..., None].repeat(3, 2).astype(np.uint8)
    rows = np.flatnonzero(cov[:, W // 2 - 2] & cov[:, W // 2 + 1])
    steps = {}
    for rule in C.BOUNDARY_GRADIENTS:
        cs = CorrectionSystem(face, tc, tf, F, screen_length=1 / 16, gutter_px=2, boundary_gradient=rule)
        out = cs.correct(img, lm).astype(np.float64)[rows, :, 0]
        h = W // 2
        steps[rule] = (out[:, h] - out[:, h - 1]).mean()            # the pair across the boundary
        # same label: the ramp stays a ramp (flatter near the boundary, where the removed step's
        # correction spreads with its own slope)
        assert 0.3 < ((out[:, h - 1] - out[:, h - 3]) + (out[:, h + 2] - out[:, h])).mean() / 4 < 1.1
    assert abs(steps["one_sided"] - 1.0) < 0.25    # the 20-level step gone, the ramp's slope kept
    assert steps["zero"] < 0.25                    # the slope lost with the step
    with pytest.raises(ValueError, match="boundary_gradient"):
        CorrectionSystem(face, tc, tf, F, boundary_gradient="mean")


def test_single_label_uniform_slice_is_unchanged(quad):
    V, F, tc, tf, face = quad
    img, lm = _two_labels(face, offset=0.0)
    lm[lm >= 0] = 3
    cs = CorrectionSystem(face, tc, tf, F, screen_length=1 / 16, gutter_px=2)
    out = cs.correct(img, lm)
    cov = face >= 0
    np.testing.assert_array_equal(out[cov], img[cov])


@pytest.fixture(scope="module")
def strip():
    """Two squares sharing a 3-D edge, unwrapped into two separate charts (one seam)."""
    F = np.array([[0, 4, 1], [0, 3, 4], [1, 5, 2], [1, 4, 5]], np.int32)
    tc = np.array([[.05, .1], [.45, .1], [.45, .9], [.05, .9], [.55, .1], [.95, .1], [.95, .9], [.55, .9]], np.float32)
    tf = np.array([[0, 2, 1], [0, 3, 2], [4, 6, 5], [4, 7, 6]], np.int32)
    Wt = 128
    face, _ = texel_map(tc, tf, Wt)
    return F, tc, tf, face


def test_seam_step_disappears(strip):
    F, tc, tf, face = strip
    Wt = face.shape[0]
    cs = CorrectionSystem(face, tc, tf, F, screen_length=1 / 16, gutter_px=2)
    assert cs.graph.n_seam_edges == 1 and cs.graph.S.shape[0] > 0
    cov = face >= 0
    img = np.zeros((Wt, Wt, 3), np.uint8)
    chart = cs.chart_tex
    img[chart == 0] = 100
    img[chart == 1] = 140
    lm = np.where(cov, 0, -1).astype(np.int32)  # one label: only the seam is a discontinuity
    out = cs.correct(img, lm)
    before, after = seam_step(img, cs), seam_step(out, cs)
    assert before == pytest.approx(40.0)
    assert after < 0.15 * before, (before, after)


def test_amg_setup_is_reused_across_channels_and_slices(quad, monkeypatch):
    import pyamg

    calls = []
    orig = pyamg.ruge_stuben_solver

    def counting(*a, **k):
        calls.append(1)
        return orig(*a, **k)

    monkeypatch.setattr(pyamg, "ruge_stuben_solver", counting)
    V, F, tc, tf, face = quad
    img, lm = _two_labels(face)
    cs = CorrectionSystem(face, tc, tf, F, screen_length=1 / 16)
    cs.correct(img, lm)
    img2, lm2 = _two_labels(face, offset=-15.0)
    cs.correct(img2, np.where(lm2 >= 0, 1 - lm2, -1).astype(np.int32))
    assert len(calls) == 1
    assert cs.last_stats["iterations"] and max(cs.last_stats["iterations"]) <= 20
    # slices with texels of their own frame kept solve their own smaller system, one setup each:
    # the whole system's hierarchy is never set up for a block of them
    calls.clear()
    kept = CorrectionSystem(face, tc, tf, F, screen_length=1 / 16)
    kept.correct(img, lm, frame=0)
    kept.correct(img2, lm2, frame=1)
    assert len(calls) == 2 and "amg_setup_s" not in kept.timings
    kept.correct(img, lm, frame=7)       # a frame with no texels of its own (held out): A's
    kept.correct(img2, lm2, frame=7)
    assert len(calls) == 3 and "amg_setup_s" in kept.timings


def test_two_systems_solve_bit_for_bit_alike(quad):
    """The AMG setup has no randomness: the same atlas and slice give the same correction to
    the last bit (smoothed aggregation's random spectral-radius estimate did not, ~3e-6)."""
    V, F, tc, tf, face = quad
    img, lm = _two_labels(face)
    solves = []
    for _ in range(2):
        g = CorrectionSystem(face, tc, tf, F, screen_length=1 / 16, gutter_px=2).graph
        solves.append(g.solve(img.reshape(-1, 3)[g.index].astype(float), lm.ravel()[g.index])[0])
    assert np.abs(solves[0]).max() > 1.0
    np.testing.assert_array_equal(solves[0], solves[1])


def test_temporal_coupling_damps_borrowed_regions(quad):
    V, F, tc, tf, face = quad
    img, lm = _two_labels(face, offset=0.0)
    cov = face >= 0
    prev = img.copy()
    cur = img.astype(int)
    cur[lm == 0] += 25  # the borrowed region (label 0 at frame 1) flickers by +25
    cur = np.clip(cur, 0, 255).astype(np.uint8)
    kw = dict(screen_length=1 / 16, temporal_length=1 / 64, gutter_px=2, keep_own_frame=False)
    cs = CorrectionSystem(face, tc, tf, F, **kw)
    plain = cs.correct(cur, lm)
    damped = cs.correct(cur, lm, previous=prev, frame=1)
    inner = cov & (lm == 0)
    d_plain = np.abs(plain[inner].astype(float) - prev[inner]).mean()
    d_damped = np.abs(damped[inner].astype(float) - prev[inner]).mean()
    assert d_damped < 0.5 * d_plain, (d_plain, d_damped)
    # with the own frame's texels kept (the default) the borrowed ones are damped all the same
    kept = CorrectionSystem(face, tc, tf, F, **{**kw, "keep_own_frame": True})
    damped = kept.correct(cur, lm, previous=prev, frame=1)
    np.testing.assert_array_equal(damped[lm == 1], cur[lm == 1])
    assert np.abs(damped[inner].astype(float) - prev[inner]).mean() < 0.5 * d_plain
    # without temporal coupling the option is ignored
    cs0 = CorrectionSystem(face, tc, tf, F, **{**kw, "temporal_length": None})
    np.testing.assert_array_equal(cs0.correct(cur, lm, previous=prev, frame=1), cs0.correct(cur, lm))


def test_bad_shapes_raise(quad):
    V, F, tc, tf, face = quad
    with pytest.raises(ValueError):
        CorrectionSystem(face, tc, tf, F, factor=3)
    cs = CorrectionSystem(face, tc, tf, F, factor=4)
    with pytest.raises(ValueError):
        cs.correct(np.zeros((10, 10, 3), np.uint8), np.zeros((10, 10), np.int32))


def test_label_boundary_step_against_pairs_listed_by_hand():
    """Mean channel-mean |difference| over right/down neighbour pairs of two different labels
    (both >= 0) inside one chart, listed pair by pair."""
    rng = np.random.default_rng(5)
    im = rng.integers(0, 256, (23, 31, 3), dtype=np.uint8)
    lm = rng.integers(-1, 4, (23, 31)).astype(np.int16)
    tf = rng.integers(-1, 9, (23, 31)).astype(np.int32)
    chart = rng.integers(0, 3, 9)
    for use_chart in (False, True):
        steps = []
        for r in range(23):
            for c in range(31):
                for rr, cc in ((r, c + 1), (r + 1, c)):
                    if rr >= 23 or cc >= 31:
                        continue
                    a, b = lm[r, c], lm[rr, cc]
                    if a < 0 or b < 0 or a == b:
                        continue
                    if use_chart and (tf[r, c] < 0 or tf[rr, cc] < 0
                                      or chart[tf[r, c]] != chart[tf[rr, cc]]):
                        continue
                    steps.append(np.abs(im[r, c].astype(float) - im[rr, cc]).mean())
        got = label_boundary_step(im, lm, tf, chart) if use_chart else label_boundary_step(im, lm)
        assert got == pytest.approx(np.mean(steps), rel=1e-12)
    assert np.isnan(label_boundary_step(im, np.zeros((23, 31), np.int16)))


@pytest.fixture(scope="module")
def small_quad():
    """The quad of ``quad`` on a 64² atlas (fast solves)."""
    F = np.array([[0, 2, 1], [0, 3, 2]], np.int32)
    tc = np.array([[.05, .05], [.95, .05], [.95, .95], [.05, .95]], np.float32)
    face, _ = texel_map(tc, F, 64)
    return F, tc, face


def test_unlabelled_texels_keep_no_gradients(small_quad):
    """Covered texels without a source label (their face had no frame; the volume filled
    them) keep no gradients of their own: they are interpolated smoothly from the labelled
    surroundings, so a pattern the fill left there is flattened, while the same pattern on
    labelled texels is kept."""
    F, tc, face = small_quad
    cov = face >= 0
    rr, cc = np.mgrid[0:64, 0:64]
    band = cov & (cc >= 24) & (cc < 40)
    checker = np.where((rr + cc) % 2 == 0, 30, -30)
    img = np.where(cov, 120 + np.where(band | (cc < 12), checker, 0), 0)[..., None].repeat(3, 2).astype(np.uint8)
    lm = np.where(cov, np.where(band, -1, 0), -1).astype(np.int32)
    cs = CorrectionSystem(face, tc, F, F, screen_length=1 / 16, gutter_px=2)
    out = cs.correct(img, lm).astype(float)
    assert np.abs(out[band] - 120).mean() < 5.0                 # the fill's checker is smoothed away
    labelled = cov & (cc < 12)
    assert np.abs(out[labelled] - img[labelled]).max() <= 1      # a labelled checker stays


def test_one_sided_guidance_skips_neighbours_across_another_boundary(small_quad):
    """The one-sided guidance of a boundary pair averages only same-label gradients: a label
    one texel wide (both its pairs cross a boundary) gets guidance 0, so its step to the equal
    colours on either side is removed, not half kept (15 of its 30 levels)."""
    F, tc, face = small_quad
    cov = face >= 0
    cc = np.mgrid[0:64, 0:64][1]
    lm = np.where(cov, np.where(cc < 32, 0, np.where(cc == 32, 1, 2)), -1).astype(np.int32)
    img = np.where(cov, np.where(lm == 1, 130, 100), 0)[..., None].repeat(3, 2).astype(np.uint8)
    cs = CorrectionSystem(face, tc, F, F, screen_length=1 / 16, gutter_px=2, keep_own_frame=False)
    out = cs.correct(img, lm).astype(float)
    rows = np.flatnonzero(cov[:, 31] & cov[:, 33])
    sliver = out[rows, 32, 0] - (out[rows, 31, 0] + out[rows, 33, 0]) / 2
    assert label_boundary_step(img, lm) == pytest.approx(30.0)
    assert np.abs(sliver).mean() < 3.0, sliver.mean()


def test_charts_touching_in_the_atlas_are_not_neighbours():
    """Texel pairs couple only inside one chart: two unrelated surface pieces whose charts touch
    in the atlas, each with its own source and colour, are not smoothed into each other (each
    is one label of one colour: nothing to correct)."""
    F = np.array([[0, 2, 1], [0, 3, 2], [4, 6, 5], [4, 7, 6]], np.int32)   # two separate squares
    tc = np.array([[.05, .1], [.5, .1], [.5, .9], [.05, .9], [.5, .1], [.95, .1], [.95, .9], [.5, .9]],
                  np.float32)
    face, _ = texel_map(tc, F, 64)
    cs = CorrectionSystem(face, tc, F, F, screen_length=1 / 16, gutter_px=2)
    chart = cs.chart_tex
    assert ((chart[:, :-1] == 0) & (chart[:, 1:] == 1)).any()   # the charts share texel edges
    lm = np.where(chart >= 0, chart, -1).astype(np.int32)
    img = np.where(chart[..., None] == 0, 100, np.where(chart[..., None] == 1, 140, 0)).repeat(3, 2).astype(np.uint8)
    out = cs.correct(img, lm)
    np.testing.assert_array_equal(out[chart >= 0], img[chart >= 0])


def test_temporal_coupling_pulls_only_borrowed_texels(small_quad):
    """The temporal term acts on borrowed texels (label >= 0 and != the slice's frame) only:
    with keep_own_frame off, the own frame's texels that changed since the previous slice
    keep their new colour away from the boundary instead of being pulled back to it."""
    F, tc, face = small_quad
    cov = face >= 0
    cc = np.mgrid[0:64, 0:64][1]
    lm = np.where(cov, (cc >= 32).astype(np.int32), -1).astype(np.int32)
    prev = np.where(cov, 110, 0)[..., None].repeat(3, 2).astype(np.uint8)
    cur = prev.copy()
    cur[lm == 1] += 25                                   # the own frame (1) saw a brighter surface
    cs = CorrectionSystem(face, tc, F, F, screen_length=1 / 16, temporal_length=1 / 64, gutter_px=2,
                          keep_own_frame=False)
    out = cs.correct(cur, lm, previous=prev, frame=1)
    assert interior_change(cur, out, lm, margin=10) < 2.0


def test_gutter_is_refilled_from_the_corrected_texels(small_quad):
    """After the solve the gutter holds the corrected colours (stex.sampling.fill_gutter of the
    covered texels), not the uncorrected ones it had: bilinear lookups at chart edges would
    otherwise bring the removed step back."""
    from stex.sampling import fill_gutter

    F, tc, face = small_quad
    cov = face >= 0
    cc = np.mgrid[0:64, 0:64][1]
    lm = np.where(cov, (cc >= 32).astype(np.int32), -1).astype(np.int32)
    img = np.where(cov, np.where(lm == 1, 140, 100), 0)[..., None].repeat(3, 2).astype(np.uint8)
    fill_gutter(img, cov, cov, 2)                        # the volume's gutter, of the raw slice
    cs = CorrectionSystem(face, tc, F, F, screen_length=1 / 16, gutter_px=2)
    out = cs.correct(img, lm)
    want = out.copy()
    want[~cov] = 0
    fill_gutter(want, cov, cov, 2)
    assert (want[~cov] > 0).any() and (out[~cov] != img[~cov]).any()
    np.testing.assert_array_equal(out, want)
