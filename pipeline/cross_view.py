"""Ids taken across the two views: a marker one view identifies is proposed to the other view's blob
that its stereo geometry allows, and that view's certainty rule decides.

Each view is identified on its own (:class:`pipeline.vision.dtrc.DTRCTracker`), and the two views do
not fail alike: the cameras see the skin from either side of the baseline, so a press that drags the
pins far in one frame (a rapid slide under friction moves the stuck skin ~0.9 separations between
two frames) can bend one view's rings beyond what ring coding and the frame-to-frame map read while
the other view's rings are read whole. The view that identified a marker says where it is in space up
to its viewing ray; the other view's blob of that marker lies where that ray, refracted through the
stack, is met by a ray of its own within the stereo check's gap and inside the gel.

A proposal is made only where the geometry leaves one reading. The pair's rays must meet within the
stereo check's gap inside the gel (:meth:`pipeline.runner.Reconstructor._locate`); along the baseline the
next marker of a row meets the same ray inside the gel too, 4-6 mm deeper or shallower, so the pair's
3-D point must also lie within :data:`XYZ_GATE` separations of where the marker's design neighbours'
3-D points put it (those identified in both views, then those placed by earlier rounds); and the blob
must be the only free blob that passes for the marker, the marker the only one that passes for the
blob. The proposals are then certified in the receiving view exactly as ring coding's are
(:func:`pipeline.vision.identity.certify`: locally consistent with its identified neighbours, anchored,
not rotated; an interior marker held by :data:`~pipeline.vision.dtrc.proposals.HELD_BY` identified
neighbours): a blob proposed as its neighbour sits a whole separation from where its neighbours put it
and is refused. The receiving
view's own ids are not changed (but for the one case below); an id is only added.

In a sequence the previous frame's pairs say more. Where crests crowd the pins, a view's ids come from the
frame-to-frame map, not from the certainty rule, which such a view fails as a whole; the design's affine map
then misplaces a marker in space by most of a separation, but its previous point moved by its neighbours' mean
motion does not. A pair that lies that close to where the marker's motion puts it (:data:`MOTION_GATE`), passes
the same one-reading tests and is held by identified neighbours in the receiving view is taken on that evidence.
A marker the frame did not pair (one view dropped its blob) keeps a place for the next frames, carried by its
neighbours' motion (:func:`pipeline.places.carry`, :data:`~pipeline.places.CARRY_FRAMES`), so that it is
predicted by its motion when it is seen again.

The other view also settles what one view cannot: a spurious blob near a marker whose neighbourhood is bent or
seen from one side leaves that view's reading ambiguous ("two blobs near its predicted position"), and the
certainty rule refuses the proposal for the same reason. A blob whose ray cannot meet the marker's ray from the
other view inside the gel is not that marker, whatever the neighbourhood predicts; with every such blob near the
proposal set aside, the receiving view's rule is applied once more and decides (:data:`SETTLE_REACH`). A blob whose
ray does meet it (one along the epipolar line) keeps the slot open.

A view's id that only the markers' motion gave (the frame-to-frame map or re-acquisition, where the view's rule
left the slot open: ``RingCoding.by_motion``) is asked the same question, and it is the one id of a view this
module may take away. The map takes the blob nearest where the marker's neighbours' motion in the image puts it;
a sharp tip dragged across the skin moves the marker under it unlike its neighbours, up to a whole separation in a
frame, onto a spurious blob where they put it, while its own blob stands free beside it. Where another free blob
within :data:`SETTLE_REACH` spacings meets the other view's marker inside the gel too, the id stands only if the
marker's motion in space settles it: its design neighbours moved alike (:data:`~pipeline.places.MOTION_SPREAD`)
and their mean motion puts it within :data:`MOTION_GATE` of the id's pair and of no other blob's pair. Otherwise
the id is left open with that reason (:data:`MOTION_UNSETTLED`).
"""

from __future__ import annotations

from dataclasses import replace
from typing import Callable

import numpy as np

from pipeline.design import SensorDesign
from pipeline.places import moved_alike, moved_with_neighbours, neighbour_sets
from pipeline.types import Blobs
from pipeline.vision.dtrc.proposals import held
from pipeline.vision.identity import certify, lattice_of
from pipeline.vision.identity.constants import R_AMBIGUOUS
from pipeline.vision.nearest import nearest_other_distances

__all__ = ["across_views", "MAX_PAIRS", "MOTION_GATE", "MOTION_UNSETTLED", "SETTLE_REACH", "XYZ_GATE"]

