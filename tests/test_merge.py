"""Multi-contact merge: mollifier normalisation and plane invariance, overlap selection with a
known peripheral bias, tap-to-global transform."""

from __future__ import annotations

import numpy as np
import pytest

from pipeline.geometry import merge as M
from pipeline.design import marker_layout, Pattern
from pipeline.types import DataError, HeightMap

EPS = M.MOLLIFIER_EPS_MM


def test_mollifier_integrates_to_one_on_a_fine_grid():
    # midpoint rule with h = eps/400 on a smooth compactly supported function: error << 1e-6
    h = EPS / 400
    s = (np.arange(-400, 400) + 0.5) * h
    X, Y = np.meshgrid(s, s)
    total = M.mollifier(np.hypot(X, Y), EPS).sum() * h * h
    assert total == pytest.approx(1.0, abs=1e-6)
    assert M.MOLLIFIER_I == pytest.approx(0.466512, abs=1e-6)
    # compact support on the eps disk, peak at the centre
    assert M.mollifier(EPS, EPS) == 0.0 and M.mollifier(1.01 * EPS, EPS) == 0.0
    assert M.mollifier(0.0, EPS) == pytest.approx(np.exp(-1) / (M.MOLLIFIER_I * EPS**2))


@pytest.mark.parametrize("dx", [0.02, 0.05, 0.1, 0.3])
def test_grid_kernel_weights_sum_to_one(dx):
    k = M.mollifier_kernel(dx, dx, EPS)
    assert k.sum() == pytest.approx(1.0, abs=1e-12)
    assert k.shape[0] % 2 == 1 and np.allclose(k, k[::-1, ::-1])
    if dx >= EPS:
        assert k.shape == (1, 1)


def test_grid_mollify_leaves_a_plane_unchanged():
    x = np.arange(0, 6, 0.05)
    y = np.arange(0, 4, 0.04)
    X, Y = np.meshgrid(x, y)
    z = 0.3 * X - 0.7 * Y + 1.5
    z[:3, :] = np.nan                       # a no-data band: edges must not be pulled toward 0
    out = M.mollify_grid(HeightMap(x, y, z), eps_mm=EPS)
    valid = np.isfinite(z)
    assert np.array_equal(np.isfinite(out.z_mm), valid)
    # interior (kernel fully inside): symmetric weights summing to 1 reproduce a plane exactly
    a = 6
    inner = np.zeros_like(valid)
    inner[3 + a:-a, a:-a] = True
    np.testing.assert_allclose(out.z_mm[inner], z[inner], atol=1e-12)
    # at the edges a one-sided average of a plane is off by at most |grad z| * eps
    np.testing.assert_array_less(np.abs(out.z_mm - z)[valid], np.hypot(0.3, 0.7) * EPS + 1e-12)


def test_grid_mollify_smooths_noise():
    rng = np.random.default_rng(3)
    x = np.arange(0, 5, 0.05)
    z = rng.normal(0, 1.0, (len(x), len(x)))
    out = M.mollify_grid(HeightMap(x, x, z), eps_mm=EPS)
    # white noise through a kernel with sum(k^2) ~ 1/effective cells: std drops by > 3x
    k = M.mollifier_kernel(0.05, 0.05, EPS)
    expect = np.sqrt(np.sum(k**2))
    assert np.std(out.z_mm[10:-10, 10:-10]) == pytest.approx(expect, rel=0.15)
    assert expect < 1 / 3


def test_scattered_mollify_plane_and_pairs():
    rng = np.random.default_rng(0)
    xy = rng.uniform(0, 10, (4000, 2))
    flat = np.column_stack([xy, np.full(len(xy), 2.5)])
    np.testing.assert_allclose(M.mollify_points(flat), 2.5, atol=1e-12)   # a constant is exact
    g = np.array([0.2, -0.1])
    tilted = np.column_stack([xy, xy @ g + 1.0])
    out = M.mollify_points(tilted)
    # a normalised average over neighbours within eps changes a plane by at most |grad z| * eps
    assert np.max(np.abs(out - tilted[:, 2])) <= np.linalg.norm(g) * EPS + 1e-12
    assert np.max(np.abs(out - tilted[:, 2])) > 0      # and some points did have neighbours
    # a pair 0.1 mm apart (rho = 0.4): weights exp(-1) on itself, exp(-1/(1-0.16)) on the other;
    # a far point keeps its z
    p = np.array([[0.0, 0.0, 0.0], [0.1, 0.0, 1.0], [5.0, 5.0, 7.0]])
    w_self, w_other = np.exp(-1.0), np.exp(-1.0 / (1.0 - 0.4**2))
    share = w_other / (w_self + w_other)
    np.testing.assert_allclose(M.mollify_points(p), [share, 1.0 - share, 7.0], rtol=1e-12)


def _hex_patch(separation=1.8, layers=9):
    xy, _ = marker_layout(Pattern("hexagon", layers, 12, separation, 0.0))
    return xy


