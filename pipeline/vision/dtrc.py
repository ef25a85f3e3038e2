"""Stage 4: Delaunay-Triangulation-Ring-Coding (DTRC) marker matching and tracking.

Per view (paper Sec. "Marker Localization", Alg. 1, Table III):

1. **Meshing** — Delaunay triangulation of the blob centres (compiled, certified; Qhull otherwise), after
   dropping isolated points far outside the lattice (nearest neighbour > ``OUTLIER_NN_FACTOR`` x the
   median). The mesh is carved from the outside: boundary triangles that are slivers (circumradius
   > ``SLIVER_RADIUS_FACTOR`` x their shortest edge, i.e. hull edges bridging a concavity) or that have
   a boundary edge longer than ``LONG_EDGE_FACTOR`` x the median edge are removed until none is left,
   so the boundary follows the marker lattice. A triangle that spans the gap of ONE missing marker
   (circumradius = pitch, shortest edge = pitch) survives, so a missing marker does not pull an inner
   marker into the outer ring.
2. **Ring extraction** — the edge ring is the set of vertices on boundary edges (edges of exactly one
   remaining triangle; interior markers have ``links`` reciprocal links, edge markers fewer), ordered
   counter-clockwise by ``atan2(v, u)`` about the centroid of the remaining points. The ring is
   peeled (its triangles removed) and the next ring extracted, ``layers`` times (Table III's ``m``).
3. **Coding** — rings are coded from the centre outward. A ring whose size equals the design's and
   whose spacing is regular is rotated onto the design ring: the cyclic shift minimising the angular
   residual against the design angles plus the rotation carried from the ring inside it (ring 1 fixes
   the rotation, unambiguous within +-half its pitch, i.e. +-30 deg for hexagons). This gives the
   canonical ids of :mod:`pipeline.design` on an undeformed sensor and is consistent between views and
   over time. A ring whose size or spacing disagrees is coded by prediction instead: each design slot
   is predicted from a local affine fit to its already-coded design neighbours and takes the blob that
   is the mutual nearest within ``PREDICT_GATE`` pitches; slots without such a blob are *unmatched*
   (reported, never guessed).

Tracking: identity is the code, so :class:`DTRCTracker` simply re-codes every frame (large, fast
motions keep identity). :class:`NearestNeighbourTracker` is the paper's KNN baseline.

Speed: with ~100-300 blobs per view, per-call overheads dominate, so the per-frame path (triangulation,
nearest neighbours, carving and peeling, angular coding, pairing) runs as a few numba-compiled kernels
(~0.3 ms per stereo frame for 127 markers); the numpy classes they replace remain the definitions
(:class:`_Mesh`). The defect paths of strongly pressed frames (irregular rings coded by prediction,
verification and growth) are compiled too: the local affine fits take their neighbours from a port of
scipy's cKDTree that reproduces its choice among equidistant lattice points, so the codes are those of
the numpy definitions (cKDTree + batched least squares, kept in the tests); a 5 mm twin press on
hexagon127 codes in ~0.5 ms instead of ~1.9 ms.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numba
import numpy as np
from scipy.spatial import Delaunay, QhullError, cKDTree

from pipeline.vision.delaunay import delaunay_certified
from pipeline.design import SensorDesign
from pipeline.vision.identity import (R_CONTRADICTED, R_NO_BLOB, REASONS, certify, certify_whole, consistent, contradicted,
                               follow, grow, lattice_of,
                               register_seed, use_triangulation)
from pipeline.vision.kdtree import kd_build, kd_query
from pipeline.types import Blobs, MarkerMatches

__all__ = ["RingCoding", "code_rings", "carry_ids", "match_stereo", "DTRCTracker", "NearestNeighbourTracker",
           "mesh_edges", "peel_rings", "OUTLIER_NN_FACTOR", "SLIVER_RADIUS_FACTOR", "LONG_EDGE_FACTOR", "PREDICT_GATE"]

#: Points whose nearest neighbour is farther than this x the median NN distance are spurious
#: (lattice points have NN = 1 pitch; 2.0 keeps a marker next to one missing neighbour).
OUTLIER_NN_FACTOR = 2.0
#: Boundary triangles with circumradius / shortest edge above this are slivers (equilateral 0.58,
#: square-lattice half 0.71, one-missing-marker gap 1.0; a hull edge over a 0.1-pitch dent ~5).
SLIVER_RADIUS_FACTOR = 1.6
#: Boundary edges longer than this x the median edge are cut (a single missing marker leaves 2.0).
LONG_EDGE_FACTOR = 2.3
#: Prediction gate in local pitches: a blob must lie within this of its predicted slot (neighbours
#: are 1 pitch apart, so 0.4 leaves a 0.2-pitch margin to the half-way point).
PREDICT_GATE = 0.4
#: Consecutive ring gaps must stay within [1/RING_GAP_TOL, RING_GAP_TOL] x the design gap (scaled);
#: one missing marker doubles a gap, a spurious one halves it.
RING_GAP_TOL = 1.5


@dataclass(frozen=True)
class RingCoding:
    """Result of ring coding one view.

    Attributes
    ----------
    ids : (N,) int64
        Canonical design id of each input blob, -1 where uncoded (spurious or ambiguous).
    ring : (N,) int64
        Peel index of each blob (0 = outermost ring found), -1 for points dropped before meshing.
    ring_sizes_found : tuple of int
        Number of blobs in each peeled ring, outermost first.
    ring_sizes_expected : tuple of int
        The design's ring sizes, outermost first.
    unmatched_ids : (M,) int64
        Design ids not coded in this view.
    mesh_edges : (E, 2) int64
        Edges (blob indices) of the carved Delaunay mesh (for drawing).
    messages : tuple of str
        Human-readable notes on mismatches.
    unmatched_reasons : tuple of str
        Why each of ``unmatched_ids`` was not identified (same order).
    """

    ids: np.ndarray
    ring: np.ndarray
    ring_sizes_found: tuple[int, ...]
    ring_sizes_expected: tuple[int, ...]
    unmatched_ids: np.ndarray
    mesh_edges: np.ndarray = field(default_factory=lambda: np.empty((0, 2), np.int64))
    messages: tuple[str, ...] = ()
    unmatched_reasons: tuple[str, ...] = ()

    @property
    def complete(self) -> bool:
        """True when every design marker was coded."""
        return len(self.unmatched_ids) == 0

    @property
    def coded(self) -> int:
        return int(np.sum(self.ids >= 0))


# ----- design rings -------------------------------------------------------------------------

_DESIGN_CACHE: dict[tuple, tuple] = {}


def _design_rings(design: SensorDesign):
    """Per layer k (0 = centre): (ids (n_k,), design xy (n_k, 2), angles about the ring centroid)."""
    key = (design.pattern.kind, design.pattern.layers, design.pattern.separation_mm)
    if key not in _DESIGN_CACHE:
        xy = design.rest_markers_mm()[:, :2]
        layers = design.marker_layers()
        rings = []
        for k in range(design.pattern.layers):
            ids = np.nonzero(layers == k)[0]
            p = xy[ids]
            c = p.mean(axis=0)
            rings.append((ids, p, np.arctan2(p[:, 1] - c[1], p[:, 0] - c[0])))
        _DESIGN_CACHE[key] = (xy, rings)
    return _DESIGN_CACHE[key]


def _marker_count(design: SensorDesign) -> int:
    """``design.marker_count`` from the cached rest layout (the property recomputes the layout)."""
    return len(_design_rings(design)[0])


_FLAT_CACHE: dict[tuple, tuple] = {}


def _design_flat(design: SensorDesign):
    """The design rings of :func:`_design_rings` flattened for the compiled coder: ids (M,), angles
    (M,), layer offsets (layers + 1,) and each layer's gap scale (:func:`_design_gap_scale`; 1 for the
    centre, whose gaps are never checked)."""
    key = (design.pattern.kind, design.pattern.layers, design.pattern.separation_mm)
    if key not in _FLAT_CACHE:
        _, rings = _design_rings(design)
        off = np.zeros(len(rings) + 1, np.intp)
        off[1:] = np.cumsum([len(ids) for ids, _, _ in rings])
        gap = np.array([1.0] + [_design_gap_scale(p) for _, p, _ in rings[1:]])
        _FLAT_CACHE[key] = (np.concatenate([ids for ids, _, _ in rings]).astype(np.int64),
                            np.concatenate([a for _, _, a in rings]).astype(np.float64), off, gap)
    return _FLAT_CACHE[key]


# ----- small compiled helpers ---------------------------------------------------------------
# The point sets are small (~100-300 blobs), so per-call numpy overhead dominated the stage; the loops
# below run compiled (numba, nopython). Where the order of floating-point operations is observable
# (sums, products) they follow the numpy definitions they replace.

_TWO_PI = 2 * math.pi


@numba.njit(cache=True)
def _wrap_scalar(a: float) -> float:
    """``(a + pi) % (2 pi) - pi`` bit for bit (numpy's floored modulo), without a modulo in the common
    case (|a + pi| < 2 pi, where the modulo is exact)."""
    x = a + math.pi
    if 0.0 <= x < _TWO_PI:
        r = x
    elif -_TWO_PI < x < 0.0:
        r = x + _TWO_PI
    else:
        r = x % _TWO_PI  # Python's float modulo: fmod, then moved into [0, 2 pi) like numpy's
    return r - math.pi


@numba.njit(cache=True)
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


@numba.njit(cache=True)
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


@numba.njit(cache=True)
def _boundary_slot(t, k, alive, across):
    """Slot k of alive triangle t is an edge of no other alive triangle."""
    j = across[t, k]
    return j < 0 or not alive[j]


@numba.njit(cache=True)
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


@numba.njit(cache=True)
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


@numba.njit(cache=True)
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


# ----- coding -------------------------------------------------------------------------------

def _cyclic_gaps(xy: np.ndarray) -> np.ndarray:
    d = np.diff(xy, axis=0, append=xy[:1])  # xy[i + 1] - xy[i], cyclic
    return np.sqrt(d[:, 0] * d[:, 0] + d[:, 1] * d[:, 1])


def _design_gap_scale(design_xy: np.ndarray) -> float:
    """Mean design gap of a ring over its median gap."""
    gd = _cyclic_gaps(design_xy)
    return float((gd / _median(gd)).mean())


@numba.njit(cache=True)
def _gaps_regular(pts, members, gap_scale):
    """Consecutive gaps of a ring (``members`` in angular order, cyclic) agree with the design's, whose
    mean gap over median gap is ``gap_scale``."""
    m = len(members)
    if m < 3:
        return True
    gf = np.empty(m)
    for i in range(m):
        a, b = members[i], members[(i + 1) % m]
        dx, dy = pts[b, 0] - pts[a, 0], pts[b, 1] - pts[a, 1]
        gf[i] = math.sqrt(dx * dx + dy * dy)
    med = _median(gf)
    for i in range(m):
        ratio = gf[i] / med / gap_scale
        if not (ratio < RING_GAP_TOL and ratio > 1 / RING_GAP_TOL):
            return False
    return True


@numba.njit(cache=True)
def _ring_by_angle(pts, members):
    """Ring members sorted CCW by atan2 about their centroid, and those angles."""
    m = len(members)
    cx = 0.0
    cy = 0.0
    for i in members:
        cx += pts[i, 0]
        cy += pts[i, 1]
    cx /= m
    cy /= m
    phi = np.empty(m)
    for j in range(m):
        phi[j] = math.atan2(pts[members[j], 1] - cy, pts[members[j], 0] - cx)
    o = np.argsort(phi, kind="mergesort")
    return members[o], phi[o]


@numba.njit(cache=True)
def _shift_code(phi, psi, theta):
    """Best cyclic shift aligning found angles ``phi`` (sorted CCW) to design ``psi`` (canonical order).

    Returns (shift, new rotation estimate, max |residual - mean|). Found point ``(i + shift) % n``
    is design slot ``i``. For shift s the residuals are ``r_i = wrap(phi[(i + s) % n] - psi[i] - theta)``,
    their circular mean ``m_s``, and the cost ``sum_i wrap(r_i - m_s)^2 + n m_s^2``; the least cost
    wins (a shift is abandoned once its partial cost reaches the best so far).
    """
    n = len(psi)
    cphi, sphi = np.cos(phi), np.sin(phi)
    cpsi, spsi = np.cos(psi), np.sin(psi)
    ct, st = math.cos(theta), math.sin(theta)
    best, best_cost, best_m = 0, np.inf, 0.0
    for s in range(n):
        # circular mean: sum_i exp(i (phi_(i+s) - psi_i)) exp(-i theta)
        zr = 0.0
        zi = 0.0
        for i in range(n):
            j = (i + s) % n
            zr += cphi[j] * cpsi[i] + sphi[j] * spsi[i]
            zi += sphi[j] * cpsi[i] - cphi[j] * spsi[i]
        m = math.atan2((zi * ct - zr * st) / n, (zr * ct + zi * st) / n)
        cost = n * m * m
        for i in range(n):
            dev = _wrap_scalar(_wrap_scalar(phi[(i + s) % n] - psi[i] - theta) - m)
            cost += dev * dev
            if cost >= best_cost:
                break
        if cost < best_cost:
            best, best_cost, best_m = s, cost, m
    spread = 0.0
    for i in range(n):
        spread = max(spread, abs(_wrap_scalar(_wrap_scalar(phi[(i + best) % n] - psi[i] - theta) - best_m)))
    return best, theta + best_m, spread


@numba.njit(cache=True)
def _code_by_angles(pts, ring_flat, ring_off, layer, theta, ids, d_ids, d_ang, d_off, d_gap):
    """Code layers ``layer, layer + 1, ...`` (peel ``n_layers - 1 - layer``) into ``ids`` while each
    ring has the design's size and regular gaps and its best shift fits (spread < half the ring's
    pitch angle), carrying the rotation ``theta`` outward.

    Returns (the first layer not coded this way, ``n_layers`` when all were; theta so far).
    """
    n_layers = len(d_off) - 1
    n_rings = len(ring_off) - 1
    while layer < n_layers:
        lo, hi = d_off[layer], d_off[layer + 1]
        r = n_layers - 1 - layer
        if r >= n_rings or ring_off[r + 1] - ring_off[r] != hi - lo:
            break
        members = ring_flat[ring_off[r]:ring_off[r + 1]]
        if layer == 0:
            ids[members[0]] = d_ids[lo]
        else:
            members, phi = _ring_by_angle(pts, members)
            if not _gaps_regular(pts, members, d_gap[layer]):
                break
            shift, theta_new, spread = _shift_code(phi, d_ang[lo:hi], theta)
            if not spread < math.pi / (hi - lo):
                break
            for i in range(hi - lo):
                ids[members[(i + shift) % (hi - lo)]] = d_ids[lo + i]
            theta = theta_new
        layer += 1
    return layer, theta


@numba.njit(cache=True)
def _unmatched(ids, n_markers):
    """Design ids (ascending) not among ``ids``."""
    present = np.zeros(n_markers, np.bool_)
    for i in ids:
        if i >= 0:
            present[i] = True
    return np.flatnonzero(~present).astype(np.int64)


# ----- prediction: kd-tree neighbours and local affine fits ---------------------------------
# The defect paths (irregular rings, verification, growth) predict design slots from local affine fits
# to the k nearest coded DESIGN points. Design lattices tie exactly (a quarter of the hexagon slots have
# two design points at the same float distance around the 8th neighbour), and which tied point enters
# the fit changes the prediction far beyond rounding. The numpy definition took the neighbours from
# scipy's cKDTree, so the kernels below reproduce cKDTree step for step (leafsize 16, median splits by
# libstdc++'s nth_element and partition, compact boxes; best-first query with its two binary heaps,
# a point replacing the farthest neighbour only when strictly nearer): same neighbours, ties included.
# The 3x3 least squares are solved directly (Gaussian elimination, partial pivoting); they differ from
# LAPACK by rounding only (~1e-15 relative), far below the gates' margins.

@numba.njit(cache=True)
def _affine_fit(query_xy, ref_xy, ref_px, k, exclude_self):
    """Predict image positions of design points from local affine fits to coded neighbours.

    Least squares (``+ 1e-9 I`` on the normal matrix) of px ~ [x, y, 1] A over the ``k`` nearest
    reference design points of each query (cKDTree's, without the query itself when
    ``exclude_self``). Returns (predicted px (Q, 2), local pixels per design mm (Q,) = sqrt |det A_2x2|).
    """
    kk = min(k + (1 if exclude_self else 0), len(ref_xy))
    tree = kd_build(ref_xy)
    nb = np.empty(kk, np.int64)
    d2 = np.empty(kk)
    pred = np.empty((len(query_xy), 2))
    scale = np.empty(len(query_xy))
    M = np.empty((3, 3))
    B = np.empty((3, 2))
    for q in range(len(query_xy)):
        kd_query(ref_xy, tree, query_xy[q, 0], query_xy[q, 1], kk, nb, d2)
        M[:] = 0.0
        B[:] = 0.0
        for t in range(1 if exclude_self else 0, kk):
            r = nb[t]
            X = (ref_xy[r, 0], ref_xy[r, 1], 1.0)
            for i in range(3):
                for j in range(3):
                    M[i, j] += X[i] * X[j]
                B[i, 0] += X[i] * ref_px[r, 0]
                B[i, 1] += X[i] * ref_px[r, 1]
        for i in range(3):
            M[i, i] += 1e-9  # as the numpy definition (keeps collinear neighbours solvable)
        # Gaussian elimination with partial pivoting (M is positive definite)
        for c in range(3):
            p = c
            for r in range(c + 1, 3):
                if abs(M[r, c]) > abs(M[p, c]):
                    p = r
            if p != c:
                for j in range(3):
                    M[c, j], M[p, j] = M[p, j], M[c, j]
                for j in range(2):
                    B[c, j], B[p, j] = B[p, j], B[c, j]
            for r in range(c + 1, 3):
                f = M[r, c] / M[c, c]
                for j in range(c, 3):
                    M[r, j] -= f * M[c, j]
                for j in range(2):
                    B[r, j] -= f * B[c, j]
        for c in range(2, -1, -1):
            for j in range(2):
                s = B[c, j]
                for i in range(c + 1, 3):
                    s -= M[c, i] * B[i, j]
                B[c, j] = s / M[c, c]
        qx, qy = query_xy[q, 0], query_xy[q, 1]
        pred[q, 0] = qx * B[0, 0] + qy * B[1, 0] + B[2, 0]
        pred[q, 1] = qx * B[0, 1] + qy * B[1, 1] + B[2, 1]
        scale[q] = math.sqrt(abs(B[0, 0] * B[1, 1] - B[0, 1] * B[1, 0]))
    return pred, scale


@numba.njit(cache=True)
def _verify_and_grow(pts, ids, active, xy_d, pitch_mm, max_rounds):
    """Uncode ids that disagree with their coded neighbours, then code free slots by prediction.

    Verification: each coded blob must lie within ``PREDICT_GATE`` local pitches of its slot predicted
    from its 8 nearest coded design neighbours. Growth (up to ``max_rounds`` rounds): every free slot
    is predicted from the coded ones and takes the nearest candidate blob (active, uncoded) when it is
    within the gate and the slot is that blob's nearest prediction (mutual nearest). Modifies ``ids``
    in place; returns the number of ids removed by verification.
    """
    gate = PREDICT_GATE * pitch_mm
    removed = 0
    coded = np.flatnonzero(ids >= 0)
    if len(coded) >= 4:
        ref_xy = xy_d[ids[coded]]
        pred, sc = _affine_fit(ref_xy, ref_xy, pts[coded], 8, True)
        for i in range(len(coded)):
            dx, dy = pred[i, 0] - pts[coded[i], 0], pred[i, 1] - pts[coded[i], 1]
            if math.sqrt(dx * dx + dy * dy) > gate * sc[i]:
                ids[coded[i]] = -1
                removed += 1
    one = np.empty(1, np.int64)
    one_d2 = np.empty(1)
    for _ in range(max_rounds):
        coded = np.flatnonzero(ids >= 0)
        used = np.zeros(len(xy_d), np.bool_)
        for i in coded:
            used[ids[i]] = True
        free = np.flatnonzero(~used)
        cand = np.flatnonzero(active & (ids < 0))
        if len(coded) < 4 or len(free) == 0 or len(cand) == 0:
            break
        pred, sc = _affine_fit(xy_d[free], xy_d[ids[coded]], pts[coded], 8, False)
        cand_px = pts[cand]
        cand_tree = kd_build(cand_px)
        pred_tree = kd_build(pred)
        take = np.full(len(free), -1, np.int64)
        for q in range(len(free)):
            kd_query(cand_px, cand_tree, pred[q, 0], pred[q, 1], 1, one, one_d2)
            j = one[0]
            if not math.sqrt(one_d2[0]) <= gate * sc[q]:
                continue
            kd_query(pred, pred_tree, cand_px[j, 0], cand_px[j, 1], 1, one, one_d2)
            if one[0] == q:
                take[q] = cand[j]
        if not np.any(take >= 0):
            break
        for q in range(len(free)):
            if take[q] >= 0:
                ids[take[q]] = free[q]
    return removed


#: A ring of the design's size but irregular spacing (a deformed skin) is rotated onto the design by
#: prediction from the rings inside it: the best cyclic shift must fit with a mean distance below
#: this many local pitches, and the runner-up shift must fit at least SHIFT_MARGIN x worse.
SHIFT_FIT = 0.45
SHIFT_MARGIN = 2.0


@numba.njit(cache=True)
def _shift_by_prediction(members, d_ids, pts, ids, xy_d, pitch_mm):
    """Cyclic shift coding a complete ring (``members`` sorted CCW) whose gaps are irregular.

    The ring's cyclic order is topological and survives deformation; only its start is unknown. Each
    design slot of the ring is predicted from a local affine fit to the coded markers (the rings
    inside, already coded), and the shift whose found points lie nearest the predictions (mean
    distance in local pitches) wins when it is unambiguous (:data:`SHIFT_FIT`, :data:`SHIFT_MARGIN`).
    Returns the shift (found point ``(i + shift) % n`` is slot ``i``), -1 when there is none.
    """
    coded = np.flatnonzero(ids >= 0)
    if len(coded) < 4:
        return -1
    pred, sc = _affine_fit(xy_d[d_ids], xy_d[ids[coded]], pts[coded], 8, False)
    n = len(d_ids)
    cost = np.empty(n)
    for s in range(n):
        acc = 0.0
        for i in range(n):
            m = members[(i + s) % n]
            dx, dy = pts[m, 0] - pred[i, 0], pts[m, 1] - pred[i, 1]
            acc += math.sqrt(dx * dx + dy * dy) / (pitch_mm * max(sc[i], 1e-9))
        cost[s] = acc / n
    best = 0
    for s in range(1, n):
        if cost[s] < cost[best]:
            best = s
    runner_up = np.inf
    for s in range(n):
        if s != best and cost[s] < runner_up:
            runner_up = cost[s]
    if cost[best] > SHIFT_FIT or (n > 1 and runner_up < SHIFT_MARGIN * cost[best]):
        return -1
    return best


def code_rings(blobs: Blobs, design: SensorDesign, *, previous: tuple[np.ndarray, np.ndarray] | None = None
               ) -> RingCoding:
    """DTRC ring coding of one view.

    Parameters
    ----------
    blobs : Blobs
        Marker centres of ONE view (px).
    design : SensorDesign
        Gives the ring count (``pattern.layers``), ring sizes and canonical ids.
    previous : (xy_px (M, 2), ids (M,)), optional
        The identified markers of the previous frame of the same view: they propose ids
        (:func:`carry_ids`) where ring coding cannot, certified like any other proposal.

    Returns
    -------
    RingCoding
        Canonical id per blob (-1 uncoded), ring membership, sizes and messages. Never raises on bad
        input: an empty or unusable point set gives all markers unmatched.

    Notes
    -----
    Assumes the image is not mirrored relative to the sensor frame (true for this sensor: u grows with
    x, v with y) and rotated by less than half the pitch angle of ring 1 (30 deg for hexagon/circular,
    22.5 deg for square).
    """
    pts = np.ascontiguousarray(blobs.xy_px, dtype=np.float64)
    n = len(pts)
    xy_d, drings = _design_rings(design)
    d_ids_flat, d_ang_flat, d_off, d_gap = _design_flat(design)
    n_layers = design.pattern.layers
    expected = tuple(len(drings[k][0]) for k in range(n_layers - 1, -1, -1))
    ids = np.full(n, -1, np.int64)
    msgs: list[str] = []
    if n < 4:
        return RingCoding(ids, np.full(n, -1, np.int64), (), expected, np.arange(len(xy_d), dtype=np.int64),
                          messages=(f"only {n} blobs",), unmatched_reasons=(f"only {n} blobs detected",) * len(xy_d))
    nn, tri = _nn_and_mesh(pts)
    use_triangulation(pts, None if tri is None else tri[0])
    med_nn = _median(nn)
    active = nn <= OUTLIER_NN_FACTOR * med_nn
    n_dropped = n - int(np.count_nonzero(active))
    if n_dropped:
        msgs.append(f"dropped {n_dropped} isolated blob(s) outside the lattice")
    ring_flat, ring_off, ring_of, edges = _peel_flat(pts, active, n_layers, med_nn, tri)
    found = tuple(int(s) for s in np.diff(ring_off))
    n_leftover = n - n_dropped - len(ring_flat)
    if n_leftover:
        msgs.append(f"{n_leftover} blob(s) left inside after {n_layers} rings")

    # code from the centre outward: peel r <-> layer n_layers - 1 - r. Complete, regular rings are
    # coded by their angles in one compiled pass; it stops at a layer needing the cases below.
    failed = bool(n_leftover or n_dropped)
    layer, theta = _code_by_angles(pts, ring_flat, ring_off, 0, 0.0, ids, d_ids_flat, d_ang_flat, d_off, d_gap)
    while layer < n_layers:
        d_ids, _, d_ang = drings[layer]
        r = n_layers - 1 - layer
        members = ring_flat[ring_off[r]:ring_off[r + 1]] if r < len(found) else np.empty(0, np.intp)
        done = False
        if len(members) == len(d_ids) and layer > 0:
            # complete but irregular (a deformed skin): the cyclic order still holds; find the
            # start by prediction from the rings inside, or for the first ring (only the centre
            # is coded) by the angular fit alone; verified against the neighbours below
            members, phi = _ring_by_angle(pts, members)
            how = "prediction from the rings inside"
            shift = _shift_by_prediction(members, d_ids, pts, ids, xy_d, design.pattern.separation_mm)
            shift = None if shift < 0 else int(shift)
            if shift is None and int((ids >= 0).sum()) < 4:
                s_ang, _, spread = _shift_code(phi, d_ang, theta)
                shift, how = (s_ang, "its angles") if spread < math.pi / len(d_ids) else (None, "")
            if shift is not None:
                ids[np.concatenate((members[shift:], members[:shift]))] = d_ids
                theta += float(np.angle(np.mean(np.exp(1j * (np.concatenate((phi[shift:], phi[:shift]))
                                                              - d_ang - theta)))))
                failed = True
                msgs.append(f"ring {r} (layer {layer}): irregular, coded by {how}")
                done = True
        if not done:
            failed = True
            msgs.append(f"ring {r} (layer {layer}): found {len(members)} blobs, expected {len(d_ids)}"
                        + ("" if len(members) != len(d_ids) else " (irregular)"))
        layer, theta = _code_by_angles(pts, ring_flat, ring_off, layer + 1, theta, ids, d_ids_flat, d_ang_flat,
                                       d_off, d_gap)
    if failed:
        # a defect anywhere may shift markers between peels: check every code against its coded
        # neighbours and fill the free slots by prediction (never by guessing)
        before = int((ids >= 0).sum())
        removed = _verify_and_grow(pts, ids, active, xy_d, design.pattern.separation_mm, n_layers + 2)
        msgs.append(f"verification removed {removed} code(s); prediction coded "
                    f"{int((ids >= 0).sum()) - before + removed} more")
    if previous is not None:
        previous = (np.asarray(previous[0], np.float64).reshape(-1, 2), np.asarray(previous[1], np.int64))
    ids, reason = _certain_ids(pts, ids, design, failed, msgs, previous)
    unmatched = _unmatched(ids, len(xy_d))
    return RingCoding(ids, ring_of, found, expected, unmatched, edges, tuple(msgs),
                      tuple(REASONS.get(int(reason[i]), REASONS[R_NO_BLOB]) for i in unmatched))


def _merge(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Union of two id proposals per blob; a blob given two different ids, or an id given to two
    different blobs, is dropped from both."""
    out = np.where(a >= 0, a, b)
    conflict = (a >= 0) & (b >= 0) & (a != b)
    out[conflict] = -1
    lab = out[out >= 0]
    u, cnt = np.unique(lab, return_counts=True)
    out[np.isin(out, u[cnt > 1])] = -1
    return out


