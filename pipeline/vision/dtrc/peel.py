"""DTRC step 2, ring extraction: the carved mesh peeled ring by ring from the outside, each ring
ordered counter-clockwise about the centroid of the points left."""

from __future__ import annotations

import math

import numba
import numpy as np

from pipeline.types import Blobs
from pipeline.vision.dtrc.mesh import (LONG_EDGE_FACTOR, OUTLIER_NN_FACTOR, SLIVER_RADIUS_FACTOR, _boundary_slot, _carve,
                                       _median, _nn_and_mesh, _triangulate)


@numba.njit(cache=True, nogil=True)
def _peel_kernel(pts, idx, simp, nb, med_edge, n_rings):
    """Compiled :func:`_peel` on the triangulation (``simp``, ``nb``) of ``pts[idx]``.

    Returns (ring members concatenated, ring offsets (R + 1,), ring index per point (-1 none), carved
    mesh edges (E, 2)). Mirrors :class:`_Mesh` (criteria, carving, edges) and the peel loop.
    """
    n = len(pts)
    m = len(simp)
    tris = np.empty((m, 3), np.intp)
    across = np.empty((m, 3), np.intp)
    sliver = np.empty(m, np.bool_)
    long_ = np.empty((m, 3), np.bool_)
    long_len = LONG_EDGE_FACTOR * med_edge
    for t in range(m):
        for k in range(3):
            tris[t, k] = idx[simp[t, k]]
        across[t, 0], across[t, 1], across[t, 2] = nb[t, 2], nb[t, 0], nb[t, 1]  # slot k opposite vertex k + 2
        a, b, c = tris[t, 0], tris[t, 1], tris[t, 2]
        abx, aby = pts[b, 0] - pts[a, 0], pts[b, 1] - pts[a, 1]
        bcx, bcy = pts[c, 0] - pts[b, 0], pts[c, 1] - pts[b, 1]
        cax, cay = pts[a, 0] - pts[c, 0], pts[a, 1] - pts[c, 1]
        la, lb, lc = np.hypot(abx, aby), np.hypot(bcx, bcy), np.hypot(cax, cay)
        area2 = abs(abx * (pts[c, 1] - pts[a, 1]) - aby * (pts[c, 0] - pts[a, 0]))
        circum = la * lb * lc / max(2 * area2, 1e-12)
        sliver[t] = circum > SLIVER_RADIUS_FACTOR * min(min(la, lb), lc)
        long_[t, 0], long_[t, 1], long_[t, 2] = la > long_len, lb > long_len, lc > long_len
    alive = np.ones(m, np.bool_)
    _carve(alive, across, sliver, long_)

    # carved mesh edges: each shared edge once, sorted by (low, high) vertex
    keys = np.empty(3 * m, np.int64)
    ends = np.empty((3 * m, 2), np.int64)
    n_e = 0
    for t in range(m):
        if not alive[t]:
            continue
        for k in range(3):
            j = across[t, k]
            if j < 0 or not alive[j] or t < j:
                u, v = tris[t, k], tris[t, (k + 1) % 3]
                if u > v:
                    u, v = v, u
                ends[n_e, 0], ends[n_e, 1] = u, v
                keys[n_e] = u * n + v
                n_e += 1
    edges = ends[:n_e][np.argsort(keys[:n_e], kind="mergesort")]

    remaining = np.zeros(n, np.bool_)
    for i in idx:
        remaining[i] = True
    ring_flat = np.empty(len(idx), np.intp)
    ring_off = np.zeros(n_rings + 1, np.intp)
    ring_of = np.full(n, -1, np.int64)
    n_found = 0
    in_tri = np.zeros(n, np.bool_)
    ring_mask = np.zeros(n, np.bool_)
    members = np.empty(n, np.intp)
    for r in range(n_rings):
        n_rem = 0
        cx = 0.0
        cy = 0.0
        for i in range(n):
            if remaining[i]:
                n_rem += 1
                cx += pts[i, 0]
                cy += pts[i, 1]
        if n_rem == 0:
            break
        in_tri[:] = False
        ring_mask[:] = False
        any_alive = False
        for t in range(m):
            if alive[t]:
                any_alive = True
                for k in range(3):
                    in_tri[tris[t, k]] = True
                    if _boundary_slot(t, k, alive, across):
                        ring_mask[tris[t, k]] = True
                        ring_mask[tris[t, (k + 1) % 3]] = True
        n_ring = 0
        for i in range(n):
            if remaining[i] and not in_tri[i]:  # isolated leftovers (e.g. the centre) belong to this ring
                ring_mask[i] = True
            if ring_mask[i] and remaining[i]:
                members[n_ring] = i
                n_ring += 1
        if n_ring == 0:
            break
        cx /= n_rem
        cy /= n_rem
        ang = np.empty(n_ring)
        for j in range(n_ring):
            ang[j] = math.atan2(pts[members[j], 1] - cy, pts[members[j], 0] - cx)
        o = np.argsort(ang, kind="mergesort")
        start = ring_off[n_found]
        for j in range(n_ring):
            i = members[o[j]]
            ring_flat[start + j] = i
            ring_of[i] = n_found
            remaining[i] = False
        n_found += 1
        ring_off[n_found] = start + n_ring
        if any_alive:
            for t in range(m):
                if alive[t] and (ring_mask[tris[t, 0]] or ring_mask[tris[t, 1]] or ring_mask[tris[t, 2]]):
                    alive[t] = False
            _carve(alive, across, sliver, long_)
    return ring_flat[:ring_off[n_found]], ring_off[:n_found + 1].copy(), ring_of, edges


