"""Parameters of the marker detector and the preset for a monocular dome sensor."""

from __future__ import annotations

import math
from dataclasses import dataclass, field, replace

import numpy as np

from pipeline.types import Blobs, DataError
from pipeline.vision.detection.candidates import RADIUS_PER_SIGMA


@dataclass(frozen=True)
class DetectionParams:
    """Parameters of :func:`detect_markers`.

    Attributes
    ----------
    sigmas_px : tuple of float
        Gaussian scales (px). Two per octave; octave ``L`` (scales in ``[1.4, 2.8) * 2**L``) runs on the
        ``2**L``-reduced image. A disc of radius ``r`` peaks at ``sigma ~ r / sqrt(2)``: the default
        1.4..8.5 px covers marker radii of about 2..12 px.
    threshold : float
        Minimum scale-normalised DoH on the [0, 1] image. A noise-free disc of contrast ``C`` gives
        about ``0.06 C**2`` (measured for radii 3-10 px), so 0.004 accepts contrast down to ~0.25.
    min_contrast : float
        Minimum (peak - surrounding ring median) intensity on the [0, 1] image.
    min_separation_px : float
        Two detections closer than this are one marker (the stronger is kept).
    border_px : int
        Peaks closer than this to the image edge are dropped.
    isolation : float
        The brightest of 8 angular sectors of the surrounding ring (mean) must stay below ``ring + isolation * contrast``
        (markers are surrounded by dark on all sides; glare touching a bright region is not).
    max_size_ratio : float
        Blobs whose scale is above ``max_size_ratio`` x or below 1/``max_size_ratio`` x the median
        scale are rejected (also: blobs with a saturated core when the median marker is not).
    max_elongation : float
        Blobs whose Hessian eigenvalue ratio exceeds this are rejected (edges, streaks).
    saturation_level : int
        Grey level treated as saturated.
    max_saturated_fraction : float
        Blobs whose ring is more than this fraction saturated sit on glare: rejected.
    centroid_radius_factor : float
        Centroid window radius as a multiple of the blob radius ``sqrt(2) * sigma``.
    centroid_iterations : int
        Re-centred centroid passes.
    debris_size_ratio : float or None
        When set, blobs whose scale is below 1/``debris_size_ratio`` x the median scale are debris, not
        markers: they are taken out BEFORE the cross-scale suppression (so a bright speck lying on a
        marker cannot shadow the marker's own, weaker, response) and never accepted, crowded or not.
        ``None`` (default): small blobs compete in the suppression and are accepted when a neighbour
        touches them (down to 1/``max_size_ratio**2``), as squeezed markers of a flat module need.
    isolation_inside : float or None
        When set, the isolation limit (as ``isolation``) for candidates inside the convex hull of the
        markers that pass the strict test. Glare (LED ring, bright rim) lies outside the marker field of
        a dome seen from inside; within it, a lit ring sector is debris or a touching neighbour.
        ``None`` (default): ``isolation`` everywhere.
    min_spacing_fraction : float or None
        When set, two accepted markers whose refined centres are closer than this fraction of the
        median nearest-neighbour spacing are one marker (the stronger response is kept): the
        cross-scale suppression works on unrefined peaks, which can converge on one marker after
        refinement. ``None`` (default): no such test.
    max_background_ratio : float or None
        When set, the median of a blob's surrounding ring must stay below this x its contrast: markers
        on a dark skin (ring ~0.1-0.35 of full scale against contrast ~0.35-0.6 on the real TacTip
        frames), not bumps on a bright rim (ring ~0.7, contrast ~0.2). ``None`` (default): no such test.
    """

    sigmas_px: tuple[float, ...] = (1.4, 2.0, 2.8, 4.0, 5.6, 8.0)
    threshold: float = 0.004
    min_contrast: float = 0.08
    min_separation_px: float = 3.0
    border_px: int = 2
    isolation: float = 0.5
    max_size_ratio: float = 1.4
    max_elongation: float = 4.0
    saturation_level: int = 250
    max_saturated_fraction: float = 0.25
    centroid_radius_factor: float = 1.5
    centroid_iterations: int = 2
    rejections: bool = field(default=True)
    debris_size_ratio: float | None = None
    isolation_inside: float | None = None
    min_spacing_fraction: float | None = None
    max_background_ratio: float | None = None

    def __post_init__(self) -> None:
        if not self.sigmas_px or any(not (s > 0 and math.isfinite(s)) for s in self.sigmas_px):
            raise DataError(f"DetectionParams.sigmas_px: need positive finite scales, got {self.sigmas_px}")
        if not self.threshold > 0:
            raise DataError(f"DetectionParams.threshold: must be > 0, got {self.threshold}")
        if self.border_px < 0 or self.min_separation_px < 0:
            raise DataError("DetectionParams.border_px / min_separation_px: must be >= 0")
        for name in ("debris_size_ratio", "isolation_inside", "min_spacing_fraction", "max_background_ratio"):
            v = getattr(self, name)
            if v is not None and not (v > 0 and math.isfinite(v)):
                raise DataError(f"DetectionParams.{name}: must be None or a positive finite number, got {v}")

    def for_marker_radius(self, radius_px: float) -> "DetectionParams":
        """These parameters with the scale space narrowed to markers of about ``radius_px`` (px).

        Keeps three consecutive scales of ``sigmas_px``: the one nearest ``radius_px / sqrt(2)`` and
        its neighbours (the same grid, so the same discretisation and scale selection as the full
        set). With the default sqrt(2) grid the interpolated scale then sizes markers from ~0.7 r to
        ~1.4 r, and the scale space costs about half (the fine scales, which run on the largest pyramid
        levels, are skipped). A blob that peaks at the lowest scale (a pin seen edge-on, ~0.73 r) and
        that only the size test would reject is sized again in a window with the scale below
        (:func:`pipeline.vision.detection.scale_space.scale_below_lowest`). Typical use:
        detect the first frame with the defaults, then ``params.for_marker_radius(marker_radius_px(blobs))``
        for the stream.

        Raises
        ------
        DataError
            ``radius_px`` is not a positive finite number.
        """
        r = float(radius_px)
        if not (r > 0 and math.isfinite(r)):
            raise DataError(f"DetectionParams.for_marker_radius: radius_px must be positive and finite, got {radius_px}")
        sig = sorted(self.sigmas_px)
        if len(sig) <= 3:
            return self
        k = int(np.argmin(np.abs(np.log(np.asarray(sig) * RADIUS_PER_SIGMA / r))))
        k = min(max(k - 1, 0), len(sig) - 3)
        return replace(self, sigmas_px=tuple(sig[k:k + 3]))