#: The lattice registration is tried when ring coding leaves more than this fraction of the blobs
#: (or slots) unidentified.
SEED_BELOW = 0.9


def _certain_ids(pts: np.ndarray, proposal: np.ndarray, design: SensorDesign, defects: bool,
                 msgs: list[str], previous=None) -> tuple[np.ndarray, np.ndarray]:
    """The certainty rule (:mod:`pipeline.vision.identity`) applied to the ring-coding proposal and, when
    ``previous`` (the previous frame's certain markers: xy_px (M, 2), ids (M,)) is given and the
    proposal is not certified whole, to the ids carried from it (:func:`carry_ids`), each extended
    by growth; when that leaves markers unidentified, also to the placements of a lattice
    registration independent of ring peeling. Markers still unidentified are then followed from the
    previous frame (:func:`pipeline.vision.identity.follow`). Returns (certified id per blob, reason code
    per design id)."""
    lat = lattice_of(design)
    n_slots = len(lat.xy)
    reason = np.full(n_slots, R_NO_BLOB, np.int64)
    if len(pts) < 4:
        return np.full(len(pts), -1, np.int64), reason
    if int((proposal >= 0).sum()) == n_slots:
        # ring coding identified every marker (the common case, pressed frames included): the
        # certainty rule need only confirm it, in one compiled pass when there is no other blob
        if certify_whole(pts, proposal, lat):
            if defects:
                msgs.append(f"certainty rule: {n_slots} of {n_slots} ids certain")
            reason[:] = 0
            return proposal.copy(), reason
        ids = certify(pts, proposal, lat, reason)
        if int((ids >= 0).sum()) == n_slots:
            if defects:
                msgs.append(f"certainty rule: {n_slots} of {n_slots} ids certain")
            return ids, reason
        reason[:] = R_NO_BLOB
    # Each proposal is made locally consistent, grown and certified on its own (a wrong proposal
    # must not spoil a right one); the two best certified results are merged and certified again.
    def run(p):
        r = np.full(n_slots, R_NO_BLOB, np.int64)
        return certify(pts, grow(pts, consistent(pts, p, lat, r), lat, r), lat, r), r

    def count(c):
        return int((c[0] >= 0).sum())

    enough = SEED_BELOW * min(n_slots, len(pts))
    cands = [run(proposal)]
    carried = None
    if previous is not None:
        carried = carry_ids(previous[0], previous[1], pts)
        if (carried >= 0).any():
            cands.append(run(carried))
    if max(map(count, cands)) < enough:
        for p in register_seed(pts, lat):
            cands.append(run(p))
            if count(cands[-1]) >= enough:
                break
    cands.sort(key=lambda c: -count(c))
    if len(cands) > 1 and count(cands[1]) > 0:
        cands.append(run(_merge(cands[0][0], cands[1][0])))
    ids, reason = max(cands, key=count)
    if carried is not None and (carried >= 0).any():
        bad = _temporally_contradicted(previous, pts, ids, carried)
        if bad.any():
            ids, reason = ids.copy(), reason.copy()
            reason[ids[bad]] = R_CONTRADICTED
            ids[bad] = -1
            msgs.append(f"withdrew {int(bad.sum())} id(s) that the previous frame's markers contradict")
    if previous is not None and int((ids >= 0).sum()) < min(n_slots, len(pts)):
        before = int((ids >= 0).sum())
        ids = follow(previous[0], previous[1], pts, ids, lat)
        if int((ids >= 0).sum()) > before:
            msgs.append(f"followed {int((ids >= 0).sum()) - before} marker(s) from the previous frame")
    reason[ids[ids >= 0]] = 0
    n_certified = int((ids >= 0).sum())
    if defects or n_certified < n_slots:
        msgs.append(f"certainty rule: {n_certified} of {n_slots} ids certain")
    return ids, reason


