"""Anchoring and rotation (tests 2 and 3 of the certainty rule): a patch of locally consistent ids is
kept only when every alternative reading of the design (lattice shifts, ring twists) is excluded by
evidence, no real outer row lies beyond it, a circular pattern's rings are centred, and its rotation
is within the unambiguous range."""

from __future__ import annotations

import math

import numba
import numpy as np

from pipeline.vision.identity.consistency import NO_RIVALS, _consistency
from pipeline.vision.identity.centring import (_centre_xy, _no_better_centre, _ring_gather, annulus_holds,
                                               centre_rings_covered)
from pipeline.vision.identity.constants import (ANCHOR_EVIDENCE, EVIDENCE_IMMEDIATE, GATE, R_INCONSISTENT, RING_CENTRE,
                                                RING_COVERAGE, RING_FIT_NO_COLLINEARITY_MM,
                                                RING_ROUND, RING_SHAPE)
from pipeline.vision.identity.fits import _design_half, _fit, _fit_sums, _gather, _image_half
from pipeline.vision.identity.lattice import RING_TWIST
from pipeline.vision.identity.neighbours import _adj
from pipeline.vision.nearest import nearest


@numba.njit(cache=True, nogil=True)
def _beyond_hits(pts, slot_of, blob_of, xy, nbr2, pitch, v_slot, v_xy, gate):
    """Per lattice site beyond the outer ring whose outer-ring slot is identified: 1 when an
    unidentified blob lies within ``gate`` local pitches of the site's position predicted from that
    slot's identified neighbourhood, else 0."""
    K = nbr2.shape[1]
    slots = np.empty(K + 1, np.int64)
    blobs = np.empty(K + 1, np.int64)
    one = np.empty(1, np.int64)
    one_d2 = np.empty(1)
    acc = np.empty(12)
    hit = np.zeros(len(v_slot), np.int64)
    for v in range(len(v_slot)):
        s = v_slot[v]
        b = blob_of[s]
        if b < 0:
            continue
        slots[0] = s
        blobs[0] = b
        m = _gather(s, nbr2, 0, K, blob_of, slots, blobs, 1)
        ox, oy, ou, ov = xy[s, 0], xy[s, 1], pts[b, 0], pts[b, 1]
        acc = _fit_sums(xy, pts, slots, blobs, m, ox, oy, ou, ov, acc)
        ok, mx, my, mu, mv, l00, l01, l10, l11 = _fit(xy, pts, slots, blobs, acc, -1, ox, oy, ou, ov, pitch)
        if ok <= 0:
            continue
        dx = v_xy[v, 0] - ox - mx
        dy = v_xy[v, 1] - oy - my
        pu = ou + mu + l00 * dx + l01 * dy
        pv = ov + mv + l10 * dx + l11 * dy
        nearest(pts, pu, pv, 1, one, one_d2)
        if slot_of[one[0]] < 0 and math.sqrt(one_d2[0]) <= gate * math.sqrt(l00 * l11 - l01 * l10) * pitch:
            hit[v] = 1
    return hit


@numba.njit(cache=True, nogil=True)
def _joined(s, j, blob_of, nbr):
    """Whether the design neighbours ``s`` and ``j`` share an identified design neighbour. A link
    without one is a bare edge across a gap: where a press crowds whole rows of pins out of the
    detection (a crest), the markers on either side of the gap are read as well one row or two
    over as in place (the missing rows shrink to nothing instead of to the crest's crowding, and
    the reading is the smoother one), so local consistency cannot tell the two readings apart
    there and the evidence that anchors one side says nothing about the other."""
    for a in range(nbr.shape[1]):
        t = nbr[s, a]
        if t < 0:
            break
        if t == j or blob_of[t] < 0:
            continue
        for b in range(nbr.shape[1]):
            u = nbr[j, b]
            if u < 0:
                break
            if u == t:
                return True
    return False


