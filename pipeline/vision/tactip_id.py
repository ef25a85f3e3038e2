"""Marker identification and image statistics for monocular dome (TacTip-type) frames.

A TacTip's dome is seen from inside by one camera: there is no second view to match, and the ring coding
of :mod:`pipeline.vision.dtrc` assumes a flat module's layout. Identification here is by position instead: a
reference frame's markers carry the ids (assigned once, e.g. by matching them to the design's projected
pin layout, or simply the reference frame's own marker indices), and every other frame's markers take the
id of the nearest reference marker when the two are each other's nearest neighbour and closer than
``gate`` × the reference's local marker spacing. This holds while a frame moves no marker by more than
about half a spacing from the reference, which taps of a few mm do (measured on the real 331-pin frames:
README "TacTip twin").

A recorded sequence is identified by :func:`identify_sequence`: frames in order of pose (or time) distance
from the reference, each against the already identified frame nearest to it, so a chain of small steps
carries the ids to the deepest, most tilted frames. Its certainty rule emits an id only when the match is
unambiguous and gives every other detected marker a reason instead (:data:`REASONS`).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.spatial import cKDTree

from pipeline.types import Blobs, DataError

__all__ = ["identify_by_reference", "identify_sequence", "SequenceIds", "local_spacing_px", "frame_stats",
           "DEFAULT_GATE", "DEFAULT_MARGIN", "REASONS"]

DEFAULT_GATE = 0.5
#: The runner-up (second-nearest detection to the expected position, and second-nearest expected
#: position to the detection) must be at least this many local spacings farther than the match.
DEFAULT_MARGIN = 0.25

#: Why a detected marker got no id (``SequenceIds.reasons``).
REASONS = {
    "outside_gate": "no expected marker position within the gate (gate x local spacing)",
    "not_mutual": "its nearest expected position has another detection nearer to it",
    "ambiguous": "a second candidate is within the margin of the nearest one",
}


def local_spacing_px(xy: np.ndarray) -> np.ndarray:
    """Distance of each point to its nearest neighbour (N,) px."""
    xy = np.asarray(xy, np.float64)
    if len(xy) < 2:
        return np.full(len(xy), np.inf)
    d, _ = cKDTree(xy).query(xy, k=2)
    return d[:, 1]


def identify_by_reference(xy: np.ndarray, ref_xy: np.ndarray, *, gate: float = DEFAULT_GATE) -> np.ndarray:
    """For each reference marker (M, 2), the index of the frame marker identified with it, or -1.

    Mutual nearest neighbours within ``gate`` × the reference marker's nearest-neighbour spacing.
    Reference rows that are NaN (unidentified ids) stay -1.
    """
    xy = np.asarray(xy, np.float64).reshape(-1, 2)
    ref_xy = np.asarray(ref_xy, np.float64).reshape(-1, 2)
    out = -np.ones(len(ref_xy), np.int64)
    ok = np.all(np.isfinite(ref_xy), axis=1)
    if len(xy) == 0 or not ok.any():
        return out
    ref_idx = np.nonzero(ok)[0]
    ref = ref_xy[ok]
    spacing = local_spacing_px(ref)
    d, j = cKDTree(xy).query(ref)
    _, back = cKDTree(ref).query(xy[j])
    good = (back == np.arange(len(ref))) & (d <= gate * spacing)
    out[ref_idx[good]] = j[good]
    return out


@dataclass(frozen=True)
class SequenceIds:
    """Identification of a sequence of frames (:func:`identify_sequence`).

    Attributes
    ----------
    ids : list of (N_f,) int64
        Per frame, the id of each detected marker (an index into the reference's ids), -1 unmatched.
    reasons : list of list of str or None
        Per frame and detected marker, ``None`` when identified, else a key of :data:`REASONS`.
    xy : list of (M, 2) float64
        Per frame, the identified position of every id (NaN where the id was not identified).
    order : (F,) int64
        The order the frames were identified in (the reference first).
    guide : (F,) int64
        Per frame, the frame it was identified against (the reference: itself).
    """

    ids: list
    reasons: list
    xy: list
    order: np.ndarray
    guide: np.ndarray


def _certain_matches(xy: np.ndarray, expected: np.ndarray, gate: float, margin: float):
    """Certainty rule: detection ``j`` takes the id ``m`` of expected position ``expected[m]`` only if
    (1) ``m`` is ``j``'s nearest expected position and ``j`` is ``m``'s nearest detection (mutual),
    (2) their distance ``d`` is at most ``gate`` × the expected layout's local spacing ``s_m`` (the
    distance from ``expected[m]`` to its nearest expected neighbour), and (3) both runners-up (the
    second-nearest detection to ``expected[m]`` and the second-nearest expected position to ``j``) are
    at least ``d + margin × s_m`` away. Returns (ids (N,) with -1, reasons (N,) list)."""
    n = len(xy)
    ids = -np.ones(n, np.int64)
    reasons: list = ["outside_gate"] * n
    ok = np.all(np.isfinite(expected), axis=1)
    if n == 0 or ok.sum() == 0:
        return ids, reasons
    eidx = np.nonzero(ok)[0]
    exp = expected[ok]
    spacing = local_spacing_px(exp)
    kd = min(2, n)
    ke = min(2, len(exp))
    d_e, j_e = cKDTree(xy).query(exp, k=kd)          # per expected: nearest detections
    d_x, m_x = cKDTree(exp).query(xy, k=ke)          # per detection: nearest expected positions
    d_e, j_e = d_e.reshape(len(exp), kd), j_e.reshape(len(exp), kd)
    d_x, m_x = d_x.reshape(n, ke), m_x.reshape(n, ke)
    for j in range(n):
        m = int(m_x[j, 0])
        d = float(d_x[j, 0])
        s = float(spacing[m])
        if not d <= gate * s:
            continue
        if int(j_e[m, 0]) != j:
            reasons[j] = "not_mutual"
            continue
        run_x = d_x[j, 1] if ke > 1 else np.inf
        run_e = d_e[m, 1] if kd > 1 else np.inf
        if min(run_x, run_e) < d + margin * s:
            reasons[j] = "ambiguous"
            continue
        ids[j] = eidx[m]
        reasons[j] = None
    return ids, reasons


#: Re-matching passes with the expected positions moved by the local displacement of the markers
#: already identified in the frame (stops when a pass identifies no more markers).
PREDICTION_PASSES = 3
#: Identified markers that predict an expected position: those within this many local spacings.
PREDICTION_REACH = 2.5
#: ... and only where their displacements agree to within this many spacings RMS.
PREDICTION_SMOOTH = 0.25


def _predict(expected: np.ndarray, xy: np.ndarray, ids: np.ndarray) -> np.ndarray:
    """Expected positions moved by the local displacement field of a first match: each id's position
    plus the mean displacement (frame - expected) of the identified ids within ``PREDICTION_REACH``
    local spacings of it, where that field is smooth (at least 3 of them, RMS deviation from their
    mean below ``PREDICTION_SMOOTH`` spacing: a skin bends smoothly; scattered displacements predict
    nothing). NaN (no expected position) where it is not."""
    ok = np.all(np.isfinite(expected), axis=1)
    got = ids[ids >= 0]
    out = np.full_like(expected, np.nan)
    if len(got) < 3 or not ok.any():
        return out
    disp = xy[ids >= 0] - expected[got]
    spacing = float(np.median(local_spacing_px(expected[ok])))
    tree = cKDTree(expected[got])
    for m in np.nonzero(ok)[0]:
        near = tree.query_ball_point(expected[m], PREDICTION_REACH * spacing)
        if len(near) < 3:
            continue
        dv = disp[near]
        mean = dv.mean(axis=0)
        if np.sqrt(np.mean(np.sum((dv - mean) ** 2, axis=1))) < PREDICTION_SMOOTH * spacing:
            out[m] = expected[m] + mean
    return out


def identify_sequence(blobs_list, poses, ref_index: int, ref_xy: np.ndarray, *, gate: float = DEFAULT_GATE,
                      margin: float = DEFAULT_MARGIN) -> SequenceIds:
    """Identify the markers of every frame of a recorded sequence of a monocular dome sensor.

    Parameters
    ----------
    blobs_list : sequence of Blobs or (N_f, 2) arrays
        Each frame's detected marker centres (px).
    poses : (F, D) array or None
        A pose (or time) coordinate per frame, scaled so that Euclidean distance measures how different
        two frames' marker layouts are (e.g. tap depth mm and tilt deg / 5). ``None``: the frame index
        (consecutive frames of a recording).
    ref_index : int
        The reference frame.
    ref_xy : (M, 2)
        The reference position of every id (NaN for ids without one). Ids are row indices.
    gate, margin : float
        The certainty rule (:func:`_certain_matches`): distance at most ``gate`` × local spacing,
        runners-up at least ``margin`` × local spacing farther.

    Frames are identified in order of pose distance from the reference, each against the already
    identified frame nearest in pose (its guide). The expected position of an id in a frame is its
    position in the guide; where the guide did not identify it, its position in the nearest frame (in
    pose) that did, else the reference. After a first match, the expected positions are moved by the
    local displacement of the markers identified so far where that field is smooth (:func:`_predict`)
    and the still unidentified markers matched again (the same rule), up to ``PREDICTION_PASSES``
    times while that identifies more. Every detected marker either gets an id by
    the certainty rule or a reason (:data:`REASONS`); an id is given at most once per frame.

    Raises
    ------
    DataError
        Inconsistent lengths, an out-of-range ``ref_index`` or a non-(M, 2) ``ref_xy``.
    """
    frames = [np.asarray(b.xy_px if isinstance(b, Blobs) else b, np.float64).reshape(-1, 2) for b in blobs_list]
    n = len(frames)
    if n == 0:
        raise DataError("identify_sequence: no frames")
    if not (0 <= int(ref_index) < n):
        raise DataError(f"identify_sequence: ref_index {ref_index} outside the {n} frames")
    ref = int(ref_index)
    ref_xy = np.asarray(ref_xy, np.float64)
    if ref_xy.ndim != 2 or ref_xy.shape[1] != 2:
        raise DataError(f"identify_sequence: ref_xy must be (M, 2), got shape {ref_xy.shape}")
    P = np.arange(n, dtype=np.float64)[:, None] if poses is None else np.asarray(poses, np.float64).reshape(n, -1)
    if not np.all(np.isfinite(P)):
        raise DataError("identify_sequence: poses must be finite")
    M = len(ref_xy)
    ids: list = [None] * n
    reasons: list = [None] * n
    xy: list = [None] * n
    guide = np.full(n, -1, np.int64)
    # the reference: its own ids, by the same rule against the reference layout
    order = np.argsort(np.linalg.norm(P - P[ref], axis=1), kind="stable")
    order = np.concatenate([[ref], order[order != ref]])
    done: list[int] = []
    for i in order:
        i = int(i)
        if not done:
            g = i
            expected = ref_xy
        else:
            dist = np.linalg.norm(P[done] - P[i], axis=1)
            g = done[int(np.argmin(dist))]
            expected = xy[g].copy()
            miss = ~np.all(np.isfinite(expected), axis=1)
            for k in np.asarray(done)[np.argsort(dist, kind="stable")]:   # nearest frames first
                if not miss.any():
                    break
                fill = miss & np.all(np.isfinite(xy[k]), axis=1)
                expected[fill] = xy[k][fill]
                miss &= ~fill
            expected[miss] = ref_xy[miss]
        fid, frs = _certain_matches(frames[i], expected, gate, margin)
        for _ in range(PREDICTION_PASSES):
            # identified markers keep their ids; the others may take an id at its predicted position
            predicted = _predict(expected, frames[i], fid)
            fid2, frs2 = _certain_matches(frames[i], predicted, gate, margin)
            new = (fid < 0) & (fid2 >= 0) & ~np.isin(fid2, fid[fid >= 0])
            if not new.any():
                break
            fid = np.where(new, fid2, fid)
            frs = [None if nw else r for nw, r in zip(new, frs)]
        pos = np.full((M, 2), np.nan)
        pos[fid[fid >= 0]] = frames[i][fid >= 0]
        ids[i], reasons[i], xy[i], guide[i] = fid, frs, pos, g
        done.append(i)
    return SequenceIds(ids=ids, reasons=reasons, xy=xy, order=order.astype(np.int64), guide=guide)


def frame_stats(grey: np.ndarray, blobs: Blobs) -> dict:
    """Image statistics of one grey frame's detected markers: count, apparent radius (px, the detector's
    sqrt(2)·sigma), contrast (grey levels: mean of the marker core minus the median of a ring at 1.6–2.2
    radii), background (median of those rings), nearest-neighbour spacing (px) and pixel noise (grey levels,
    mean absolute deviation of the Laplacian-filtered background between the markers, scaled to a Gaussian sigma); medians over the markers."""
    grey = np.asarray(grey)
    n = len(blobs)
    if n == 0:
        return {"count": 0, "radius_px": None, "contrast": None, "background": None, "spacing_px": None,
                "noise": None}
    h, w = grey.shape
    r = np.sqrt(2.0) * blobs.sigma_px
    yy, xx = np.mgrid[-12:13, -12:13]
    core, ring = [], []
    g = grey.astype(np.float64)
    for (u, v), rad in zip(blobs.xy_px, r):
        iu, iv = int(round(u)), int(round(v))
        y0, y1, x0, x1 = iv - 12, iv + 13, iu - 12, iu + 13
        if y0 < 0 or x0 < 0 or y1 > h or x1 > w:
            continue
        patch = g[y0:y1, x0:x1]
        rc = np.hypot(xx - (u - iu), yy - (v - iv))
        c = patch[rc <= 0.5 * rad]
        rg = patch[(rc >= 1.6 * rad) & (rc <= 2.2 * rad)]
        if len(c) and len(rg):
            core.append(c.mean())
            ring.append(np.median(rg))
    core, ring = np.asarray(core), np.asarray(ring)
    # noise: MAD of the Laplacian over background pixels (between markers, away from any marker)
    lap = (4 * g[1:-1, 1:-1] - g[:-2, 1:-1] - g[2:, 1:-1] - g[1:-1, :-2] - g[1:-1, 2:]) / np.sqrt(20.0)
    mask = np.zeros_like(g, bool)
    hull_lo, hull_hi = blobs.xy_px.min(axis=0), blobs.xy_px.max(axis=0)
    mask[int(hull_lo[1]):int(hull_hi[1]), int(hull_lo[0]):int(hull_hi[0])] = True
    bg_level = float(np.median(ring)) if len(ring) else float("nan")
    mask &= np.abs(g - bg_level) < 12
    import cv2  # local: the rest of the module is numpy/scipy

    near = np.zeros(g.shape, np.uint8)
    for (u, v), rad in zip(blobs.xy_px, r):
        cv2.circle(near, (int(round(u)), int(round(v))), int(np.ceil(1.8 * rad)), 1, -1)
    mask &= near == 0
    lm = mask[1:-1, 1:-1]
    vals = lap[lm]
    noise = float(np.sqrt(np.pi / 2) * np.mean(np.abs(vals - vals.mean()))) if lm.sum() > 50 else float("nan")
    return {"count": int(n), "radius_px": float(np.median(r)),
            "contrast": float(np.median(core - ring)) if len(core) else None,
            "background": bg_level, "spacing_px": float(np.median(local_spacing_px(blobs.xy_px))),
            "noise": noise}
