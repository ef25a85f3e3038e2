"""Compiled Delaunay triangulation of small 2-D point sets, certified to be THE Delaunay triangulation.

Qhull (``scipy.spatial.Delaunay``) costs ~0.3 ms for 127 points, most of it set-up, which was a large
part of the per-frame budget of marker identification (:mod:`pipeline.vision.dtrc`). So the triangulation is
computed by a compiled sweep-hull (Delaunator's algorithm: points added in order of distance from a
seed circumcentre, the convex hull kept as a linked list, Lawson flips) and then CERTIFIED: every
point used, every triangle counter-clockwise, every interior edge strictly locally Delaunay and the
hull strictly convex, each with a relative margin far above rounding. Such a triangulation is the
unique Delaunay triangulation, i.e. the one Qhull returns. Anything short of the certificate
(duplicates, collinear or co-circular points, e.g. exact lattices) is reported uncertified, and the
caller falls back to Qhull, so results never depend on which path ran (tests/test_dtrc.py).
"""

from __future__ import annotations

import math

import numba
import numpy as np

__all__ = ["delaunay_certified"]

#: Relative margins of the certificate (rounding error of the predicates is ~1e-15 relative).
_ORIENT_MARGIN = 1e-10
_INCIRCLE_MARGIN = 1e-9


@numba.njit(cache=True, nogil=True)
def _orient(ax, ay, bx, by, cx, cy):
    """Twice the signed area of (a, b, c): > 0 counter-clockwise (x right, y up)."""
    return (bx - ax) * (cy - ay) - (by - ay) * (cx - ax)


@numba.njit(cache=True, nogil=True)
def _incircle(ax, ay, bx, by, cx, cy, px, py):
    """(det, permanent): det > 0 when p is inside the circumcircle of the counter-clockwise triangle
    (a, b, c); the permanent (the same terms in absolute value) bounds det's rounding error."""
    dx, dy = ax - px, ay - py
    ex, ey = bx - px, by - py
    fx, fy = cx - px, cy - py
    ap = dx * dx + dy * dy
    bp = ex * ex + ey * ey
    cp = fx * fx + fy * fy
    det = dx * (ey * cp - bp * fy) - dy * (ex * cp - bp * fx) + ap * (ex * fy - ey * fx)
    perm = (abs(dx) * (abs(ey) * cp + bp * abs(fy)) + abs(dy) * (abs(ex) * cp + bp * abs(fx))
            + ap * (abs(ex) * abs(fy) + abs(ey) * abs(fx)))
    return det, perm


@numba.njit(cache=True, nogil=True)
def _hash_key(x, y, cx, cy, size):
    """Hull hash bucket of a point: its pseudo-angle (monotone in the angle, no trigonometry) about c."""
    dx, dy = x - cx, y - cy
    s = abs(dx) + abs(dy)
    p = dx / s if s > 0 else 0.0
    a = (3.0 - p if dy > 0 else 1.0 + p) / 4.0
    return int(math.floor(a * size)) % size


@numba.njit(cache=True, nogil=True)
def _link(half, a, b):
    half[a] = b
    if b != -1:
        half[b] = a


@numba.njit(cache=True, nogil=True)
def _legalize(a, tri, half, pts, hull_tri, hull_prev, hull_start, stack):
    """Flip edges from halfedge ``a`` until they are locally Delaunay (Lawson). Returns the halfedge
    that ends on the hull from the new point (Delaunator's bookkeeping)."""
    sp = 0
    ar = 0
    while True:
        b = half[a]
        a0 = a - a % 3
        ar = a0 + (a + 2) % 3
        if b == -1:
            if sp == 0:
                break
            sp -= 1
            a = stack[sp]
            continue
        b0 = b - b % 3
        al = a0 + (a + 1) % 3
        bl = b0 + (b + 2) % 3
        p0, pr, pl, p1 = tri[ar], tri[a], tri[al], tri[bl]
        det, _ = _incircle(pts[p0, 0], pts[p0, 1], pts[pr, 0], pts[pr, 1], pts[pl, 0], pts[pl, 1],
                           pts[p1, 0], pts[p1, 1])
        if det > 0:  # p1 inside the circumcircle of (p0, pr, pl): flip pr-pl to p0-p1
            tri[a] = p1
            tri[b] = p0
            hbl = half[bl]
            if hbl == -1:  # the flipped edge's far side was a hull edge: move its reference
                e = hull_start
                while True:
                    if hull_tri[e] == bl:
                        hull_tri[e] = a
                        break
                    e = hull_prev[e]
                    if e == hull_start:
                        break
            _link(half, a, hbl)
            _link(half, b, half[ar])
            _link(half, ar, bl)
            if sp < len(stack):
                stack[sp] = b0 + (b + 1) % 3
                sp += 1
        else:
            if sp == 0:
                break
            sp -= 1
            a = stack[sp]
    return ar