def _peel_flat(pts: np.ndarray, active: np.ndarray, n_rings: int, med_edge: float, tri=None):
    """:func:`_peel` with the rings concatenated: (members, offsets (R + 1,), ring index of every point
    (-1 in none), carved mesh edges)."""
    pts = np.ascontiguousarray(pts, dtype=np.float64)
    idx = np.flatnonzero(active)
    n = len(pts)
    if len(idx) == 0:
        return np.empty(0, np.intp), np.zeros(1, np.intp), np.full(n, -1, np.int64), np.empty((0, 2), np.int64)
    simp, nb = tri if tri is not None and len(idx) == n else _triangulate(pts[idx])
    return _peel_kernel(pts, idx, simp, nb, float(med_edge), int(n_rings))


def _peel(pts: np.ndarray, active: np.ndarray, n_rings: int, med_edge: float, tri=None):
    """Peel up to ``n_rings`` rings. Returns (list of index arrays, outermost first; carved mesh edges).

    One Delaunay triangulation per view: peeling only marks triangles dead in an ``alive`` mask and
    reads the boundary from the neighbour table (compiled, :func:`_peel_kernel`; the definition is
    :class:`_Mesh`). ``tri``: a triangulation of all points to reuse when every point is active.
    """
    ring_flat, ring_off, _, edges = _peel_flat(pts, active, n_rings, med_edge, tri)
    return [ring_flat[ring_off[r]:ring_off[r + 1]] for r in range(len(ring_off) - 1)], edges


def peel_rings(blobs: Blobs, n_rings: int) -> tuple[list[np.ndarray], np.ndarray, np.ndarray]:
    """Design-free DTRC meshing + ring peeling (steps 1-2 repeated ``n_rings`` times).

    Returns (rings: list of blob-index arrays, outermost first, each CCW in atan2(v, u);
    mesh edges (E, 2); mask (N,) of blobs kept for meshing, i.e. not isolated outliers).
    """
    pts = np.ascontiguousarray(blobs.xy_px, dtype=np.float64)
    if len(pts) < 4:
        return [], np.empty((0, 2), np.int64), np.ones(len(pts), bool)
    nn, tri = _nn_and_mesh(pts)
    med = _median(nn)
    active = nn <= OUTLIER_NN_FACTOR * med
    rings, edges = _peel(pts, active, n_rings, med, tri)
    return rings, edges, active
