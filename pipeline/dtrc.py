"""Stage 4: Delaunay-Triangulation-Ring-Coding (DTRC) marker matching and tracking.

Per view (paper Sec. "Marker Localization", Alg. 1, Table III):

1. **Meshing** — Delaunay triangulation of the blob centres (``scipy.spatial.Delaunay``), after
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
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
from scipy.spatial import Delaunay, QhullError, cKDTree

from pipeline.design import SensorDesign
from pipeline.types import Blobs, MarkerMatches

__all__ = ["RingCoding", "code_rings", "match_stereo", "DTRCTracker", "NearestNeighbourTracker",
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
    """

    ids: np.ndarray
    ring: np.ndarray
    ring_sizes_found: tuple[int, ...]
    ring_sizes_expected: tuple[int, ...]
    unmatched_ids: np.ndarray
    mesh_edges: np.ndarray = field(default_factory=lambda: np.empty((0, 2), np.int64))
    messages: tuple[str, ...] = ()

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


# ----- meshing and peeling ------------------------------------------------------------------

def _wrap(a: np.ndarray) -> np.ndarray:
    return (a + np.pi) % (2 * np.pi) - np.pi


def _triangulate(pts: np.ndarray, *, with_exact: bool = False):
    """Delaunay simplices (M, 3) and their neighbours (M, 3) (``neighbors[t, k]``: triangle opposite
    vertex k, -1 on the hull); joggled when exact lattices leave co-circular points unused.
    ``with_exact`` also returns whether the triangulation is the exact (unjoggled) one using every point."""
    empty = np.empty((0, 3), np.intp)
    out = (empty, empty, False)
    if len(pts) >= 3:
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


def _nn_and_mesh(pts: np.ndarray):
    """Nearest-neighbour distance of every point (N,) and, when it could be reused, the Delaunay
    triangulation of all points ((simp, nb) or None).

    The nearest neighbour of a point is one of its Delaunay neighbours, so an exact triangulation
    gives the NN distances as the shortest incident edges (no k-d tree); otherwise a k-d tree is used.
    """
    simp, nb, exact = _triangulate(pts, with_exact=True)
    if not exact or len(simp) == 0:
        return cKDTree(pts).query(pts, k=2)[0][:, 1], None
    e = np.concatenate([simp[:, [0, 1]], simp[:, [1, 2]], simp[:, [2, 0]]])
    d = pts[e[:, 0]] - pts[e[:, 1]]
    length = np.sqrt(d[:, 0] * d[:, 0] + d[:, 1] * d[:, 1])
    nn = np.full(len(pts), np.inf)
    np.minimum.at(nn, e[:, 0], length)
    np.minimum.at(nn, e[:, 1], length)
    return nn, (simp, nb)


def _edge_keys(tris: np.ndarray, n: int):
    e = np.concatenate([tris[:, [0, 1]], tris[:, [1, 2]], tris[:, [2, 0]]])
    e.sort(axis=1)
    return e[:, 0] * n + e[:, 1], e


class _Mesh:
    """A Delaunay triangulation with per-triangle edge slots (slot k = edge (v_k, v_{k+1 mod 3})),
    the triangle across each slot (-1 on the hull) and the carving criteria, so that the boundary of
    any subset of triangles (an ``alive`` mask) follows from the neighbour table without sorting."""

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


