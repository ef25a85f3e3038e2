"""A circular pattern's centring against its nearest rival: the same blobs read with the centre on a marker
of ring 1 (part of the anchoring test, :mod:`pipeline.vision.identity.anchoring`)."""

from __future__ import annotations

import math

import numba
import numpy as np

from pipeline.vision.identity.constants import (RING_ALT_COVERAGE, RING_ALT_RATIO, RING_COVERAGE,
                                                RING_FIT_NO_COLLINEARITY_MM, RING_MIN_MARKERS)
from pipeline.vision.identity.fits import _design_half, _fit_sums, _image_half


@numba.njit(cache=True, nogil=True)
def _centre_xy(xy, layer_of):
    """Design x-y of the centre slot (ring 0) of a circular pattern."""
    c0x = 0.0
    c0y = 0.0
    for s in range(len(layer_of)):
        if layer_of[s] == 0:
            c0x, c0y = xy[s, 0], xy[s, 1]
    return c0x, c0y


@numba.njit(cache=True, nogil=True)
def _ring_gather(slot_of, members, layer_of, k, min_cov, sel, slots):
    """The blobs of ``members`` that ``slot_of`` puts on ring ``k`` into ``sel`` and their slots into ``slots``;
    their count, or -1 when they are fewer than ``min_cov`` of the ring's slots or fewer than
    :data:`RING_MIN_MARKERS` (too few to judge the ring by)."""
    size = 0
    for s in range(len(layer_of)):
        if layer_of[s] == k:
            size += 1
    m = 0
    for b in members:
        if slot_of[b] >= 0 and layer_of[slot_of[b]] == k:
            sel[m] = b
            slots[m] = slot_of[b]
            m += 1
    if m < max(int(math.ceil(min_cov * size)), RING_MIN_MARKERS):
        return -1
    return m


@numba.njit(cache=True, nogil=True)
def _ring_residual(pts, slot_of, members, xy, layer_of, min_cov):
    """The largest residual of the per-ring affine fits of rings 1-3 (design ring -> the blobs of
    ``members`` that ``slot_of`` puts on it), over the mean radius of ring 1 about its fit's centre, as
    :func:`_centre_kernel` measures it; -1 where a ring has fewer than ``min_cov`` of its slots (or 4)."""
    c0x, c0y = _centre_xy(xy, layer_of)
    sel = np.empty(len(members), np.int64)
    slots = np.empty(len(members), np.int64)
    acc = np.empty(12)
    worst = 0.0
    rad1 = 1.0
    for k in range(1, 4):
        m = _ring_gather(slot_of, members, layer_of, k, min_cov, sel, slots)
        if m < 0:
            return -1.0
        acc = _fit_sums(xy, pts, slots, sel, m, c0x, c0y, 0.0, 0.0, acc)
        _, mx, my, i00, i01, i11 = _design_half(acc[0], acc[1], acc[2], acc[5], acc[6], acc[7],
                                                RING_FIT_NO_COLLINEARITY_MM)
        mu, mv, l00, l01, l10, l11 = _image_half(acc[0], mx, my, acc[3], acc[4], acc[8], acc[9], acc[10], acc[11],
                                                 i00, i01, i11)
        cu = mu - l00 * mx - l01 * my
        cv = mv - l10 * mx - l11 * my
        r = 0.0
        rsum = 0.0
        for i in range(m):
            dx = xy[slots[i], 0] - c0x
            dy = xy[slots[i], 1] - c0y
            r = max(r, math.hypot(pts[sel[i], 0] - cu - l00 * dx - l01 * dy, pts[sel[i], 1] - cv - l10 * dx - l11 * dy))
            rsum += math.hypot(pts[sel[i], 0] - cu, pts[sel[i], 1] - cv)
        if k == 1:
            rad1 = rsum / m
        worst = max(worst, r)
    return worst / rad1 if rad1 > 0 else -1.0


_RING1_SHIFTS: dict = {}


def _ring1_shifts(lat) -> np.ndarray:
    """(N, 6) the slot each slot becomes when the reading is moved so that the centre falls on each
    marker of ring 1 (the nearest slot within 0.3 pitches, else -1); per lattice, computed once."""
    key = id(lat)
    hit = _RING1_SHIFTS.get(key)
    if hit is not None and hit[0] is lat:
        return hit[1]
    from scipy.spatial import cKDTree

    centre = lat.xy[np.flatnonzero(lat.layer_of == 0)[0]]
    tree = cKDTree(lat.xy)
    cols = []
    for s1 in np.flatnonzero(lat.layer_of == 1):
        d, j = tree.query(lat.xy - (lat.xy[s1] - centre))
        cols.append(np.where(d < 0.3 * lat.pitch, j, -1))
    tab = np.ascontiguousarray(np.column_stack(cols).astype(np.int64))
    _RING1_SHIFTS[key] = (lat, tab)
    return tab


def _no_better_centre(pts, slot_of, members, lat) -> bool:
    """No reading of the same blobs centred on a marker of ring 1 instead fits rings 1-3 as rings of
    equally spaced markers :data:`RING_ALT_RATIO` times better than this one. Near the centre a
    circular pattern is locally a hexagonal lattice, so a reading centred one marker off passes the
    per-ring gates where a press bends the rings and defects thin them to the coverage allowed
    (circular217, 5 mm, sigma 3 mm, 0.66 mm off the axis, 2 % defects: 158 ids, all wrong, rings 1-3 at
    0.21 of ring 1's radius, the true centring of those blobs at 0.017)."""
    r0 = _ring_residual(pts, slot_of, members, lat.xy, lat.layer_of, RING_COVERAGE)
    if r0 <= 0:
        return True
    tab = _ring1_shifts(lat)
    alt = np.full(len(slot_of), -1, np.int64)
    for j in range(tab.shape[1]):
        alt[members] = tab[slot_of[members], j]
        r = _ring_residual(pts, alt, members, lat.xy, lat.layer_of, RING_ALT_COVERAGE)
        if r > 0 and r0 > RING_ALT_RATIO * r:
            return False
    return True
