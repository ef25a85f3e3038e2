"""Half-octave area pyramid of a uint8 view on the [0, 1] scale (the levels the scale space runs on)."""

from __future__ import annotations

import functools
import math

import cv2
import numba
import numpy as np

from pipeline.vision.detection.images import Workspace, grey_float

#: A level is halved again only while it is at least this many px on its short side (smaller, the
#: level is reused: its scales have no room for a marker anyway).
_MIN_HALVED_SIDE_PX = 10
#: Overlaps (source cells) below this are ignored, as OpenCV's computeResizeAreaTab does.
_AREA_EPS = 1e-3


def _half_mean(img: np.ndarray, name: str) -> np.ndarray:
    """Exact 2x2 mean (odd last row/column dropped) into a reused buffer."""
    h2, w2 = img.shape[0] // 2, img.shape[1] // 2
    src = img if img.shape == (2 * h2, 2 * w2) else img[: 2 * h2, : 2 * w2]
    return cv2.resize(src, (w2, h2), dst=Workspace.get(name, (h2, w2)), interpolation=cv2.INTER_AREA)


@numba.njit(cache=True, nogil=True)
def half_u8(grey, out):
    """2x2 mean of a uint8 image on the [0, 1] scale (odd last row/column dropped) into ``out``:
    the integer sum of the four, scaled once."""
    scale = np.float32(0.25 / 255.0)
    h2, w2 = out.shape
    pairs = np.empty(2 * w2, np.int32)
    for y in range(h2):
        # row by row (vectorises also on a strided view, e.g. one half of a stereo frame)
        r0, r1 = grey[2 * y], grey[2 * y + 1]
        for x in range(2 * w2):
            pairs[x] = np.int32(r0[x]) + np.int32(r1[x])
        for x in range(w2):
            out[y, x] = np.float32(pairs[2 * x] + pairs[2 * x + 1]) * scale
    return out


