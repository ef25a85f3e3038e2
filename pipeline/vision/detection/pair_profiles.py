"""The two tests of :mod:`pipeline.vision.detection.pairs`, compiled: for each examined blob, its window's light,
its long axis, and the profiles that show two pins (the dark line between touching pins, the waist of overlapping
ones).

One pass over every examined blob of a view. The arithmetic is numpy's, step for step: float ranges and sums
in numpy's order (:mod:`pipeline.vision.detection.numpy_order`), the median of three chords as
``scipy.ndimage.median_filter(size=3, mode="nearest")``, so a view's blobs come out as they did when each test
was written in numpy (tests/test_detection_kernels.py compares them). On a real TacTip view (~15 blobs profiled) the
numpy version took 3.4-3.8 ms, most of it per-call overhead on windows of ~150 pixels.
"""

from __future__ import annotations

import math

import numba
import numpy as np

from pipeline.vision.detection.numpy_order import arange as _arange, float_sum as _sum

__all__ = ["pair_pins", "compile_pair_pins"]

#: Profile samples per pixel along the long axis and across it, and the across-axis offsets (px) averaged
#: by the dark-line test.
STEP_PX = 0.5
ACROSS_PX = (-1.0, 0.0, 1.0)
#: Background of the pair window: this percentile of its pixels (the dark skin around the pair).
BACKGROUND_PERCENTILE = 10


@numba.njit(cache=True, nogil=True)
def _sample(patch, bx, by, ux, uy, t, o):
    """Light of ``patch`` (bilinear, clamped to it) at ``t`` along (ux, uy) and ``o`` across from (bx, by)
    (patch px): (len(o), len(t))."""
    h, w = patch.shape
    out = np.empty((len(o), len(t)))
    for i in range(len(o)):
        for j in range(len(t)):
            x = min(max(bx + t[j] * ux - o[i] * uy, 0.0), w - 1.0)
            y = min(max(by + t[j] * uy + o[i] * ux, 0.0), h - 1.0)
            x0 = min(int(math.floor(x)), w - 2) if w > 1 else 0
            y0 = min(int(math.floor(y)), h - 2) if h > 1 else 0
            fx, fy = x - x0, y - y0
            x1, y1 = min(x0 + 1, w - 1), min(y0 + 1, h - 1)
            out[i, j] = ((patch[y0, x0] * (1 - fx) + patch[y0, x1] * fx) * (1 - fy)
                         + (patch[y1, x0] * (1 - fx) + patch[y1, x1] * fx) * fy)
    return out


@numba.njit(cache=True, nogil=True)
def _line(patch, bx, by, ux, uy, bg, px, py, wt, cx, cy, r, min_apart, peak, dip):
    """The dark-line test: (found, pin a, pin c) from the two halves' centroids."""
    t = _arange(-r, r + 1e-9, STEP_PX)
    light = _sample(patch, bx, by, ux, uy, t, np.array(ACROSS_PX))
    prof = ((light[0] - bg) + (light[1] - bg) + (light[2] - bg)) / 3.0
    a, c = -1, -1
    for j in range(len(t)):
        if t[j] < 0 and (a < 0 or prof[j] > prof[a]):
            a = j
        if t[j] > 0 and (c < 0 or prof[j] > prof[c]):
            c = j
    none = (False, 0.0, 0.0, 0.0, 0.0)
    if a < 0 or c < 0:
        return none
    low = min(prof[a], prof[c])
    if low < peak * prof.max() or t[c] - t[a] < min_apart or prof[a:c + 1].min() > dip * low:
        return none
    side = (px - cx) * ux + (py - cy) * uy
    out = np.zeros(4)
    for k in range(2):
        half = (side < 0) if k == 0 else (side >= 0)
        hw = wt[half]
        tot = _sum(hw)
        if not tot > 0:
            return none
        out[2 * k] = _sum(hw * px[half]) / tot
        out[2 * k + 1] = _sum(hw * py[half]) / tot
    return True, out[0], out[1], out[2], out[3]


@numba.njit(cache=True, nogil=True)
def _median3(a, b, c):
    return max(min(a, b), min(max(a, b), c))


