"""Intact fans: a marker whose design neighbours surround it in the image as they do in the design
(no fold, swap or mirror, nothing else inside) is consistent however strongly a press crowds them."""

from __future__ import annotations

import math

import numba

from pipeline.vision.identity.constants import _NEED_SEARCH, FAN_DEGENERATE, FAN_MAX_GAP_DEG, FAN_MAX_STRETCH
from pipeline.vision.identity.fits import _fit_sums
from pipeline.vision.nearest import nearest


@numba.njit(cache=True, nogil=True)
def _fan_turns_once(p, c, ring, m):
    """Do the points ``p[ring[:m]]`` surround ``p[c]`` as a closed fan: every triangle
    (c, ring[i], ring[i+1]) counter-clockwise and the fan turning once about ``c``? (With every step
    counter-clockwise, the turns are the crossings of the ray from ``c`` along +x.)"""
    if m < 3:
        return False
    turns = 0
    cx = p[c, 0]
    cy = p[c, 1]
    for i in range(m):
        a = ring[i]
        b = ring[i + 1] if i + 1 < m else ring[0]
        ax = p[a, 0] - cx
        ay = p[a, 1] - cy
        bx = p[b, 0] - cx
        by = p[b, 1] - cy
        if ax * by - ay * bx <= 0.0:
            return False
        if ay < 0.0 <= by:                    # upward, and (counter-clockwise step) at x > 0
            turns += 1
    return turns == 1