#: Candidate pairs (free blobs of one view × markers only the other view identified) tested at most
#: (128 × 128, ~10 ms a round on this machine's core); beyond, the view is left as it is (a view that
#: identified almost nothing is read from its own blobs or the rest pattern, not rebuilt pair by pair
#: from the other).
MAX_PAIRS = 16384
#: A pair's 3-D point must lie within this many separations of where its design neighbours' 3-D points
#: (identified in both views, or placed by an earlier round) put the marker, by a local affine map of the design plane into space. Along
#: the baseline the next marker of a row meets the same ray 4-6 mm deeper or shallower (1.8-2.5 mm
#: patterns); the skin between two neighbours is smooth.
XYZ_GATE = 0.5
#: In a sequence, a marker the previous frame placed in space is predicted by its own previous point moved by the
#: mean motion of its design neighbours (placed in both frames), and its pair must lie within this many
#: separations of that: on the twin's narrow-sine presses from rest (1 mm a frame, crests crowding the pins) that
#: prediction is within 0.12-0.21 separations of the marker at every frame, where the design's affine map errs by
#: up to 0.85 at 5 mm. Such a pair is taken without the receiving view's certainty rule (which a crowded view
#: fails as a whole: its ids come from the frame-to-frame map), so long as the receiving view identifies
#: :data:`~pipeline.vision.dtrc.proposals.HELD_BY` of its design neighbours: the pair's rays meet within the stereo
#: check's gap, its point lies where the marker's own motion puts it, and no other free blob or wanted marker
#: passes: along the rays the next marker lies 4-6 mm off, and a blob that passes lies within ~0.1 separation
#: of where the marker itself projects.
MOTION_GATE = 0.3
#: A proposal the receiving view refuses only because a free blob stands near it (two blobs near its
#: predicted position, ``R_AMBIGUOUS``) is settled by the stereo geometry where every free blob within this many
#: of the view's blob spacings of it has rays that cannot meet the marker's ray in the other view inside the gel
#: (within the stereo check's gap): such a blob is not that marker whatever the neighbourhood predicts, and
#: the rule is applied again without it (a blob of the view's own one-view ambiguity lies within the growth
#: gate widened by the bend, well inside a spacing).
SETTLE_REACH = 1.0
Locate = Callable[[np.ndarray, np.ndarray, np.ndarray], tuple[np.ndarray, np.ndarray]]


def across_views(blobs: tuple[Blobs, Blobs], codings: tuple, design: SensorDesign, locate: Locate,
                 previous=None) -> tuple:
    """The two views' codings ``((RingCoding, from_rest), (RingCoding, from_rest))`` (left, right), each
    completed from the other (see the module notes). ``locate(left_px, right_px, ids)`` -> (ok (n,) bool,
    xyz (n, 3) mm): the stereo check's test that a left and a right pixel are one marker of that id, and
    the point they give. ``previous``: the previous frame's markers in the same space (``.ids``, ``.xyz_mm``,
    e.g. the stereo check's cloud), which predict this frame's by their motion (:data:`MOTION_GATE`)."""
    (lc, lrest), (rc, rrest) = codings
    if lc.ids.size == 0 or rc.ids.size == 0:
        return codings
    lat = lattice_of(design)
    settle = lc.by_motion.any() or rc.by_motion.any()
    todo = [_only_in(b.ids, a.ids, len(lat.xy)) for a, b in ((lc, rc), (rc, lc))]
    if not settle and not any(len(w) and (a.ids < 0).any() for w, a in zip(todo, (lc, rc))):
        return codings
    space, before = _in_space(blobs, lc, rc, lat, locate, previous)
    if settle:
        was = (lc.ids, rc.ids)
        lc, rc = (_motion_settled(blobs[0].xy_px, lc, blobs[1].xy_px, rc, True, lat, space, before, locate),
                  _motion_settled(blobs[1].xy_px, rc, blobs[0].xy_px, lc, False, lat, space, before, locate))
        for old, new in zip(was, (lc.ids, rc.ids)):
            if new is not old:                  # an id left open is not a marker placed in space either
                space[_only_in(old, new, len(lat.xy))] = np.nan
        todo = [_only_in(b.ids, a.ids, len(lat.xy)) for a, b in ((lc, rc), (rc, lc))]
    left = _complete(blobs[0].xy_px, lc, todo[0], blobs[1].xy_px, rc, True, lat, space, before, locate)
    right = _complete(blobs[1].xy_px, rc, todo[1], blobs[0].xy_px, lc, False, lat, space, before, locate)
    return (left, lrest), (right, rrest)


