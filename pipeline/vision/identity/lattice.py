"""The design geometry the certainty rule needs, computed once per pattern (:class:`Lattice`):
neighbour tables, symmetry, the alternative readings of a patch, the sites beyond the outer ring,
the design fans and the tables of the leave-one-out fits."""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from scipy.spatial import cKDTree

from pipeline.vision.identity.consistency import NO_RIVALS, _blob_of, _consistency
from pipeline.vision.identity.constants import (BEYOND_EMPTY, FAN_MAX_GAP_DEG, GATE, IMMEDIATE_PITCHES, LATTICE_STEP,
                                                MIN_PATCH, NEIGHBOURHOOD_PITCHES, R_INCONSISTENT, ROTATION_MARGIN_DEG,
                                                SLOT_MATCH_SHIFT, SLOT_MATCH_SYMMETRY)
from pipeline.vision.identity.fans import _fan_turns_once
from pipeline.vision.identity.fits import _loo_design


@dataclass(frozen=True)
class Lattice:
    """Design geometry the certainty rule needs, computed once per pattern.

    ``xy`` (N, 2) design x-y (mm); ``pitch`` median nearest-neighbour distance (mm); ``nbr`` (N, K)
    design neighbours within 1.5 pitches, -1 padded, nearest first; ``nbr2`` the same within
    :data:`NEIGHBOURHOOD_PITCHES`; ``alpha_deg`` rotational symmetry angle;
    ``alt`` (A, N) slot -> slot maps of the alternative readings (-1: outside the design);
    ``alt_names`` their descriptions; ``layer_of`` (N,) ring of each slot (0 = centre);
    ``translation_lattice`` whether the pattern is a piece of a translation lattice (hexagonal,
    square) rather than rings of equally spaced markers (circular); ``alt_first`` (A, N) 0 where an
    alternative breaks the slot's neighbourhood on the design itself (tested first), else 1;
    ``beyond_slot`` (V,), ``beyond_xy`` (V, 2) lattice sites one step beyond the outer ring and the
    outer-ring slot each is predicted from (empty for circular patterns); ``fan`` (N, K) the design
    neighbours of ``nbr`` in counter-clockwise order about each slot, -1 padded: a closed fan of
    triangles where they surround the slot (``fan_closed``), else (the outer ring) an open one
    starting after the widest gap; a row of -1 where they form neither.
    """

    xy: np.ndarray
    pitch: float
    nbr: np.ndarray
    nbr2: np.ndarray
    alpha_deg: float
    alt: np.ndarray
    alt_names: tuple
    layer_of: np.ndarray
    translation_lattice: bool
    alt_first: np.ndarray
    beyond_slot: np.ndarray
    beyond_xy: np.ndarray
    outer_ring: np.ndarray
    fan: np.ndarray
    fan_closed: np.ndarray
    loo_m: np.ndarray
    loo_tab: np.ndarray


_CACHE: dict = {}
#: How the alternative readings that turn every ring by a few slots are named (``Lattice.alt_names``).
RING_TWIST = "each ring turned by"