@numba.njit(cache=True, nogil=True)
def _certify(pts, tri, half, hull_start, hull_next, hull_n):
    """True when the triangles (``tri``, 3 per triangle, ``half``: opposite halfedges) are certainly
    THE Delaunay triangulation of all ``pts``: all points used, Euler count, strictly CCW triangles,
    consistent adjacency, interior edges strictly locally Delaunay, strictly convex hull."""
    n = len(pts)
    nt = len(tri)
    used = np.zeros(n, np.bool_)
    for h in range(nt):
        used[tri[h]] = True
    if not used.all() or nt // 3 != 2 * n - 2 - hull_n:
        return False
    for t in range(0, nt, 3):
        a, b, c = tri[t], tri[t + 1], tri[t + 2]
        dx1, dy1 = pts[b, 0] - pts[a, 0], pts[b, 1] - pts[a, 1]
        dx2, dy2 = pts[c, 0] - pts[a, 0], pts[c, 1] - pts[a, 1]
        if not dx1 * dy2 - dy1 * dx2 > _ORIENT_MARGIN * (abs(dx1 * dy2) + abs(dy1 * dx2)):
            return False
    n_hull_edges = 0
    for h in range(nt):
        g = half[h]
        if g < 0:
            n_hull_edges += 1
            continue
        hn = h - h % 3 + (h + 1) % 3
        gn = g - g % 3 + (g + 1) % 3
        if half[g] != h or tri[g] != tri[hn] or tri[gn] != tri[h]:
            return False
        if h < g:
            p0 = tri[h - h % 3 + (h + 2) % 3]
            p1 = tri[g - g % 3 + (g + 2) % 3]
            det, perm = _incircle(pts[p0, 0], pts[p0, 1], pts[tri[h], 0], pts[tri[h], 1],
                                  pts[tri[hn], 0], pts[tri[hn], 1], pts[p1, 0], pts[p1, 1])
            if not det < -_INCIRCLE_MARGIN * perm:
                return False
    if n_hull_edges != hull_n:
        return False
    e = hull_start
    for _ in range(hull_n):
        q = hull_next[e]
        r = hull_next[q]
        dx1, dy1 = pts[q, 0] - pts[e, 0], pts[q, 1] - pts[e, 1]
        dx2, dy2 = pts[r, 0] - pts[e, 0], pts[r, 1] - pts[e, 1]
        if not dx1 * dy2 - dy1 * dx2 > _ORIENT_MARGIN * (abs(dx1 * dy2) + abs(dy1 * dx2)):
            return False
        e = q
    return e == hull_start


