"""The candidate record: one row per scale-space peak, passed between the detector's stages.

Candidates are a plain (N, 6) float64 array so that the compiled kernels read them at array speed;
these constants name its columns (numba folds them into the kernels as literals). Full-resolution
pixel coordinates follow the pixel-centre convention of :mod:`pipeline.types`.
"""

from __future__ import annotations

import math

import numpy as np

#: Column of the sub-pixel peak position u (px, full resolution).
X = 0
#: Column of the sub-pixel peak position v (px, full resolution).
Y = 1
#: Column of the continuous detection scale sigma (px, full resolution; parabola in log-sigma).
SIGMA = 2
#: Column of the scale-normalised DoH at the peak (on the [0, 1] image).
RESPONSE = 3
#: Column of the Hessian eigenvalue ratio (>= 1; edges and streaks are large).
ELONGATION = 4
#: Column of the measuring scale (px): SIGMA quantised to 1/MEASURE_STEPS_PER_OCTAVE octave, so that
#: candidates of one measuring scale share the pixel offsets of their ring, window and core.
MEASURE_SIGMA = 5
#: Number of columns.
COLUMNS = 6

#: Steps per octave of the measuring-scale grid (1/8 octave: ~9 % in radius, under a pixel for the
#: marker radii the default scales cover, and few enough distinct scales to share offset tables).
MEASURE_STEPS_PER_OCTAVE = 8

#: Radius (px) of a disc per DoH scale (px): a disc of radius ``r`` peaks at ``sigma = r / sqrt(2)``.
RADIUS_PER_SIGMA = math.sqrt(2.0)


def empty() -> np.ndarray:
    """No candidates: the (0, COLUMNS) record."""
    return np.empty((0, COLUMNS))