#: A frame's motion is small when this fraction of its certified markers moved less than
#: :data:`SMALL_MOTION` local spacings since the previous frame ...
SMALL_MOTION_QUANTILE = 0.95
#: ... (then a marker's nearest blob within a third of a spacing is that marker: a neighbour, at
#: least ~0.6 spacings away even where the skin crowds, would have to move more than a quarter).
SMALL_MOTION = 0.25


def _temporally_contradicted(previous, pts: np.ndarray, ids: np.ndarray, carried: np.ndarray) -> np.ndarray:
    """Blobs whose certified id the previous frame contradicts (bool mask), when the frame's motion is
    small: :data:`SMALL_MOTION_QUANTILE` of the markers certified in both frames (``ids`` on ``pts``
    now, ``previous`` then) moved less than :data:`SMALL_MOTION` local spacings. Then every marker is
    still the blob nearest to where it was, so a certified id is contradicted when the blob carries
    another marker's id from the previous frame (:func:`carry_ids`), when its id was carried to
    another blob, or when the marker of that id moved more than a third of a spacing (the carrying
    gate) while its neighbours barely moved. After a larger step a marker's previous nearest blob may
    be its neighbour, and nothing is withdrawn."""
    bad = np.zeros(len(pts), bool)
    lab = np.flatnonzero(ids >= 0)
    if len(lab) < 3 or len(pts) < 3 or len(previous[1]) == 0:
        return bad
    where = np.full(int(max(ids.max(), previous[1].max())) + 1, -1, np.int64)
    where[previous[1]] = np.arange(len(previous[1]))
    j = where[ids[lab]]
    both = j >= 0
    if both.sum() < 3:
        return bad
    step = np.linalg.norm(pts[lab[both]] - previous[0][j[both]], axis=1)
    spacing = float(np.median(cKDTree(pts).query(pts, k=2)[0][:, 1]))
    if np.quantile(step, SMALL_MOTION_QUANTILE) >= SMALL_MOTION * spacing:
        return bad
    bad |= contradicted(ids, carried)
    bad[lab[both][step > spacing / 3]] = True
    return bad


