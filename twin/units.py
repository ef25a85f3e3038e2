"""Unit conversions between the project's millimetres and MuJoCo's SI units.

Everything outside the MuJoCo side (:mod:`twin.physics`, :mod:`twin.model`, :mod:`twin.stick`,
:mod:`twin.solve`) works in mm (sensor frame). MuJoCo works in metres, kg,
seconds, N and Pa; this module is the only place where the factor 1e-3 appears in arithmetic.
"""

from __future__ import annotations

import numpy as np

__all__ = ["M_PER_MM", "PA_PER_MPA", "mm_to_m", "m_to_mm", "mpa_to_pa"]

M_PER_MM = 1e-3
PA_PER_MPA = 1e6


def mm_to_m(x_mm):
    """Millimetres → metres (scalars or arrays, float64)."""
    return np.asarray(x_mm, dtype=np.float64) * M_PER_MM


def m_to_mm(x_m):
    """Metres → millimetres (scalars or arrays, float64)."""
    return np.asarray(x_m, dtype=np.float64) / M_PER_MM


def mpa_to_pa(e_mpa: float) -> float:
    """Young's modulus MPa → Pa."""
    return float(e_mpa) * PA_PER_MPA
