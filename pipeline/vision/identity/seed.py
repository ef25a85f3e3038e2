"""A proposal independent of ring peeling: similarity placements of the design on the blobs
(:func:`register_seed`), for the certainty rule to decide among."""

from __future__ import annotations

import math

import cv2
import numpy as np
from scipy.spatial import cKDTree

from pipeline.vision.identity.constants import SEED_RADIUS
from pipeline.vision.identity.lattice import Lattice

#: The placements are scored on a distance map of the blobs rasterised at this many raster pixels per
#: separation ...
SEED_RASTER_PX = 12.0
#: ... a projected slot counts as landing on a blob within this many separations of one ...
SEED_HIT = 0.3
#: ... and a raster larger than this many cells (a blob set spread far beyond any pattern) is not
#: scored at all.
SEED_RASTER_MAX_CELLS = 4_000_000
#: The first ring about a candidate centre of a circular pattern: blobs between these distances
#: (separations) from it.
SEED_RING1_INNER = 0.7
SEED_RING1_OUTER = 1.3
#: With ``spread``, the placements of a hexagonal or square lattice are anchored on the blobs nearest six
#: points this fraction of the pattern's radius from its middle (the radius estimated as sqrt(2) times
#: the blobs' median distance from their median, which it is for markers filling a disc).
SEED_SPREAD_RADIUS = 0.5


def register_seed(pts: np.ndarray, lat: Lattice, *, max_hypotheses: int = 800, n_best: int = 8,
                  spread: bool = False) -> list:
    """A proposal independent of ring peeling: the similarity transform (scale from the median
    nearest-neighbour distance, rotation within the unambiguous range from the directions to the
    nearest neighbours, translation putting one of the central blobs on one of the central slots)
    under which the most design slots land on a blob. A lattice placed one pitch off fits the
    interior as well as the truth (and a press bulges the pattern, so the boundary may not fit a
    similarity at all): the ``n_best`` best distinct placements are returned, as proposals (an id
    per blob, -1 none: every slot whose projection has exactly one blob within a third of a
    separation and that lies within :data:`SEED_RADIUS` separations of the slot the placement was
    anchored on, where a similarity still fits a bulged pattern), best first; growth and the
    anchoring test decide among them.

    ``spread`` (hexagonal and square lattices): the placements are anchored instead on six blobs
    around the middle (:data:`SEED_SPREAD_RADIUS`), each tried on every slot. A sharp press at the
    middle crowds the central blobs and displaces them by up to half a separation, so no placement
    anchored there fits the rest of the pattern and none labels the central blobs right; half-way
    out, at least some anchors sit on skin the press barely moved, and the proposal labels the
    neighbourhood of that anchor, from where growth reaches inwards."""
    n = len(pts)
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
    c_des = lat.xy.mean(axis=0)
    if spread and lat.translation_lattice:
        r_img = SEED_SPREAD_RADIUS * math.sqrt(2.0) * float(np.median(np.hypot(*(pts - c_img).T)))
        turn = np.arange(6) * (math.pi / 3)
        b_idx = np.unique(tree.query(c_img + r_img * np.stack([np.cos(turn), np.sin(turn)], axis=1))[1])
        s_idx = np.arange(len(lat.xy))
    else:
        b_idx = tree.query(c_img, k=min(7 if lat.translation_lattice else 19, n))[1]
        s_idx = np.argsort(np.hypot(*(lat.xy - c_des).T), kind="stable")[:19]
    # score by a distance map of the blobs (one lookup per projected slot)
    scale_map = SEED_RASTER_PX / pitch_px
    lo = pts.min(axis=0) - 2 * pitch_px
    hi = pts.max(axis=0) + 2 * pitch_px
    shape = (int((hi[1] - lo[1]) * scale_map) + 2, int((hi[0] - lo[0]) * scale_map) + 2)
    if shape[0] * shape[1] > SEED_RASTER_MAX_CELLS:
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
        ring1 = tree.query_ball_point(anchor_px, SEED_RING1_OUTER * pitch_px)
        th = np.zeros(len(anchor_px))
        scale_h = np.full(len(anchor_px), s0)
        rad_des = float(np.mean(np.hypot(*(lat.xy[lat.layer_of == 1] - lat.xy[centre]).T)))
        for i, lst in enumerate(ring1):
            v = pts[[j for j in lst if np.hypot(*(pts[j] - anchor_px[i])) > SEED_RING1_INNER * pitch_px]] - anchor_px[i]
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
        hit = dd <= SEED_HIT * SEED_RASTER_PX
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