def carry_ids(prev_xy_px: np.ndarray, prev_ids: np.ndarray, pts: np.ndarray) -> np.ndarray:
    """Ids of the previous frame's identified markers proposed for the current blobs: each previous
    marker goes to the nearest current blob when that blob is within a third of the local spacing,
    at least twice as near as the second-nearest blob, and nearest to no other previous marker.
    Only a proposal: a whole pattern that moved by one spacing between frames carries consistently
    wrong ids, which the anchoring test withdraws."""
    out = np.full(len(pts), -1, np.int64)
    if len(pts) < 2 or len(prev_ids) < 2:
        return out
    tree = cKDTree(pts)
    spacing = float(np.median(tree.query(pts, k=2)[0][:, 1]))
    d, j = tree.query(prev_xy_px, k=2)
    ok = (d[:, 0] <= spacing / 3) & (d[:, 1] >= 2 * d[:, 0])
    u, cnt = np.unique(j[ok, 0], return_counts=True)
    ok &= ~np.isin(j[:, 0], u[cnt > 1])
    out[j[ok, 0]] = prev_ids[ok]
    return out


# ----- stereo matching and tracking ---------------------------------------------------------

@numba.njit(cache=True)
def _pair_indices(left_ids, right_ids, n_markers):
    """Ids coded in both views (ascending), their blob index in each view, and the other ids."""
    li = np.full(n_markers, -1, np.int64)
    ri = np.full(n_markers, -1, np.int64)
    for k in range(len(left_ids)):
        if left_ids[k] >= 0:
            li[left_ids[k]] = k
    for k in range(len(right_ids)):
        if right_ids[k] >= 0:
            ri[right_ids[k]] = k
    both = (li >= 0) & (ri >= 0)
    mid = np.flatnonzero(both).astype(np.int64)
    return mid, li[mid], ri[mid], np.flatnonzero(~both).astype(np.int64)