#: Detection for a monocular dome (TacTip-type) sensor: one camera inside a dark hemispherical skin,
#: markers of one size on pins, LED glare and the bright rim only outside the marker field, and debris
#: in the gel (bright specks of about half a marker's scale, measured sigma 0.4-0.67 x the median on the
#: real 331-pin frames against >= 0.74 x for markers) next to or on markers. Specks are removed before
#: the scale suppression, a ring sector lit by a speck or a touching neighbour inside the marker field
#: is tolerated up to the marker's own contrast, centres that converge after refinement closer than
#: half the local spacing are one marker, and a marker's surround is darker than the marker stands
#: out from it (the skin is dark; the bright rim outside it is not).
MONOCULAR_DOME = DetectionParams(debris_size_ratio=1.4, isolation_inside=1.0, min_spacing_fraction=0.5,
                                 max_background_ratio=1.0)


def marker_radius_px(blobs: Blobs) -> float:
    """Typical marker radius (px) of a detection: ``sqrt(2)`` x the median scale.

    Raises
    ------
    DataError
        ``blobs`` is empty.
    """
    if len(blobs) == 0:
        raise DataError("marker_radius_px: no blobs detected, cannot estimate the marker radius")
    return float(RADIUS_PER_SIGMA * np.median(blobs.sigma_px))

