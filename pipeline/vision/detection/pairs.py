"""Two touching pins found as one blob, split back into the two pins.

Pins on a flank seen obliquely are foreshortened to narrow ellipses; two of them touching side by side read as
one round blob at the pair's scale, centred on the dark line between them. :func:`separate_pairs` finds such
blobs among the accepted ones and replaces each by its two pins.
"""

from __future__ import annotations

import numpy as np
from scipy.spatial import cKDTree

from pipeline.vision.detection.candidates import ELONGATION, RADIUS_PER_SIGMA, SIGMA, X, Y
from pipeline.vision.detection.params import DetectionParams
from pipeline.vision.detection.photometry import WINDOW_MARGIN_PX
from pipeline.vision.detection.rejection import LOCAL_SIZE_NEIGHBOURS

__all__ = ["separate_pairs", "PAIR_MIN_ELONGATION", "PAIR_MIN_SCALE_FRACTION", "PAIR_PEAK_FRACTION", "PAIR_DIP",
           "PAIR_CENTRE_FRACTION", "PAIR_TAKEN_FRACTION"]


#: Two pins touching side by side on a flank seen obliquely (each foreshortened to a narrow ellipse)
#: make one round blob, which the scale space finds at the pair's scale, centred between them (2.2-3.7
#: px off either pin on the twin's presses at 5 mm). Such a blob is Hessian-elongated along the pair
#: (measured 1.39-2.17, where ~90 % of single markers are below ``PAIR_MIN_ELONGATION``) and at least
#: ``PAIR_MIN_SCALE_FRACTION`` x its neighbours' typical scale (measured >= 0.9); only those are examined.
PAIR_MIN_ELONGATION = 1.3
PAIR_MIN_SCALE_FRACTION = 0.9
#: The blob is two pins when the light along its long axis (within its radius, averaged over 3 px
#: across) has a peak on each side of its centre, both at least ``PAIR_PEAK_FRACTION`` of the
#: brightest point, at least one typical marker radius apart, with a dip between them down to
#: ``PAIR_DIP`` of the dimmer peak (above the background: the window's 10th percentile). The dark
#: line between two touching pins reads 0.57-0.82; a single marker's flat top has none.
PAIR_PEAK_FRACTION = 0.9
PAIR_DIP = 0.85
#: Only blobs whose centre pixel is below this fraction of the brightest pixel within half their
#: radius (grey levels; the dark line between two pins reads 0.66-0.79 of their plateau, a marker's
#: flat top ~1) are profiled.
PAIR_CENTRE_FRACTION = 0.92
#: A half whose centroid lies closer than this fraction of the two halves' distance to another blob
#: is that blob's pin, already found: only the other half replaces the blob (re-centred on its own pin).
PAIR_TAKEN_FRACTION = 0.5
#: Background of the pair window: this percentile of its pixels (the dark skin around the pair).
_PAIR_BACKGROUND_PERCENTILE = 10
#: Profile samples per pixel along the long axis, and the across-axis offsets (px) averaged.
_PAIR_STEP_PX = 0.5
_PAIR_ACROSS_PX = (-1.0, 0.0, 1.0)