@numba.njit(cache=True, nogil=True)
def _components(slot_of, blob_of, nbr, triangles=False):
    """Connected patches of identified blobs (design neighbours within 1.5 pitches both identified):
    patch index per blob, -1 for unidentified blobs. With ``triangles``, two neighbours are joined
    only through an identified design triangle: a third marker, identified, neighbour of both
    (:func:`_joined`)."""
    n = len(slot_of)
    comp = np.full(n, -1, np.int64)
    stack = np.empty(n, np.int64)
    c = 0
    for b0 in range(n):
        if slot_of[b0] < 0 or comp[b0] >= 0:
            continue
        comp[b0] = c
        sp = 0
        stack[sp] = b0
        sp += 1
        while sp > 0:
            sp -= 1
            b = stack[sp]
            s = slot_of[b]
            for k in range(nbr.shape[1]):
                j = nbr[s, k]
                if j < 0:
                    break
                bj = blob_of[j]
                if bj >= 0 and comp[bj] < 0 and (not triangles or _joined(s, j, blob_of, nbr)):
                    comp[bj] = c
                    stack[sp] = bj
                    sp += 1
        c += 1
    return comp


@numba.njit(cache=True, nogil=True)
def _rotation_deg(pts_img, xy_des) -> float:
    """In-plane rotation (deg) of the Procrustes fit of image points onto design points."""
    m = len(pts_img)
    ax = ay = bx = by = 0.0
    for i in range(m):
        ax += xy_des[i, 0]
        ay += xy_des[i, 1]
        bx += pts_img[i, 0]
        by += pts_img[i, 1]
    ax /= m
    ay /= m
    bx /= m
    by /= m
    c00 = c01 = c10 = c11 = 0.0          # sum a_i b_i^T
    for i in range(m):
        p = xy_des[i, 0] - ax
        q = xy_des[i, 1] - ay
        u = pts_img[i, 0] - bx
        v = pts_img[i, 1] - by
        c00 += p * u
        c01 += p * v
        c10 += q * u
        c11 += q * v
    return math.degrees(math.atan2(c01 - c10, c00 + c11))


def _centre_holds(pts, slot_of, members, lat) -> bool:
    """The first three rings of a circular pattern, as identified, are rings of equally spaced
    markers about one point, seen through one smooth map: each ring's blobs (at least 2/3 of its
    slots) fit an affine image of the design ring to within :data:`RING_ROUND` of ring 1's mean
    radius, the three fits share their centre (within :data:`RING_CENTRE`: an off-centre press
    moves the rings' centres apart by ~0.1 radius) and their shape (linear parts proportional to
    within :data:`RING_SHAPE`: a press changes each ring's radius, a camera's perspective is common to all).
    About a marker of ring 1 the pattern also shows rings of about six and twelve markers, but its
    third ring is not eighteen markers 20 deg apart; where a press bends the rings and defects thin
    them to the coverage allowed, the same blobs read about a marker of ring 1 must not fit them
    better (:func:`~pipeline.vision.identity.centring._no_better_centre`). A patch without those rings
    (the centre hidden) is centred by three rings further out instead
    (:func:`~pipeline.vision.identity.centring.annulus_holds`)."""
    if not centre_rings_covered(slot_of, members, lat.layer_of):
        return annulus_holds(pts, slot_of, members, lat)
    return _centre_rings_hold(pts, slot_of, members, lat)


def _centre_rings_hold(pts, slot_of, members, lat) -> bool:
    """:func:`_centre_holds` on rings 1-3 (the patch holds them)."""
    return (_centre_kernel(pts, slot_of, members, lat.xy, lat.layer_of, RING_ROUND, RING_CENTRE)
            and _no_better_centre(pts, slot_of, members, lat))


_UNTWISTED: dict = {}


def _untwisted(lat) -> tuple[np.ndarray, np.ndarray]:
    """``lat.alt`` and ``lat.alt_first`` without the readings that turn every ring by a few slots; per
    lattice, computed once."""
    hit = _UNTWISTED.get(id(lat))
    if hit is None or hit[0] is not lat:
        keep = np.array([not name.startswith(RING_TWIST) for name in lat.alt_names], bool)
        hit = _UNTWISTED[id(lat)] = (lat, lat.alt[keep], lat.alt_first[keep])
    return hit[1], hit[2]


