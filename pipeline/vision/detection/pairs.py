"""Two touching pins found as one blob, split back into the two pins.

Pins on a flank seen obliquely are foreshortened to narrow ellipses; two of them touching side by side read as
one round blob at the pair's scale, centred on the dark line between them. Pins crowded into a crest overlap in
the image instead (discs 8-9 px apart with radius ~6 px on hexagon217_sep180 under a 5 mm sine press): the blob
is a figure of eight with no dark line, its waist only narrower. :func:`separate_pairs` finds both among the
accepted blobs and replaces each by its two pins.
"""

from __future__ import annotations

import numpy as np
from scipy.ndimage import median_filter
from scipy.spatial import cKDTree

from pipeline.vision.detection.candidates import ELONGATION, RADIUS_PER_SIGMA, SIGMA, X, Y
from pipeline.vision.detection.params import DetectionParams
from pipeline.vision.detection.photometry import WINDOW_MARGIN_PX
from pipeline.vision.detection.rejection import LOCAL_SIZE_NEIGHBOURS

__all__ = ["separate_pairs", "PAIR_MIN_ELONGATION", "PAIR_MIN_SCALE_FRACTION", "PAIR_PEAK_FRACTION", "PAIR_DIP",
           "PAIR_CENTRE_FRACTION", "PAIR_TAKEN_FRACTION", "PAIR_WAIST", "PAIR_END_FRACTION",
           "PAIR_WAIST_MIN_SCALE_FRACTION"]


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
#: Two overlapping pins: the light summed across the long axis (the blob's cross-section, within its window) has
#: a maximum on each side of the centre, both at least ``PAIR_PEAK_FRACTION`` of the larger, at least one typical
#: marker radius apart, with a waist between them down to ``PAIR_WAIST`` of the smaller. Two flat discs of radius r
#: whose centres lie d apart have the cross-section of the larger chord, 2 sqrt(r^2 - (t -+ d/2)^2): widest at
#: either centre, 2 sqrt(r^2 - d^2/4) at the waist (0.60-0.80 of it for d = 1.2-1.6 r; measured 0.71-0.85 on the
#: twin's crests); one marker, round or foreshortened to an ellipse, has a single widest chord at its centre.
#: Each pin is placed at the middle of its widest chords, its disc's centre. The chords are taken as the median
#: of three neighbouring ones (a speck touching a marker's end widened one chord on a real TacTip frame), and
#: beyond each pin, half a marker radius past the blob's own radius, they narrow again to at most
#: ``PAIR_END_FRACTION`` of its widest (a marker touching another end-on widens towards it: not a pair).
PAIR_WAIST = 0.85
PAIR_END_FRACTION = 0.9
#: Only a blob at least this many times its neighbours' typical scale gets the waist test: two overlapping pins are
#: found at a coarser scale than either (1.10-1.40x on the twin's crests), a single marker, round or foreshortened,
#: at about its neighbours' (on the 41 real TacTip frames a median of 0.99, 90 % below 1.07, none split). Without
#: it every elongated marker of a real frame was profiled: ~90 a view, 16 ms instead of 0.8 ms.
PAIR_WAIST_MIN_SCALE_FRACTION = 1.05
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
    """Accepted blobs that are two touching or overlapping pins seen as one, replaced by the two pins.

    ``cand`` and ``xy`` are the accepted candidates and their centres. A blob examined (see
    :data:`PAIR_MIN_ELONGATION`) is two pins when the light along its long axis shows two peaks with a
    dip between (:data:`PAIR_DIP`; only where its centre is darker than its top, :data:`PAIR_CENTRE_FRACTION`):
    it is split across that axis at its centroid, each half's centroid (light above the background) a pin;
    or, at the pair's scale (:data:`PAIR_WAIST_MIN_SCALE_FRACTION`), when its cross-section along that axis has a waist between two widest chords (:data:`PAIR_WAIST`),
    each pin at its widest chord. A pin gets the neighbours' typical scale and the blob's response, unless
    another blob already stands there (:data:`PAIR_TAKEN_FRACTION`). Returns the new candidates and centres
    (split blobs removed, their pins appended); unchanged with fewer than ``LOCAL_SIZE_NEIGHBOURS + 1`` blobs.
    """
    n = len(xy)
    h, w = grey.shape
    which = np.flatnonzero(cand[:, ELONGATION] >= PAIR_MIN_ELONGATION)
    if n < LOCAL_SIZE_NEIGHBOURS + 1 or len(which) == 0:
        return cand, xy
    # the centre of a touching pair's blob lies on the dark line between the pins; a marker's on its flat top
    ix = np.clip(np.rint(xy[which, 0]).astype(np.intp), 0, w - 1)
    iy = np.clip(np.rint(xy[which, 1]).astype(np.intp), 0, h - 1)
    reach = max(1, int(np.ceil(RADIUS_PER_SIGMA * float(cand[which, SIGMA].max()) / 2)))
    off = np.arange(-reach, reach + 1)
    ox, oy = np.meshgrid(off, off)
    top = grey[np.clip(iy[:, None] + oy.ravel(), 0, h - 1), np.clip(ix[:, None] + ox.ravel(), 0, w - 1)].max(axis=1)
    dark = np.zeros(n, bool)
    dark[which] = grey[iy, ix] < PAIR_CENTRE_FRACTION * top
    tree = cKDTree(xy)
    _, nb = tree.query(xy[which], k=LOCAL_SIZE_NEIGHBOURS + 1)
    local = np.full(n, np.inf)
    local[which] = np.median(cand[nb[:, 1:], SIGMA], axis=1)
    which = which[cand[which, SIGMA] >= PAIR_MIN_SCALE_FRACTION * local[which]]
    if len(which) == 0:
        return cand, xy
    drop = np.zeros(n, bool)
    new_rows, new_xy = [], []
    waist = cand[:, SIGMA] >= PAIR_WAIST_MIN_SCALE_FRACTION * local
    for i in which[dark[which] | waist[which]]:
        win = _Window.of(grey, xy[i], RADIUS_PER_SIGMA * float(cand[i, SIGMA]), params)
        if win is None:
            continue
        pins = _line_pins(win, RADIUS_PER_SIGMA * local[i]) if dark[i] else None
        if pins is None and waist[i]:
            pins = _waist_pins(win, RADIUS_PER_SIGMA * local[i])
        if pins is None:
            continue
        sep = float(np.hypot(*(pins[0] - pins[1])))
        drop[i] = True
        for pin in pins:
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