@numba.njit(cache=True, nogil=True)
def _embedded(pts, search, adj_ptr, adj_idx, b, s, blob_of, xy, fan, closed, pitch, gate, ring, near, near_d2,
              acc):
    """Is blob ``b`` the vertex of an intact image of its slot's design fan (deformed-ring
    certification)? Every design neighbour of the closed fan ``fan[s]`` is identified; their blobs
    surround ``b`` counter-clockwise in the design's order, turning once (no fold, no swap, no
    mirror); no other blob lies inside the fan; and ``b`` lies within ``gate`` local pitches of the
    position the affine map of its neighbours predicts (stretch up to :data:`FAN_MAX_STRETCH`). A
    smooth deformation keeps all of this however strongly it crowds or shears the fan, so the
    complete rings of a pressed skin are certified where the leave-one-out fits of
    :func:`_consistency` (which must extrapolate across a strongly curved neighbourhood) fail.

    An open fan (a slot of the outer ring, ``closed[s]`` False) must turn counter-clockwise at every
    step but the widest and be exactly ``b``'s Delaunay neighbourhood (``adj_ptr``, ``adj_idx``:
    :func:`use_triangulation`; nothing else touches ``b``, outside the pattern included).

    Returns 1 (intact), 0 (not), or :data:`_NEED_SEARCH` when only the blob search of the emptiness
    test is left and ``search`` (blob searches allowed) is False. ``ring``, ``near``, ``near_d2``, ``acc``:
    work arrays (fan width, >= :data:`FAN_QUERY`, and (12,) for the sums of
    :func:`~pipeline.vision.identity.fits._fit_sums`, which the fan's affine map shares)."""
    K = fan.shape[1]
    if fan[s, 0] < 0:
        return 0
    m = 0
    for k in range(K):
        j = fan[s, k]
        if j < 0:
            break
        if blob_of[j] < 0:
            return 0
        ring[m] = blob_of[j]
        m += 1
    if closed[s]:
        if not _fan_turns_once(pts, b, ring, m):
            return 0
    else:
        total = 0.0
        for i in range(m - 1):
            ax = pts[ring[i], 0] - pts[b, 0]
            ay = pts[ring[i], 1] - pts[b, 1]
            bx = pts[ring[i + 1], 0] - pts[b, 0]
            by = pts[ring[i + 1], 1] - pts[b, 1]
            cr = ax * by - ay * bx
            if cr <= 0.0:
                return 0
            total += math.atan2(cr, ax * bx + ay * by)
        if total >= 2.0 * math.pi - math.radians(FAN_MAX_GAP_DEG):
            return 0
    # the neighbours' affine map (least squares, design relative to slot s, image relative to b)
    # predicts b
    _fit_sums(xy, pts, fan[s], ring, m, xy[s, 0], xy[s, 1], pts[b, 0], pts[b, 1], acc)
    sx, sy, su, sv = acc[1], acc[2], acc[3], acc[4]
    sxx, sxy, syy = acc[5], acc[6], acc[7]
    sux, suy, svx, svy = acc[8], acc[9], acc[10], acc[11]
    mx, my, mu, mv = sx / m, sy / m, su / m, sv / m
    sxx -= m * mx * mx
    sxy -= m * mx * my
    syy -= m * my * my
    cux = sux - m * mu * mx
    cuy = suy - m * mu * my
    cvx = svx - m * mv * mx
    cvy = svy - m * mv * my
    det = sxx * syy - sxy * sxy
    if not det > FAN_DEGENERATE * pitch ** 4:
        return 0
    l00 = (cux * syy - cuy * sxy) / det
    l01 = (cuy * sxx - cux * sxy) / det
    l10 = (cvx * syy - cvy * sxy) / det
    l11 = (cvy * sxx - cvx * sxy) / det
    dl = l00 * l11 - l01 * l10
    if dl <= 0.0:
        return 0
    fro = l00 * l00 + l01 * l01 + l10 * l10 + l11 * l11
    s_max = math.sqrt(max(fro / 2 + math.sqrt(max(fro * fro / 4 - dl * dl, 0.0)), 0.0))
    if s_max * s_max > FAN_MAX_STRETCH * dl:
        return 0
    # prediction at the slot (design offset 0) relative to b
    pu = mu - l00 * mx - l01 * my
    pv = mv - l10 * mx - l11 * my
    if pu * pu + pv * pv > gate * gate * dl * pitch * pitch:
        return 0
    # no other blob inside the fan. When b's Delaunay neighbours are exactly the fan's blobs, the
    # fan's triangles are Delaunay triangles (the fan is in angular order about b), hence empty.
    if adj_ptr[b + 1] - adj_ptr[b] == m:
        hit = 0
        for q in range(adj_ptr[b], adj_ptr[b + 1]):
            for i in range(m):
                if ring[i] == adj_idx[q]:
                    hit += 1
                    break
        if hit == m:
            return 1
    if not closed[s]:
        return 0
    if not search:
        return _NEED_SEARCH
    # Otherwise: usually the fan's own blobs are still the nearest ones, so every other blob is
    # farther than all of them (outside the fan); else the nearer blobs are tested against the
    # fan's triangles
    r2 = 0.0
    for i in range(m):
        dx = pts[ring[i], 0] - pts[b, 0]
        dy = pts[ring[i], 1] - pts[b, 1]
        r2 = max(r2, dx * dx + dy * dy)
    kq = min(len(pts), m + 1)
    nearest(pts, pts[b, 0], pts[b, 1], kq, near, near_d2)
    if kq == m + 1:
        own = 0
        for q in range(kq):
            if near[q] == b:
                own += 1
            else:
                for i in range(m):
                    if ring[i] == near[q]:
                        own += 1
                        break
        if own == kq:
            return 1
    kq = min(len(pts), len(near))
    nearest(pts, pts[b, 0], pts[b, 1], kq, near, near_d2)
    if kq == len(near) and near_d2[kq - 1] < r2:
        return 0                                      # too many blobs to tell
    for q in range(kq):
        j = near[q]
        if near_d2[q] >= r2:
            break
        if j == b:
            continue
        member = False
        for i in range(m):
            if ring[i] == j:
                member = True
                break
        if member:
            continue
        px = pts[j, 0]
        py = pts[j, 1]
        for i in range(m):
            a = ring[i]
            c = ring[i + 1] if i + 1 < m else ring[0]
            # inside (or on) triangle (b, a, c), which is counter-clockwise
            if ((pts[a, 0] - pts[b, 0]) * (py - pts[b, 1]) - (pts[a, 1] - pts[b, 1]) * (px - pts[b, 0]) >= 0.0
                    and (pts[c, 0] - pts[a, 0]) * (py - pts[a, 1]) - (pts[c, 1] - pts[a, 1]) * (px - pts[a, 0]) >= 0.0
                    and (pts[b, 0] - pts[c, 0]) * (py - pts[c, 1]) - (pts[b, 1] - pts[c, 1]) * (px - pts[c, 0]) >= 0.0):
                return 0
    return 1
