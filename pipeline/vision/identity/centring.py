"""A circular pattern's centring against its nearest rival: the same blobs read with the centre on a marker
of ring 1 (part of the anchoring test, :mod:`pipeline.vision.identity.anchoring`)."""

from __future__ import annotations

import math

import numba
import numpy as np

from pipeline.vision.identity.constants import (ANNULUS_COVERAGE, ANNULUS_TWIST, RING_ALT_COVERAGE, RING_ALT_RATIO,
                                                RING_CENTRE, RING_COVERAGE, RING_FIT_NO_COLLINEARITY_MM,
                                                RING_MIN_MARKERS, RING_ROUND, RING_SHAPE)
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
def _ring_map(pts, slots, sel, m, xy, c0x, c0y, acc):
    """The least-squares affine map of a ring's design slots ``slots[:m]`` (about the design centre (c0x, c0y))
    onto its blobs ``sel[:m]``: (image of the centre u, v, L00, L01, L10, L11); ``acc`` (12,) work array."""
    acc = _fit_sums(xy, pts, slots, sel, m, c0x, c0y, 0.0, 0.0, acc)
    _, mx, my, i00, i01, i11 = _design_half(acc[0], acc[1], acc[2], acc[5], acc[6], acc[7],
                                            RING_FIT_NO_COLLINEARITY_MM)
    mu, mv, l00, l01, l10, l11 = _image_half(acc[0], mx, my, acc[3], acc[4], acc[8], acc[9], acc[10], acc[11],
                                             i00, i01, i11)
    return mu - l00 * mx - l01 * my, mv - l10 * mx - l11 * my, l00, l01, l10, l11


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
        cu, cv, l00, l01, l10, l11 = _ring_map(pts, slots, sel, m, xy, c0x, c0y, acc)
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
    return _no_better_centre_kernel(pts, slot_of, members, lat.xy, lat.layer_of, _ring1_shifts(lat))


@numba.njit(cache=True, nogil=True)
def _no_better_centre_kernel(pts, slot_of, members, xy, layer_of, tab):
    """:func:`_no_better_centre` in one compiled call (``tab``: :func:`_ring1_shifts`)."""
    r0 = _ring_residual(pts, slot_of, members, xy, layer_of, RING_COVERAGE)
    if r0 <= 0:
        return True
    alt = np.full(len(slot_of), -1, np.int64)
    for j in range(tab.shape[1]):
        for b in members:
            alt[b] = tab[slot_of[b], j]
        r = _ring_residual(pts, alt, members, xy, layer_of, RING_ALT_COVERAGE)
        if r > 0 and r0 > RING_ALT_RATIO * r:
            return False
    return True


def _covered(slot_of, members, layer_of, k, min_cov) -> tuple[np.ndarray, np.ndarray]:
    """(blobs, their slots) of ``members`` that ``slot_of`` puts on ring ``k`` (:func:`_ring_gather`; empty when
    fewer than ``min_cov`` of the ring's slots or than :data:`RING_MIN_MARKERS`)."""
    sel, slots = np.empty(len(members), np.int64), np.empty(len(members), np.int64)
    m = max(_ring_gather(slot_of, members, layer_of, k, min_cov, sel, slots), 0)
    return sel[:m], slots[:m]


def centre_rings_covered(slot_of, members, layer_of) -> bool:
    """Rings 1-3 each hold :data:`RING_COVERAGE` of their slots (the centre test can be made)."""
    return all(len(_covered(slot_of, members, layer_of, k, RING_COVERAGE)[0]) for k in (1, 2, 3))


def annulus_holds(pts, slot_of, members, lat) -> bool:
    """:func:`annulus_twist` within :data:`ANNULUS_TWIST`."""
    twist = annulus_twist(pts, slot_of, members, lat)
    return twist is not None and twist <= ANNULUS_TWIST


def annulus_twist(pts, slot_of, members, lat) -> float | None:
    """The centre test of a circular pattern read without its centre rings (a glare spot or an
    occluder over the middle of the skin): three consecutive rings further out, each holding
    :data:`ANNULUS_COVERAGE` of its slots, are rings of equally spaced markers about one point seen
    through one smooth map, as :func:`~pipeline.vision.identity.anchoring._centre_holds` asks of rings
    1-3 (:data:`RING_ROUND`, :data:`RING_CENTRE`, :data:`RING_SHAPE`, in image pitches), and they are
    not twisted against each other.

    Far from the centre a ring of n markers turned by one slot is still a ring, its affine fit as good,
    and its neighbours barely notice (rings k and k + 1 turned by one slot each differ by
    60 / (k (k + 1)) deg); only the rings' relative turns tell the reading from a twisted one. Each ring's
    affine map has a rotation; a reading with every ring turned by one slot spreads those rotations by
    2 pi (1 / n_k0 - 1 / n_k2) (5 deg for rings 4-6, 2.5 deg for rings 6-8) more than the true one.
    Returns the spread in units of that twist (:func:`annulus_holds` keeps it below
    :data:`ANNULUS_TWIST`, so that the true reading and a twisted one cannot both pass), or None where the
    rings fail the other tests or three such rings are not there."""
    layer_of = lat.layer_of
    top = int(layer_of.max())
    c0 = np.array(_centre_xy(lat.xy, layer_of))
    for k0 in range(2, top - 1):
        rings = [_covered(slot_of, members, layer_of, k, ANNULUS_COVERAGE) for k in (k0, k0 + 1, k0 + 2)]
        if all(len(on) for on, _ in rings):
            break
    else:
        return None
    L, cen, turn, worst = [], [], [], 0.0
    acc = np.empty(12)
    for on, slots in rings:
        cu, cv, l00, l01, l10, l11 = _ring_map(pts, slots, on, len(on), lat.xy, c0[0], c0[1], acc)
        L.append(np.array([[l00, l01], [l10, l11]]))
        cen.append(np.array([cu, cv]))
        worst = max(worst, float(np.hypot(*((lat.xy[slots] - c0) @ L[-1].T + cen[-1] - pts[on]).T).max()))
        turn.append(math.atan2(l10 - l01, l00 + l11))
    ring0 = layer_of == k0
    pitch = float(np.hypot(*(pts[rings[0][0]] - cen[0]).T).mean()
                  / (np.hypot(*(lat.xy[ring0] - c0).T).mean() / lat.pitch))   # image pitch at ring k0
    if worst > RING_ROUND * pitch:
        return None
    for k in (1, 2):
        if np.hypot(*(cen[k] - cen[0])) > RING_CENTRE * pitch:
            return None
        sc = float(np.sum(L[k] * L[0]) / np.sum(L[0] * L[0]))
        if not sc > 0 or np.linalg.norm(L[k] - sc * L[0]) > RING_SHAPE * sc * np.linalg.norm(L[0]):
            return None
    centre = members[layer_of[slot_of[members]] == 0]
    if len(centre) and np.hypot(*(pts[centre[0]] - cen[0])) > RING_CENTRE * pitch:
        return None
    spread = np.ptp(np.unwrap(np.array(turn)))
    n = [int(np.count_nonzero(layer_of == k)) for k in (k0, k0 + 2)]
    return float(spread / (2 * math.pi * (1 / n[0] - 1 / n[1])))
