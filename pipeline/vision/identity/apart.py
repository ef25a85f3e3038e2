"""Whether a marker next to lost design neighbours can have shared its blob with one of them.

A marker one of whose immediate design neighbours was not followed into the previous frame may have
merged with that neighbour into one blob (pins crowded until the detector no longer separated them),
so the frame-to-frame map gives it a tighter gate (:data:`pipeline.vision.identity.temporal.F2F_GATE_ALONE`),
unless each such neighbour has a blob of its own now, where the marker's neighbourhood puts it. Shared by
the frame-to-frame map and re-acquisition (:mod:`pipeline.vision.identity.reacquire`).
"""

from __future__ import annotations

import math

import numba
import numpy as np

from pipeline.vision.nearest import nearest_in, y_order

#: A lost neighbour stands apart from the marker when it has a blob of its own within this many local
#: spacings of where the marker's neighbourhood puts it (:func:`lost_neighbours_apart`): a neighbour whose
#: blob was missing from the previous frame (glare, a worn marker, a spurious blob beside it) and is back
#: cannot share the marker's blob.
F2F_APART = 0.3


def lost_neighbours_apart(P, prev_ids, pred, jac, which, known, design_nbr, design_xy, pts, s_prev) -> np.ndarray:
    """Markers (of ``which``) whose immediate design neighbours missing from the previous frame each have a
    blob of their own now (of ``pts`` (n, 2)), so that none of them can have merged with the marker into one
    blob (the case :data:`~pipeline.vision.identity.temporal.F2F_GATE_ALONE` guards): the neighbour's previous
    position is put where the design-to-image map of the marker's known neighbours (a linear map of design
    offsets, fitted to at least two, spread in two directions) places it beside the marker, moved on by the
    marker's frame-to-frame map (Jacobian ``jac``); its nearest blob now must be another than the marker's
    predicted one and within :data:`F2F_APART` local spacings of that place. A neighbour without such a blob
    (missing now too, or crowded onto the marker) leaves the marker at the tight gate. Compiled
    (:func:`_apart`); the map is the least-squares one of the normal equations, the spread test the smaller
    singular value of the design offsets (what ``np.linalg.lstsq`` and ``matrix_rank`` give, to rounding)."""
    row = np.full(len(known), -1, np.int64)
    row[prev_ids] = np.arange(len(prev_ids))
    return _apart(np.ascontiguousarray(P, np.float64), np.asarray(prev_ids, np.int64),
                  np.ascontiguousarray(pred, np.float64), np.ascontiguousarray(jac, np.float64),
                  np.asarray(which, np.bool_), np.asarray(known, np.bool_), np.asarray(design_nbr, np.int64),
                  np.ascontiguousarray(design_xy, np.float64), np.ascontiguousarray(pts, np.float64).reshape(-1, 2),
                  np.asarray(s_prev, np.float64), row)


@numba.njit(cache=True, nogil=True)
def _apart(P, prev_ids, pred, jac, which, known, design_nbr, design_xy, pts, s_prev, row):
    out = np.zeros(len(P), np.bool_)
    n = len(pts)
    if n == 0:
        return out
    by_y, ys = np.empty(n, np.int64), np.empty(n)
    swept = y_order(pts, by_y, ys)
    oi, od = np.empty(1, np.int64), np.empty(1)
    places = np.empty((design_nbr.shape[1], 2))
    for i in range(len(P)):
        if not which[i]:
            continue
        me = prev_ids[i]
        n_have = n_missing = 0
        a = b = c = gx0 = gx1 = gy0 = gy1 = 0.0      # G = dD' dD; dD' Y (columns: image x, y)
        big = 0.0
        for t in range(design_nbr.shape[1]):
            nbr = design_nbr[me, t]
            if nbr < 0:
                continue
            if not known[nbr]:
                n_missing += 1
                continue
            n_have += 1
            dx = design_xy[nbr, 0] - design_xy[me, 0]
            dy = design_xy[nbr, 1] - design_xy[me, 1]
            big = max(big, abs(dx), abs(dy))
            ux = P[row[nbr], 0] - P[i, 0]
            uy = P[row[nbr], 1] - P[i, 1]
            a += dx * dx
            b += dx * dy
            c += dy * dy
            gx0 += dx * ux
            gx1 += dy * ux
            gy0 += dx * uy
            gy1 += dy * uy
        if n_have < 2 or n_missing == 0:
            continue
        lmax = 0.5 * (a + c) + math.sqrt(0.25 * (a - c) * (a - c) + b * b)
        det = a * c - b * b
        if lmax <= 0.0 or math.sqrt(max(det / lmax, 0.0)) <= 1e-6 * big:
            continue                                   # the known neighbours on one line: no map
        # A (2, 2): design offset (row vector) -> previous image offset, A = G^-1 dD' Y
        a00 = (c * gx0 - b * gx1) / det
        a10 = (a * gx1 - b * gx0) / det
        a01 = (c * gy0 - b * gy1) / det
        a11 = (a * gy1 - b * gy0) / det
        k = 0
        for t in range(design_nbr.shape[1]):
            nbr = design_nbr[me, t]
            if nbr < 0 or known[nbr]:
                continue
            ex = design_xy[nbr, 0] - design_xy[me, 0]
            ey = design_xy[nbr, 1] - design_xy[me, 1]
            vx = ex * a00 + ey * a10                   # previous image offset
            vy = ex * a01 + ey * a11
            places[k, 0] = pred[i, 0] + vx * jac[i, 0] + vy * jac[i, 1]
            places[k, 1] = pred[i, 1] + vx * jac[i, 2] + vy * jac[i, 3]
            k += 1
        out[i] = _stands_apart(pts, by_y, ys, swept, places[:k], pred[i, 0], pred[i, 1], s_prev[i], oi, od)
    return out


@numba.njit(inline="always")
def _stands_apart(pts, by_y, ys, swept, places, x, y, spacing, oi, od):
    """:func:`stand_apart` on blobs ordered by :func:`~pipeline.vision.nearest.y_order` (``oi``, ``od``: one-entry
    buffers)."""
    nearest_in(pts, by_y, ys, swept, x, y, 1, oi, od)
    mine = oi[0]
    for k in range(len(places)):
        nearest_in(pts, by_y, ys, swept, places[k, 0], places[k, 1], 1, oi, od)
        if oi[0] == mine or not (math.sqrt(od[0]) <= F2F_APART * spacing):
            return False
    return True


def stand_apart(pts: np.ndarray, places: np.ndarray, pred: np.ndarray, spacing: float) -> bool:
    """Whether each of ``places`` (k, 2), where a marker's lost neighbours are put now, has a blob (of ``pts``
    (n, 2)) of its own within :data:`F2F_APART` local spacings (``spacing``, px) that is not the marker's
    nearest blob to its prediction ``pred`` (2,)."""
    pts = np.ascontiguousarray(pts, np.float64).reshape(-1, 2)
    if len(pts) == 0:
        return len(places) == 0
    return _stand_apart(pts, np.ascontiguousarray(places, np.float64).reshape(-1, 2), float(pred[0]), float(pred[1]),
                        float(spacing))


@numba.njit(cache=True, nogil=True)
def _stand_apart(pts, places, x, y, spacing):
    by_y, ys = np.empty(len(pts), np.int64), np.empty(len(pts))
    swept = y_order(pts, by_y, ys)
    return _stands_apart(pts, by_y, ys, swept, places, x, y, spacing, np.empty(1, np.int64), np.empty(1))
