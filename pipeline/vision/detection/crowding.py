"""Touching markers: whose light lights a candidate's ring, which candidates are flanked on opposite sides, and
centroids with a touching neighbour's light left out. Used by :func:`pipeline.vision.detection.rejection.screen`.

Each is one compiled pass over the candidates it examines (pins crowd under a steep flank; on a real TacTip view
~15-30 candidates touch a neighbour). The arithmetic is the numpy code's these replaced, in its order (sums
pairwise, :mod:`pipeline.vision.detection.numpy_order`; the median as ``np.median``), so the same blobs come out
bit for bit (tests/test_detection_kernels.py compares them on real and twin frames).
"""

from __future__ import annotations

import math

import numba
import numpy as np

from pipeline.vision.detection.images import U8_SCALE
from pipeline.vision.detection.numpy_order import float_sum, median
from pipeline.vision.detection.params import DetectionParams
from pipeline.vision.nearest import x_order, x_range
from pipeline.vision.detection.photometry import RING_IN, RING_WIDTH_PX, RUNAWAY_FRACTION, RUNAWAY_PX, SECTORS, \
    WINDOW_MARGIN_PX

__all__ = ["ring_spread", "flanked", "split_centroids", "PEER_HALF_ANGLE_RAD", "FLANK_MIN_ANGLE_RAD"]

#: A touching peer explains the ring sectors whose centre direction is within this angle (rad) of
#: its own: the sector it lies in and, when it sits near a boundary, the next one.
PEER_HALF_ANGLE_RAD = np.pi / 4
#: Two peers lighting a candidate's ring flank it when seen at least this angle apart from its centre.
FLANK_MIN_ANGLE_RAD = 3 * np.pi / 4
_SECTOR_CENTRES = -np.pi + (np.arange(SECTORS) + 0.5) * (2 * np.pi / SECTORS)


@numba.njit(cache=True, nogil=True)
def _touching(xy, radius, reach, order, xs, rmax, i):
    """Indices of the peers (``order``, x-ordered as ``xs``; other than ``i``) close enough to light candidate
    ``i``'s ring."""
    lo, hi = x_range(xs, xy[i, 0], reach[i] + rmax)
    out = np.empty(hi - lo, np.int64)
    m = 0
    for k in range(lo, hi):
        j = order[k]
        if j != i and math.hypot(xy[j, 0] - xy[i, 0], xy[j, 1] - xy[i, 1]) <= reach[i] + radius[j]:
            out[m] = j
            m += 1
    return out[:m]


@numba.njit(cache=True, nogil=True)
def _ring_spread_kernel(xy, radius, sectors, spread, reach, order, xs, rmax, examine, centres, half_angle):
    crowded = np.zeros(len(xy), np.bool_)
    n_sec = sectors.shape[1]
    for i in examine:
        near = _touching(xy, radius, reach, order, xs, rmax, i)
        if len(near) == 0:
            continue
        crowded[i] = True
        masked = np.zeros(n_sec, np.bool_)
        for j in near:
            ang = math.atan2(xy[j, 1] - xy[i, 1], xy[j, 0] - xy[i, 0])
            for s in range(n_sec):
                if abs((centres[s] - ang + np.pi) % (2 * np.pi) - np.pi) < half_angle:
                    masked[s] = True
        if masked.sum() <= n_sec // 2:
            best = -np.inf
            for s in range(n_sec):
                if not masked[s]:
                    v = sectors[i, s]
                    if np.isnan(v):
                        best = v
                        break
                    best = max(best, v)
            spread[i] = best
    return spread, crowded