def _pair(left: Blobs, right: Blobs, lc: RingCoding, rc: RingCoding, n_markers: int) -> MarkerMatches:
    mid, li, ri, unmatched = _pair_indices(lc.ids, rc.ids, n_markers)
    return MarkerMatches(ids=mid, left_px=left.xy_px[li], right_px=right.xy_px[ri], unmatched_ids=unmatched)


def match_stereo(left: Blobs, right: Blobs, design: SensorDesign) -> MarkerMatches:
    """Match markers between the left and right views by their DTRC codes.

    Parameters
    ----------
    left, right : Blobs
        Marker centres in each half image (right coordinates relative to the right half).
    design : SensorDesign

    Returns
    -------
    MarkerMatches
        Ids coded in both views (ascending), their pixel centres, and ``unmatched_ids``: design ids
        not coded in at least one view.
    """
    return _pair(left, right, code_rings(left, design), code_rings(right, design), _marker_count(design))


class DTRCTracker:
    """DTRC tracking: every frame is re-coded, so identity survives arbitrarily large motion; the
    previous frame's identified markers propose ids where coding alone cannot (crowding, large
    deformation, partial occlusion), under the same certainty rule.

    ``update(left, right) -> MarkerMatches`` (also callable). ``last_codings`` holds the two
    :class:`RingCoding` of the latest frame.
    """

    def __init__(self, design: SensorDesign, *, temporal: bool = True) -> None:
        self.design = design
        self.temporal = temporal
        self.last_codings: tuple[RingCoding, RingCoding] | None = None
        self._previous: list | None = None

    def update(self, left: Blobs, right: Blobs) -> MarkerMatches:
        prev = self._previous if self.temporal else None
        lc = code_rings(left, self.design, previous=None if prev is None else prev[0])
        rc = code_rings(right, self.design, previous=None if prev is None else prev[1])
        self.last_codings = (lc, rc)
        self._previous = [(b.xy_px[c.ids >= 0], c.ids[c.ids >= 0]) for b, c in ((left, lc), (right, rc))]
        return _pair(left, right, lc, rc, _marker_count(self.design))

    __call__ = update

    def forget(self, ids: np.ndarray) -> None:
        """Drop ``ids`` from the markers the next frame is given as certain in the previous one: a
        pair of views whose rays do not meet (the runner's stereo check) is not one marker, so at
        least one view's id is wrong and must not be carried on."""
        if self._previous is None or len(ids) == 0:
            return
        self._previous = [(xy[~np.isin(i, ids)], i[~np.isin(i, ids)]) for xy, i in self._previous]

    def reset(self) -> None:
        self.last_codings = None
        self._previous = None