@numba.njit(cache=True, nogil=True)
def _centre_kernel(pts, slot_of, members, xy, layer_of, ring_round, ring_centre):
    """:func:`_centre_holds` (compiled)."""
    c0x, c0y = _centre_xy(xy, layer_of)
    L = np.zeros((3, 2, 2))
    cen = np.zeros((3, 2))
    res = np.zeros(3)
    sel = np.empty(len(members), np.int64)
    slots = np.empty(len(members), np.int64)
    acc = np.empty(12)
    for k in range(1, 4):
        m = _ring_gather(slot_of, members, layer_of, k, RING_COVERAGE, sel, slots)
        if m < 0:
            return False
        acc = _fit_sums(xy, pts, slots, sel, m, c0x, c0y, 0.0, 0.0, acc)
        ok, mx, my, mu, mv, l00, l01, l10, l11 = _fit(xy, pts, slots, sel, acc, -1, c0x, c0y, 0.0, 0.0,
                                                  RING_FIT_NO_COLLINEARITY_MM)
        if ok == 0:
            return False
        if ok < 0:
            # refit without the plausibility limits: a ring is judged by its residuals below
            _, mx, my, i00, i01, i11 = _design_half(acc[0], acc[1], acc[2], acc[5], acc[6], acc[7],
                                                    RING_FIT_NO_COLLINEARITY_MM)
            mu, mv, l00, l01, l10, l11 = _image_half(acc[0], mx, my, acc[3], acc[4], acc[8], acc[9], acc[10], acc[11],
                                                     i00, i01, i11)
        L[k - 1, 0, 0], L[k - 1, 0, 1], L[k - 1, 1, 0], L[k - 1, 1, 1] = l00, l01, l10, l11
        cen[k - 1, 0] = mu - l00 * mx - l01 * my
        cen[k - 1, 1] = mv - l10 * mx - l11 * my
        r = 0.0
        for i in range(m):
            dx = xy[slots[i], 0] - c0x
            dy = xy[slots[i], 1] - c0y
            pu = cen[k - 1, 0] + l00 * dx + l01 * dy
            pv = cen[k - 1, 1] + l10 * dx + l11 * dy
            r = max(r, math.hypot(pts[sel[i], 0] - pu, pts[sel[i], 1] - pv))
        res[k - 1] = r
    rad1 = 0.0
    n1 = 0
    for b in members:
        if layer_of[slot_of[b]] == 1:
            rad1 += math.hypot(pts[b, 0] - cen[0, 0], pts[b, 1] - cen[0, 1])
            n1 += 1
    rad1 /= n1
    if max(res[0], max(res[1], res[2])) > ring_round * rad1:
        return False
    for k in range(1, 3):
        if math.hypot(cen[k, 0] - cen[0, 0], cen[k, 1] - cen[0, 1]) > ring_centre * rad1:
            return False
        num = 0.0
        den = 0.0
        for i in range(2):
            for j in range(2):
                num += L[k, i, j] * L[0, i, j]
                den += L[0, i, j] * L[0, i, j]
        sc = num / den
        if not sc > 0:
            return False
        dev = 0.0
        ref = 0.0
        for i in range(2):
            for j in range(2):
                dev += (L[k, i, j] - sc * L[0, i, j]) ** 2
                ref += (sc * L[0, i, j]) ** 2
        if math.sqrt(dev) > RING_SHAPE * math.sqrt(ref):
            return False
    for b in members:
        if layer_of[slot_of[b]] == 0:
            if math.hypot(pts[b, 0] - cen[0, 0], pts[b, 1] - cen[0, 1]) > ring_centre * rad1:
                return False
    return True


