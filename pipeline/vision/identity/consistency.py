"""Local consistency (test 1 of the certainty rule): every labelled blob and its identified
immediate neighbours agree with the leave-one-out affine fits of its design neighbourhood, or the
blob is the vertex of an intact fan; :func:`consistent` strips inconsistent labels until none is
left."""

from __future__ import annotations

import math

import numba
import numpy as np

from pipeline.vision.identity.constants import (_NEED_SEARCH, AMBIGUITY_MARGIN, CLOSE_BLOB, DISPLACED_REACH,
                                                EXTRAPOLATION_REACH, FAN_QUERY, GATE, GROW_GATE, LOCAL_ONLY,
                                                MIN_IMMEDIATE, R_AMBIGUOUS, R_FEW, R_INCONSISTENT, SETTLED,
                                                STANDS_OUT)
from pipeline.vision.identity.fans import _embedded
from pipeline.vision.identity.fits import _fit, _fit_sums, _fit_tab, _gather, _row_length
from pipeline.vision.identity.neighbours import _adj
from pipeline.vision.nearest import nearest_in, y_order


#: No blob competes for a slot beyond the growth gate (see ``rival`` of :func:`_loo_status`).
NO_RIVALS = np.zeros(0, np.bool_)


@numba.njit(cache=True, nogil=True)
def _consistency(pts, search, adj_ptr, adj_idx, slot_of, blob_of, xy, nbr, nbr2, loo_m, loo_tab, fan, closed,
                 pitch, gate, order, stop_after, rival):
    """Status of every labelled blob: 0 consistent, R_FEW too few neighbours, R_INCONSISTENT.

    The neighbourhood of a blob's slot is the identified slots of ``nbr2``; the blob itself and
    each identified immediate neighbour (``nbr``) must lie within ``gate`` local pitches of the
    position the affine map fitted to the rest of the neighbourhood predicts for it; and the blob
    must be the unambiguous nearest blob to its own prediction (R_AMBIGUOUS otherwise: at least
    twice as near as the second-nearest and 0.15 pitches nearer). A blob failing these is still
    consistent when it is the vertex of an intact image of its design fan (:func:`_embedded`).
    With ``search`` False (no blob searches: the first, cheap pass) a blob whose test needs a blob
    search gets :data:`_NEED_SEARCH` instead (not counted as inconsistent).
    Blobs are visited in ``order``; with ``stop_after`` > 0 the visit stops once that many are
    inconsistent (the anchoring test needs only that much evidence)."""
    n = len(slot_of)
    status = np.zeros(n, np.int64)
    K = nbr2.shape[1]
    slots = np.empty(K + 1, np.int64)
    blobs = np.empty(K + 1, np.int64)
    acc = np.empty(12)
    two = np.empty(2, np.int64)
    two_d2 = np.empty(2)
    ring = np.empty(fan.shape[1], np.int64)
    near = np.empty(FAN_QUERY, np.int64)
    near_d2 = np.empty(FAN_QUERY)
    # the blob searches sweep the blobs in y order, sorted at the first search (sweep[0]: 0 not yet,
    # 1 sorted, 2 not sortable: brute force)
    by_y = np.empty(len(pts), np.int64)
    ys = np.empty(len(pts))
    sweep = np.zeros(1, np.int64)
    n_bad = 0
    for b in order:
        if stop_after > 0 and n_bad >= stop_after:
            break
        s = slot_of[b]
        if s < 0:
            continue
        # an intact fan is the cheaper test, and the one a strongly pressed neighbourhood passes
        # (slots without a fan, e.g. every slot of a circular pattern, go straight to the fits)
        e = 0
        if fan[s, 0] >= 0:
            e = _embedded(pts, search, adj_ptr, adj_idx, b, s, blob_of, xy, fan, closed, pitch, gate, ring,
                          near, near_d2, acc)
        if e == 1:
            st = 0
        elif e == _NEED_SEARCH:
            st = _NEED_SEARCH
        else:
            # the extrapolation reach only where a design fan backs the slot's reading: a pattern
            # without fans (circular) has nothing else to stop a reading shifted by a marker once
            # the competed slots are withdrawn
            ext = EXTRAPOLATION_REACH if fan[s, 0] >= 0 else 0.0
            st = _loo_status(pts, search, b, s, slot_of, blob_of, xy, nbr, nbr2, loo_m, loo_tab, pitch, gate,
                             slots, blobs, acc, two, two_d2, K, by_y, ys, sweep, ext, rival)
        status[b] = st
        if st == R_INCONSISTENT:
            n_bad += 1
    return status


