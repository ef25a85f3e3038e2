"""From proposals to certain ids: the ring-coding proposal, ids carried from the previous frame and
lattice registrations, each certified by :mod:`pipeline.vision.identity`, merged, checked against
the previous frame and completed by following markers from it."""

from __future__ import annotations

import numpy as np
from scipy.spatial import cKDTree

from pipeline.design import SensorDesign
from pipeline.vision.identity import (R_CONTRADICTED, R_NO_BLOB, certify, certify_whole, consistent, contradicted, follow,
                                      grow, lattice_of, register_seed)


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