def _in_space(blobs, lc, rc, lat, locate: Locate, previous) -> tuple[np.ndarray, tuple]:
    """The markers both views identified, placed in space ((N, 3) by design id, NaN where not: their pairs that
    pass the stereo check's test), and the previous frame's places (``previous``; NaN where none) with those of
    checked pairs only (carried places set aside)."""
    both = np.intersect1d(lc.ids[lc.ids >= 0], rc.ids[rc.ids >= 0])
    ok, xyz = locate(blobs[0].xy_px[_index(lc.ids)[both]], blobs[1].xy_px[_index(rc.ids)[both]], both)
    space = np.full((len(lat.xy), 3), np.nan)
    space[both[ok]] = xyz[ok]
    before = np.full_like(space, np.nan)
    measured = before                      # the previous frame's points of checked pairs only
    if previous is not None and len(previous.ids):
        before[previous.ids] = previous.xyz_mm
        age = getattr(previous, "age", None)
        if age is not None and np.any(age > 0):
            measured = before.copy()
            measured[previous.ids[age > 0]] = np.nan
    return space, (before, measured)


#: Why a view's id that only the markers' motion gave is withdrawn (:func:`_motion_settled`).
MOTION_UNSETTLED = ("followed by its motion alone, and another free blob near it meets the other view's marker "
                    "inside the gel too")


def _motion_settled(pts: np.ndarray, coding, other_pts: np.ndarray, other, is_left: bool, lat, space: np.ndarray,
                    before: tuple, locate: Locate):
    """``coding`` of one view's blobs ``pts`` without the ids that only the markers' motion gave (``by_motion``)
    where neither the stereo geometry nor the marker's motion in space settles which blob it is: a free blob of
    this view within :data:`SETTLE_REACH` blob spacings of the id's blob whose rays also meet the other view's
    marker of that id inside the gel, unless the marker's previous point moved by its design neighbours' mean
    motion (``before``, ``space``: :func:`_in_space`) lies within :data:`MOTION_GATE` separations of the id's
    pair and of no such blob's. The frame-to-frame map takes the blob nearest where the marker's neighbours'
    motion in the image puts it, clear of the next; a sharp tip dragged across the skin moves the marker under
    it unlike its neighbours (up to a whole separation in a frame), onto a spurious blob there, while its own
    blob stands free within a spacing. Both blobs are then the marker as far as the two views can tell, and the
    id is left open with that reason (the other view's id stands; no pair is made)."""
    moved = np.flatnonzero(coding.by_motion)
    if len(moved) == 0 or not (coding.ids < 0).any():
        return coding
    where = _index(other.ids)
    i = coding.ids[moved]
    has = i < len(where)
    moved, i = moved[has], i[has]
    has = where[i] >= 0
    moved, i = moved[has], i[has]
    if len(moved) == 0:
        return coding
    free = np.flatnonzero(coding.ids < 0)
    spacing = float(np.median(nearest_other_distances(np.ascontiguousarray(pts, np.float64))))
    near = np.hypot(*(pts[free][None, :, :] - pts[moved][:, None, :]).transpose(2, 0, 1)) <= SETTLE_REACH * spacing
    k, f = np.nonzero(near)
    if len(k) == 0:
        return coding
    a, b = pts[free[f]], other_pts[where[i[k]]]
    ok, xyz = locate(*((a, b) if is_left else (b, a)), i[k])
    k, xyz = k[ok], xyz[ok]
    gate = MOTION_GATE * lat.pitch
    open_ = []
    for m in np.unique(k).tolist():
        j = i[m]
        p = moved_alike(j, before, lat, space) if np.isfinite(before[0][j, 0]) else None
        if (p is None or not np.linalg.norm(space[j] - p) <= gate
                or (np.linalg.norm(xyz[k == m] - p, axis=1) <= gate).any()):
            open_.append(moved[m])
    if not open_:
        return coding
    open_ = np.array(open_, np.int64)
    ids, carried, by_motion = coding.ids.copy(), coding.carried.copy(), coding.by_motion.copy()
    gone = ids[open_]
    ids[open_] = -1
    carried[np.isin(carried, gone)] = -1
    by_motion[open_] = False
    unmatched = np.concatenate([coding.unmatched_ids, gone])
    order = np.argsort(unmatched, kind="stable")
    reasons = coding.unmatched_reasons + (MOTION_UNSETTLED,) * len(gone)
    return replace(coding, ids=ids, carried=carried, by_motion=by_motion, unmatched_ids=unmatched[order],
                   unmatched_reasons=tuple(reasons[j] for j in order),
                   messages=coding.messages + (f"left {len(gone)} id(s) followed by motion open: another blob near "
                                               "each meets the other view's marker too",))