@numba.njit(cache=True, nogil=True)
def _search(pts, x, y, two, two_d2, by_y, ys, sweep):
    """The two blobs nearest to (x, y), as :func:`nearest` finds them (:func:`nearest_swept`)."""
    if sweep[0] == 0:
        sweep[0] = 1 if y_order(pts, by_y, ys) else 2
    nearest_in(pts, by_y, ys, sweep[0] == 1, x, y, 2, two, two_d2)


@numba.njit(cache=True, nogil=True)
def _loo_status(pts, search, b, s, slot_of, blob_of, xy, nbr, nbr2, loo_m, loo_tab, pitch, gate, slots, blobs, acc,
                two, two_d2, K, by_y, ys, sweep, extrapolation, rival):
    """The leave-one-out test of :func:`_consistency` for blob ``b`` labelled ``s``: its status.

    The immediate design neighbours ``nbr[s]`` are the first entries of ``nbr2[s]`` (both sorted
    by distance; :func:`lattice_of` checks it), so the identified neighbourhood is gathered in one
    pass with the immediate ones first, and the second shell only when it is fitted at all.

    A blob that passes every test while a free blob (``slot_of`` -1) lies within :data:`GROW_GATE` of
    its prediction is R_AMBIGUOUS when either blob may be the slot's marker: when the neighbourhood
    has a wide gap (the prediction is extrapolated, and its reach grows with the extrapolation by
    ``extrapolation``: :data:`EXTRAPOLATION_REACH` where the slot has a design fan, else 0), or when
    the blob is displaced from an otherwise affine neighbourhood (farther from its prediction than
    :data:`SETTLED` and :data:`STANDS_OUT` times the largest residual of its immediate neighbours),
    or when the free blob is no farther off than a bend of that neighbourhood may displace the slot's
    own pin (:data:`DISPLACED_REACH` times that residual). Decided last, so that a blob failing a
    neighbour's residual stays R_INCONSISTENT, the evidence the anchoring test counts.

    ``rival`` (per blob; :data:`NO_RIVALS` for none): blobs that may be the slot's own pin displaced by
    the bend. Such a blob competes within :data:`GROW_GATE` widened by the largest residual of the
    immediate neighbours, as far as :data:`DISPLACED_REACH` times it (the certified reading's last test,
    ``certify._unrivalled``; the other callers pass none and keep the growth gate)."""
    n_design = _row_length(nbr, s)
    slots[0] = s
    blobs[0] = b
    m = _gather(s, nbr2, 0, n_design, blob_of, slots, blobs, 1)
    n_imm = m - 1
    if n_imm < LOCAL_ONLY:
        # the second shell completes the neighbourhood fitted where few immediate neighbours are
        # identified; with LOCAL_ONLY or more, only the closed immediate neighbourhood is fitted,
        # where a strongly curved press is still affine
        m = _gather(s, nbr2, n_design, K, blob_of, slots, blobs, m)
    if m < 4 or n_imm < MIN_IMMEDIATE:
        return R_FEW
    ox, oy, ou, ov = xy[s, 0], xy[s, 1], pts[b, 0], pts[b, 1]
    # the whole design neighbourhood identified: the design half of each fit is tabulated
    whole = n_imm == n_design and m == loo_m[s]
    d1 = 0.0
    reach = GROW_GATE                       # where a free blob competes (widened below)
    d_free = 0.0                            # the second-nearest blob's distance from the prediction
    free_near = False
    bent_rival = False
    r_max = 0.0                             # largest residual of an immediate neighbour
    _fit_sums(xy, pts, slots, blobs, m, ox, oy, ou, ov, acc)
    for q in range(n_imm + 1):              # the blob itself and its immediate neighbours
        if whole:
            ok, mx, my, mu, mv, l00, l01, l10, l11 = _fit_tab(xy, pts, slots, blobs, acc, q, ox, oy, ou, ov, loo_tab[s, q])
            dx = loo_tab[s, q, 7]
            dy = loo_tab[s, q, 8]
        else:
            ok, mx, my, mu, mv, l00, l01, l10, l11 = _fit(xy, pts, slots, blobs, acc, q, ox, oy, ou, ov, pitch)
            dx = xy[slots[q], 0] - ox - mx
            dy = xy[slots[q], 1] - oy - my
        if ok < 0:
            return R_INCONSISTENT
        if ok == 0:
            if q == 0:
                return R_FEW
            continue
        pu = ou + mu + l00 * dx + l01 * dy
        pv = ov + mv + l10 * dx + l11 * dy
        scale = math.sqrt(l00 * l11 - l01 * l10) * pitch
        r = math.hypot(pts[blobs[q], 0] - pu, pts[blobs[q], 1] - pv) / scale
        if r > gate:
            return R_INCONSISTENT
        if q > 0:
            r_max = max(r_max, r)
        if q == 0 and len(pts) >= 2:
            if not search:
                return _NEED_SEARCH
            _search(pts, pu, pv, two, two_d2, by_y, ys, sweep)
            d1 = math.sqrt(two_d2[0]) / scale
            d2 = math.sqrt(two_d2[1]) / scale
            if two[0] != b or d2 < 2 * d1 or d2 - d1 < AMBIGUITY_MARGIN:
                return R_AMBIGUOUS
            if n_imm <= n_design - 2:
                # the prediction is extrapolated from one side of the slot: its error grows with the
                # offset of the identified immediate neighbours' centroid from the slot
                cx = 0.0
                cy = 0.0
                for k in range(1, n_imm + 1):
                    cx += xy[slots[k], 0] - ox
                    cy += xy[slots[k], 1] - oy
                reach += extrapolation * math.hypot(cx, cy) / (n_imm * pitch)
            free_near = slot_of[two[1]] < 0
            bent_rival = len(rival) > 0 and rival[two[1]]
            d_free = d2
            if n_imm <= n_design - 2:
                # a neighbourhood with a wide gap extrapolates its prediction: a second blob closer
                # to b than CLOSE_BLOB separations leaves open which of the two is the marker
                _search(pts, pts[b, 0], pts[b, 1], two, two_d2, by_y, ys, sweep)
                if math.sqrt(two_d2[1]) < CLOSE_BLOB * scale:
                    return R_AMBIGUOUS
    # the bend that shows in the neighbours' residuals displaces the slot's own pin too: a rival blob
    # competes within the growth gate widened by it, as far as that bend may displace the pin
    if bent_rival:
        reach = max(reach, min(reach + r_max, DISPLACED_REACH * r_max))
    free_near = free_near and d_free <= reach
    if free_near and (n_imm <= n_design - 2 or d1 > max(SETTLED, STANDS_OUT * r_max)
                      or d_free <= DISPLACED_REACH * r_max):
        return R_AMBIGUOUS
    return 0