def _peel(pts: np.ndarray, active: np.ndarray, n_rings: int, med_edge: float, tri=None):
    """Peel up to ``n_rings`` rings. Returns (list of index arrays, outermost first; carved mesh edges).

    One Delaunay triangulation per view: peeling only marks triangles dead in an ``alive`` mask and
    reads the boundary from the neighbour table. ``tri``: a triangulation of all points to reuse
    when every point is active.
    """
    idx = np.nonzero(active)[0]
    n = len(pts)
    rings: list[np.ndarray] = []
    if len(idx) == 0:
        return rings, np.empty((0, 2), np.int64)
    mesh = _Mesh(pts, idx, med_edge, tri if len(idx) == n else None)
    tris = mesh.tris
    alive, on_b = mesh.carve(np.ones(len(tris), bool))
    edges = mesh.edges(alive, n)
    remaining = np.zeros(n, bool)
    remaining[idx] = True
    for _ in range(n_rings):
        rem = np.nonzero(remaining)[0]
        if len(rem) == 0:
            break
        in_tri = np.zeros(n, bool)
        ring_mask = np.zeros(n, bool)
        if alive.any():
            in_tri[tris[alive].ravel()] = True
            t, k = np.nonzero(on_b)
            ring_mask[tris[t, k]] = True
            ring_mask[tris[t, (k + 1) % 3]] = True
        ring_mask |= remaining & ~in_tri  # isolated leftovers (e.g. the centre) belong to this ring
        ring_idx = np.nonzero(ring_mask & remaining)[0]
        if len(ring_idx) == 0:
            break
        c = pts[rem].sum(axis=0) / len(rem)
        ang = np.arctan2(pts[ring_idx, 1] - c[1], pts[ring_idx, 0] - c[0])
        rings.append(ring_idx[np.argsort(ang, kind="stable")])
        remaining[ring_idx] = False
        if alive.any():
            alive &= ~ring_mask[tris].any(axis=1)
            alive, on_b = mesh.carve(alive)
    return rings, edges


def peel_rings(blobs: Blobs, n_rings: int) -> tuple[list[np.ndarray], np.ndarray, np.ndarray]:
    """Design-free DTRC meshing + ring peeling (steps 1-2 repeated ``n_rings`` times).

    Returns (rings: list of blob-index arrays, outermost first, each CCW in atan2(v, u);
    mesh edges (E, 2); mask (N,) of blobs kept for meshing, i.e. not isolated outliers).
    """
    pts = np.asarray(blobs.xy_px, dtype=np.float64)
    if len(pts) < 4:
        return [], np.empty((0, 2), np.int64), np.ones(len(pts), bool)
    nn, tri = _nn_and_mesh(pts)
    med = _median(nn)
    active = nn <= OUTLIER_NN_FACTOR * med
    rings, edges = _peel(pts, active, n_rings, med, tri)
    return rings, edges, active


# ----- coding -------------------------------------------------------------------------------