def _bilinear(patch: np.ndarray, x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """``patch`` (float) sampled bilinearly at (x, y) (patch px; clamped to the patch)."""
    h, w = patch.shape
    x = np.clip(x, 0.0, w - 1.0)
    y = np.clip(y, 0.0, h - 1.0)
    x0 = np.minimum(np.floor(x).astype(np.intp), w - 2) if w > 1 else np.zeros(len(x), np.intp)
    y0 = np.minimum(np.floor(y).astype(np.intp), h - 2) if h > 1 else np.zeros(len(y), np.intp)
    fx, fy = x - x0, y - y0
    x1, y1 = np.minimum(x0 + 1, w - 1), np.minimum(y0 + 1, h - 1)
    return ((patch[y0, x0] * (1 - fx) + patch[y0, x1] * fx) * (1 - fy)
            + (patch[y1, x0] * (1 - fx) + patch[y1, x1] * fx) * fy)


def separate_pairs(grey: np.ndarray, cand: np.ndarray, xy: np.ndarray,
                   params: DetectionParams) -> tuple[np.ndarray, np.ndarray]:
    """Accepted blobs that are two touching pins seen as one, replaced by the two pins.

    ``cand`` and ``xy`` are the accepted candidates and their centres. A blob examined (see
    :data:`PAIR_MIN_ELONGATION`) whose light along its long axis shows two peaks with a dip between
    (:data:`PAIR_DIP`) is split across that axis at its centroid; each half's centroid (light above
    the background) is a pin, with the neighbours' typical scale and the blob's response, unless another
    blob already stands there (:data:`PAIR_TAKEN_FRACTION`). Returns the new candidates and centres
    (split blobs removed, their pins appended); unchanged with fewer than
    ``LOCAL_SIZE_NEIGHBOURS + 1`` blobs.
    """
    n = len(xy)
    h, w = grey.shape
    which = np.flatnonzero(cand[:, ELONGATION] >= PAIR_MIN_ELONGATION)
    if n < LOCAL_SIZE_NEIGHBOURS + 1 or len(which) == 0:
        return cand, xy
    # the centre of a pair's blob lies on the dark line between the pins; a marker's on its flat top
    ix = np.clip(np.rint(xy[which, 0]).astype(np.intp), 0, w - 1)
    iy = np.clip(np.rint(xy[which, 1]).astype(np.intp), 0, h - 1)
    reach = max(1, int(np.ceil(RADIUS_PER_SIGMA * float(cand[which, SIGMA].max()) / 2)))
    off = np.arange(-reach, reach + 1)
    ox, oy = np.meshgrid(off, off)
    top = grey[np.clip(iy[:, None] + oy.ravel(), 0, h - 1), np.clip(ix[:, None] + ox.ravel(), 0, w - 1)].max(axis=1)
    which = which[grey[iy, ix] < PAIR_CENTRE_FRACTION * top]
    if len(which) == 0:
        return cand, xy
    tree = cKDTree(xy)
    _, nb = tree.query(xy[which], k=LOCAL_SIZE_NEIGHBOURS + 1)
    local = np.full(n, np.inf)
    local[which] = np.median(cand[nb[:, 1:], SIGMA], axis=1)
    which = which[cand[which, SIGMA] >= PAIR_MIN_SCALE_FRACTION * local[which]]
    if len(which) == 0:
        return cand, xy
    drop = np.zeros(n, bool)
    new_rows, new_xy = [], []
    for i in which:
        r = RADIUS_PER_SIGMA * float(cand[i, SIGMA])
        r_win = params.centroid_radius_factor * r + WINDOW_MARGIN_PX
        x0, y0 = float(xy[i, 0]), float(xy[i, 1])
        xa, xb = max(0, int(np.floor(x0 - r_win))), min(w - 1, int(np.ceil(x0 + r_win)))
        ya, yb = max(0, int(np.floor(y0 - r_win))), min(h - 1, int(np.ceil(y0 + r_win)))
        if xb - xa < 2 or yb - ya < 2:
            continue
        patch = grey[ya:yb + 1, xa:xb + 1].astype(np.float64)
        gx = np.arange(xa, xb + 1, dtype=np.float64)[None, :]
        gy = np.arange(ya, yb + 1, dtype=np.float64)[:, None]
        inside = (gx - x0) ** 2 + (gy - y0) ** 2 <= r_win * r_win
        v = patch[inside]
        px = np.broadcast_to(gx, patch.shape)[inside]
        py = np.broadcast_to(gy, patch.shape)[inside]
        k_bg = int(len(v) * _PAIR_BACKGROUND_PERCENTILE / 100)
        bg = float(np.partition(v, k_bg)[k_bg])
        wt = np.maximum(v - bg, 0.0)
        tot = wt.sum()
        if tot <= 0:
            continue
        cx, cy = (wt * px).sum() / tot, (wt * py).sum() / tot
        dx, dy = px - cx, py - cy
        sxx, syy, sxy = (wt * dx * dx).sum(), (wt * dy * dy).sum(), (wt * dx * dy).sum()
        ang = 0.5 * np.arctan2(2 * sxy, sxx - syy)          # the long axis
        ux, uy = np.cos(ang), np.sin(ang)
        t = np.arange(-r, r + 1e-9, _PAIR_STEP_PX)
        o = np.asarray(_PAIR_ACROSS_PX)[:, None]
        prof = _bilinear(patch, (cx - xa + t * ux - o * uy).ravel(),
                         (cy - ya + t * uy + o * ux).ravel()).reshape(len(o), len(t)).mean(axis=0) - bg
        neg, pos = t < 0, t > 0
        if not (neg.any() and pos.any()):
            continue
        a = int(np.argmax(np.where(neg, prof, -np.inf)))
        c = int(np.argmax(np.where(pos, prof, -np.inf)))
        low = min(prof[a], prof[c])
        if (low < PAIR_PEAK_FRACTION * prof.max() or t[c] - t[a] < RADIUS_PER_SIGMA * local[i]
                or prof[a:c + 1].min() > PAIR_DIP * low):
            continue
        side = dx * ux + dy * uy
        halves = []
        for half in (side < 0, side >= 0):
            hw = wt[half]
            if hw.sum() > 0:
                halves.append(np.array([(hw * px[half]).sum() / hw.sum(), (hw * py[half]).sum() / hw.sum()]))
        if len(halves) < 2:
            continue
        sep = float(np.hypot(*(halves[0] - halves[1])))
        drop[i] = True
        for pin in halves:
            d, j = tree.query(pin, k=2)
            if any(jj != i and dd < PAIR_TAKEN_FRACTION * sep for dd, jj in zip(d, j)):
                continue
            row = cand[i].copy()
            row[X], row[Y], row[SIGMA] = pin[0], pin[1], local[i]
            new_rows.append(row)
            new_xy.append(pin)
    if not drop.any():
        return cand, xy
    if not new_rows:
        return cand[~drop], xy[~drop]
    return np.vstack([cand[~drop], new_rows]), np.vstack([xy[~drop], new_xy])