@numba.njit(cache=True, nogil=True)
def _waist(patch, bx, by, ux, uy, bg, wt_max, cx, cy, r, min_apart, peak, waist, end):
    """The waist test: (found, pin a, pin c), each pin at the middle of its side's widest chords."""
    none = (False, 0.0, 0.0, 0.0, 0.0)
    reach = r + 0.5 * min_apart
    t = _arange(-reach, reach + 1e-9, STEP_PX)
    o = _arange(-r, r + 1e-9, STEP_PX)
    light = _sample(patch, bx, by, ux, uy, t, o)
    n, c0 = len(t), len(o) // 2
    thr = 0.5 * wt_max
    raw = np.zeros(n)
    mid = np.zeros(n)
    for j in range(n):
        hi = 0
        while c0 + hi < len(o) and light[c0 + hi, j] - bg > thr:      # the run from the axis outward
            hi += 1
        lo = 0
        while c0 - lo >= 0 and light[c0 - lo, j] - bg > thr:
            lo += 1
        raw[j] = (hi + lo - 1) * STEP_PX if hi > 0 else 0.0
        mid[j] = (hi - lo) * STEP_PX / 2
    width = np.empty(n)
    for j in range(n):
        width[j] = _median3(raw[max(j - 1, 0)], raw[j], raw[min(j + 1, n - 1)])
    wa, wc = -np.inf, -np.inf
    for j in range(n):
        if t[j] < 0:
            wa = max(wa, width[j])
        elif t[j] > 0:
            wc = max(wc, width[j])
    if wa == -np.inf or wc == -np.inf:
        return none
    if min(wa, wc) <= 0 or min(wa, wc) < peak * max(wa, wc):
        return none
    if max(width[0] / wa, width[n - 1] / wc) > end:                  # each pin's chords narrow again beyond it
        return none
    pa = (t < 0) & (width >= 0.95 * wa)
    pc = (t > 0) & (width >= 0.95 * wc)
    ta, tc = _sum(t[pa]) / pa.sum(), _sum(t[pc]) / pc.sum()
    between = (t > t[pa].max()) & (t < t[pc].min())
    if tc - ta < min_apart or not between.any() or width[between].min() > waist * min(wa, wc):
        return none
    oa, oc = _sum(mid[pa]) / pa.sum(), _sum(mid[pc]) / pc.sum()
    return (True, cx + ta * ux - oa * uy, cy + ta * uy + oa * ux, cx + tc * ux - oc * uy, cy + tc * uy + oc * ux)


@numba.njit(cache=True, nogil=True)
def pair_pins(grey, xs, ys, rs, r_wins, min_aparts, dark, waist, peak, dip, waist_fraction, end):
    """Two pins per examined blob, where its light shows them.

    Parameters: ``grey`` (H, W) uint8; per blob its centre ``xs``, ``ys``, radius ``rs``, window radius ``r_wins``,
    the neighbours' typical radius ``min_aparts`` (the pins at least that far apart) and which tests apply
    (``dark``: the dark-line test first; ``waist``: the waist test where the dark line is not found); the
    thresholds of :mod:`pipeline.vision.detection.pairs`. Returns (n,) bool found and (n, 2, 2) pins (px).
    """
    h, w = grey.shape
    n = len(xs)
    found = np.zeros(n, np.bool_)
    pins = np.zeros((n, 2, 2))
    for k in range(n):
        if not (dark[k] or waist[k]):
            continue
        x0, y0, r_win = xs[k], ys[k], r_wins[k]
        xa, xb = max(0, int(math.floor(x0 - r_win))), min(w - 1, int(math.ceil(x0 + r_win)))
        ya, yb = max(0, int(math.floor(y0 - r_win))), min(h - 1, int(math.ceil(y0 + r_win)))
        if xb - xa < 2 or yb - ya < 2:
            continue
        patch = grey[ya:yb + 1, xa:xb + 1].astype(np.float64)
        m = 0
        px = np.empty(patch.size)
        py = np.empty(patch.size)
        v = np.empty(patch.size)
        for i in range(yb - ya + 1):
            for j in range(xb - xa + 1):
                gx, gy = float(xa + j), float(ya + i)
                if (gx - x0) ** 2 + (gy - y0) ** 2 <= r_win * r_win:
                    px[m], py[m], v[m] = gx, gy, patch[i, j]
                    m += 1
        px, py, v = px[:m], py[:m], v[:m]
        k_bg = int(m * BACKGROUND_PERCENTILE / 100)
        bg = np.sort(v)[k_bg]
        wt = np.maximum(v - bg, 0.0)
        tot = _sum(wt)
        if tot <= 0:
            continue
        cx, cy = _sum(wt * px) / tot, _sum(wt * py) / tot
        dx, dy = px - cx, py - cy
        sxx, syy, sxy = _sum(wt * dx * dx), _sum(wt * dy * dy), _sum(wt * dx * dy)
        ang = 0.5 * math.atan2(2 * sxy, sxx - syy)          # the long axis
        ux, uy = math.cos(ang), math.sin(ang)
        bx, by = cx - xa, cy - ya
        res = (False, 0.0, 0.0, 0.0, 0.0)
        if dark[k]:
            res = _line(patch, bx, by, ux, uy, bg, px, py, wt, cx, cy, rs[k], min_aparts[k], peak, dip)
        if not res[0] and waist[k]:
            res = _waist(patch, bx, by, ux, uy, bg, wt.max(), cx, cy, rs[k], min_aparts[k], peak, waist_fraction,
                         end)
        if res[0]:
            found[k] = True
            pins[k, 0, 0], pins[k, 0, 1], pins[k, 1, 0], pins[k, 1, 1] = res[1], res[2], res[3], res[4]
    return found, pins


def compile_pair_pins() -> None:
    """Compile (or load from numba's cache) :func:`pair_pins` for the types detection passes, on two touching
    discs (:func:`pipeline.vision.detection.detect.compile_crowded_kernels`)."""
    grey = np.full((24, 32), 20, np.uint8)
    yy, xx = np.mgrid[:24, :32]
    grey[((xx - 12) ** 2 + (yy - 12) ** 2 <= 25) | ((xx - 20) ** 2 + (yy - 12) ** 2 <= 25)] = 200
    one = np.ones(1)
    pair_pins(grey, 16.0 * one, 12.0 * one, 8.0 * one, 11.0 * one, 5.0 * one, np.ones(1, np.bool_),
              np.ones(1, np.bool_), 0.9, 0.85, 0.85, 0.9)