def _blob_of(slot_of: np.ndarray, n_slots: int) -> np.ndarray:
    b = np.full(n_slots, -1, np.int64)
    lab = np.flatnonzero(slot_of >= 0)
    b[slot_of[lab]] = lab
    return b


def _statuses(pts, adj, slot_of, lat, order=None, rival=NO_RIVALS):
    """:func:`_consistency` of every labelled blob; blob searches run only for the blobs whose test
    needs one (usually none does: intact fans are checked on the Delaunay triangulation)."""
    blob_of = _blob_of(slot_of, len(lat.xy))
    order = np.arange(len(slot_of)) if order is None else order
    search = not lat.translation_lattice          # no fans: every test searches
    st = _consistency(pts, search, adj[0], adj[1], slot_of, blob_of, lat.xy, lat.nbr, lat.nbr2, lat.loo_m,
                      lat.loo_tab, lat.fan, lat.fan_closed, lat.pitch, GATE, order, 0, rival)
    need = np.flatnonzero(st == _NEED_SEARCH)
    if len(need):
        st2 = _consistency(pts, True, adj[0], adj[1], slot_of, blob_of, lat.xy, lat.nbr, lat.nbr2,
                           lat.loo_m, lat.loo_tab, lat.fan, lat.fan_closed, lat.pitch, GATE, need, 0, rival)
        st[need] = st2[need]
    return st


def consistent(pts, slot_of, lat, reason):
    """Remove labels failing local consistency until none does; records the reason per slot."""
    slot_of = slot_of.copy()
    adj = _adj(pts)
    for _ in range(len(lat.xy)):
        st = _statuses(pts, adj, slot_of, lat)
        bad = np.flatnonzero(st > 0)
        if len(bad) == 0:
            break
        reason[slot_of[bad]] = st[bad]
        slot_of[bad] = -1
    return slot_of