def _truth(xy):
    return 0.1 * xy[:, 0] + 0.05 * xy[:, 1] + 1.0


def _bias(r, R=14.4):
    return 0.6 * (r / R) ** 4   # over-estimate growing toward the periphery (paper, Data Processing)


def test_overlap_keeps_lower_unbiased_points():
    xy = _hex_patch()
    R = np.max(np.hypot(*xy.T))
    # tap B = tap A's lattice shifted by 8 spacings + 0.3 mm: every overlap point of B has an A
    # point exactly 0.3 mm away (< T = 0.6 mm), every other distance is > 1.5 mm
    shift = np.array([8 * 1.8 + 0.3, 0.0])
    taps, bias = [], []
    for c in (np.zeros(2), shift):
        p = xy + c
        b = _bias(np.hypot(*(p - c).T), R)
        taps.append(np.column_stack([p, _truth(p) + b]))
        bias.append(b)
    sel = M.select_overlap(taps)
    o = np.flatnonzero(sel.overlap)
    assert len(o) > 40
    np.testing.assert_allclose(sel.nn_dist_mm[o], 0.3, atol=1e-9)
    assert np.all(sel.nn_index[sel.nn_index[o]] == o)                # mutual pairs
    assert np.all(sel.keep[o] != sel.keep[sel.nn_index[o]])          # exactly one of each pair kept
    assert np.all(sel.keep[~sel.overlap])                             # non-overlap points all kept
    b_all = np.concatenate(bias)
    kept, dropped = o[sel.keep[o]], o[~sel.keep[o]]
    # the kept point of each pair is the less biased one, except near the mid-line where the two
    # biases differ by less than the truth's own change across the pair (0.1 mm/mm * 0.3 mm)
    partner = sel.nn_index[kept]
    clear = np.abs(b_all[kept] - b_all[partner]) > 0.1 * 0.3
    assert np.all(b_all[kept][clear] < b_all[partner][clear])
    assert b_all[kept].mean() < 0.5 * b_all[dropped].mean()
    # merged surface follows the lower, unbiased points: each kept point's error is at most the
    # smaller bias of its pair plus the truth's change across the pair; overall RMS drops
    res = M.merge_taps(taps, eps_mm=None)
    pts = sel.points_mm
    err = pts[:, 2] - _truth(pts[:, :2])
    assert np.all(err[kept] <= np.minimum(b_all[kept], b_all[partner]) + 0.1 * 0.3 + 1e-12)
    ov = res.overlap
    err_merged = res.points_mm[ov, 2] - _truth(res.points_mm[ov, :2])
    assert np.sqrt(np.mean(err_merged**2)) < 0.7 * np.sqrt(np.mean(err[o] ** 2))
    assert len(res.points_mm) == sum(len(t) for t in taps) - len(o) // 2


def test_same_tap_points_never_pair_and_far_taps_do_not_overlap():
    xy = _hex_patch(separation=0.4, layers=4)   # denser than T within one tap
    a = np.column_stack([xy, np.zeros(len(xy))])
    b = a + [100.0, 0.0, 0.0]
    sel = M.select_overlap([a, b])
    assert not sel.overlap.any() and sel.keep.all()
    assert np.all(np.isinf(sel.nn_dist_mm))


def test_tap_points_to_global_for_a_downward_sensor():
    pts = np.array([[1.0, 2.0, -0.5], [0.0, 0.0, 0.0]])
    g = M.tap_points_to_global(pts, (100.0, 50.0, 0.0))
    # skin pushed 0.5 mm into the sensor (sensor z = -0.5) is 0.5 mm ABOVE the tap plane
    np.testing.assert_allclose(g, [[101.0, 48.0, 0.5], [100.0, 50.0, 0.0]])
    np.testing.assert_allclose(M.tap_points_to_global(pts, (1, 1, 1), facing_down=False), pts + 1)


def test_bad_input_is_reported():
    with pytest.raises(DataError, match="tap 1"):
        M.merge_taps([np.zeros((3, 3)), np.zeros((3, 2))])
    with pytest.raises(DataError, match="NaN"):
        M.merge_taps([np.full((2, 3), np.nan)])


def test_grid_points_masks_gaps():
    xy = np.stack(np.meshgrid(np.arange(0, 10.0), np.arange(0, 10.0)), -1).reshape(-1, 2)
    p = np.column_stack([xy, 0.5 * xy[:, 0]])
    hm = M.grid_points(p, np.arange(-2, 12, 0.5), np.arange(0, 9, 0.5), max_gap_mm=1.0)
    ok = np.isfinite(hm.z_mm)
    X, _ = np.meshgrid(hm.x_mm, hm.y_mm)
    np.testing.assert_allclose(hm.z_mm[ok], 0.5 * X[ok], atol=1e-9)
    assert not ok[:, hm.x_mm < -1.0].any() and ok[:, (hm.x_mm >= 0) & (hm.x_mm <= 9)].all()