class NearestNeighbourTracker:
    """The paper's KNN baseline: ids carried from the previous frame to the nearest blob.

    The first frame (or after :meth:`reset`) is coded by DTRC. Afterwards each view independently
    moves every id to the nearest current blob within ``gate_factor`` x the median marker pitch of
    the first frame; when two ids claim one blob the closer keeps it, the other becomes unmatched.
    """

    def __init__(self, design: SensorDesign, *, gate_factor: float = 1.0) -> None:
        self.design = design
        self.gate_factor = float(gate_factor)
        self._prev: list[dict[int, np.ndarray]] | None = None
        self._gate = [math.inf, math.inf]

    def reset(self) -> None:
        self._prev = None

    def _carry(self, view: int, blobs: Blobs) -> dict[int, np.ndarray]:
        prev = self._prev[view]
        if not prev or len(blobs) == 0:
            return {}
        pid = np.fromiter(prev.keys(), np.int64)
        ppx = np.asarray([prev[i] for i in pid])
        d, j = cKDTree(blobs.xy_px).query(ppx)
        ok = d <= self._gate[view]
        out: dict[int, np.ndarray] = {}
        best: dict[int, tuple[float, int]] = {}
        for i, dd, jj, k in zip(pid, d, j, ok):
            if k and (jj not in best or dd < best[jj][0]):
                best[int(jj)] = (float(dd), int(i))
        for jj, (_, i) in best.items():
            out[i] = blobs.xy_px[jj]
        return out

    def update(self, left: Blobs, right: Blobs) -> MarkerMatches:
        n = self.design.marker_count
        if self._prev is None:
            lc, rc = code_rings(left, self.design), code_rings(right, self.design)
            views = []
            for v, (b, c) in enumerate(((left, lc), (right, rc))):
                ok = c.ids >= 0
                views.append({int(i): b.xy_px[k] for i, k in zip(c.ids[ok], np.nonzero(ok)[0])})
                if len(b) >= 2:
                    nn, _ = cKDTree(b.xy_px).query(b.xy_px, k=2)
                    self._gate[v] = self.gate_factor * float(np.median(nn[:, 1]))
        else:
            views = [self._carry(0, left), self._carry(1, right)]
        self._prev = views
        common = sorted(set(views[0]) & set(views[1]))
        ids = np.asarray(common, np.int64)
        lp = np.asarray([views[0][i] for i in common]).reshape(-1, 2)
        rp = np.asarray([views[1][i] for i in common]).reshape(-1, 2)
        return MarkerMatches(ids, lp, rp, np.setdiff1d(np.arange(n, dtype=np.int64), ids))

    __call__ = update
