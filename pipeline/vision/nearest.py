"""Nearest neighbours in one defined order: ascending squared distance, ties broken by the lower index.

Why the order is defined: design lattices tie exactly (a quarter of the hexagon slots have two design
points at the same float distance around the 8th neighbour), and the defect path of ring coding
(:mod:`pipeline.vision.dtrc.prediction`) fits local affine maps to the k nearest coded DESIGN points;
which tied point enters a fit changes the prediction far beyond rounding. With ties going to the lower
design index, the neighbours (hence the codes) are a function of the design and the coded set alone,
not of a search structure's internals or of the order in which blobs were detected.

Two searches:

- :func:`design_order` / :func:`nearest_members`: among a subset of the design points (the coded
  ones) around a design point, from a table computed once per design (the design is static; the
  subset changes per frame and per growth round).
- :func:`nearest`: among the blob centres of one frame (a few hundred points, searched a few times
  per blob on the defect paths): brute force, exact, with no structure to build or keep per frame.
  Blob centres are measured positions; exact ties there are rare and the rule merely makes them
  reproducible.

Two sweeps for the compiled loops of a frame's few hundred blobs, in place of a k-d tree's per-query call:
:func:`nearest_other_distances` (each point's distance to its nearest other, by :func:`nearest_swept`) and
:func:`x_order` / :func:`x_range` (the points within a reach in x, before an exact distance test);
:func:`knn` answers a k-d tree's ``query`` from Python for a frame's points without building one.

Squared distances are ``dx * dx + dy * dy`` everywhere (numpy and the compiled kernels round alike),
so the table and the brute-force searches agree bit for bit.
"""

from __future__ import annotations

import numba
import numpy as np
from scipy.spatial import cKDTree

__all__ = ["DESIGN_ORDER_WIDTH", "design_order", "nearest", "nearest_members", "y_order", "nearest_swept",
           "nearest_in", "nearest_other_distances", "knn", "x_order", "x_range"]

#: Design points listed per design point in :func:`design_order`: about four hexagonal shells, enough
#: for the 8 nearest coded points wherever the coded set is not sparse; a query that runs past its row
#: falls back to a brute-force search (same order).
DESIGN_ORDER_WIDTH = 64


def design_order(xy: np.ndarray, width: int = DESIGN_ORDER_WIDTH) -> np.ndarray:
    """Per design point (row), the nearest design points in (squared distance, index) order, itself
    first; ``-1`` pads a row after the last entry that is certainly in order.

    The candidates come from one cKDTree query of ``width`` neighbours; they are re-sorted by
    (squared distance, index). A point outside the candidates may tie with the last candidate's
    distance (cKDTree keeps an arbitrary one of tied points), so when a row does not list every
    point, the candidates at its largest distance are dropped: every entry left precedes every point
    not listed. Rows listing every point (``width >= len(xy)``) are complete and unpadded.
    """
    xy = np.ascontiguousarray(xy, dtype=np.float64)
    n = len(xy)
    kq = min(n, int(width))
    nb = cKDTree(xy).query(xy, k=kq)[1].reshape(n, kq).astype(np.int64)
    dx = xy[nb, 0] - xy[:, None, 0]
    dy = xy[nb, 1] - xy[:, None, 1]
    d2 = dx * dx + dy * dy
    o = np.lexsort((nb, d2), axis=-1)
    nb = np.take_along_axis(nb, o, axis=1)
    d2 = np.take_along_axis(d2, o, axis=1)
    if kq < n:
        nb[d2 >= d2[:, -1:]] = -1
    return np.ascontiguousarray(nb)


@numba.njit(inline="always")
def _keep(out_idx, out_d2, n, k, i, d):
    """Offer point ``i`` at squared distance ``d`` to the sorted prefix ``out_idx[:n]`` / ``out_d2[:n]`` of at most
    ``k`` entries; returns the new length. (squared distance, index) is compared as a pair, so points may be
    offered in any order: of tied points the lower index stays first."""
    if n == k:
        if not (d < out_d2[k - 1] or (d == out_d2[k - 1] and i < out_idx[k - 1])):
            return n
        j = k - 1
    else:
        j = n
        n += 1
    while j > 0 and (out_d2[j - 1] > d or (out_d2[j - 1] == d and out_idx[j - 1] > i)):
        out_idx[j] = out_idx[j - 1]
        out_d2[j] = out_d2[j - 1]
        j -= 1
    out_idx[j] = i
    out_d2[j] = d
    return n