class _Window:
    """One examined blob's light: the pixels within its window (``px``, ``py``, above-background weights ``wt``),
    their centroid, the long axis ``(ux, uy)``, the patch and its offset, the background and the blob's radius ``r``."""

    __slots__ = ("patch", "xa", "ya", "px", "py", "wt", "bg", "cx", "cy", "ux", "uy", "r")

    @classmethod
    def of(cls, grey: np.ndarray, centre: np.ndarray, r: float, params: DetectionParams) -> "_Window | None":
        h, w = grey.shape
        r_win = params.centroid_radius_factor * r + WINDOW_MARGIN_PX
        x0, y0 = float(centre[0]), float(centre[1])
        xa, xb = max(0, int(np.floor(x0 - r_win))), min(w - 1, int(np.ceil(x0 + r_win)))
        ya, yb = max(0, int(np.floor(y0 - r_win))), min(h - 1, int(np.ceil(y0 + r_win)))
        if xb - xa < 2 or yb - ya < 2:
            return None
        self = cls()
        self.patch = grey[ya:yb + 1, xa:xb + 1].astype(np.float64)
        gx = np.arange(xa, xb + 1, dtype=np.float64)[None, :]
        gy = np.arange(ya, yb + 1, dtype=np.float64)[:, None]
        inside = (gx - x0) ** 2 + (gy - y0) ** 2 <= r_win * r_win
        v = self.patch[inside]
        self.px = np.broadcast_to(gx, self.patch.shape)[inside]
        self.py = np.broadcast_to(gy, self.patch.shape)[inside]
        k_bg = int(len(v) * _PAIR_BACKGROUND_PERCENTILE / 100)
        self.bg = float(np.partition(v, k_bg)[k_bg])
        self.wt = np.maximum(v - self.bg, 0.0)
        tot = self.wt.sum()
        if tot <= 0:
            return None
        self.cx, self.cy = (self.wt * self.px).sum() / tot, (self.wt * self.py).sum() / tot
        dx, dy = self.px - self.cx, self.py - self.cy
        sxx, syy, sxy = (self.wt * dx * dx).sum(), (self.wt * dy * dy).sum(), (self.wt * dx * dy).sum()
        ang = 0.5 * np.arctan2(2 * sxy, sxx - syy)          # the long axis
        self.ux, self.uy = np.cos(ang), np.sin(ang)
        self.xa, self.ya, self.r = xa, ya, r
        return self

    def sample(self, t: np.ndarray, o: np.ndarray) -> np.ndarray:
        """Light above the background at ``t`` along the long axis and ``o`` across it from the centroid:
        (len(o), len(t))."""
        o = np.asarray(o, np.float64)[:, None]
        vals = _bilinear(self.patch, (self.cx - self.xa + t * self.ux - o * self.uy).ravel(),
                         (self.cy - self.ya + t * self.uy + o * self.ux).ravel())
        return vals.reshape(len(o), len(t)) - self.bg