def lattice_of(design) -> Lattice:
    key = (design.pattern.kind, design.pattern.layers, design.pattern.separation_mm)
    if key in _CACHE:
        return _CACHE[key]
    xy = np.ascontiguousarray(design.rest_markers_mm()[:, :2], dtype=np.float64)
    layers = design.marker_layers()
    n = len(xy)
    tree = cKDTree(xy)
    d, _ = tree.query(xy, k=2)
    pitch = float(np.median(d[:, 1]))
    def table(radius):
        lists = tree.query_ball_point(xy, radius * pitch)
        k = max(len(x) for x in lists) - 1
        t = np.full((n, max(k, 1)), -1, np.int64)
        for i, lst in enumerate(lists):
            others = sorted((j for j in lst if j != i), key=lambda j: (np.hypot(*(xy[j] - xy[i])), j))
            t[i, :len(others)] = others
        return t

    nbr, nbr2 = table(IMMEDIATE_PITCHES), table(NEIGHBOURHOOD_PITCHES)
    # both tables are sorted by distance, so each slot's immediate neighbours open its wider
    # neighbourhood (the leave-one-out test gathers them in one pass relying on it)
    n_imm = np.count_nonzero(nbr >= 0, axis=1)
    if not all(np.array_equal(nbr2[i, :n_imm[i]], nbr[i, :n_imm[i]]) for i in range(n)):
        raise AssertionError(f"{design.name}: the immediate design neighbours do not open the wider neighbourhood")
    # rotational symmetry: the largest k-fold rotation mapping the design onto itself
    c = xy.mean(axis=0)
    alpha = 360.0
    for fold in (12, 8, 6, 4, 3, 2):
        t = 2 * math.pi / fold
        R = np.array([[math.cos(t), -math.sin(t)], [math.sin(t), math.cos(t)]])
        dd, _ = tree.query((xy - c) @ R.T + c)
        if np.all(dd < SLOT_MATCH_SYMMETRY * pitch):
            alpha = 360.0 / fold
            break
    # alternatives: every lattice translation that keeps some slots on slots, and ring twists
    centre = int(np.argmin(np.hypot(*(xy - c).T)))
    maps, names = [], []
    for s in range(n):
        if s == centre:
            continue
        t = xy[s] - xy[centre]
        dd, jj = tree.query(xy + t)
        m = np.where(dd < SLOT_MATCH_SHIFT * pitch, jj, -1)
        if np.count_nonzero(m >= 0) >= MIN_PATCH:
            maps.append(m)
            names.append(f"shifted by ({t[0]:+.2f}, {t[1]:+.2f}) mm")
    for j in (-2, -1, 1, 2):
        m = np.arange(n)
        for lay in np.unique(layers):
            ids = np.flatnonzero(layers == lay)
            if len(ids) > 1:
                m[ids] = ids[(np.arange(len(ids)) + j) % len(ids)]
        maps.append(m)
        names.append(f"{RING_TWIST} {j:+d} slot(s)")
    # rings read one ring further out / in (slot -> the slot of the next ring at the nearest angle):
    # on a circular pattern a patch away from the centre is locally the same either way
    ring_ids = [np.flatnonzero(layers == lay) for lay in range(int(layers.max()) + 1)]
    ang = np.arctan2(xy[:, 1] - c[1], xy[:, 0] - c[0])
    for step in (1, -1):
        m = np.full(n, -1, np.int64)
        for lay, ids in enumerate(ring_ids):
            if not 0 <= lay + step < len(ring_ids):
                continue
            tgt = ring_ids[lay + step]
            if len(ids) == 1 or len(tgt) == 1:
                m[ids] = tgt[0] if len(tgt) == 1 else -1
                continue
            dang = np.abs(np.angle(np.exp(1j * (ang[ids][:, None] - ang[tgt][None, :]))))
            m[ids] = tgt[np.argmin(dang, axis=1)]
        maps.append(m)
        names.append(f"rings read one ring {'further out' if step > 0 else 'further in'}")
    # hexagonal and square patterns are pieces of a translation lattice; circular ones are not
    lattice = design.pattern.kind in ("hexagon", "square")
    # sites one lattice step beyond the outer ring (hexagonal and square patterns): a reading
    # shifted by a row finds the pattern's real outer row there
    v_slot, v_xy = [], []
    if lattice:
        centre_nb = nbr[centre][nbr[centre] >= 0]
        steps = xy[centre_nb] - xy[centre]
        steps = steps[np.hypot(*steps.T) <= LATTICE_STEP * pitch]
        outer = np.flatnonzero(layers == layers.max())
        for s_ in outer:
            for v in steps:
                q = xy[s_] + v
                if tree.query(q)[0] > BEYOND_EMPTY * pitch:
                    v_slot.append(s_)
                    v_xy.append(q)
    v_slot = np.asarray(v_slot, np.int64)
    v_xy = np.asarray(v_xy, np.float64).reshape(-1, 2)
    # fans: the immediate neighbours in counter-clockwise order, closed where they surround the
    # slot (every triangle of the fan turns counter-clockwise and the fan turns once). Only on
    # translation lattices (hexagonal, square): concentric rings of equally spaced markers are
    # locally almost a hexagonal lattice in many readings (a reading of a pressed circular pattern
    # shifted by a marker kept intact fans over 150 of 217 markers in the identification benchmark),
    # and only the metric leave-one-out fits tell those apart.
    fan = np.full(nbr.shape, -1, np.int64)
    fan_closed = np.zeros(n, bool)
    for s_ in range(n if lattice else 0):
        nb_ = nbr[s_][nbr[s_] >= 0]
        if len(nb_) < 3:
            continue
        a_ = np.arctan2(xy[nb_, 1] - xy[s_, 1], xy[nb_, 0] - xy[s_, 0])
        o_ = np.argsort(a_, kind="stable")
        cyc, a_ = nb_[o_], a_[o_]
        gaps = np.diff(np.concatenate([a_, [a_[0] + 2 * np.pi]]))
        if gaps.max() <= np.radians(FAN_MAX_GAP_DEG):
            if _fan_turns_once(xy, s_, cyc, len(cyc)):
                fan[s_, :len(cyc)] = cyc
                fan_closed[s_] = True
            continue
        # open fan (the outer ring): start after the widest gap; every other step must turn
        # counter-clockwise by less than the gap limit
        k0 = (int(np.argmax(gaps)) + 1) % len(cyc)
        cyc = np.roll(cyc, -k0)
        inner_gaps = np.delete(np.roll(gaps, -k0), -1)
        if inner_gaps.size and inner_gaps.max() <= np.radians(FAN_MAX_GAP_DEG) and inner_gaps.min() > 0:
            fan[s_, :len(cyc)] = cyc
    # per alternative: 0 for the slots whose neighbourhoods it breaks on the design itself, else 1
    alt = np.array(maps, np.int64).reshape(-1, n)
    loo_m, loo_tab = _loo_design(xy, nbr, nbr2, pitch)
    first = np.ones(alt.shape, np.int64)
    for a in range(len(alt)):
        g = alt[a].copy()
        u, cnt = np.unique(g[g >= 0], return_counts=True)
        g[np.isin(g, u[cnt > 1])] = -1
        st = _consistency(xy, True, np.zeros(n + 1, np.int64), np.zeros(0, np.int64), g, _blob_of(g, n), xy,
                          nbr, nbr2, loo_m, loo_tab, fan, fan_closed, pitch, GATE, np.arange(n), 0, NO_RIVALS)
        first[a, st == R_INCONSISTENT] = 0
    outer_ring = np.flatnonzero(layers == layers.max()).astype(np.int64)
    lat = Lattice(xy, pitch, nbr, nbr2, alpha, alt, tuple(names),
                  layers.astype(np.int64), lattice, first, v_slot, v_xy, outer_ring, fan, fan_closed, loo_m, loo_tab)
    _CACHE[key] = lat
    return lat


def rotation_limit_deg(lat: Lattice) -> float:
    """Largest |in-plane rotation| at which ids are emitted (half the symmetry angle minus the margin)."""
    return lat.alpha_deg / 2 - ROTATION_MARGIN_DEG
