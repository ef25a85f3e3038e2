"""Where the terrain demonstration scans: the paper's nine regions and the zigzag tap plan over each.

The regions are latitude/longitude boxes around the features the paper discusses (mountains, seas,
channels); their kind decides how :mod:`benchmarks.terrain_score` scores them. Boxes and tap centres
are in the map frame of :mod:`twin.terrain` (mm).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Sequence

import numpy as np

from pipeline.types import DataError
from twin.terrain import MAP_WIDTH_MM, x_mm_from_lon, y_mm_from_lat

__all__ = ["Region", "REGIONS", "WHOLE_MAP", "region", "region_names", "plan_scan", "SCAN_STEP_MM"]

# ----- regions ------------------------------------------------------------------------------

@dataclass(frozen=True)
class Region:
    """A scan region: a latitude/longitude box (deg, lon in [-180, 180), lon_min < lon_max) and the
    kind of feature the paper discusses there."""

    key: str
    name: str
    lat_min: float
    lat_max: float
    lon_min: float
    lon_max: float
    kind: str        # mountains | sea | channel | all

    def box_mm(self) -> tuple[float, float, float, float]:
        """(x0, x1, y0, y1) in the map frame, mm."""
        return (float(x_mm_from_lon(self.lon_min)), float(x_mm_from_lon(self.lon_max)) if self.lon_max < 180 else MAP_WIDTH_MM,
                float(y_mm_from_lat(self.lat_min)), float(y_mm_from_lat(self.lat_max)))


# The paper's nine regions (Fig. "map" (c) i-ix); boxes chosen to frame each feature with some
# surrounding land/sea, numbered as in the paper.
REGIONS: dict[str, Region] = {r.key: r for r in (
    Region("rocky", "(i) Rocky Mountains", 32.0, 58.0, -128.0, -100.0, "mountains"),
    Region("gulf_of_mexico", "(ii) Gulf of Mexico", 16.0, 32.0, -100.0, -78.0, "sea"),
    Region("andes", "(iii) Andes", -45.0, -5.0, -82.0, -58.0, "mountains"),
    Region("drake", "(iv) Drake Passage", -70.0, -50.0, -78.0, -52.0, "channel"),
    Region("english_channel", "(v) English Channel", 46.0, 54.0, -8.0, 4.0, "channel"),
    Region("mozambique", "(vi) Mozambique Channel", -28.0, -10.0, 30.0, 52.0, "channel"),
    Region("black_caspian", "(vii) Black and Caspian Seas", 35.0, 48.0, 26.0, 56.0, "sea"),
    Region("himalaya", "(viii) Himalaya", 24.0, 40.0, 70.0, 98.0, "mountains"),
    Region("okhotsk", "(ix) Sea of Okhotsk", 42.0, 64.0, 132.0, 166.0, "sea"),
)}
WHOLE_MAP = Region("world", "Whole map", -90.0, 90.0, -180.0, 180.0, "all")


def region_names() -> list[str]:
    return list(REGIONS)


def region(key: str) -> Region:
    """Look up a region by key (``rocky``, ``andes``, ... or ``world``)."""
    if key == WHOLE_MAP.key:
        return WHOLE_MAP
    try:
        return REGIONS[key]
    except KeyError:
        raise DataError(f"unknown terrain region {key!r} (choose from {', '.join(REGIONS)}, world)") from None


SCAN_STEP_MM = 15.0      # the paper's horizontal step between taps


def plan_scan(box_mm: Sequence[float], *, step_mm: float = SCAN_STEP_MM) -> np.ndarray:
    """Zigzag (boustrophedon) tap centres covering ``box_mm = (x0, x1, y0, y1)`` (map frame).

    ``n = ceil(extent / step)`` centres per axis (at least one), spaced ``step_mm`` and centred on
    the box, so their span is at most the box extent and the box edges lie within ``step/2`` of the
    outermost centres (covered by a sensor of radius >= step/sqrt(2) = 10.6 mm; the dense pattern's
    is 14.4 mm). Rows run south to north; odd rows run east to west.

    Returns
    -------
    (n_taps, 2) float64 tap centres (x, y) in mm, in visiting order.
    """
    x0, x1, y0, y1 = (float(v) for v in box_mm)
    if not (x1 > x0 and y1 > y0):
        raise DataError(f"scan box {tuple(box_mm)} mm: need x0 < x1 and y0 < y1")
    if not step_mm > 0:
        raise DataError(f"scan step must be > 0 mm, got {step_mm}")

    def axis(lo, hi):
        n = max(1, int(math.ceil((hi - lo) / step_mm - 1e-9)))
        return (lo + hi) / 2 + (np.arange(n) - (n - 1) / 2) * step_mm

    xs, ys = axis(x0, x1), axis(y0, y1)
    rows = [np.column_stack([xs if r % 2 == 0 else xs[::-1], np.full(len(xs), y)]) for r, y in enumerate(ys)]
    return np.vstack(rows)