@numba.njit(cache=True, nogil=True)
def nearest(pts, x, y, k, out_idx, out_d2):
    """The ``k`` (``<= len(pts)``) points of ``pts`` nearest to ``(x, y)``, in (squared distance, index)
    order, into ``out_idx`` / ``out_d2`` (squared distances). Brute force: one pass keeping a sorted
    prefix; a point enters only when strictly nearer than the k-th kept, and the points come in index
    order, so of tied points the lower index stays first."""
    n = 0
    for i in range(len(pts)):
        dx = pts[i, 0] - x
        dy = pts[i, 1] - y
        n = _keep(out_idx, out_d2, n, k, i, dx * dx + dy * dy)


@numba.njit(cache=True, nogil=True)
def y_order(pts, by_y, ys):
    """Fill ``by_y`` with the point indices in ascending ``y`` and ``ys`` with those ``y`` (for
    :func:`nearest_swept`); returns False, leaving the sweep unusable, when a coordinate is not finite."""
    for i in range(len(pts)):
        if not (np.isfinite(pts[i, 0]) and np.isfinite(pts[i, 1])):
            return False
    by_y[:] = np.argsort(pts[:, 1], kind="mergesort")
    for j in range(len(pts)):
        ys[j] = pts[by_y[j], 1]
    return True


@numba.njit(cache=True, nogil=True)
def nearest_swept(pts, by_y, ys, x, y, k, out_idx, out_d2):
    """:func:`nearest`, the same points in the same order, visiting only the points whose ``y`` is
    within the k-th distance: out from ``y`` through ``ys`` (:func:`y_order`) in both directions,
    each direction stopping at the first point with ``dy * dy`` beyond the k-th kept squared distance
    (every later point is at least as far in ``y``, and ``dx * dx + dy * dy >= dy * dy`` in floating
    point too, rounding being monotonic). A blob search in a frame of a few hundred markers then
    looks at a handful of them instead of all."""
    if not (np.isfinite(x) and np.isfinite(y)):
        nearest(pts, x, y, k, out_idx, out_d2)
        return
    hi = np.searchsorted(ys, y)
    n = _sweep(pts, by_y, hi, len(ys), 1, x, y, k, out_idx, out_d2, 0)
    _sweep(pts, by_y, hi - 1, -1, -1, x, y, k, out_idx, out_d2, n)


@numba.njit(inline="always")
def nearest_in(pts, by_y, ys, swept, x, y, k, out_idx, out_d2):
    """:func:`nearest_swept` where :func:`y_order` sorted the points (``swept``), else :func:`nearest` (a point
    with a coordinate that is not finite leaves no usable order): the same points in the same order either way."""
    if swept:
        nearest_swept(pts, by_y, ys, x, y, k, out_idx, out_d2)
    else:
        nearest(pts, x, y, k, out_idx, out_d2)


@numba.njit(inline="always")
def _sweep(pts, by_y, start, stop, step, x, y, k, out_idx, out_d2, n):
    """One direction of :func:`nearest_swept`: offer the points ``by_y[start:stop:step]`` in turn to the
    ``n`` kept so far, stopping at the first whose ``dy * dy`` is beyond the k-th kept squared distance;
    returns the new count."""
    for j in range(start, stop, step):
        i = by_y[j]
        dy = pts[i, 1] - y
        if n == k and dy * dy > out_d2[k - 1]:
            break
        dx = pts[i, 0] - x
        n = _keep(out_idx, out_d2, n, k, i, dx * dx + dy * dy)
    return n