def _anchored(pts, slot_of, members, lat) -> bool:
    """Is the patch ``members`` (blob indices) excluded from every alternative reading?"""
    alt, alt_first = lat.alt, lat.alt_first
    if not lat.translation_lattice:
        # rings of equally spaced markers read one ring further out, turned, or shifted by a
        # marker are locally almost a hexagonal lattice; only the rings about the centre fix the
        # reading: they must be concentric circles about one point
        if centre_rings_covered(slot_of, members, lat.layer_of):
            if not _centre_rings_hold(pts, slot_of, members, lat):
                return False
        elif annulus_holds(pts, slot_of, members, lat):
            # read without the centre rings: far out, turning every ring by a slot or two leaves the
            # neighbourhoods almost intact, so local evidence cannot exclude it; the rings' relative
            # turns (:func:`annulus_holds`) did
            alt, alt_first = _untwisted(lat)
        else:
            return False
    if len(alt) == 0:
        return True
    adj = _adj(pts)
    # without the blob search first (usually enough evidence), then with it
    for search in (False, True) if lat.translation_lattice else (True,):
        if _alternatives_excluded(pts, search, adj[0], adj[1], slot_of,
                                  members, alt, alt_first, lat.xy, lat.nbr, lat.nbr2, lat.loo_m, lat.loo_tab,
                                  lat.fan, lat.fan_closed, lat.pitch, GATE, ANCHOR_EVIDENCE):
            return True
    return False


@numba.njit(cache=True, nogil=True)
def _alternatives_excluded(pts, search, adj_ptr, adj_idx, slot_of, members, alt, alt_first, xy, nbr, nbr2, loo_m,
                           loo_tab, fan, closed, pitch, gate, evidence):
    """Every alternative reading ``alt[a]`` of the patch ``members`` is excluded by ``evidence``
    markers: pushed outside the design (its map gives -1; only markers with EVIDENCE_IMMEDIATE
    identified immediate neighbours count) or inconsistent under it. A reading that
    sends two markers to one slot keeps neither (no evidence either way). Blobs whose slots the
    reading breaks on the design itself (``alt_first`` 0) are tested first, and the test stops once
    the evidence is complete."""
    n_slots = alt.shape[1]
    n = len(slot_of)
    alt_slot = np.full(n, -1, np.int64)
    blob_of = np.full(n_slots, -1, np.int64)
    hits = np.zeros(n_slots, np.int64)
    order = np.empty(len(members), np.int64)
    # identified immediate neighbours of each member: only well-embedded markers are evidence
    in_patch = np.zeros(n_slots, np.bool_)
    for b in members:
        in_patch[slot_of[b]] = True
    embedded = np.zeros(n, np.bool_)
    for b in members:
        c = 0
        for k in range(nbr.shape[1]):
            j = nbr[slot_of[b], k]
            if j < 0:
                break
            if in_patch[j]:
                c += 1
        embedded[b] = c >= EVIDENCE_IMMEDIATE
    for a in range(alt.shape[0]):
        outside = 0
        for b in members:
            if alt[a, slot_of[b]] < 0 and embedded[b]:
                outside += 1
                if outside >= evidence:
                    break
        if outside >= evidence:
            continue
        hits[:] = 0
        for b in members:
            t = alt[a, slot_of[b]]
            if t >= 0:
                hits[t] += 1
        for b in members:
            t = alt[a, slot_of[b]]
            alt_slot[b] = t if (t >= 0 and hits[t] == 1) else -1
        blob_of[:] = -1
        for b in members:
            if alt_slot[b] >= 0:
                blob_of[alt_slot[b]] = b
        k = 0
        for first in range(2):
            for b in members:
                if alt_first[a, slot_of[b]] == first:
                    order[k] = b
                    k += 1
        need = evidence - outside
        st = _consistency(pts, search, adj_ptr, adj_idx, alt_slot, blob_of, xy, nbr, nbr2, loo_m, loo_tab, fan,
                          closed, pitch, gate, order, need, NO_RIVALS)
        bad = 0
        for b in members:
            if st[b] == R_INCONSISTENT:
                bad += 1
        for b in members:
            alt_slot[b] = -1
        if bad < need:
            return False
    return True