def _only_in(ids: np.ndarray, other: np.ndarray, n: int) -> np.ndarray:
    """The ids (>= 0, < n) in ``ids`` and not in ``other``, sorted: ``np.setdiff1d`` of the identified ids by a mask
    over the design's n ids (a tenth of its cost, on every frame)."""
    has = np.zeros(n, bool)
    has[ids[ids >= 0]] = True
    has[other[other >= 0]] = False
    return np.flatnonzero(has)


def _index(ids: np.ndarray) -> np.ndarray:
    """Blob index of each design id (-1 where none)."""
    where = np.full(int(max(ids.max(), 0)) + 1, -1, np.int64)
    where[ids[ids >= 0]] = np.flatnonzero(ids >= 0)
    return where


def _predicted(want: np.ndarray, lat, space: np.ndarray, before: tuple) -> tuple[np.ndarray, np.ndarray]:
    """(len(want), 3) where each marker's identified design neighbours put it in space (NaN where fewer
    than three of them, not on one line, have a 3-D point), and (len(want),) whether that is by its motion:
    where the previous frame placed the marker (``before[0]``, NaN where not: a checked pair's point or a
    place carried by :func:`pipeline.places.carry`) and three of its neighbours in both frames (``before[1]``:
    checked pairs' points only), its previous place moved by their mean motion; otherwise a local affine map of
    the design plane, fitted to its immediate neighbours or, where those are too few, to the neighbours within 2.5
    pitches (over which a press bends the skin more: a bent fit misses the marker's point, and no pair is
    proposed)."""
    out = np.full((len(want), 3), np.nan)
    moved = np.zeros(len(want), bool)
    before, measured = before
    for k, i in enumerate(want.tolist()):
        if np.isfinite(before[i, 0]):
            p = moved_with_neighbours(i, before[i], lat, space, measured)
            if p is not None:
                out[k], moved[k] = p, True
                continue
        for nb in neighbour_sets(i, lat, space):
            A = np.c_[lat.xy[nb] - lat.xy[i], np.ones(len(nb))]
            if np.linalg.svd(A[:, :2] / lat.pitch, compute_uv=False)[-1] < 0.5:   # on one line: no plane
                continue
            out[k] = np.linalg.lstsq(A, space[nb], rcond=None)[0][2]
            break
    return out, moved


def _complete(pts: np.ndarray, coding, want: np.ndarray, other_pts: np.ndarray, other, is_left: bool, lat,
              space: np.ndarray, before: np.ndarray, locate: Locate):
    """``coding`` of one view's blobs ``pts`` with the ids ``want`` that only ``other`` (the other view's
    coding of ``other_pts``) identified, certified in this view (or placed by their motion, :data:`MOTION_GATE`)."""
    ids = coding.ids
    free = np.flatnonzero(ids < 0)
    if len(free) == 0 or len(want) == 0 or len(free) * len(want) > MAX_PAIRS:
        return coding
    proposal, space = ids.copy(), space.copy()
    by_motion = np.zeros(len(ids), bool)
    index = _index(other.ids)
    while len(free) and len(want):
        # the markers placed in space so far (both views', then this round's pairs) place the next ones
        pred, moved = _predicted(want, lat, space, before)
        w = np.flatnonzero(np.isfinite(pred[:, 0]))
        if len(w) == 0:
            break
        fi, wi = (a.ravel() for a in np.meshgrid(np.arange(len(free)), w, indexing="ij"))
        a_px, b_px = pts[free[fi]], other_pts[index[want[wi]]]
        ok, xyz = locate(*((a_px, b_px) if is_left else (b_px, a_px)), want[wi])
        gate = np.where(moved[wi], MOTION_GATE, XYZ_GATE) * lat.pitch
        near = np.linalg.norm(np.nan_to_num(xyz - pred[wi], nan=np.inf), axis=1) <= gate
        ok = (ok & near).reshape(len(free), len(w))
        one = ok & (ok.sum(axis=1, keepdims=True) == 1) & (ok.sum(axis=0, keepdims=True) == 1)
        bi, wj = np.nonzero(one)
        if len(bi) == 0:
            break
        proposal[free[bi]] = want[w[wj]]
        by_motion[free[bi]] = moved[w[wj]]
        space[want[w[wj]]] = xyz.reshape(len(free), len(w), 3)[bi, wj]
        free, want = np.delete(free, bi), np.delete(want, w[wj])
    new = np.flatnonzero((proposal >= 0) & (ids < 0))
    if len(new) == 0:
        return coding
    reason = np.zeros(len(lat.xy), np.int64)
    certified = certify(pts, proposal, lat, reason)
    certified, open_ = _resolved(pts, proposal, certified, reason, new, other_pts[index[proposal[new]]], is_left, lat,
                                 locate)
    took = new[(certified[new] == proposal[new]) | (by_motion[new] & ~open_[new])]
    if len(took):
        # held by identified neighbours in this view: on a translation lattice every id (a proposal the rule
        # certified too), elsewhere those placed by their motion alone
        check = took if lat.translation_lattice else took[by_motion[took] & (certified[took] != proposal[took])]
        taken = np.zeros(len(ids), bool)
        taken[took] = True
        thin = check[~held(np.where(taken, proposal, ids), check, lat)]
        took = np.setdiff1d(took, thin)
    if len(took) == 0:
        return coding
    out = ids.copy()
    out[took] = proposal[took]
    carried = coding.carried.copy()
    open_ = (carried[took] < 0) & ~np.isin(proposal[took], carried)
    carried[took[open_]] = proposal[took[open_]]
    gained = set(proposal[took].tolist())
    keep = [k for k, i in enumerate(coding.unmatched_ids.tolist()) if i not in gained]
    return replace(coding, ids=out, carried=carried, unmatched_ids=coding.unmatched_ids[keep],
                   unmatched_reasons=tuple(coding.unmatched_reasons[k] for k in keep),
                   messages=coding.messages + (f"the other view's ids certified {len(took)} more marker(s) through the "
                                               "stereo geometry",))