@functools.lru_cache(maxsize=32)
def area_table(ssize: int, dsize: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Area-resampling weights from ``ssize`` to ``dsize`` samples, as OpenCV's INTER_AREA computes
    them (computeResizeAreaTab): each output cell averages the input cells it overlaps, weighted by
    the overlap. Returns (source index, float32 weight, pointer (dsize + 1,)) in CSR form."""
    scale = ssize / dsize
    idx, wts, ptr = [], [], [0]
    for d in range(dsize):
        f1 = d * scale
        f2 = f1 + scale
        cell = min(scale, ssize - f1)
        s2 = min(math.floor(f2), ssize - 1)
        s1 = min(math.ceil(f1), s2)
        if s1 - f1 > _AREA_EPS:
            idx.append(s1 - 1)
            wts.append((s1 - f1) / cell)
        for k in range(s1, s2):
            idx.append(k)
            wts.append(1.0 / cell)
        if f2 - s2 > _AREA_EPS:
            idx.append(s2)
            wts.append(min(f2 - s2, 1.0, cell) / cell)
        ptr.append(len(idx))
    return np.array(idx, np.intp), np.array(wts, np.float32), np.array(ptr, np.intp)


@functools.lru_cache(maxsize=32)
def area_taps(ssize: int, dsize: int) -> tuple[np.ndarray, np.ndarray]:
    """:func:`area_table` as a fixed number of taps per output sample: output ``d`` is
    ``sum_t weights[t, d] * src[first[d] + t]`` for t in ``range(len(weights))``, with zero weights
    where the sample has fewer taps (the source cells of one sample are consecutive). Returns (first
    (dsize,), weights (T, dsize) float32); ``first + T - 1`` stays inside the source."""
    idx, wts, ptr = area_table(ssize, dsize)
    n = np.diff(ptr)
    taps = int(min(n.max(), ssize))
    first = np.minimum(idx[ptr[:-1]], ssize - taps).astype(np.intp)
    weights = np.zeros((taps, dsize), np.float32)
    for d in range(dsize):
        cells = idx[ptr[d]:ptr[d + 1]]
        assert np.all(np.diff(cells) == 1)
        weights[cells - first[d], d] = wts[ptr[d]:ptr[d + 1]]
    return first, weights


@numba.njit(cache=True, nogil=True)
def _area_resize_kernel(src, xf, xw, yi, yw, yp, out, row):
    """Separable area resampling of ``src`` into ``out`` with :func:`area_table` weights: rows
    first (contiguous, vectorised), then the columns of the combined row (:func:`area_taps`: a fixed
    tap count, tap by tap across the row, vectorised); float32 throughout.

    Each output is ``0 + w_0 s_0 + w_1 s_1 + ...`` in the order of the source cells, as a loop over
    the CSR table sums it; the padding taps add ``0 * s`` = +0 (finite ``s``), which leaves a sum that
    is never -0 unchanged, so the result is the same bit for bit.
    """
    n_taps, w1 = xw.shape
    for y in range(out.shape[0]):
        row[:] = 0.0
        for k in range(yp[y], yp[y + 1]):
            wk, r = yw[k], yi[k]
            for x in range(src.shape[1]):
                row[x] += wk * src[r, x]
        o = out[y]
        o[:] = 0.0
        for t in range(n_taps):
            wt = xw[t]
            for x in range(w1):
                o[x] += wt[x] * row[xf[x] + t]
    return out


def area_resize(src: np.ndarray, w1: int, h1: int, name: str) -> np.ndarray:
    """``src`` (float32) area-resampled to ``(h1, w1)`` into a reused buffer: OpenCV's INTER_AREA
    (within 2e-7 on [0, 1] images; tests/test_detection.py) at less than half its cost for the
    non-integer sqrt(2) reduction, where OpenCV takes its general path (measured on one thread,
    320x240 -> 226x170: 0.074 ms against 0.18 ms)."""
    return _area_resize_kernel(src, *area_taps(src.shape[1], w1), *area_table(src.shape[0], h1),
                               Workspace.get(name, (h1, w1)), Workspace.get(name + "_row", (src.shape[1],)))


def pyramid_level(grey: np.ndarray, j: int, cache: dict) -> tuple[np.ndarray, float, float]:
    """Half-octave pyramid level ``j`` of the uint8 image ``grey``: the image area-reduced
    ~``sqrt(2)**j`` times, float32 on the [0, 1] scale.

    Level ``j`` is the exact 2x2 mean of level ``j - 2`` (level 2 straight from the uint8 pixels, so
    the full-resolution float image is never made unless level 0 or 1 is asked for), except the odd
    bases: level 3 is an INTER_AREA resize of level 2 by 1/sqrt(2) (level 1, used only for scales
    below ~1.4 px, one of the full image). Returns (image, fx, fy): level pixel ``(i_x, i_y)`` is
    centred at full pixel ``((i_x + 0.5) fx - 0.5, (i_y + 0.5) fy - 0.5)``.
    """
    if j not in cache:
        if j == 0:
            cache[0] = (grey_float(grey), 1.0, 1.0)
        elif j == 2 and min(grey.shape) >= _MIN_HALVED_SIDE_PX:
            h2, w2 = grey.shape[0] // 2, grey.shape[1] // 2
            cache[2] = (half_u8(grey, Workspace.get("lvl2", (h2, w2))), 2.0, 2.0)
        elif j in (1, 3):
            prev, px, py = pyramid_level(grey, j - 1 if j == 1 else 2, cache)
            h, w = prev.shape
            w1, h1 = max(1, int(round(w / math.sqrt(2)))), max(1, int(round(h / math.sqrt(2))))
            img = area_resize(prev, w1, h1, f"lvl{j}")
            cache[j] = (img, px * w / w1, py * h / h1)
        else:
            prev, fx, fy = pyramid_level(grey, j - 2, cache)
            if min(prev.shape) < _MIN_HALVED_SIDE_PX:
                cache[j] = cache[j - 2]
            else:
                cache[j] = (_half_mean(prev, f"lvl{j}"), 2 * fx, 2 * fy)
    return cache[j]

