"""The detector: candidates, suppression, refinement and rejection chained for one camera view."""

from __future__ import annotations

import numpy as np

from pipeline.types import Blobs
from pipeline.vision.detection.candidates import RESPONSE, SIGMA
from pipeline.vision.detection.images import to_grey
from pipeline.vision.detection.params import DetectionParams
from pipeline.vision.detection.peaks import spacing_suppress, suppress
from pipeline.vision.detection.photometry import refine_and_measure
from pipeline.vision.detection.pairs import separate_pairs
from pipeline.vision.detection.rejection import screen, separate_debris
from pipeline.vision.detection.scale_space import find_candidates


#: Views smaller than this (px, either side) hold no marker the default scales can find: empty result.
MIN_IMAGE_SIDE_PX = 8


def detect_markers(image: np.ndarray, *, params: DetectionParams = DetectionParams()) -> Blobs:
    """Detect bright circular markers in one camera view.

    Parameters
    ----------
    image : (H, W) or (H, W, 3) uint8
        One view (grey or BGR), any size; e.g. ``StereoFrame.left``.
    params : DetectionParams
        Scales, thresholds and rejection rules.

    Returns
    -------
    Blobs
        ``xy_px`` (N, 2) float64 sub-pixel centres (u, v), pixel-centre convention of
        :mod:`pipeline.types`; ``sigma_px`` (N,) detection scale (radius ~ sqrt(2) sigma);
        ``response`` (N,) scale-normalised DoH. Sorted by ``v`` then ``u``. Empty images, blank or
        saturated images give ``Blobs.empty()``.

    Raises
    ------
    DataError
        ``image`` is not a uint8 grey/BGR array.

    Notes
    -----
    Markers below ~2 px radius (sigma < 1.4) or above ~12 px are not found with the default scales.
    Centre accuracy on noise-free anti-aliased discs of radius >= 3 px is a few hundredths of a pixel
    (tests/test_detection.py). Dark-on-bright blobs are ignored by design.
    """
    grey = to_grey(image)
    if grey.size == 0 or min(grey.shape) < MIN_IMAGE_SIDE_PX:
        return Blobs.empty()
    cand_all = find_candidates(grey, params)
    cand = suppress(cand_all, params.min_separation_px)
    if len(cand) == 0:
        return Blobs.empty()
    measured = refine_and_measure(grey, cand, params)
    debris = np.zeros(len(cand), bool)
    if params.rejections and params.debris_size_ratio is not None:
        cand, debris, measured = separate_debris(grey, cand_all, cand, measured, params)
    keep, xy = screen(grey, cand, measured, debris, params)
    h, w = grey.shape
    b = params.border_px
    keep &= (xy[:, 0] >= b) & (xy[:, 0] <= w - 1 - b) & (xy[:, 1] >= b) & (xy[:, 1] <= h - 1 - b)
    xy, cand = xy[keep], cand[keep]
    if params.rejections:
        cand, xy = separate_pairs(grey, cand, xy, params)
    if params.min_spacing_fraction is not None and len(xy) >= 3:
        keep = spacing_suppress(xy, cand[:, RESPONSE], params.min_spacing_fraction)
        xy, cand = xy[keep], cand[keep]
    order = np.lexsort((xy[:, 0], xy[:, 1]))
    return Blobs(xy[order], cand[order, SIGMA], cand[order, RESPONSE])


def compile_crowded_kernels() -> None:
    """Compile (or load from numba's cache) the kernels only crowded views or the monocular dome's screens reach:
    the pair tests on two touching discs, the touching-marker screens on three touching candidates, the ring
    background, the local size and the spacing suppression. A stream whose first frames reach none of them would
    otherwise pay their compilation (~10-20 s) on a later frame."""
    from pipeline.vision.detection.crowding import flanked, ring_spread, split_centroids
    from pipeline.vision.detection.pair_profiles import compile_pair_pins
    from pipeline.vision.detection.rejection import _local_scale, _ring_background

    compile_pair_pins()
    grey = np.full((24, 32), 20, np.uint8)
    grey[8:16, 6:26] = 200
    xy = np.array([[10.0, 12.0], [16.0, 12.0], [22.0, 12.0]])
    radius, every = np.full(3, 3.0), np.ones(3, bool)
    ring_spread(xy, radius, np.zeros((3, 8)), every, every)
    flanked(xy, radius, every, every)
    split_centroids(grey, xy, radius, every, every, DetectionParams())
    _ring_background(grey, xy, radius)
    spacing_suppress(xy, np.ones(3), 0.5)
    cand = np.zeros((8, 3))
    cand[:, 0] = np.arange(8.0)
    _local_scale(cand, np.ones(8, bool), np.ones(8, bool))