def _median(a: np.ndarray) -> float:
    """Median of a 1-D array (np.median's result without its per-call overhead)."""
    s = np.sort(a)
    n = len(s)
    return float((s[(n - 1) // 2] + s[n // 2]) / 2)


def _cyclic_gaps(xy: np.ndarray) -> np.ndarray:
    d = np.diff(xy, axis=0, append=xy[:1])  # xy[i + 1] - xy[i], cyclic
    return np.sqrt(d[:, 0] * d[:, 0] + d[:, 1] * d[:, 1])


def _design_gap_scale(design_xy: np.ndarray) -> float:
    """Mean design gap of a ring over its median gap (cached with the ring)."""
    key = design_xy.tobytes()
    hit = _GAP_CACHE.get(key)
    if hit is None:
        gd = _cyclic_gaps(design_xy)
        hit = _GAP_CACHE[key] = float((gd / _median(gd)).mean())
    return hit


_GAP_CACHE: dict[bytes, float] = {}


def _gaps_regular(found: np.ndarray, design_xy: np.ndarray) -> bool:
    """Consecutive gaps of a ring (both cyclic, in angular order) agree with the design's."""
    if len(found) < 3:
        return True
    gf = _cyclic_gaps(found)
    ratio = gf / _median(gf) / _design_gap_scale(design_xy)
    return bool(np.all((ratio < RING_GAP_TOL) & (ratio > 1 / RING_GAP_TOL)))


_SHIFTS: dict[int, np.ndarray] = {}


def _shift_code(phi: np.ndarray, psi: np.ndarray, theta: float) -> tuple[int, float, float]:
    """Best cyclic shift aligning found angles ``phi`` (sorted CCW) to design ``psi`` (canonical order).

    Returns (shift, new rotation estimate, max |residual - mean|). Found point ``(i + shift) % n``
    is design slot ``i``.
    """
    n = len(psi)
    shifts = _SHIFTS.get(n)
    if shifts is None:
        shifts = _SHIFTS[n] = (np.arange(n)[:, None] + np.arange(n)[None, :]) % n  # row s: found (i + s) % n
    r = _wrap(phi[shifts] - psi[None, :] - theta)
    # circular mean of each row: sum_i exp(i r_si) = (exp(i phi)[shifts] @ exp(-i psi)) exp(-i theta)
    z = (np.exp(1j * phi)[shifts] @ np.exp(-1j * psi)) * complex(math.cos(theta), -math.sin(theta))
    m = np.arctan2(z.imag / n, z.real / n)
    dev = _wrap(r - m[:, None])
    cost = np.einsum("ij,ij->i", dev, dev) + n * m * m
    s = int(np.argmin(cost))
    return s, theta + float(m[s]), float(np.max(np.abs(dev[s])))


def _affine_predict(query_xy: np.ndarray, ref_xy: np.ndarray, ref_px: np.ndarray, *, k: int = 8,
                    exclude_self: bool = False) -> tuple[np.ndarray, np.ndarray]:
    """Predict image positions of design points from local affine fits to coded neighbours.

    Batched least squares over the ``k`` nearest coded design neighbours of each query point.
    Returns (predicted px (Q, 2), local pixels per design mm (Q,)).
    """
    kk = min(k + int(exclude_self), len(ref_xy))
    _, nb = cKDTree(ref_xy).query(query_xy, k=kk)
    nb = nb.reshape(len(query_xy), -1)
    if exclude_self:
        nb = nb[:, 1:]
    X = np.concatenate([ref_xy[nb], np.ones(nb.shape + (1,))], axis=2)  # (Q, k, 3)
    Y = ref_px[nb]  # (Q, k, 2)
    XtX = np.einsum("qki,qkj->qij", X, X) + 1e-9 * np.eye(3)
    XtY = np.einsum("qki,qkj->qij", X, Y)
    A = np.linalg.solve(XtX, XtY)  # (Q, 3, 2)
    pred = np.einsum("qi,qij->qj", np.column_stack([query_xy, np.ones(len(query_xy))]), A)
    scale = np.sqrt(np.abs(np.linalg.det(A[:, :2, :2])))
    return pred, scale


def _verify_and_grow(pts: np.ndarray, ids: np.ndarray, active: np.ndarray, xy_d: np.ndarray,
                     pitch_mm: float, max_rounds: int) -> int:
    """Uncode ids that disagree with their coded neighbours, then code free slots by prediction.

    Modifies ``ids`` in place; returns the number of ids removed by verification.
    """
    gate = PREDICT_GATE * pitch_mm
    removed = 0
    coded = np.nonzero(ids >= 0)[0]
    if len(coded) >= 4:
        pred, sc = _affine_predict(xy_d[ids[coded]], xy_d[ids[coded]], pts[coded], exclude_self=True)
        bad = np.linalg.norm(pred - pts[coded], axis=1) > gate * sc
        ids[coded[bad]] = -1
        removed = int(bad.sum())
    for _ in range(max_rounds):
        coded = np.nonzero(ids >= 0)[0]
        free_slots = np.setdiff1d(np.arange(len(xy_d)), ids[coded])
        cand = np.nonzero(active & (ids < 0))[0]
        if len(coded) < 4 or len(free_slots) == 0 or len(cand) == 0:
            break
        pred, sc = _affine_predict(xy_d[free_slots], xy_d[ids[coded]], pts[coded])
        d, j = cKDTree(pts[cand]).query(pred)
        back = cKDTree(pred).query(pts[cand[j]])[1]
        ok = (d <= gate * sc) & (back == np.arange(len(free_slots)))
        if not ok.any():
            break
        ids[cand[j[ok]]] = free_slots[ok]
    return removed


#: A ring of the design's size but irregular spacing (a deformed skin) is rotated onto the design by
#: prediction from the rings inside it: the best cyclic shift must fit with a mean distance below
#: this many local pitches, and the runner-up shift must fit at least SHIFT_MARGIN x worse.
SHIFT_FIT = 0.45
SHIFT_MARGIN = 2.0


def _shift_by_prediction(members: np.ndarray, d_ids: np.ndarray, pts: np.ndarray, ids: np.ndarray,
                         xy_d: np.ndarray, pitch_mm: float) -> int | None:
    """Cyclic shift coding a complete ring (``members`` sorted CCW) whose gaps are irregular.

    The ring's cyclic order is topological and survives deformation; only its start is unknown. Each
    design slot of the ring is predicted from a local affine fit to the coded markers (the rings
    inside, already coded), and the shift whose found points lie nearest the predictions wins when
    it is unambiguous (:data:`SHIFT_FIT`, :data:`SHIFT_MARGIN`). Returns None otherwise.
    """
    coded = np.nonzero(ids >= 0)[0]
    if len(coded) < 4:
        return None
    pred, sc = _affine_predict(xy_d[d_ids], xy_d[ids[coded]], pts[coded])
    n = len(d_ids)
    shifts = _SHIFTS.get(n)
    if shifts is None:
        shifts = _SHIFTS[n] = (np.arange(n)[:, None] + np.arange(n)[None, :]) % n
    p = pts[members]
    dist = np.linalg.norm(p[shifts] - pred[None, :, :], axis=2) / (pitch_mm * np.maximum(sc, 1e-9))[None, :]
    cost = dist.mean(axis=1)
    order = np.argsort(cost)
    best = int(order[0])
    if cost[best] > SHIFT_FIT or (n > 1 and cost[order[1]] < SHIFT_MARGIN * cost[best]):
        return None
    return best


def code_rings(blobs: Blobs, design: SensorDesign) -> RingCoding:
    """DTRC ring coding of one view.

    Parameters
    ----------
    blobs : Blobs
        Marker centres of ONE view (px).
    design : SensorDesign
        Gives the ring count (``pattern.layers``), ring sizes and canonical ids.

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
    pts = np.asarray(blobs.xy_px, dtype=np.float64)
    n = len(pts)
    xy_d, drings = _design_rings(design)
    n_layers = design.pattern.layers
    expected = tuple(len(drings[k][0]) for k in range(n_layers - 1, -1, -1))
    ids = np.full(n, -1, np.int64)
    ring_of = np.full(n, -1, np.int64)
    msgs: list[str] = []
    if n < 4:
        return RingCoding(ids, ring_of, (), expected, np.arange(len(xy_d), dtype=np.int64),
                          messages=(f"only {n} blobs",))
    nn, tri = _nn_and_mesh(pts)
    med_nn = _median(nn)
    active = nn <= OUTLIER_NN_FACTOR * med_nn
    if (~active).any():
        msgs.append(f"dropped {int((~active).sum())} isolated blob(s) outside the lattice")
    rings, edges = _peel(pts, active, n_layers, med_nn, tri)
    for r, members in enumerate(rings):
        ring_of[members] = r
    found = tuple(len(r) for r in rings)
    leftover = active & (ring_of < 0)
    if leftover.any():
        msgs.append(f"{int(leftover.sum())} blob(s) left inside after {n_layers} rings")

    # code from the centre outward: peel r <-> layer n_layers - 1 - r
    theta = 0.0
    failed = bool(leftover.any() or (~active).any())
    for layer in range(n_layers):
        d_ids, d_xy, d_ang = drings[layer]
        r = n_layers - 1 - layer
        members = rings[r] if r < len(rings) else np.empty(0, np.intp)
        done = False
        if len(members) == len(d_ids):
            if layer == 0:
                ids[members[0]] = d_ids[0]
                done = True
            else:
                p = pts[members]
                c = p.sum(axis=0) / len(p)
                phi = np.arctan2(p[:, 1] - c[1], p[:, 0] - c[0])
                o = np.argsort(phi, kind="stable")
                members, phi = members[o], phi[o]
                if _gaps_regular(pts[members], d_xy):
                    shift, theta_new, spread = _shift_code(phi, d_ang, theta)
                    if spread < math.pi / len(d_ids):
                        ids[np.concatenate((members[shift:], members[:shift]))] = d_ids
                        theta = theta_new
                        done = True
                if not done:
                    # complete but irregular (a deformed skin): the cyclic order still holds; find the
                    # start by prediction from the rings inside, or for the first ring (only the centre
                    # is coded) by the angular fit alone; verified against the neighbours below
                    how = "prediction from the rings inside"
                    shift = _shift_by_prediction(members, d_ids, pts, ids, xy_d, design.pattern.separation_mm)
                    if shift is None and int((ids >= 0).sum()) < 4:
                        s_ang, _, spread = _shift_code(phi, d_ang, theta)
                        shift, how = (s_ang, "its angles") if spread < math.pi / len(d_ids) else (None, "")
                    if shift is not None:
                        ids[np.concatenate((members[shift:], members[:shift]))] = d_ids
                        theta += float(np.angle(np.mean(np.exp(1j * (np.roll(phi, -shift) - d_ang - theta)))))
                        failed = True
                        msgs.append(f"ring {r} (layer {layer}): irregular, coded by {how}")
                        done = True
        if not done:
            failed = True
            msgs.append(f"ring {r} (layer {layer}): found {len(members)} blobs, expected {len(d_ids)}"
                        + ("" if len(members) != len(d_ids) else " (irregular)"))
    if failed:
        # a defect anywhere may shift markers between peels: check every code against its coded
        # neighbours and fill the free slots by prediction (never by guessing)
        before = int((ids >= 0).sum())
        removed = _verify_and_grow(pts, ids, active, xy_d, design.pattern.separation_mm, n_layers + 2)
        msgs.append(f"verification removed {removed} code(s); prediction coded "
                    f"{int((ids >= 0).sum()) - before + removed} more")
    all_ids = np.arange(len(xy_d), dtype=np.int64)
    present = np.zeros(len(xy_d), bool)
    present[ids[ids >= 0]] = True
    unmatched = all_ids[~present]
    return RingCoding(ids, ring_of, found, expected, unmatched, edges, tuple(msgs))


# ----- stereo matching and tracking ---------------------------------------------------------

def _pair(left: Blobs, right: Blobs, lc: RingCoding, rc: RingCoding, n_markers: int) -> MarkerMatches:
    li = np.full(n_markers, -1, np.int64)
    ri = np.full(n_markers, -1, np.int64)
    ok_l, ok_r = lc.ids >= 0, rc.ids >= 0
    li[lc.ids[ok_l]] = np.nonzero(ok_l)[0]
    ri[rc.ids[ok_r]] = np.nonzero(ok_r)[0]
    both = (li >= 0) & (ri >= 0)
    mid = np.nonzero(both)[0].astype(np.int64)
    return MarkerMatches(ids=mid, left_px=left.xy_px[li[both]], right_px=right.xy_px[ri[both]],
                         unmatched_ids=np.nonzero(~both)[0].astype(np.int64))


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
    return _pair(left, right, code_rings(left, design), code_rings(right, design), design.marker_count)


class DTRCTracker:
    """DTRC tracking: every frame is re-coded, so identity survives arbitrarily large motion.

    ``update(left, right) -> MarkerMatches`` (also callable). ``last_codings`` holds the two
    :class:`RingCoding` of the latest frame.
    """

    def __init__(self, design: SensorDesign) -> None:
        self.design = design
        self.last_codings: tuple[RingCoding, RingCoding] | None = None

    def update(self, left: Blobs, right: Blobs) -> MarkerMatches:
        lc, rc = code_rings(left, self.design), code_rings(right, self.design)
        self.last_codings = (lc, rc)
        return _pair(left, right, lc, rc, self.design.marker_count)

    __call__ = update

    def reset(self) -> None:
        self.last_codings = None


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
