"""Data types passed between pipeline stages (and handed over by the twin).

Frozen dataclasses of numpy arrays, validated on construction: shape, dtype and finiteness. Empty
results keep their shape (``(0, 2)``, never ``None``). Units ride in names (``_mm``, ``_px``,
``_deg``, ``_s``). Pixels are OpenCV ``(u, v)`` = (column, row), origin at the centre of the top-left
pixel. 3-D output is in the sensor frame documented in :mod:`pipeline.design` (mm).

Modules: :mod:`.frames` (frames, blobs, matches, clouds, surfaces and the array checks) and
:mod:`.calibration` (:class:`StereoCalibration`, its YAML files and :func:`nominal_calibration`).
"""

from pipeline.types.calibration import CalibrationError, StereoCalibration, lens_folds_over, nominal_calibration
from pipeline.types.frames import (FRAME_HEIGHT_PX, FRAME_WIDTH_PX, Blobs, DataError, HeightMap, MarkerCloud,
                                   MarkerMatches, SkinSurface, StereoFrame, checked_array)

__all__ = [
    "DataError",
    "FRAME_WIDTH_PX",
    "FRAME_HEIGHT_PX",
    "StereoFrame",
    "Blobs",
    "MarkerMatches",
    "MarkerCloud",
    "SkinSurface",
    "HeightMap",
    "StereoCalibration",
    "CalibrationError",
    "checked_array",
    "lens_folds_over",
    "nominal_calibration",
]
