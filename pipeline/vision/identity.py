"""The certainty rule of marker identification: an id is emitted only when the geometry leaves no
other reading; every other marker is unmatched, with a reason.

Ring coding (:mod:`pipeline.vision.dtrc`), a lattice registration and the previous frame only *propose*
ids. A proposal becomes an identification through three tests, each about the sensor's geometry:

1. **Local consistency.** A marker's closed design neighbourhood (the marker and its identified
   design neighbours within 1.5 separations) must be one smooth piece of skin: every member lies
   within :data:`GATE` local separations of the position a local affine map fitted to the *others*
   predicts for it (leave-one-out). The fit needs three non-collinear neighbours; the local map
   must keep orientation (the image is not mirrored) and may stretch at most :data:`MAX_STRETCH`
   times more along one axis than along the other. A skin can bulge, shear and crowd smoothly; it
   cannot swap two neighbours, and a marker labelled as its neighbour sits a whole separation from
   its prediction. Inconsistent markers are removed until every remaining neighbourhood agrees.
2. **Anchoring.** Local consistency fixes ids only up to the lattice's own symmetries: a patch of
   correctly related markers could be shifted by a lattice vector, or (rings of a circular
   pattern) turned by one slot per ring, and still be locally perfect. Each connected patch of
   identified markers is compared with every such alternative reading of the design; an
   alternative is excluded by evidence: markers of the patch that it would push outside the design
   (they are there, consistent with their neighbours, so the design must contain them) plus markers
   whose neighbourhoods it breaks. A patch is anchored only if every alternative is excluded by at
   least :data:`ANCHOR_EVIDENCE` markers; otherwise all its ids are withdrawn ("not anchored").
   A patch that does not reach the pattern's outer ring on enough sides (e.g. the far side of an
   occlusion) is therefore left unidentified rather than guessed.
3. **Rotation.** Turning the pattern by its symmetry angle (60 deg for hexagonal and circular
   patterns, 90 deg for square ones) changes nothing in the image. The in-plane rotation of each
   patch (Procrustes, image against design) must be within +-(half the symmetry angle - 7.5 deg),
   i.e. +-22.5 deg or +-37.5 deg; beyond, the patch is withdrawn ("rotation ambiguous").

Growth extends anchored patches: a free design slot predicted from three or more identified
neighbours takes the nearest blob when it lies within :data:`GROW_GATE` local separations, is at
least twice as near as the second-nearest blob (and 0.15 separations nearer), and no other free
slot claims it; new ids then pass the same three tests.

What remains possible, by construction: a blob that is not a marker but sits where a missing
marker should be (within :data:`GROW_GATE` of its slot) is indistinguishable from that marker
displaced, and takes its id. The identification benchmark therefore places spurious blobs at least
half a separation from the slots of missing markers (anywhere else, including next to present
markers, is allowed).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import cv2
import numba
import numpy as np
from scipy.spatial import cKDTree

from pipeline.vision.kdtree import kd_build, kd_query

__all__ = ["GATE", "GROW_GATE", "ANCHOR_EVIDENCE", "MAX_STRETCH", "ROTATION_MARGIN_DEG", "REASONS",
           "lattice_of", "consistent", "certify", "certify_whole", "contradicted", "follow", "grow", "register_seed", "rotation_limit_deg", "use_triangulation"]

#: Leave-one-out gate, in local separations. A correct marker's prediction error is its own centre
#: error plus the fit's (detector noise ~0.01, jitter tested up to 0.3); a marker carrying its
#: neighbour's id is ~1 separation off.
GATE = 0.35
#: Growth gate, in local separations: a blob farther than this from a free slot's prediction is not
#: taken (a neighbouring marker is >= 0.7 separations away even with 0.3 separations of jitter).
GROW_GATE = 0.4
#: A blob takes (or keeps) an id only if it is at least twice as near to the slot's prediction as
#: any other blob and this many local separations nearer.
AMBIGUITY_MARGIN = 0.15
#: A marker with two or more unidentified design neighbours (its prediction is extrapolated across
#: the gap) is ambiguous when another blob lies within this many local separations of it: a spurious
#: blob 0.2-0.3 separations from such a marker in a strongly pressed view was nearer the
#: extrapolated prediction than the marker itself.
CLOSE_BLOB = 0.4
#: Temporal certification (:func:`follow`): design neighbours identified in both frames a followed
#: marker's motion is taken from, and the gate (fraction of the blob's nearest-neighbour distance)
#: about its prediction.
FOLLOW_NEIGHBOURS = 3
FOLLOW_GATE = 0.35
#: Markers of evidence needed to exclude an alternative reading of a patch.
ANCHOR_EVIDENCE = 2
#: Largest ratio of the two singular values of a local affine map. Pins crowding on a steep flank
#: exceed 1.6 (a twin terrain tap on hexagon217 lost 27 of 217 ids at 1.6); a patch whose ids jump
#: by one slot across a seam fits as a shear of about one separation per row (ratio ~2-3).
MAX_STRETCH = 2.0
#: Margin kept from half the pattern's symmetry angle.
ROTATION_MARGIN_DEG = 7.5
#: Radius (design separations) of the neighbourhood a local affine map is fitted to: two shells,
#: so that a slot on the convex edge of an identified patch (two immediate neighbours) still has a
#: fit, while the map stays local (a press changes the skin's local scale over several separations).
NEIGHBOURHOOD_PITCHES = 2.1
#: A circular pattern's first three rings must each fit an affine image of the design ring to within
#: this fraction of ring 1's radius (measured: <= 0.17 under a 5 mm off-centre press through the
#: nominal cameras; a reading centred on a marker of ring 1 leaves >= 0.31 on ring 2, 0.39 on ring 3).
RING_ROUND = 0.22
#: ... and their centres must agree to within this fraction of ring 1's radius (a reading centred
#: on a marker of ring 1 is a whole radius off).
RING_CENTRE = 0.3
#: Radius (design separations) about its anchor slot within which a similarity placement proposes
#: ids (growth takes over beyond: a press bulges the pattern by up to ~15 % of its radius).
SEED_RADIUS = 3.5
#: Identified immediate neighbours (within 1.5 separations) a marker needs.
MIN_IMMEDIATE = 2
#: ... and to count as evidence against an alternative reading that would put it outside the design.
#: A spurious blob just outside the pattern, which a reading shifted by one row takes for an outer-
#: ring marker, has only the two true outer-ring markers beside it; the markers of a pattern's outer
#: ring have three or four.
EVIDENCE_IMMEDIATE = 3
#: With this many identified immediate neighbours a marker's neighbourhood fit uses only them (the
#: second shell is used where fewer are identified: at the edge of a patch or of a gap).
LOCAL_ONLY = 5
#: A patch is withdrawn when unidentified blobs sit where the lattice would continue one step
#: beyond the design's outer ring (hexagonal, square) beside this many consecutive outer-ring slots:
#: a reading shifted by one row leaves the pattern's real outer row there (a side of 7-9 blobs in a
#: row); spurious blobs land there scattered.
BEYOND_HITS = 5
#: Largest ratio of the singular values of the affine map a closed fan's neighbours may show when
#: the fan is intact (:func:`_embedded`): its topology, not the map's shape, rules out seams and
#: swaps there, so only a fold-free crowding limit is kept (measured up to 1.9 at the tip of a 5 mm
#: press of the sharpest twin Gaussian on the 0.5 mm skin).
FAN_MAX_STRETCH = 3.0
#: A slot has a closed fan only if its design neighbours leave no angular gap wider than this about
#: it (hexagonal 60, square 45 deg inside the pattern; an outer-ring slot leaves >= 180 deg).
FAN_MAX_GAP_DEG = 135.0
#: Nearest blobs examined for the emptiness of a fan (a hexagonal fan has 6 vertices).
FAN_QUERY = 24
#: Smallest patch that is reported (a patch needs neighbourhoods of three to be tested at all).
MIN_PATCH = 4

# per-slot reason codes (0 = identified)
R_OK, R_NO_BLOB, R_AMBIGUOUS, R_INCONSISTENT, R_FEW, R_ANCHOR, R_ROTATION, R_CONTRADICTED = range(8)
#: internal status: the test needs the k-d tree of the blobs (built only when some blob needs it)
_NEED_TREE = 99
REASONS = {
    R_NO_BLOB: "no blob at its predicted position",
    R_AMBIGUOUS: "two blobs near its predicted position",
    R_INCONSISTENT: "inconsistent with its identified neighbours",
    R_FEW: "fewer than three identified neighbours",
    R_ANCHOR: "in a patch that could be shifted along the lattice (not anchored)",
    R_ROTATION: "pattern rotation beyond the unambiguous range",
    R_CONTRADICTED: "two certified readings disagree (this frame's coding and the previous frame's ids)",
}


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

    nbr, nbr2 = table(1.5), table(NEIGHBOURHOOD_PITCHES)
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
        if np.all(dd < 0.1 * pitch):
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
        m = np.where(dd < 0.25 * pitch, jj, -1)
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
        names.append(f"each ring turned by {j:+d} slot(s)")
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
        steps = steps[np.hypot(*steps.T) <= 1.1 * pitch]
        outer = np.flatnonzero(layers == layers.max())
        for s_ in outer:
            for v in steps:
                q = xy[s_] + v
                if tree.query(q)[0] > 0.5 * pitch:
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
    dtree = kd_build(xy)
    for a in range(len(alt)):
        g = alt[a].copy()
        u, cnt = np.unique(g[g >= 0], return_counts=True)
        g[np.isin(g, u[cnt > 1])] = -1
        st = _consistency(xy, dtree, True, np.zeros(n + 1, np.int64), np.zeros(0, np.int64), g, _blob_of(g, n), xy,
                          nbr, nbr2, loo_m, loo_tab, fan, fan_closed, pitch, GATE, np.arange(n), 0)
        first[a, st == R_INCONSISTENT] = 0
    outer_ring = np.flatnonzero(layers == layers.max()).astype(np.int64)
    lat = Lattice(xy, pitch, nbr, nbr2, alpha, alt, tuple(names),
                  layers.astype(np.int64), lattice, first, v_slot, v_xy, outer_ring, fan, fan_closed, loo_m, loo_tab)
    _CACHE[key] = lat
    return lat


def rotation_limit_deg(lat: Lattice) -> float:
    """Largest |in-plane rotation| at which ids are emitted (half the symmetry angle minus the margin)."""
    return lat.alpha_deg / 2 - ROTATION_MARGIN_DEG


# ----- local affine fits ------------------------------------------------------------------------

@numba.njit(cache=True)
def _fit_sums(xy, pts, slots, blobs, m, ox, oy, ou, ov, acc):
    """Sums over points ``0..m-1`` of (slots, blobs) for :func:`_fit`, coordinates taken relative to
    (ox, oy) in the design and (ou, ov) in the image (keeps the downdated sums well conditioned),
    written into ``acc`` (12,) (a work array: the tests run per blob, so no allocation here)."""
    a0 = a1 = a2 = a3 = a4 = a5 = a6 = a7 = a8 = a9 = a10 = a11 = 0.0
    for i in range(m):
        x = xy[slots[i], 0] - ox
        y = xy[slots[i], 1] - oy
        u = pts[blobs[i], 0] - ou
        v = pts[blobs[i], 1] - ov
        a0 += 1.0
        a1 += x
        a2 += y
        a3 += u
        a4 += v
        a5 += x * x
        a6 += x * y
        a7 += y * y
        a8 += u * x
        a9 += u * y
        a10 += v * x
        a11 += v * y
    acc[0], acc[1], acc[2], acc[3], acc[4], acc[5] = a0, a1, a2, a3, a4, a5
    acc[6], acc[7], acc[8], acc[9], acc[10], acc[11] = a6, a7, a8, a9, a10, a11
    return acc


@numba.njit(cache=True)
def _fit(xy, pts, slots, blobs, acc, skip, ox, oy, ou, ov, pitch):
    """:func:`_fit_map` with the stretch limit :data:`MAX_STRETCH`."""
    return _fit_map(xy, pts, slots, blobs, acc, skip, ox, oy, ou, ov, pitch, MAX_STRETCH)


@numba.njit(cache=True)
def _fit_map(xy, pts, slots, blobs, acc, skip, ox, oy, ou, ov, pitch, max_stretch):
    """Affine map design -> image from the points summed in ``acc`` (:func:`_fit_sums`) without
    point ``skip`` (-1: none).

    Returns (ok, mean design x, y, mean image u, v, L00, L01, L10, L11), means relative to the
    origins of :func:`_fit_sums`. ``ok`` is 1 for a usable map, 0 when fewer than three points
    remain or they are (nearly) collinear, -1 when the map mirrors or stretches more than
    ``max_stretch`` (no smooth skin does that).
    """
    c0, c1, c2, c3, c4, c5 = acc[0], acc[1], acc[2], acc[3], acc[4], acc[5]
    c6, c7, c8, c9, c10, c11 = acc[6], acc[7], acc[8], acc[9], acc[10], acc[11]
    if skip >= 0:
        x = xy[slots[skip], 0] - ox
        y = xy[slots[skip], 1] - oy
        u = pts[blobs[skip], 0] - ou
        v = pts[blobs[skip], 1] - ov
        c0 -= 1.0
        c1 -= x
        c2 -= y
        c3 -= u
        c4 -= v
        c5 -= x * x
        c6 -= x * y
        c7 -= y * y
        c8 -= u * x
        c9 -= u * y
        c10 -= v * x
        c11 -= v * y
    cnt = c0
    if cnt < 2.5:
        return 0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0
    mx, my, mu, mv = c1 / cnt, c2 / cnt, c3 / cnt, c4 / cnt
    sxx = c5 - cnt * mx * mx
    sxy = c6 - cnt * mx * my
    syy = c7 - cnt * my * my
    cux = c8 - cnt * mu * mx
    cuy = c9 - cnt * mu * my
    cvx = c10 - cnt * mv * mx
    cvy = c11 - cnt * mv * my
    det = sxx * syy - sxy * sxy
    tr = sxx + syy
    lam_min = tr / 2 - math.sqrt(max(tr * tr / 4 - det, 0.0))
    if lam_min < 0.1 * pitch * pitch:
        return 0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0
    i00, i01, i11 = syy / det, -sxy / det, sxx / det
    l00 = cux * i00 + cuy * i01
    l01 = cux * i01 + cuy * i11
    l10 = cvx * i00 + cvy * i01
    l11 = cvx * i01 + cvy * i11
    dl = l00 * l11 - l01 * l10
    if dl <= 0.0:
        return -1, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0
    fro = l00 * l00 + l01 * l01 + l10 * l10 + l11 * l11
    s_max = math.sqrt(max(fro / 2 + math.sqrt(max(fro * fro / 4 - dl * dl, 0.0)), 0.0))
    s_min = dl / s_max
    if s_max > max_stretch * s_min:
        return -1, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0
    return 1, mx, my, mu, mv, l00, l01, l10, l11


@numba.njit(cache=True)
def _loo_design(xy, nbr, nbr2, pitch):
    """The design half of every leave-one-out fit of :func:`_loo_status` when a slot's whole
    neighbourhood is identified (the common case): ``m`` (N,) the number of points fitted (the slot
    and the neighbours :func:`_loo_status` gathers), and ``tab`` (N, K1 + 1, 9) per slot and left-out
    point q (0 = the slot, then its immediate neighbours): usable (1.0, else 0.0: too few or
    collinear points), the point count, the design means, the inverse of the design scatter (00, 01,
    11) and the left-out point's design offset from the mean. Computed by the very operations of
    :func:`_fit_sums` and :func:`_fit_map`, so a fit that takes them is bit for bit the full one."""
    N = len(xy)
    K = nbr2.shape[1]
    K1 = nbr.shape[1]
    m_of = np.zeros(N, np.int64)
    tab = np.zeros((N, K1 + 1, 9))
    slots = np.empty(K + 1, np.int64)
    for s in range(N):
        n_design = 0
        for k1 in range(K1):
            if nbr[s, k1] < 0:
                break
            n_design += 1
        slots[0] = s
        m = 1
        for k in range(K):
            j = nbr2[s, k]
            if j < 0 or (k >= n_design and n_design >= LOCAL_ONLY):
                break
            slots[m] = j
            m += 1
        m_of[s] = m
        ox, oy = xy[s, 0], xy[s, 1]
        a0 = a1 = a2 = a5 = a6 = a7 = 0.0
        for i in range(m):
            x = xy[slots[i], 0] - ox
            y = xy[slots[i], 1] - oy
            a0 += 1.0
            a1 += x
            a2 += y
            a5 += x * x
            a6 += x * y
            a7 += y * y
        for q in range(n_design + 1):
            x = xy[slots[q], 0] - ox
            y = xy[slots[q], 1] - oy
            c0 = a0 - 1.0
            c1 = a1 - x
            c2 = a2 - y
            c5 = a5 - x * x
            c6 = a6 - x * y
            c7 = a7 - y * y
            cnt = c0
            tab[s, q, 1] = cnt
            if cnt < 2.5:
                continue
            mx, my = c1 / cnt, c2 / cnt
            sxx = c5 - cnt * mx * mx
            sxy = c6 - cnt * mx * my
            syy = c7 - cnt * my * my
            det = sxx * syy - sxy * sxy
            tr = sxx + syy
            lam_min = tr / 2 - math.sqrt(max(tr * tr / 4 - det, 0.0))
            if lam_min < 0.1 * pitch * pitch:
                continue
            tab[s, q, 0] = 1.0
            tab[s, q, 2], tab[s, q, 3] = mx, my
            tab[s, q, 4], tab[s, q, 5], tab[s, q, 6] = syy / det, -sxy / det, sxx / det
            tab[s, q, 7] = xy[slots[q], 0] - ox - mx
            tab[s, q, 8] = xy[slots[q], 1] - oy - my
    return m_of, tab


@numba.njit(cache=True)
def _fit_tab(xy, pts, slots, blobs, acc, skip, ox, oy, ou, ov, row):
    """:func:`_fit` (point ``skip`` left out) with its design half taken from a row of the table of
    :func:`_loo_design`; the image half is the same sequence of operations as :func:`_fit_map`'s."""
    if row[0] == 0.0:
        return 0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0
    x = xy[slots[skip], 0] - ox
    y = xy[slots[skip], 1] - oy
    u = pts[blobs[skip], 0] - ou
    v = pts[blobs[skip], 1] - ov
    c3 = acc[3] - u
    c4 = acc[4] - v
    c8 = acc[8] - u * x
    c9 = acc[9] - u * y
    c10 = acc[10] - v * x
    c11 = acc[11] - v * y
    cnt, mx, my = row[1], row[2], row[3]
    mu, mv = c3 / cnt, c4 / cnt
    cux = c8 - cnt * mu * mx
    cuy = c9 - cnt * mu * my
    cvx = c10 - cnt * mv * mx
    cvy = c11 - cnt * mv * my
    i00, i01, i11 = row[4], row[5], row[6]
    l00 = cux * i00 + cuy * i01
    l01 = cux * i01 + cuy * i11
    l10 = cvx * i00 + cvy * i01
    l11 = cvx * i01 + cvy * i11
    dl = l00 * l11 - l01 * l10
    if dl <= 0.0:
        return -1, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0
    fro = l00 * l00 + l01 * l01 + l10 * l10 + l11 * l11
    s_max = math.sqrt(max(fro / 2 + math.sqrt(max(fro * fro / 4 - dl * dl, 0.0)), 0.0))
    s_min = dl / s_max
    if s_max > MAX_STRETCH * s_min:
        return -1, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0
    return 1, mx, my, mu, mv, l00, l01, l10, l11


