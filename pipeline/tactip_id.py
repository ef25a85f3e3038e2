"""Marker identification and image statistics for monocular dome (TacTip-type) frames.

A TacTip's dome is seen from inside by one camera: there is no second view to match, and the ring coding
of :mod:`pipeline.dtrc` assumes a flat module's layout. Identification here is by position instead: a
reference frame's markers carry the ids (assigned once, e.g. by matching them to the design's projected
pin layout), and every other frame's markers take the id of the nearest reference marker when the two
are each other's nearest neighbour and closer than ``gate`` × the reference's local marker spacing.
This holds while a frame moves no marker by more than about half a spacing from the reference, which
taps of a few mm do (measured on the real 331-pin frames: README "TacTip twin").
"""

from __future__ import annotations

import numpy as np
from scipy.spatial import cKDTree

from pipeline.types import Blobs

__all__ = ["identify_by_reference", "local_spacing_px", "frame_stats", "DEFAULT_GATE"]

DEFAULT_GATE = 0.5


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
    rr = np.hypot(xx, yy)
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