@numba.njit(cache=True, nogil=True)
def delaunay_certified(pts):
    """Sweep-hull Delaunay triangulation of (N, 2) points: (simplices (M, 3), neighbours (M, 3) in
    scipy's convention (``neighbors[t, k]`` opposite vertex k, -1 on the hull), certified). Only a
    certified result may be used (see the section comment)."""
    n = len(pts)
    empty = np.empty((0, 3), np.intp)
    if n < 3:
        return empty, empty.copy(), False
    xs = pts[:, 0]
    ys = pts[:, 1]
    bx, by = (xs.min() + xs.max()) / 2, (ys.min() + ys.max()) / 2
    # seed triangle: the point nearest the box centre, its nearest neighbour, and the point making
    # the smallest circumcircle with them
    i0 = 0
    best = np.inf
    for i in range(n):
        d = (xs[i] - bx) ** 2 + (ys[i] - by) ** 2
        if d < best:
            i0, best = i, d
    i1 = -1
    best = np.inf
    for i in range(n):
        d = (xs[i] - xs[i0]) ** 2 + (ys[i] - ys[i0]) ** 2
        if i != i0 and 0 < d < best:
            i1, best = i, d
    if i1 < 0:
        return empty, empty.copy(), False
    i2 = -1
    best = np.inf
    dx, dy = xs[i1] - xs[i0], ys[i1] - ys[i0]
    for i in range(n):
        if i == i0 or i == i1:
            continue
        ex, ey = xs[i] - xs[i0], ys[i] - ys[i0]
        den = dx * ey - dy * ex
        if den == 0:
            continue
        bl, cl = dx * dx + dy * dy, ex * ex + ey * ey
        ux, uy = (ey * bl - dy * cl) * 0.5 / den, (dx * cl - ex * bl) * 0.5 / den
        r = ux * ux + uy * uy
        if r < best:
            i2, best = i, r
    if i2 < 0:
        return empty, empty.copy(), False
    if _orient(xs[i0], ys[i0], xs[i1], ys[i1], xs[i2], ys[i2]) < 0:
        i1, i2 = i2, i1
    dx, dy = xs[i1] - xs[i0], ys[i1] - ys[i0]
    ex, ey = xs[i2] - xs[i0], ys[i2] - ys[i0]
    bl, cl = dx * dx + dy * dy, ex * ex + ey * ey
    den = 0.5 / (dx * ey - dy * ex)
    ccx, ccy = xs[i0] + (ey * bl - dy * cl) * den, ys[i0] + (dx * cl - ex * bl) * den
    order = np.argsort((xs - ccx) ** 2 + (ys - ccy) ** 2)

    max_tri = max(2 * n - 5, 1)
    tri = np.empty(3 * max_tri, np.intp)  # halfedge h = 3 t + k runs tri[h] -> tri[3 t + (k + 1) % 3]
    half = np.empty(3 * max_tri, np.intp)  # opposite halfedge, -1 on the hull
    hull_prev = np.zeros(n, np.intp)
    hull_next = np.zeros(n, np.intp)  # CCW hull as a linked list; hull_next[i] == i: removed
    hull_tri = np.zeros(n, np.intp)  # halfedge of the hull edge (i, hull_next[i])
    hsize = max(int(math.ceil(math.sqrt(n))), 1)
    hull_hash = np.full(hsize, -1, np.intp)
    stack = np.empty(3 * max_tri + 16, np.intp)

    hull_start = i0
    hull_n = 3
    hull_next[i0], hull_next[i1], hull_next[i2] = i1, i2, i0
    hull_prev[i0], hull_prev[i1], hull_prev[i2] = i2, i0, i1
    hull_tri[i0], hull_tri[i1], hull_tri[i2] = 0, 1, 2
    hull_hash[_hash_key(xs[i0], ys[i0], ccx, ccy, hsize)] = i0
    hull_hash[_hash_key(xs[i1], ys[i1], ccx, ccy, hsize)] = i1
    hull_hash[_hash_key(xs[i2], ys[i2], ccx, ccy, hsize)] = i2
    tri[0], tri[1], tri[2] = i0, i1, i2
    half[0] = half[1] = half[2] = -1
    nt = 3

    for k in range(n):
        i = order[k]
        if i == i0 or i == i1 or i == i2:
            continue
        x, y = xs[i], ys[i]
        # a hull edge near the point's angle, then the first edge it sees (strictly right of it)
        start = 0
        key = _hash_key(x, y, ccx, ccy, hsize)
        for j in range(hsize):
            start = hull_hash[(key + j) % hsize]
            if start != -1 and start != hull_next[start]:
                break
        start = hull_prev[start]
        e = start
        while True:
            q = hull_next[e]
            if _orient(xs[e], ys[e], xs[q], ys[q], x, y) < 0:
                break
            e = q
            if e == start:
                e = -1
                break
        if e == -1:
            continue  # a duplicate or numerically on the hull: left unused (fails the certificate)
        q = hull_next[e]
        t = nt
        tri[t], tri[t + 1], tri[t + 2] = e, i, q
        half[t] = -1
        half[t + 1] = -1
        _link(half, t + 2, hull_tri[e])
        nt += 3
        hull_tri[i] = _legalize(t + 2, tri, half, pts, hull_tri, hull_prev, hull_start, stack)
        hull_tri[e] = t
        hull_n += 1
        # walk forward along the hull adding triangles while the point sees the edges
        nx = hull_next[e]
        while True:
            q = hull_next[nx]
            if not _orient(xs[nx], ys[nx], xs[q], ys[q], x, y) < 0:
                break
            t = nt
            tri[t], tri[t + 1], tri[t + 2] = nx, i, q
            _link(half, t, hull_tri[i])
            half[t + 1] = -1
            _link(half, t + 2, hull_tri[nx])
            nt += 3
            hull_tri[i] = _legalize(t + 2, tri, half, pts, hull_tri, hull_prev, hull_start, stack)
            hull_next[nx] = nx
            hull_n -= 1
            nx = q
        # and backward, when the first visible edge was where the search started
        if e == start:
            while True:
                q = hull_prev[e]
                if not _orient(xs[q], ys[q], xs[e], ys[e], x, y) < 0:
                    break
                t = nt
                tri[t], tri[t + 1], tri[t + 2] = q, i, e
                half[t] = -1
                _link(half, t + 1, hull_tri[e])
                _link(half, t + 2, hull_tri[q])
                nt += 3
                _legalize(t + 2, tri, half, pts, hull_tri, hull_prev, hull_start, stack)
                hull_tri[q] = t
                hull_next[e] = e
                hull_n -= 1
                e = q
        hull_start = e
        hull_prev[i] = e
        hull_next[e] = i
        hull_prev[nx] = i
        hull_next[i] = nx
        hull_hash[_hash_key(x, y, ccx, ccy, hsize)] = i
        hull_hash[_hash_key(xs[e], ys[e], ccx, ccy, hsize)] = e

    m = nt // 3
    simp = tri[:nt].reshape(m, 3).copy()
    nb = np.empty((m, 3), np.intp)
    for h in range(nt):  # halfedge 3 t + k is opposite vertex (k + 2) % 3
        g = half[h]
        nb[h // 3, (h % 3 + 2) % 3] = g // 3 if g >= 0 else -1
    return simp, nb, _certify(pts, tri[:nt], half[:nt], hull_start, hull_next, hull_n)