@numba.njit(cache=True)
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


@numba.njit(cache=True)
def _embedded(pts, tree, has_tree, adj_ptr, adj_idx, b, s, blob_of, xy, fan, closed, pitch, gate, ring, near, near_d2):
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

    Returns 1 (intact), 0 (not), or :data:`_NEED_TREE` when only the blob search of the emptiness
    test is left and ``has_tree`` is False. ``ring``, ``near``, ``near_d2``: work arrays (fan width,
    and >= :data:`FAN_QUERY`)."""
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
    sx = sy = su = sv = sxx = sxy = syy = sux = suy = svx = svy = 0.0
    for i in range(m):
        x = xy[fan[s, i], 0] - xy[s, 0]
        y = xy[fan[s, i], 1] - xy[s, 1]
        u = pts[ring[i], 0] - pts[b, 0]
        v = pts[ring[i], 1] - pts[b, 1]
        sx += x
        sy += y
        su += u
        sv += v
        sxx += x * x
        sxy += x * y
        syy += y * y
        sux += u * x
        suy += u * y
        svx += v * x
        svy += v * y
    mx, my, mu, mv = sx / m, sy / m, su / m, sv / m
    sxx -= m * mx * mx
    sxy -= m * mx * my
    syy -= m * my * my
    cux = sux - m * mu * mx
    cuy = suy - m * mu * my
    cvx = svx - m * mv * mx
    cvy = svy - m * mv * my
    det = sxx * syy - sxy * sxy
    if not det > 1e-12 * pitch ** 4:
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
    if not has_tree:
        return _NEED_TREE
    # Otherwise: usually the fan's own blobs are still the nearest ones, so every other blob is
    # farther than all of them (outside the fan); else the nearer blobs are tested against the
    # fan's triangles
    r2 = 0.0
    for i in range(m):
        dx = pts[ring[i], 0] - pts[b, 0]
        dy = pts[ring[i], 1] - pts[b, 1]
        r2 = max(r2, dx * dx + dy * dy)
    kq = min(len(pts), m + 1)
    kd_query(pts, tree, pts[b, 0], pts[b, 1], kq, near, near_d2)
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
    kd_query(pts, tree, pts[b, 0], pts[b, 1], kq, near, near_d2)
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


@numba.njit(cache=True)
def _consistency(pts, tree, has_tree, adj_ptr, adj_idx, slot_of, blob_of, xy, nbr, nbr2, loo_m, loo_tab, fan, closed,
                 pitch, gate, order, stop_after):
    """Status of every labelled blob: 0 consistent, R_FEW too few neighbours, R_INCONSISTENT.

    The neighbourhood of a blob's slot is the identified slots of ``nbr2``; the blob itself and
    each identified immediate neighbour (``nbr``) must lie within ``gate`` local pitches of the
    position the affine map fitted to the rest of the neighbourhood predicts for it; and the blob
    must be the unambiguous nearest blob to its own prediction (R_AMBIGUOUS otherwise: at least
    twice as near as the second-nearest and 0.15 pitches nearer). A blob failing these is still
    consistent when it is the vertex of an intact image of its design fan (:func:`_embedded`).
    ``tree``: :func:`kd_build` of ``pts``; with ``has_tree`` False (a placeholder tree) a blob whose
    test needs a blob search gets :data:`_NEED_TREE` instead (not counted as inconsistent).
    Blobs are visited in ``order``; with ``stop_after`` > 0 the visit stops once that many are
    inconsistent (the anchoring test needs only that much evidence)."""
    n = len(slot_of)
    status = np.zeros(n, np.int64)
    K = nbr2.shape[1]
    K1 = nbr.shape[1]
    slots = np.empty(K + 1, np.int64)
    blobs = np.empty(K + 1, np.int64)
    acc = np.empty(12)
    two = np.empty(2, np.int64)
    two_d2 = np.empty(2)
    ring = np.empty(fan.shape[1], np.int64)
    near = np.empty(FAN_QUERY, np.int64)
    near_d2 = np.empty(FAN_QUERY)
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
            e = _embedded(pts, tree, has_tree, adj_ptr, adj_idx, b, s, blob_of, xy, fan, closed, pitch, gate, ring,
                          near, near_d2)
        if e == 1:
            st = 0
        elif e == _NEED_TREE:
            st = _NEED_TREE
        else:
            st = _loo_status(pts, tree, has_tree, b, s, blob_of, xy, nbr, nbr2, loo_m, loo_tab, pitch, gate, slots,
                             blobs, acc, two, two_d2, K, K1)
        status[b] = st
        if st == R_INCONSISTENT:
            n_bad += 1
    return status


@numba.njit(cache=True)
def _loo_status(pts, tree, has_tree, b, s, blob_of, xy, nbr, nbr2, loo_m, loo_tab, pitch, gate, slots, blobs, acc, two,
                two_d2, K, K1):
    """The leave-one-out test of :func:`_consistency` for blob ``b`` labelled ``s``: its status.

    The immediate design neighbours ``nbr[s]`` are the first entries of ``nbr2[s]`` (both sorted
    by distance; :func:`lattice_of` checks it), so the identified neighbourhood is gathered in one
    pass with the immediate ones first, and the second shell only when it is fitted at all."""
    n_design = 0
    for k1 in range(K1):
        if nbr[s, k1] < 0:
            break
        n_design += 1
    slots[0] = s
    blobs[0] = b
    m = 1
    for k in range(n_design):
        j = nbr2[s, k]
        if blob_of[j] >= 0:
            slots[m] = j
            blobs[m] = blob_of[j]
            m += 1
    n_imm = m - 1
    if n_imm < LOCAL_ONLY:
        # the second shell completes the neighbourhood fitted where few immediate neighbours are
        # identified; with LOCAL_ONLY or more, only the closed immediate neighbourhood is fitted,
        # where a strongly curved press is still affine
        for k in range(n_design, K):
            j = nbr2[s, k]
            if j < 0:
                break
            if blob_of[j] >= 0:
                slots[m] = j
                blobs[m] = blob_of[j]
                m += 1
    if m < 4 or n_imm < MIN_IMMEDIATE:
        return R_FEW
    ox, oy, ou, ov = xy[s, 0], xy[s, 1], pts[b, 0], pts[b, 1]
    # the whole design neighbourhood identified: the design half of each fit is tabulated
    whole = n_imm == n_design and m == loo_m[s]
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
        if q == 0 and len(pts) >= 2:
            if not has_tree:
                return _NEED_TREE
            kd_query(pts, tree, pu, pv, 2, two, two_d2)
            d1 = math.sqrt(two_d2[0]) / scale
            d2 = math.sqrt(two_d2[1]) / scale
            if two[0] != b or d2 < 2 * d1 or d2 - d1 < AMBIGUITY_MARGIN:
                return R_AMBIGUOUS
            if n_imm <= n_design - 2:
                # a neighbourhood with a wide gap extrapolates its prediction: a second blob closer
                # to b than CLOSE_BLOB separations leaves open which of the two is the marker
                kd_query(pts, tree, pts[b, 0], pts[b, 1], 2, two, two_d2)
                if math.sqrt(two_d2[1]) < CLOSE_BLOB * scale:
                    return R_AMBIGUOUS
    return 0


@numba.njit(cache=True)
def _predict_free(pts, blob_of, xy, nbr, pitch):
    """Predicted image position and local pitch (px) of every free slot with a usable fit from its
    identified neighbours; ``scale`` 0 where there is none."""
    N = len(blob_of)
    K = nbr.shape[1]
    pred = np.zeros((N, 2))
    scale = np.zeros(N)
    slots = np.empty(K, np.int64)
    blobs = np.empty(K, np.int64)
    acc = np.empty(12)
    for s in range(N):
        if blob_of[s] >= 0:
            continue
        m = 0
        for k in range(K):
            j = nbr[s, k]
            if j < 0:
                break
            if blob_of[j] >= 0:
                slots[m] = j
                blobs[m] = blob_of[j]
                m += 1
        if m < 3:
            continue
        ox, oy, ou, ov = xy[s, 0], xy[s, 1], pts[blobs[0], 0], pts[blobs[0], 1]
        acc = _fit_sums(xy, pts, slots, blobs, m, ox, oy, ou, ov, acc)
        ok, mx, my, mu, mv, l00, l01, l10, l11 = _fit(xy, pts, slots, blobs, acc, -1, ox, oy, ou, ov, pitch)
        if ok <= 0:
            continue
        pred[s, 0] = ou + mu - l00 * mx - l01 * my
        pred[s, 1] = ov + mv - l10 * mx - l11 * my
        scale[s] = math.sqrt(l00 * l11 - l01 * l10) * pitch
    return pred, scale


# ----- the rule ---------------------------------------------------------------------------------

_TREES: dict = {}


def _tree(pts: np.ndarray):
    """:func:`kd_build` of the blob centres, kept for the arrays of the frame being identified."""
    key = id(pts)
    hit = _TREES.get(key)
    if hit is not None and hit[0] is pts:
        return hit[1]
    _TREES.clear()
    t = kd_build(pts)
    _TREES[key] = (pts, t)
    return t


_MESHES: dict = {}
_PLACEHOLDER_TREE = kd_build(np.zeros((1, 2)))
_NO_ADJ = (np.zeros(1, np.int64), np.zeros(0, np.int64))


def use_triangulation(pts: np.ndarray, simplices: np.ndarray | None) -> None:
    """Register the Delaunay triangles (M, 3) of the blob centres ``pts`` (the very array later
    passed to :func:`certify`), which ring coding has computed anyway: a blob whose Delaunay
    neighbours are exactly its design fan has an empty fan without a neighbour search. ``None``
    forgets the registered triangles (the emptiness test then searches)."""
    _MESHES.clear()
    if simplices is not None and len(simplices):
        _MESHES[id(pts)] = (pts, _adjacency(np.ascontiguousarray(simplices, dtype=np.int64), len(pts)))


def _adj(pts: np.ndarray):
    hit = _MESHES.get(id(pts))
    if hit is not None and hit[0] is pts:
        return hit[1]
    return (np.zeros(len(pts) + 1, np.int64), _NO_ADJ[1])


@numba.njit(cache=True)
def _adjacency(simp, n):
    """Neighbour lists (CSR: ``ptr`` (n+1,), ``idx``) of the vertices of triangles ``simp``."""
    cnt = np.zeros(n + 1, np.int64)
    for t in range(len(simp)):
        for k in range(3):
            cnt[simp[t, k] + 1] += 2
    ptr = np.cumsum(cnt)
    raw = np.empty(ptr[-1], np.int64)
    fill = ptr[:-1].copy()
    for t in range(len(simp)):
        for k in range(3):
            a = simp[t, k]
            raw[fill[a]] = simp[t, (k + 1) % 3]
            raw[fill[a] + 1] = simp[t, (k + 2) % 3]
            fill[a] += 2
    out_ptr = np.zeros(n + 1, np.int64)
    out = np.empty(ptr[-1], np.int64)
    w = 0
    for a in range(n):
        out_ptr[a] = w
        for q in range(ptr[a], ptr[a + 1]):
            v = raw[q]
            dup = False
            for r in range(out_ptr[a], w):
                if out[r] == v:
                    dup = True
                    break
            if not dup:
                out[w] = v
                w += 1
    out_ptr[n] = w
    return out_ptr, out[:w]


def _blob_of(slot_of: np.ndarray, n_slots: int) -> np.ndarray:
    b = np.full(n_slots, -1, np.int64)
    lab = np.flatnonzero(slot_of >= 0)
    b[slot_of[lab]] = lab
    return b


def _statuses(pts, adj, slot_of, lat, order=None):
    """:func:`_consistency` of every labelled blob; the k-d tree of the blobs is built only when
    some blob's test needs a search (usually none does: intact fans are checked on the Delaunay
    triangulation)."""
    blob_of = _blob_of(slot_of, len(lat.xy))
    order = np.arange(len(slot_of)) if order is None else order
    has_tree = not lat.translation_lattice          # no fans: every test searches
    st = _consistency(pts, _tree(pts) if has_tree else _PLACEHOLDER_TREE, has_tree, adj[0], adj[1], slot_of, blob_of,
                      lat.xy, lat.nbr, lat.nbr2, lat.loo_m, lat.loo_tab, lat.fan, lat.fan_closed, lat.pitch, GATE, order, 0)
    need = np.flatnonzero(st == _NEED_TREE)
    if len(need):
        st2 = _consistency(pts, _tree(pts), True, adj[0], adj[1], slot_of, blob_of, lat.xy, lat.nbr, lat.nbr2,
                           lat.loo_m, lat.loo_tab, lat.fan, lat.fan_closed, lat.pitch, GATE, need, 0)
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


@numba.njit(cache=True)
def _beyond_hits(pts, tree, slot_of, blob_of, xy, nbr2, pitch, v_slot, v_xy, gate):
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
        m = 1
        for k in range(K):
            j = nbr2[s, k]
            if j < 0:
                break
            if blob_of[j] >= 0:
                slots[m] = j
                blobs[m] = blob_of[j]
                m += 1
        ox, oy, ou, ov = xy[s, 0], xy[s, 1], pts[b, 0], pts[b, 1]
        acc = _fit_sums(xy, pts, slots, blobs, m, ox, oy, ou, ov, acc)
        ok, mx, my, mu, mv, l00, l01, l10, l11 = _fit(xy, pts, slots, blobs, acc, -1, ox, oy, ou, ov, pitch)
        if ok <= 0:
            continue
        dx = v_xy[v, 0] - ox - mx
        dy = v_xy[v, 1] - oy - my
        pu = ou + mu + l00 * dx + l01 * dy
        pv = ov + mv + l10 * dx + l11 * dy
        kd_query(pts, tree, pu, pv, 1, one, one_d2)
        if slot_of[one[0]] < 0 and math.sqrt(one_d2[0]) <= gate * math.sqrt(l00 * l11 - l01 * l10) * pitch:
            hit[v] = 1
    return hit


@numba.njit(cache=True)
def _components(slot_of, blob_of, nbr):
    """Connected patches of identified blobs (design neighbours within 1.5 pitches both identified):
    patch index per blob, -1 for unidentified blobs."""
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
                if bj >= 0 and comp[bj] < 0:
                    comp[bj] = c
                    stack[sp] = bj
                    sp += 1
        c += 1
    return comp


@numba.njit(cache=True)
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


def _circle(p: np.ndarray):
    """Least-squares circle (centre (2,), radius) through points (m, 2), m >= 3 (Kasa's fit)."""
    A = np.column_stack([2 * p, np.ones(len(p))])
    sol, *_ = np.linalg.lstsq(A, (p * p).sum(axis=1), rcond=None)
    c = sol[:2]
    return c, math.sqrt(max(sol[2] + c @ c, 0.0))


def _centre_holds(pts, slot_of, members, lat) -> bool:
    """The first three rings of a circular pattern, as identified, are rings of equally spaced
    markers about one point, seen through one smooth map: each ring's blobs (at least 2/3 of its
    slots) fit an affine image of the design ring to within :data:`RING_ROUND` of ring 1's mean
    radius, the three fits share their centre (within :data:`RING_CENTRE`: an off-centre press
    moves the rings' centres apart by ~0.1 radius) and their shape (linear parts proportional to
    within 25 %: a press changes each ring's radius, a camera's perspective is common to all).
    About a marker of ring 1 the pattern also shows rings of about six and twelve markers, but its
    third ring is not eighteen markers 20 deg apart."""
    return _centre_kernel(pts, slot_of, members, lat.xy, lat.layer_of, RING_ROUND, RING_CENTRE)


@numba.njit(cache=True)
def _centre_kernel(pts, slot_of, members, xy, layer_of, ring_round, ring_centre):
    """:func:`_centre_holds` (compiled)."""
    c0x = 0.0
    c0y = 0.0
    for s in range(len(layer_of)):
        if layer_of[s] == 0:
            c0x, c0y = xy[s, 0], xy[s, 1]
    L = np.zeros((3, 2, 2))
    cen = np.zeros((3, 2))
    res = np.zeros(3)
    sel = np.empty(len(members), np.int64)
    slots = np.empty(len(members), np.int64)
    acc = np.empty(12)
    for k in range(1, 4):
        size = 0
        for s in range(len(layer_of)):
            if layer_of[s] == k:
                size += 1
        m = 0
        for b in members:
            if layer_of[slot_of[b]] == k:
                sel[m] = b
                slots[m] = slot_of[b]
                m += 1
        if m < max(int(math.ceil(2.0 / 3.0 * size)), 4):
            return False
        acc = _fit_sums(xy, pts, slots, sel, m, c0x, c0y, 0.0, 0.0, acc)
        ok, mx, my, mu, mv, l00, l01, l10, l11 = _fit(xy, pts, slots, sel, acc, -1, c0x, c0y, 0.0, 0.0, 1e-9)
        if ok == 0:
            return False
        if ok < 0:
            # refit without the plausibility limits: a ring is judged by its residuals below
            cnt = acc[0]
            mx, my, mu, mv = acc[1] / cnt, acc[2] / cnt, acc[3] / cnt, acc[4] / cnt
            sxx = acc[5] - cnt * mx * mx
            sxy = acc[6] - cnt * mx * my
            syy = acc[7] - cnt * my * my
            det = sxx * syy - sxy * sxy
            i00, i01, i11 = syy / det, -sxy / det, sxx / det
            cux = acc[8] - cnt * mu * mx
            cuy = acc[9] - cnt * mu * my
            cvx = acc[10] - cnt * mv * mx
            cvy = acc[11] - cnt * mv * my
            l00 = cux * i00 + cuy * i01
            l01 = cux * i01 + cuy * i11
            l10 = cvx * i00 + cvy * i01
            l11 = cvx * i01 + cvy * i11
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
        if math.sqrt(dev) > 0.25 * math.sqrt(ref):
            return False
    for b in members:
        if layer_of[slot_of[b]] == 0:
            if math.hypot(pts[b, 0] - cen[0, 0], pts[b, 1] - cen[0, 1]) > ring_centre * rad1:
                return False
    return True


def _anchored(pts, slot_of, members, lat) -> bool:
    """Is the patch ``members`` (blob indices) excluded from every alternative reading?"""
    if not lat.translation_lattice and not _centre_holds(pts, slot_of, members, lat):
        # rings of equally spaced markers read one ring further out, turned, or shifted by a
        # marker are locally almost a hexagonal lattice; only the rings about the centre fix the
        # reading: they must be concentric circles about one point
        return False
    if len(lat.alt) == 0:
        return True
    adj = _adj(pts)
    # without the blob search first (usually enough evidence), then with it
    tries = ((_PLACEHOLDER_TREE, False), (None, True)) if lat.translation_lattice else ((None, True),)
    for tree, has_tree in tries:
        if _alternatives_excluded(pts, _tree(pts) if tree is None else tree, has_tree, adj[0], adj[1], slot_of,
                                  members, lat.alt, lat.alt_first, lat.xy, lat.nbr, lat.nbr2, lat.loo_m, lat.loo_tab,
                                  lat.fan, lat.fan_closed, lat.pitch, GATE, ANCHOR_EVIDENCE):
            return True
    return False


@numba.njit(cache=True)
def _alternatives_excluded(pts, tree, has_tree, adj_ptr, adj_idx, slot_of, members, alt, alt_first, xy, nbr, nbr2, loo_m,
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
        st = _consistency(pts, tree, has_tree, adj_ptr, adj_idx, alt_slot, blob_of, xy, nbr, nbr2, loo_m, loo_tab, fan,
                          closed, pitch, gate, order, need)
        bad = 0
        for b in members:
            if st[b] == R_INCONSISTENT:
                bad += 1
        for b in members:
            alt_slot[b] = -1
        if bad < need:
            return False
    return True


def certify_whole(pts: np.ndarray, slot_of: np.ndarray, lat: Lattice) -> bool:
    """The common case in one compiled pass: every blob carries a proposed id, and every id of the
    design is proposed (no defect at all). True when :func:`certify` would keep the whole proposal:
    every marker consistent without a blob search (intact fans, :func:`_embedded`), the pattern
    within the rotation limit, excluded from every alternative reading (and, for circular
    patterns, centred). False means only "not decided here": :func:`certify` decides."""
    N = len(lat.xy)
    if len(pts) != N or len(slot_of) != N or N < MIN_PATCH:
        return False
    adj = _adj(pts)
    if len(adj[1]) == 0:
        return False
    if not _whole_kernel(pts, _PLACEHOLDER_TREE, adj[0], adj[1], slot_of, lat.xy, lat.nbr, lat.nbr2, lat.loo_m,
                         lat.loo_tab, lat.fan, lat.fan_closed, lat.pitch, GATE, rotation_limit_deg(lat), lat.alt,
                         lat.alt_first, ANCHOR_EVIDENCE):
        return False
    members = np.arange(N, dtype=np.int64)
    return lat.translation_lattice or _centre_holds(pts, slot_of, members, lat)


@numba.njit(cache=True)
def _whole_kernel(pts, tree, adj_ptr, adj_idx, slot_of, xy, nbr, nbr2, loo_m, loo_tab, fan, closed, pitch, gate, limit, alt,
                  alt_first, evidence):
    """:func:`certify_whole` without the circular patterns' centre test."""
    n = len(slot_of)
    blob_of = np.full(len(xy), -1, np.int64)
    for b in range(n):
        s = slot_of[b]
        if s < 0 or blob_of[s] >= 0:
            return False
        blob_of[s] = b
    order = np.arange(n)
    has_tree = False
    if fan[:, 0].max() < 0:
        # no fans (circular patterns): every test searches
        tree = kd_build(pts)
        has_tree = True
    st = _consistency(pts, tree, has_tree, adj_ptr, adj_idx, slot_of, blob_of, xy, nbr, nbr2, loo_m, loo_tab, fan, closed,
                      pitch, gate, order, 0)
    n_need = 0
    for b in range(n):
        if st[b] == _NEED_TREE:
            n_need += 1
        elif st[b] != 0:
            return False
    if n_need:
        # the fans that are not exactly Delaunay stars need the blob search
        tree = kd_build(pts)
        has_tree = True
        need = np.empty(n_need, np.int64)
        k = 0
        for b in range(n):
            if st[b] == _NEED_TREE:
                need[k] = b
                k += 1
        st = _consistency(pts, tree, True, adj_ptr, adj_idx, slot_of, blob_of, xy, nbr, nbr2, loo_m, loo_tab, fan, closed,
                          pitch, gate, need, 0)
        for b in need:
            if st[b] != 0:
                return False
    des = np.empty((n, 2))
    for b in range(n):
        des[b, 0] = xy[slot_of[b], 0]
        des[b, 1] = xy[slot_of[b], 1]
    if abs(_rotation_deg(pts, des)) > limit:
        return False
    if alt.shape[0] == 0:
        return True
    if _alternatives_excluded(pts, tree, has_tree, adj_ptr, adj_idx, slot_of, order, alt, alt_first, xy, nbr, nbr2, loo_m,
                              loo_tab, fan, closed, pitch, gate, evidence):
        return True
    if has_tree:
        return False
    return _alternatives_excluded(pts, kd_build(pts), True, adj_ptr, adj_idx, slot_of, order, alt, alt_first, xy, nbr, nbr2,
                                  loo_m, loo_tab, fan, closed, pitch, gate, evidence)


def certify(pts: np.ndarray, slot_of: np.ndarray, lat: Lattice, reason: np.ndarray | None = None):
    """Apply the certainty rule to a proposal.

    Parameters
    ----------
    pts : (n, 2) float64 blob centres (px)
    slot_of : (n,) int64 proposed design id per blob (-1 none; ids unique)
    lat : :class:`Lattice`
    reason : (N,) int64, optional, updated in place with the reason code of every withdrawn id

    Returns
    -------
    (n,) int64 certified ids (-1 where withdrawn).
    """
    N = len(lat.xy)
    if reason is None:
        reason = np.zeros(N, np.int64)
    slot_of = consistent(pts, slot_of, lat, reason)
    lab = np.flatnonzero(slot_of >= 0)
    if len(lab) == 0:
        return slot_of
    blob_of = _blob_of(slot_of, N)
    # patches: identified design neighbours (every such pair passed the consistency test)
    comp_of = _components(slot_of, blob_of, lat.nbr)
    comp = comp_of[lab]
    n_comp = int(comp.max()) + 1
    beyond = np.zeros(n_comp, np.int64)
    if len(lat.beyond_slot) and len(lab) < len(slot_of):   # a hit is an unidentified blob
        hits = _beyond_hits(pts, _tree(pts), slot_of, blob_of, lat.xy, lat.nbr2, lat.pitch, lat.beyond_slot,
                            lat.beyond_xy, GROW_GATE)
        # a real outer row continues along the ring: the longest run of consecutive outer-ring
        # slots (cyclic, canonical order) with a blob beyond them, per patch
        outer = lat.outer_ring
        hit_slot = np.zeros(N, bool)
        hit_slot[lat.beyond_slot[hits > 0]] = True
        h = hit_slot[outer]
        if h.any() and not h.all():
            start = int(np.argmin(h))                     # a slot without a hit: runs do not wrap
            h = np.roll(h, -start)
            o = np.roll(outer, -start)
            run = 0
            for k in range(len(h)):
                run = run + 1 if h[k] else 0
                if run >= BEYOND_HITS:
                    b = blob_of[o[k]]
                    if b >= 0:
                        beyond[comp_of[b]] = max(beyond[comp_of[b]], run)
        elif h.all():
            beyond[:] = len(h)
    limit = rotation_limit_deg(lat)
    for c in range(n_comp):
        members = lab[comp == c]
        code = R_OK
        if len(members) < MIN_PATCH:
            code = R_FEW
        elif abs(_rotation_deg(np.ascontiguousarray(pts[members]), np.ascontiguousarray(lat.xy[slot_of[members]]))) > limit:
            code = R_ROTATION
        elif beyond[c] >= BEYOND_HITS:
            code = R_ANCHOR
        elif not _anchored(pts, slot_of, members, lat):
            code = R_ANCHOR
        if code != R_OK:
            reason[slot_of[members]] = code
            slot_of[members] = -1
    return slot_of


def contradicted(slot_of: np.ndarray, other: np.ndarray) -> np.ndarray:
    """Blobs whose id in ``slot_of`` a second certified reading ``other`` (same blobs) contradicts: it
    gives the blob another id, or gives the blob's id to another blob. Two readings that both passed
    the certainty rule yet disagree cannot both be right, and nothing in one frame says which is:
    a row of markers lost at the edge of the view lets the row beside it be read one row over with
    every neighbourhood still a smooth, moderately stretched map, while the same blobs followed from
    the previous frame (motion a fraction of the spacing) keep their own ids. Returns a bool mask."""
    a = slot_of >= 0
    bad = a & (other >= 0) & (other != slot_of)
    where_other = np.full(max(int(slot_of.max(initial=-1)), int(other.max(initial=-1))) + 1, -1, np.int64)
    lab = np.flatnonzero(other >= 0)
    where_other[other[lab]] = lab
    mine = np.flatnonzero(a)
    w = where_other[slot_of[mine]]
    bad[mine[(w >= 0) & (w != mine)]] = True
    return bad


def follow(prev_xy: np.ndarray, prev_ids: np.ndarray, pts: np.ndarray, slot_of: np.ndarray, lat: Lattice,
           max_rounds: int = 16) -> np.ndarray:
    """Temporal certification: markers of the previous frame followed into this one.

    A marker certain in the previous frame (``prev_xy`` (M, 2) px, ``prev_ids`` (M,)) but not
    identified here is predicted at its previous position moved by the mean motion of at least
    :data:`FOLLOW_NEIGHBOURS` of its design neighbours (within :data:`NEIGHBOURHOOD_PITCHES`)
    identified in both frames. The nearest blob takes its id when it is within :data:`FOLLOW_GATE`
    of its own nearest-neighbour distance from the prediction, at least twice as near as the
    second-nearest blob, unidentified, and claimed by no other followed marker. Rounds repeat so
    that followed markers carry their neighbours' motion on. Returns the ids with the followed
    ones added. The skin moves smoothly between frames (a press, a slide), so where ring coding
    and the local geometric tests cannot decide (crowding, strong deformation) the identity of
    a marker is still fixed by where it was.
    """
    N = len(lat.xy)
    out = slot_of.copy()
    if len(pts) < 3 or len(prev_ids) == 0:
        return out
    P = np.full((N, 2), np.nan)
    P[prev_ids] = prev_xy
    tree = cKDTree(pts)
    nn = tree.query(pts, k=2)[0][:, 1]
    nb = lat.nbr2
    valid_nb = nb >= 0
    nb0 = np.where(valid_nb, nb, 0)
    for _ in range(max_rounds):
        C = np.full((N, 2), np.nan)
        lab = np.flatnonzero(out >= 0)
        C[out[lab]] = pts[lab]
        moved = C - P                                         # NaN unless in both frames
        ok_nb = valid_nb & np.isfinite(moved[nb0, 0])
        cnt = ok_nb.sum(axis=1)
        free = np.flatnonzero(np.isnan(C[:, 0]) & np.isfinite(P[:, 0]) & (cnt >= FOLLOW_NEIGHBOURS))
        if len(free) == 0:
            break
        disp = np.where(ok_nb[free][..., None], moved[nb0[free]], 0.0).sum(axis=1) / cnt[free][:, None]
        pred = P[free] + disp
        d, j = tree.query(pred, k=2)
        j1 = j[:, 0]
        take = (d[:, 0] <= FOLLOW_GATE * nn[j1]) & (d[:, 1] >= 2 * d[:, 0]) & (out[j1] < 0)
        u, c = np.unique(j1[take], return_counts=True)
        take &= ~np.isin(j1, u[c > 1])
        if not take.any():
            break
        out[j1[take]] = free[take]
    return out


def grow(pts: np.ndarray, slot_of: np.ndarray, lat: Lattice, reason: np.ndarray, tree=None,
         max_rounds: int = 64) -> np.ndarray:
    """Extend certified patches slot by slot (see the module notes), re-testing after every round."""
    N = len(lat.xy)
    slot_of = slot_of.copy()
    if len(pts) < 2:
        return slot_of
    tree = cKDTree(pts) if tree is None else tree
    for _ in range(max_rounds):
        blob_of = _blob_of(slot_of, N)
        pred, scale = _predict_free(pts, blob_of, lat.xy, lat.nbr2, lat.pitch)
        free = np.flatnonzero(scale > 0)
        if len(free) == 0:
            break
        d, j = tree.query(pred[free], k=2)
        d1, d2 = d[:, 0] / scale[free], d[:, 1] / scale[free]
        near = d1 <= GROW_GATE
        reason[free[~near]] = R_NO_BLOB
        amb = near & ~((d2 >= 2 * d1) & (d2 - d1 >= AMBIGUITY_MARGIN))
        reason[free[amb]] = R_AMBIGUOUS
        take = near & ~amb & (slot_of[j[:, 0]] < 0)
        cand = j[take, 0]
        slots = free[take]
        # a blob claimed by two free slots is ambiguous for both
        u, cnt = np.unique(cand, return_counts=True)
        dup = np.isin(cand, u[cnt > 1])
        reason[slots[dup]] = R_AMBIGUOUS
        cand, slots = cand[~dup], slots[~dup]
        if len(cand) == 0:
            break
        trial = slot_of.copy()
        trial[cand] = slots
        trial = consistent(pts, trial, lat, reason)
        if np.array_equal(trial >= 0, slot_of >= 0) and np.array_equal(trial, slot_of):
            break
        gained = np.count_nonzero(trial >= 0) - np.count_nonzero(slot_of >= 0)
        slot_of = trial
        if gained <= 0:
            break
    return slot_of


def register_seed(pts: np.ndarray, lat: Lattice, *, max_hypotheses: int = 800, n_best: int = 8) -> list:
    """A proposal independent of ring peeling: the similarity transform (scale from the median
    nearest-neighbour distance, rotation within the unambiguous range from the directions to the
    nearest neighbours, translation putting one of the central blobs on one of the central slots)
    under which the most design slots land on a blob. A lattice placed one pitch off fits the
    interior as well as the truth (and a press bulges the pattern, so the boundary may not fit a
    similarity at all): the ``n_best`` best distinct placements are returned, as proposals (an id
    per blob, -1 none: every slot whose projection has exactly one blob within a third of a
    separation and that lies within :data:`SEED_RADIUS` separations of the slot the placement was
    anchored on, where a similarity still fits a bulged pattern), best first; growth and the
    anchoring test decide among them."""
    n = len(pts)
    N = len(lat.xy)
    out: list = []
    if n < 4:
        return out
    tree = cKDTree(pts)
    dn, jn = tree.query(pts, k=min(7, n))
    pitch_px = float(np.median(dn[:, 1]))
    if not pitch_px > 0:
        return out
    s0 = pitch_px / lat.pitch
    # rotation, per hypothesis: the directions to a blob's nearest neighbours (k of them, k-fold
    # symmetric about a lattice point) against those about the design slot it is put on
    fold = 4 if lat.nbr.shape[1] == 8 and lat.translation_lattice else 6

    def local_angle(p, at, nb):
        v = p[nb] - p[at][:, None, :]
        z = np.exp(1j * fold * np.arctan2(v[..., 1], v[..., 0])).mean(axis=1)
        return np.degrees(np.angle(z)) / fold

    # translations: central blobs on central slots
    c_img = np.median(pts, axis=0)
    b_idx = tree.query(c_img, k=min(7 if lat.translation_lattice else 19, n))[1]
    c_des = lat.xy.mean(axis=0)
    s_idx = np.argsort(np.hypot(*(lat.xy - c_des).T), kind="stable")[:19]
    # score by a distance map of the blobs (one lookup per projected slot)
    scale_map = 12.0 / pitch_px  # 12 raster pixels per separation
    lo = pts.min(axis=0) - 2 * pitch_px
    hi = pts.max(axis=0) + 2 * pitch_px
    shape = (int((hi[1] - lo[1]) * scale_map) + 2, int((hi[0] - lo[0]) * scale_map) + 2)
    if shape[0] * shape[1] > 4_000_000:
        return out

    raster = np.full(shape, 255, np.uint8)
    rc = np.rint((pts - lo) * scale_map).astype(np.int64)
    raster[rc[:, 1], rc[:, 0]] = 0
    dist = cv2.distanceTransform(raster, cv2.DIST_L2, cv2.DIST_MASK_PRECISE)
    placements: list = []
    ang_b = local_angle(pts, b_idx, jn[b_idx][:, 1:fold + 1])
    dtree = cKDTree(lat.xy)
    ang_s = local_angle(lat.xy, s_idx, dtree.query(lat.xy[s_idx], k=fold + 1)[1][:, 1:])
    period = 360.0 / fold
    lim = lat.alpha_deg / 2
    th = ang_b[:, None] - ang_s[None, :]
    th = ((th + period / 2) % period - period / 2).ravel()
    bb = np.repeat(b_idx, len(s_idx))
    ss = np.tile(s_idx, len(b_idx))
    anchor_px = pts[bb]
    if not lat.translation_lattice:
        # a circular pattern is fixed by its centre: the centre slot on a central blob, or on the
        # apex of an equilateral triangle over two adjacent central blobs (a missing centre marker)
        centre = int(np.argmin(np.hypot(*(lat.xy - c_des).T)))
        apex = []
        for b in b_idx:
            for k in (1, 2):
                q = pts[jn[b, k]] - pts[b]
                for sgn in (1.0, -1.0):
                    apex.append(pts[b] + 0.5 * q + sgn * (math.sqrt(3) / 2) * np.array([-q[1], q[0]]))
        apex = np.array(apex)
        apex = apex[tree.query(apex)[0] > 0.5 * pitch_px]
        anchor_px = np.vstack([pts[b_idx], apex])
        ring1 = tree.query_ball_point(anchor_px, 1.3 * pitch_px)
        th = np.zeros(len(anchor_px))
        scale_h = np.full(len(anchor_px), s0)
        rad_des = float(np.mean(np.hypot(*(lat.xy[lat.layer_of == 1] - lat.xy[centre]).T)))
        for i, lst in enumerate(ring1):
            v = pts[[j for j in lst if np.hypot(*(pts[j] - anchor_px[i])) > 0.7 * pitch_px]] - anchor_px[i]
            if len(v):
                th[i] = np.degrees(np.angle(np.exp(1j * fold * np.arctan2(v[:, 1], v[:, 0])).mean())) / fold
                # the first ring's radius: a press bulges the centre, the median spacing misses it
                scale_h[i] = float(np.mean(np.hypot(*v.T))) / rad_des
        ss = np.full(len(anchor_px), centre)
    if lat.translation_lattice:
        scale_h = np.full(len(anchor_px), s0)
    cands = [th + k * period for k in range(-int(lim // period) - 1, int(lim // period) + 2)]
    TH, AP, SS, SC = [], [], [], []
    for c_ in cands:
        keep = np.abs(c_) <= lim
        TH.append(c_[keep])
        AP.append(anchor_px[keep])
        SS.append(ss[keep])
        SC.append(scale_h[keep])
    TH = np.concatenate(TH)[:max_hypotheses]
    AP = np.concatenate(AP)[:max_hypotheses]
    SS = np.concatenate(SS)[:max_hypotheses]
    SC = np.concatenate(SC)[:max_hypotheses]
    if len(TH):
        t = np.radians(TH)
        cos, sin = np.cos(t) * SC, np.sin(t) * SC
        # (H, N, 2): slot xy rotated and scaled per hypothesis, then moved so slot SS lands on AP
        rx = cos[:, None] * lat.xy[None, :, 0] - sin[:, None] * lat.xy[None, :, 1]
        ry = sin[:, None] * lat.xy[None, :, 0] + cos[:, None] * lat.xy[None, :, 1]
        proj_all = np.stack([rx, ry], axis=2)
        off = AP - proj_all[np.arange(len(SS)), SS]
        P = (proj_all + off[:, None, :] - lo) * scale_map  # (H, N, 2)
        u = np.rint(P[..., 0]).astype(np.int64)
        v = np.rint(P[..., 1]).astype(np.int64)
        inside = (u >= 0) & (v >= 0) & (u < shape[1]) & (v < shape[0])
        dd = np.full(u.shape, np.inf, np.float32)
        dd[inside] = dist[v[inside], u[inside]]
        # ranked on the slots that land on a blob (for a circular pattern only those within 3.5
        # separations of the centre: its rings fit a similarity only near the centre when the
        # skin bulges)
        near = np.hypot(*(lat.xy[None, :, :] - lat.xy[SS][:, None, :]).transpose(2, 0, 1)) <= SEED_RADIUS * lat.pitch
        hit = dd <= 0.3 * 12.0
        if not lat.translation_lattice:
            hit &= near
        score = np.count_nonzero(hit, axis=1)
        # many (blob, slot) pairs give the same placement: keep the best distinct ones
        key = np.rint(off / (0.5 * pitch_px)).astype(np.int64)
        key = key[:, 0] * 1_000_003 + key[:, 1] + np.rint(TH / 2.0).astype(np.int64) * 7_919
        # ties (a shifted lattice fits as many slots) are broken by how near the placement puts
        # the design's centre to the middle of the blobs
        centre_off = np.hypot(*(proj_all.mean(axis=1) + off - c_img).T) / pitch_px
        order = np.lexsort((centre_off, -score))
        _, first = np.unique(key[order], return_index=True)
        for h in order[np.sort(first)][:n_best]:
            placements.append((int(score[h]), float(centre_off[h]), proj_all[h] + off[h], near[h]))
    placements.sort(key=lambda x: (-x[0], x[1]))
    for _, _, p, nr in placements[:n_best]:
        d, j = tree.query(p, k=2)
        ok = nr & (d[:, 0] <= pitch_px / 3) & (d[:, 1] >= 2 * d[:, 0])
        u, cnt = np.unique(j[ok, 0], return_counts=True)
        ok &= ~np.isin(j[:, 0], u[cnt > 1])
        prop = np.full(n, -1, np.int64)
        prop[j[ok, 0]] = np.flatnonzero(ok)
        out.append(prop)
    return out