def _line_pins(win: _Window, min_apart: float) -> list[np.ndarray] | None:
    """Two touching pins: the light along the long axis (3 px across) peaks on either side of a dip
    (:data:`PAIR_DIP`); the pins are the two halves' centroids. None where it does not."""
    t = np.arange(-win.r, win.r + 1e-9, _PAIR_STEP_PX)
    prof = win.sample(t, _PAIR_ACROSS_PX).mean(axis=0)
    neg, pos = t < 0, t > 0
    if not (neg.any() and pos.any()):
        return None
    a = int(np.argmax(np.where(neg, prof, -np.inf)))
    c = int(np.argmax(np.where(pos, prof, -np.inf)))
    low = min(prof[a], prof[c])
    if low < PAIR_PEAK_FRACTION * prof.max() or t[c] - t[a] < min_apart or prof[a:c + 1].min() > PAIR_DIP * low:
        return None
    side = (win.px - win.cx) * win.ux + (win.py - win.cy) * win.uy
    halves = []
    for half in (side < 0, side >= 0):
        hw = win.wt[half]
        if hw.sum() > 0:
            halves.append(np.array([(hw * win.px[half]).sum() / hw.sum(), (hw * win.py[half]).sum() / hw.sum()]))
    return halves if len(halves) == 2 else None


def _waist_pins(win: _Window, min_apart: float) -> list[np.ndarray] | None:
    """Two overlapping pins (:data:`PAIR_WAIST`): the chord of the blob through each point of its long axis,
    across it, where the light stays above half the window's brightest; two widest chords, a waist between.
    Each pin at the middle of its widest chords (those within 5 % of its side's widest). None where not."""
    reach = win.r + 0.5 * min_apart          # past the pins' far ends, where a pair blob's scale falls short of them
    t = np.arange(-reach, reach + 1e-9, _PAIR_STEP_PX)
    o = np.arange(-win.r, win.r + 1e-9, _PAIR_STEP_PX)
    light = win.sample(t, o)
    c0 = len(o) // 2
    above = light > 0.5 * float(win.wt.max())
    hi = np.argmin(np.vstack([above[c0:], np.zeros((1, len(t)), bool)]), axis=0)       # run from the axis outward
    lo = np.argmin(np.vstack([above[c0::-1], np.zeros((1, len(t)), bool)]), axis=0)
    width = np.where(above[c0], (hi + lo - 1) * _PAIR_STEP_PX, 0.0)
    width = median_filter(width, size=3, mode="nearest")
    mid = (hi - lo) * _PAIR_STEP_PX / 2
    neg, pos = t < 0, t > 0
    if not (neg.any() and pos.any()):
        return None
    wa, wc = width[neg].max(), width[pos].max()
    if min(wa, wc) <= 0 or min(wa, wc) < PAIR_PEAK_FRACTION * max(wa, wc):
        return None
    if max(width[0] / wa, width[-1] / wc) > PAIR_END_FRACTION:   # each pin's chords narrow again beyond it
        return None
    pa = neg & (width >= 0.95 * wa)
    pc = pos & (width >= 0.95 * wc)
    ta, tc = float(t[pa].mean()), float(t[pc].mean())
    between = (t > t[pa].max()) & (t < t[pc].min())
    if tc - ta < min_apart or not between.any() or width[between].min() > PAIR_WAIST * min(wa, wc):
        return None
    pins = []
    for tt, oo in ((ta, float(mid[pa].mean())), (tc, float(mid[pc].mean()))):
        pins.append(np.array([win.cx + tt * win.ux - oo * win.uy, win.cy + tt * win.uy + oo * win.ux]))
    return pins
