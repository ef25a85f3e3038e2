"""DTRC step 3 for complete, regular rings: the design rings, and the cyclic shift rotating a found
ring onto its design ring by angle, carried outward from the centre."""

from __future__ import annotations

import math

import numba
import numpy as np

from pipeline.design import SensorDesign
from pipeline.vision.dtrc.mesh import _median
from pipeline.vision.nearest import design_order


#: one missing marker doubles a gap, a spurious one halves it.
RING_GAP_TOL = 1.5


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


_ORDER_CACHE: dict[tuple, np.ndarray] = {}


def _design_order(design: SensorDesign) -> np.ndarray:
    """:func:`pipeline.vision.nearest.design_order` of the design points of :func:`_design_rings`: the
    neighbour table the defect path's affine predictions take their neighbours from."""
    key = (design.pattern.kind, design.pattern.layers, design.pattern.separation_mm)
    if key not in _ORDER_CACHE:
        _ORDER_CACHE[key] = design_order(_design_rings(design)[0])
    return _ORDER_CACHE[key]


def _marker_count(design: SensorDesign) -> int:
    """``design.marker_count`` from the cached rest layout (the property recomputes the layout)."""
    return len(_design_rings(design)[0])


_FLAT_CACHE: dict[tuple, tuple] = {}


def _design_radii(design: SensorDesign) -> np.ndarray:
    """Each layer's mean design radius about the centre (mm; 0 for the centre)."""
    xy, rings = _design_rings(design)
    c = xy[rings[0][0]].mean(axis=0)
    return np.array([float(np.hypot(*(p - c).T).mean()) for _, p, _ in rings])


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


@numba.njit(cache=True, nogil=True)
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


# ----- coding -------------------------------------------------------------------------------

def _cyclic_gaps(xy: np.ndarray) -> np.ndarray:
    d = np.diff(xy, axis=0, append=xy[:1])  # xy[i + 1] - xy[i], cyclic
    return np.sqrt(d[:, 0] * d[:, 0] + d[:, 1] * d[:, 1])


def _design_gap_scale(design_xy: np.ndarray) -> float:
    """Mean design gap of a ring over its median gap."""
    gd = _cyclic_gaps(design_xy)
    return float((gd / _median(gd)).mean())


@numba.njit(cache=True, nogil=True)
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


@numba.njit(cache=True, nogil=True)
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


@numba.njit(cache=True, nogil=True)
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


@numba.njit(cache=True, nogil=True)
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


@numba.njit(cache=True, nogil=True)
def _unmatched(ids, n_markers):
    """Design ids (ascending) not among ``ids``."""
    present = np.zeros(n_markers, np.bool_)
    for i in ids:
        if i >= 0:
            present[i] = True
    return np.flatnonzero(~present).astype(np.int64)


#: The rotation read from a circular pattern's rings without its centre is taken when the rings' phases
#: agree with it to this many ring spacings RMS (each ring at its radius, weighted by its blobs). It is
#: a proposal: a twist of the rings that fits nearly as well (the outer rings of 48 and 42 markers
#: turned by one slot each stay within 0.07 spacings RMS) is told apart by the certainty rule's
#: centre test (:func:`pipeline.vision.identity.centring.annulus_twist`).
ANNULUS_FIT = 0.05
#: A blob is taken as a member of the design ring whose radius (in the outer ring's radii, the
#: outer ring whitened to a circle) is nearest, when within this many ring spacings of it.
ANNULUS_BAND = 0.3
ANNULUS_STEP = math.radians(0.05)
ANNULUS_RANGE = math.radians(30.0)


def _annulus_rotation(pts, active, outer, d_ang, d_off, d_radius):
    """The in-plane rotation (rad) of a circular pattern read without its centre, or None.

    ``outer``: the blobs of the complete outer ring (peel 0). Its centroid and second moments map the
    view so that the outer ring is a circle of the design's outer radius (a camera's perspective and a
    bulge keep rings nearly concentric ellipses); each other active blob is taken for the design ring
    of nearest radius (``d_radius`` per layer) when within :data:`ANNULUS_BAND`. A ring of n equally
    spaced markers fixes the rotation only modulo its pitch 2 pi / n, through the phase
    ``arg sum exp(i n phi)`` of its blobs against the design ring's; rings of different sizes fix it
    jointly (two consecutive rings of 6k and 6k + 6 markers modulo 60 deg). The rotation within
    +-30 deg that the blobs agree on best, each at its ring's radius (a distance in pixels), is taken
    when the fit is tight.
    """
    n_layers = len(d_off) - 1
    p = pts[outer]
    c = p.mean(axis=0)
    w, v = np.linalg.eigh(np.cov((p - c).T))
    if not w.min() > 0:
        return None
    white = v @ np.diag(1 / np.sqrt(w)) @ v.T
    q = (pts - c) @ white.T
    scale = d_radius[n_layers - 1] / float(np.hypot(*q[outer].T).mean())
    q *= scale
    rad = np.hypot(*q.T)
    phi = np.arctan2(q[:, 1], q[:, 0])
    ring = np.searchsorted((d_radius[1:] + d_radius[:-1]) / 2, rad)
    spacing = np.diff(d_radius).min()
    member = active & (ring >= 1) & (np.abs(rad - d_radius[ring.clip(0, n_layers - 1)]) <= ANNULUS_BAND * spacing)
    member[outer] = True
    ring[outer] = n_layers - 1
    grid = np.arange(-ANNULUS_RANGE, ANNULUS_RANGE + ANNULUS_STEP / 2, ANNULUS_STEP)
    cost = np.zeros_like(grid)
    used = 0
    for layer in np.unique(ring[member]):
        on = member & (ring == layer)
        n = d_off[layer + 1] - d_off[layer]
        if np.count_nonzero(on) < 3:
            continue
        design_phase = np.angle(np.exp(1j * n * d_ang[d_off[layer]:d_off[layer + 1]]).sum())
        t = (np.angle(np.exp(1j * n * phi[on]).sum()) - design_phase) / n
        cost += ((np.angle(np.exp(1j * n * (grid - t))) / n * d_radius[layer]) ** 2) * np.count_nonzero(on)
        used += np.count_nonzero(on)
    if used == 0:
        return None
    rms = np.sqrt(cost / used) / spacing
    i = int(np.argmin(rms))
    return None if rms[i] > ANNULUS_FIT else float(grid[i])
