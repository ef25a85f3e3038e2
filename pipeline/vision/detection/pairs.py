"""Two touching pins found as one blob, split back into the two pins.

Pins on a flank seen obliquely are foreshortened to narrow ellipses; two of them touching side by side read as
one round blob at the pair's scale, centred on the dark line between them. Pins crowded into a crest overlap in
the image instead (discs 8-9 px apart with radius ~6 px on hexagon217_sep180 under a 5 mm sine press): the blob
is a figure of eight with no dark line, its waist only narrower. :func:`separate_pairs` finds both among the
accepted blobs and replaces each by its two pins.
"""

from __future__ import annotations

import numpy as np
from scipy.spatial import cKDTree

from pipeline.vision.detection.candidates import ELONGATION, RADIUS_PER_SIGMA, SIGMA, X, Y
from pipeline.vision.detection.pair_profiles import pair_pins
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
    which = which[dark[which] | waist[which]]
    r = RADIUS_PER_SIGMA * cand[which, SIGMA]
    found, pins = pair_pins(np.ascontiguousarray(grey), xy[which, 0].copy(), xy[which, 1].copy(), r,
                            params.centroid_radius_factor * r + WINDOW_MARGIN_PX, RADIUS_PER_SIGMA * local[which],
                            dark[which], waist[which], PAIR_PEAK_FRACTION, PAIR_DIP, PAIR_WAIST, PAIR_END_FRACTION)
    for i, pair in zip(which[found], pins[found]):
        sep = float(np.hypot(*(pair[0] - pair[1])))
        drop[i] = True
        for pin in pair:
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
