"""DTRC step 1, meshing: the Delaunay triangulation of the blob centres, nearest-neighbour distances
from its edges, and the carving of boundary slivers and long edges (:class:`_Mesh` is the numpy
definition; the compiled carving below is what the per-frame path runs)."""

from __future__ import annotations

import math

import numba
import numpy as np
from scipy.spatial import Delaunay, QhullError, cKDTree

from pipeline.vision.delaunay import delaunay_certified


#: (lattice points have NN = 1 pitch; 2.0 keeps a marker next to one missing neighbour).
OUTLIER_NN_FACTOR = 2.0
#: Boundary triangles with circumradius / shortest edge above this are slivers (equilateral 0.58,
#: square-lattice half 0.71, one-missing-marker gap 1.0; a hull edge over a 0.1-pitch dent ~5).
SLIVER_RADIUS_FACTOR = 1.6
#: Boundary edges longer than this x the median edge are cut (a single missing marker leaves 2.0).
LONG_EDGE_FACTOR = 2.3
#: Prediction gate in local pitches: a blob must lie within this of its predicted slot (neighbours


@numba.njit(cache=True, nogil=True)
def _median(a: np.ndarray) -> float:
    """Median of a 1-D array (np.median's result without its per-call overhead)."""
    s = np.sort(a)
    n = len(s)
    return (s[(n - 1) // 2] + s[n // 2]) / 2


# ----- meshing and peeling ------------------------------------------------------------------

def _triangulate(pts: np.ndarray, *, with_exact: bool = False):
    """Delaunay simplices (M, 3) and their neighbours (M, 3) (``neighbors[t, k]``: triangle opposite
    vertex k, -1 on the hull); joggled when exact lattices leave co-circular points unused.
    ``with_exact`` also returns whether the triangulation is the exact (unjoggled) one using every point.

    The certified compiled triangulation (:func:`pipeline.vision.delaunay.delaunay_certified`) is used when it exists; otherwise Qhull.
    Triangle order and vertex rotation may differ between the two; nothing downstream depends on them.
    """
    empty = np.empty((0, 3), np.intp)
    out = (empty, empty, False)
    if len(pts) >= 3:
        simp, nb, certified = delaunay_certified(np.ascontiguousarray(pts, dtype=np.float64))
        if certified:
            out = (simp, nb, True)
        else:
            try:
                tri = Delaunay(pts)
                exact = np.count_nonzero(np.bincount(tri.simplices.ravel(), minlength=len(pts))) == len(pts)
                if not exact:
                    tri = Delaunay(pts, qhull_options="QJ Qbb Qc")
                out = (tri.simplices.astype(np.intp), tri.neighbors.astype(np.intp), exact)
            except QhullError:
                try:
                    tri = Delaunay(pts, qhull_options="QJ Qbb Qc")
                    out = (tri.simplices.astype(np.intp), tri.neighbors.astype(np.intp), False)
                except QhullError:
                    pass
    return out if with_exact else out[:2]


@numba.njit(cache=True, nogil=True)
def _nn_from_triangles(pts, simp):
    """Shortest incident edge of every point of a triangulation using all of them."""
    nn = np.full(len(pts), np.inf)
    for t in range(len(simp)):
        for k in range(3):
            a, b = simp[t, k], simp[t, (k + 1) % 3]
            dx, dy = pts[a, 0] - pts[b, 0], pts[a, 1] - pts[b, 1]
            length = math.sqrt(dx * dx + dy * dy)
            nn[a] = min(nn[a], length)
            nn[b] = min(nn[b], length)
    return nn


def _nn_and_mesh(pts: np.ndarray):
    """Nearest-neighbour distance of every point (N,) and, when it could be reused, the Delaunay
    triangulation of all points ((simp, nb) or None).

    The nearest neighbour of a point is one of its Delaunay neighbours, so an exact triangulation
    gives the NN distances as the shortest incident edges (no k-d tree); otherwise a k-d tree is used.
    """
    pts = np.ascontiguousarray(pts, dtype=np.float64)
    simp, nb, exact = _triangulate(pts, with_exact=True)
    if not exact or len(simp) == 0:
        return cKDTree(pts).query(pts, k=2)[0][:, 1], None
    return _nn_from_triangles(pts, simp), (simp, nb)


def _edge_keys(tris: np.ndarray, n: int):
    e = np.concatenate([tris[:, [0, 1]], tris[:, [1, 2]], tris[:, [2, 0]]])
    e.sort(axis=1)
    return e[:, 0] * n + e[:, 1], e


class _Mesh:
    """A Delaunay triangulation with per-triangle edge slots (slot k = edge (v_k, v_{k+1 mod 3})),
    the triangle across each slot (-1 on the hull) and the carving criteria, so that the boundary of
    any subset of triangles (an ``alive`` mask) follows from the neighbour table without sorting.

    This numpy class is the reference definition of meshing and carving; the per-frame path runs the
    compiled equivalent (:func:`_peel_kernel`), which tests check against it."""

    def __init__(self, pts: np.ndarray, idx: np.ndarray, med_edge: float, tri=None) -> None:
        simp, nb = _triangulate(pts[idx]) if tri is None else tri
        self.tris = idx[simp] if len(simp) else simp
        self.across = nb[:, [2, 0, 1]] if len(nb) else nb  # slot k is opposite vertex k + 2
        if len(self.tris) == 0:
            self.sliver = np.empty((0,), bool)
            self.long = np.empty((0, 3), bool)
            return
        a, b, c = pts[self.tris[:, 0]], pts[self.tris[:, 1]], pts[self.tris[:, 2]]
        ab, bc, ca = b - a, c - b, a - c
        la, lb, lc = np.hypot(ab[:, 0], ab[:, 1]), np.hypot(bc[:, 0], bc[:, 1]), np.hypot(ca[:, 0], ca[:, 1])
        area2 = np.abs(ab[:, 0] * (c - a)[:, 1] - ab[:, 1] * (c - a)[:, 0])
        circum = la * lb * lc / np.maximum(2 * area2, 1e-12)
        self.sliver = circum > SLIVER_RADIUS_FACTOR * np.minimum(np.minimum(la, lb), lc)
        self.long = np.column_stack([la, lb, lc]) > LONG_EDGE_FACTOR * med_edge

    def on_boundary(self, alive: np.ndarray) -> np.ndarray:
        """(M, 3) mask: the slot is an edge of exactly one alive triangle (this one)."""
        nb_alive = np.where(self.across >= 0, alive[self.across], False)
        return alive[:, None] & ~nb_alive

    def carve(self, alive: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Remove boundary slivers and long boundary edges until the boundary follows the lattice.
        Returns the carved alive mask and its boundary (:meth:`on_boundary`)."""
        alive = alive.copy()
        on_b = self.on_boundary(alive)
        for _ in range(len(alive)):
            bad = on_b.any(axis=1) & (self.sliver | (on_b & self.long).any(axis=1))
            if not bad.any():
                break
            alive &= ~bad
            on_b = self.on_boundary(alive)
        return alive, on_b

    def edges(self, alive: np.ndarray, n: int) -> np.ndarray:
        """Unique undirected edges (E, 2) of the alive triangles, in :func:`mesh_edges` order."""
        if not alive.any():
            return np.empty((0, 2), np.int64)
        t = np.arange(len(alive))[:, None]
        nb_alive = np.where(self.across >= 0, alive[self.across], False)
        own = alive[:, None] & (~nb_alive | (t < self.across))  # a shared edge once
        tt, kk = np.nonzero(own)
        e = np.column_stack([self.tris[tt, kk], self.tris[tt, (kk + 1) % 3]])
        e.sort(axis=1)
        return e[np.argsort(e[:, 0] * n + e[:, 1], kind="stable")].astype(np.int64)


def mesh_edges(tris: np.ndarray, n: int) -> np.ndarray:
    """Unique undirected edges (E, 2) of a triangle list."""
    if len(tris) == 0:
        return np.empty((0, 2), np.int64)
    keys, e = _edge_keys(tris, n)
    _, first = np.unique(keys, return_index=True)
    return e[first].astype(np.int64)


@numba.njit(cache=True, nogil=True)
def _boundary_slot(t, k, alive, across):
    """Slot k of alive triangle t is an edge of no other alive triangle."""
    j = across[t, k]
    return j < 0 or not alive[j]


@numba.njit(cache=True, nogil=True)
def _is_bad(t, alive, across, sliver, long_):
    """:meth:`_Mesh.carve`'s removal rule for alive triangle t: on the boundary, and a sliver or with
    a long boundary edge."""
    on_b = False
    long_b = False
    for k in range(3):
        if _boundary_slot(t, k, alive, across):
            on_b = True
            long_b = long_b or long_[t, k]
    return on_b and (sliver[t] or long_b)


@numba.njit(cache=True, nogil=True)
def _carve(alive, across, sliver, long_):
    """:meth:`_Mesh.carve` in place, with a work list instead of whole-mesh sweeps. Removing a
    triangle only adds boundary slots to the others, so "bad" only grows as triangles go: any removal
    order ends at the same (largest) set with no bad triangle, the one the sweeps reach."""
    m = len(alive)
    stack = np.empty(m, np.intp)
    queued = np.zeros(m, np.bool_)
    sp = 0
    for t in range(m - 1, -1, -1):
        if alive[t]:
            stack[sp] = t
            queued[t] = True
            sp += 1
    while sp > 0:
        sp -= 1
        t = stack[sp]
        queued[t] = False
        if alive[t] and _is_bad(t, alive, across, sliver, long_):
            alive[t] = False
            for k in range(3):
                j = across[t, k]
                if j >= 0 and alive[j] and not queued[j]:
                    stack[sp] = j
                    queued[j] = True
                    sp += 1