@numba.njit(cache=True, nogil=True)
def nearest_members(xy, order, member, s, k, skip_self, out):
    """The ``k`` design points with ``member`` True nearest to design point ``s`` (without ``s`` itself
    when ``skip_self``), in (squared distance, index) order, into ``out``; returns how many were found
    (fewer than ``k`` only when there are fewer members). ``order``: :func:`design_order` of ``xy``;
    when its row runs out before ``k`` members, a brute-force search over all members decides."""
    n = 0
    row = order[s]
    for t in range(len(row)):
        j = row[t]
        if j < 0:
            break
        if member[j] and not (skip_self and j == s):
            out[n] = j
            n += 1
            if n == k:
                return n
    if order.shape[1] >= len(xy):
        return n  # the row listed every point
    # brute force over the members, as :func:`nearest`
    d2 = np.empty(k)
    x, y = xy[s, 0], xy[s, 1]
    n = 0
    for i in range(len(xy)):
        if not member[i] or (skip_self and i == s):
            continue
        dx = xy[i, 0] - x
        dy = xy[i, 1] - y
        n = _keep(out, d2, n, k, i, dx * dx + dy * dy)
    return n


@numba.njit(cache=True, nogil=True)
def nearest_other_distances(pts):
    """Each point's distance to its nearest other point (inf for a lone point): the second of the two nearest
    :func:`knn` finds from the point itself (the first is the point, or a duplicate of it, at 0). What ``cKDTree(pts).query(pts, k=2)`` gives, value for value (tests/test_temporal_kernels.py):
    ~8 us for 217 points against ~90 us for building and querying the tree."""
    return _knn(pts, pts, 2)[0][:, 1].copy()


def knn(pts: np.ndarray, queries: np.ndarray, k: int) -> tuple[np.ndarray, np.ndarray]:
    """The ``k`` points of ``pts`` (n, 2) nearest to each of ``queries`` (q, 2): (distances (q, k), indices
    (q, k)), nearest first, as ``cKDTree(pts).query(queries, k=k)`` gives them for ``k > 1`` (an entry beyond
    the n points at inf with index n; distances the square roots of ``dx * dx + dy * dy``, value for value),
    of tied points the lower index first (a k-d tree keeps an arbitrary one). For a frame's few hundred
    blobs a sweep (:func:`nearest_swept`) instead of a tree built per call: ~10 us for a hundred queries
    against ~60 us for building and querying the tree."""
    pts = np.ascontiguousarray(pts, np.float64).reshape(-1, 2)
    queries = np.ascontiguousarray(queries, np.float64).reshape(-1, 2)
    return _knn(pts, queries, int(k))


@numba.njit(cache=True, nogil=True)
def _knn(pts, queries, k):
    n, m = len(pts), len(queries)
    d = np.full((m, k), np.inf)
    idx = np.full((m, k), n, np.int64)
    kk = min(k, n)
    if kk == 0:
        return d, idx
    by_y, ys = np.empty(n, np.int64), np.empty(n)
    swept = y_order(pts, by_y, ys)
    oi, od = np.empty(kk, np.int64), np.empty(kk)
    for i in range(m):
        nearest_in(pts, by_y, ys, swept, queries[i, 0], queries[i, 1], kk, oi, od)
        for t in range(kk):
            idx[i, t] = oi[t]
            d[i, t] = np.sqrt(od[t])
    return d, idx


def x_order(xy: np.ndarray, mask: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """The indices of ``mask`` (all where None) ordered by x, and their x (float64, contiguous), for
    :func:`x_range`."""
    idx = np.arange(len(xy)) if mask is None else np.flatnonzero(mask)
    order = idx[np.argsort(xy[idx, 0], kind="stable")]
    return order, np.ascontiguousarray(xy[order, 0], np.float64)


@numba.njit(cache=True, nogil=True)
def x_range(xs, x, reach):
    """Slice ``lo:hi`` of the x-ordered ``xs`` (:func:`x_order`) within ``reach`` of ``x`` (a hair wider: the
    caller's exact distance test follows)."""
    return np.searchsorted(xs, x - reach - 1e-9), np.searchsorted(xs, x + reach + 1e-9, side="right")