def ring_spread(xy: np.ndarray, radius: np.ndarray, sectors: np.ndarray, peers: np.ndarray,
                examine: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Brightest ring sector (minus the ring median) per candidate, not counting sectors that look at
    a touching marker; and whether the candidate touches one.

    A marker squeezed against its neighbours (pins crowding under a steep flank) has bright ring
    sectors too, but that light is another marker's: sectors whose centre direction lies within
    :data:`PEER_HALF_ANGLE_RAD` (45 deg) of a ``peers`` candidate (one that passed the contrast, shape, saturation and
    upper size tests) closer than the two rings' reach (``RING_IN r + RING_WIDTH_PX + r_peer``) are left out. Glare
    stays rejected: a bright region that is not itself a marker-sized blob explains no sector. At least half
    the sectors must remain, else the candidate keeps its plain brightest sector. Only candidates with
    ``examine`` set are looked at (the others keep their plain spread and are not ``crowded``).

    Returns
    -------
    spread : (N,) brightest unexplained sector minus the ring median
    crowded : (N,) bool, a peer touches the candidate's ring
    """
    spread = sectors.max(axis=1)
    if np.count_nonzero(peers) < 2 or not examine.any():
        return spread, np.zeros(len(xy), dtype=bool)
    xy = np.ascontiguousarray(xy, np.float64)
    radius = np.ascontiguousarray(radius, np.float64)
    return _ring_spread_kernel(xy, radius, np.ascontiguousarray(sectors, np.float64), spread,
                               RING_IN * radius + RING_WIDTH_PX, *x_order(xy, peers), float(radius.max()),
                               np.flatnonzero(examine), _SECTOR_CENTRES, PEER_HALF_ANGLE_RAD)


@numba.njit(cache=True, nogil=True)
def _flanked_kernel(xy, radius, reach, order, xs, rmax, which, min_angle):
    out = np.zeros(len(xy), np.bool_)
    for i in which:
        near = _touching(xy, radius, reach, order, xs, rmax, i)
        if len(near) < 2:
            continue
        ang = np.empty(len(near))
        for k in range(len(near)):
            ang[k] = math.atan2(xy[near[k], 1] - xy[i, 1], xy[near[k], 0] - xy[i, 0])
        for a in range(len(near)):
            for b in range(len(near)):
                if abs((ang[a] - ang[b] + np.pi) % (2 * np.pi) - np.pi) >= min_angle:
                    out[i] = True
    return out


def flanked(xy: np.ndarray, radius: np.ndarray, which: np.ndarray, peers: np.ndarray) -> np.ndarray:
    """(N,) bool: candidates of ``which`` with two ``peers`` on opposite sides (seen at least
    :data:`FLANK_MIN_ANGLE_RAD` apart) each close enough to light its ring (``RING_IN r + RING_WIDTH_PX
    + r_peer``, as in :func:`ring_spread`)."""
    if np.count_nonzero(peers) < 2 or not which.any():
        return np.zeros(len(xy), bool)
    xy = np.ascontiguousarray(xy, np.float64)
    radius = np.ascontiguousarray(radius, np.float64)
    return _flanked_kernel(xy, radius, RING_IN * radius + RING_WIDTH_PX, *x_order(xy, peers), float(radius.max()),
                           np.flatnonzero(which), FLANK_MIN_ANGLE_RAD)


@numba.njit(cache=True, nogil=True)
def _split_kernel(grey, xy, radius, which, order, xs, radius_factor, iterations, u8_scale):
    out = xy.copy()
    h, w = grey.shape
    for i in which:
        r = radius[i]
        r_win = radius_factor * r + WINDOW_MARGIN_PX
        lo, hi = x_range(xs, xy[i, 0], 2 * r_win)
        nb = np.empty(hi - lo, np.int64)
        m = 0
        for k in range(lo, hi):               # the neighbours within twice the window of the blob's own centre
            j = order[k]
            if j != i and (xy[j, 0] - xy[i, 0]) ** 2 + (xy[j, 1] - xy[i, 1]) ** 2 <= (2 * r_win) ** 2:
                nb[m] = j
                m += 1
        c0, c1 = xy[i, 0], xy[i, 1]
        for _ in range(max(1, iterations)):
            x0, x1 = int(max(0, math.floor(c0 - r_win))), int(min(w - 1, math.ceil(c0 + r_win)))
            y0, y1 = int(max(0, math.floor(c1 - r_win))), int(min(h - 1, math.ceil(c1 + r_win)))
            ny, nx = y1 - y0 + 1, x1 - x0 + 1
            wts, wx, wy = np.zeros(ny * nx), np.zeros(ny * nx), np.zeros(ny * nx)
            ring = np.empty(ny * nx)
            n_ring = 0
            v = np.empty(ny * nx)
            own = np.zeros(ny * nx, np.bool_)
            for a in range(ny):
                gy = float(y0 + a)
                for b in range(nx):
                    gx = float(x0 + b)
                    k = a * nx + b
                    d2 = (gx - c0) ** 2 + (gy - c1) ** 2
                    mine = d2 <= r_win * r_win
                    for q in range(m):
                        mine = mine and d2 < (gx - xy[nb[q], 0]) ** 2 + (gy - xy[nb[q], 1]) ** 2
                    own[k] = mine
                    v[k] = np.float64(np.float32(grey[y0 + a, x0 + b]) * u8_scale)
                    if mine and d2 >= (RING_IN * r) ** 2:
                        ring[n_ring] = v[k]
                        n_ring += 1
            bg = median(ring[:n_ring]) if n_ring > 0 else 0.0
            for a in range(ny):
                for b in range(nx):
                    k = a * nx + b
                    wts[k] = max(v[k] - bg, 0.0) if own[k] else 0.0
                    wx[k] = wts[k] * float(x0 + b)
                    wy[k] = wts[k] * float(y0 + a)
            tot = float_sum(wts)
            if tot <= 0:
                break
            n0, n1 = float_sum(wx) / tot, float_sum(wy) / tot
            if math.hypot(n0 - xy[i, 0], n1 - xy[i, 1]) > RUNAWAY_FRACTION * r + RUNAWAY_PX:
                break
            c0, c1 = n0, n1
        out[i, 0], out[i, 1] = c0, c1
    return out


def split_centroids(grey: np.ndarray, xy: np.ndarray, radius: np.ndarray, which: np.ndarray,
                    peers: np.ndarray, params: DetectionParams) -> np.ndarray:
    """Centroids of touching markers with each neighbour's light excluded.

    The plain centroid window (``centroid_radius_factor`` x r) of a marker squeezed against another
    takes in the neighbour's edge and is pulled toward it (measured ~1.5 px for a 1 px gap). For the
    candidates in ``which`` the window is split Voronoi-wise: pixels nearer to a ``peers`` centre (one within
    twice the window of the candidate) than to this one are left out; background = median of the window's
    remaining pixels outside ``RING_IN r``. Two re-centred passes, as for isolated markers. Returns the updated
    (N, 2) centres.
    """
    if not which.any():
        return xy.copy()
    xy = np.ascontiguousarray(xy, np.float64)
    return _split_kernel(np.ascontiguousarray(grey), xy, np.ascontiguousarray(radius, np.float64),
                         np.flatnonzero(which), *x_order(xy, peers), float(params.centroid_radius_factor),
                         int(params.centroid_iterations), U8_SCALE)