def _resolved(pts: np.ndarray, proposal: np.ndarray, certified: np.ndarray, reason: np.ndarray, new: np.ndarray,
              other_px: np.ndarray, is_left: bool, lat, locate: Locate) -> tuple[np.ndarray, np.ndarray]:
    """``certified`` (the receiving view's certainty rule on ``proposal``) with the proposed ids it refused only as
    ambiguous certified again where the stereo geometry settles the ambiguity (:data:`SETTLE_REACH`): the free blobs
    near each such proposal whose rays cannot meet the marker's ray in the other view (``other_px``, per blob of
    ``new``) inside the gel are set aside, and the rule is applied once more to the rest of the view. Only those
    proposals are taken from that second pass. Also returns, per blob, the proposals whose ambiguity the geometry
    leaves open (a free blob near it meets the marker's ray inside the gel too): not taken by their motion either,
    which alone would then choose between two blobs the marker may be (a sharp tip dragged across the skin moves
    the marker under it unlike its neighbours, onto a spurious blob beside it)."""
    unsettled = np.zeros(len(pts), bool)
    amb = new[(certified[new] < 0) & (reason[np.maximum(proposal[new], 0)] == R_AMBIGUOUS)]
    if len(amb) == 0:
        return certified, unsettled
    free = np.flatnonzero(proposal < 0)
    if len(free) == 0:
        return certified, unsettled
    other = dict(zip(new.tolist(), other_px))
    spacing = float(np.median(nearest_other_distances(pts)))
    aside = np.zeros(len(pts), bool)
    keep = np.zeros(len(pts), bool)          # a free blob that could be one of the markers it is near
    for b in amb.tolist():
        c = free[np.hypot(*(pts[free] - pts[b]).T) <= SETTLE_REACH * spacing]
        if len(c) == 0:
            continue
        o = np.repeat(other[b][None, :], len(c), axis=0)
        ok, _ = locate(*((pts[c], o) if is_left else (o, pts[c])), np.full(len(c), proposal[b], np.int64))
        keep[c[ok]] = True
        aside[c[~ok]] = True
        unsettled[b] = ok.any()
    aside &= ~keep
    if not aside.any():
        return certified, unsettled
    rest = np.flatnonzero(~aside)
    again = np.full(len(pts), -1, np.int64)
    again[rest] = certify(pts[rest], proposal[rest], lat, np.zeros(len(lat.xy), np.int64))
    settled = amb[(again[amb] == proposal[amb]) & ~unsettled[amb]]
    if len(settled) == 0:
        return certified, unsettled
    certified = certified.copy()
    certified[settled] = proposal[settled]
    return certified, unsettled
