"""The terrain demonstration's world relief map and the relief under a tap (twin side).

The map frame, the relief map built from a DEM (:class:`TerrainMap`, :func:`relief_from_dem`, the packaged
asset, the printable mesh) and the terrain under a tap. The DEM readers (ETOPO grids, resampling, land mask)
are :mod:`twin.dem`; they work in degrees and metres and know nothing of the map frame.

Paper, "Experiments III": a 320 x 160 x 9.7 mm printed world relief (land from a DEM, ocean floor
flattened to -3000 m along the coastline), scanned by a robot tapping a StereoTacTip in a zigzag
with 15 mm steps over nine regions.

Map frame (mm), the one every function here uses unless it says otherwise
------------------------------------------------------------------------
Equirectangular (EPSG:4326 plate carree), 320 mm for 360 deg of longitude and 160 mm for 180 deg of
latitude (the same 8/9 mm per degree on both axes)::

    x_mm = ((lon_deg - 180) mod 360) * 320 / 360      # 0 at the antimeridian, growing eastward
    y_mm = (lat_deg + 90) * 160 / 180                 # 0 at the south pole, growing northward

so the origin is the corner (180 deg E = 180 deg W, 90 deg S) named by the paper, x runs east from the
antimeridian through Greenwich (x = 160 mm) back to the antimeridian (x = 320 mm), i.e. the ordinary
[-180, 180) EPSG:4326 world map with its lower-left corner at the origin
(``(lon - 180) mod 360 == (lon + 180) mod 360``). The frame is right handed with z up.

Vertical scale. The paper gives three numbers: the model is 9.7 mm tall, the ocean floor is flattened
to -3000 m, and the global origin sits at 2 mm "corresponding to an altitude of 0 m". A single linear
scale cannot honour all three with the ocean floor on the bottom of the print (2 mm for 3000 m puts
Everest at 7.9 mm, not 9.7 mm). We take the one linear scale that maps the flattened ocean floor to
0 mm and sea level to 2 mm, ``1 mm = 1500 m`` (:data:`M_PER_MM`), and put a solid base slab of
:data:`BASE_MM` = 9.7 - (2 + 8848/1500) = 1.80 mm under the ocean floor, so that a DEM reaching
Everest's 8848 m prints exactly 9.7 mm tall. Heights ``z_mm`` of the map frame are measured from the
ocean floor (top of the base slab): ocean 0 mm, sea level 2 mm, Everest 7.90 mm.

Global frame (the paper's O_global): the map frame shifted down by 2 mm, so z_global = 0 is sea
level: ``z_global_mm = z_mm - SEA_LEVEL_MM``. Taps go from z_global = 8 mm down to z_global = 0 mm.

Land is decided by a real land mask (``global_land_mask``, 1 km GLOBE), not by ``z > 0``: the Caspian
and the Dead Sea are land in that mask and keep their (negative) DEM relief, the Black Sea is sea.
"""

from __future__ import annotations

import contextlib
import hashlib
import io
import math
import zipfile
import zlib
from dataclasses import dataclass
from importlib import resources
from pathlib import Path
from typing import Sequence

import numpy as np

from pipeline.types import HeightMap
from twin.dem import Dem, TerrainFileError, _bilinear_periodic, land_mask, resample_dem

# TerrainFileError is re-exported: the relief asset's readers here raise it too
__all__ = [
    "MAP_WIDTH_MM", "MAP_DEPTH_MM", "MAP_HEIGHT_MM", "SEA_LEVEL_MM", "M_PER_MM", "OCEAN_FLOOR_M",
    "BASE_MM", "MM_PER_DEG", "TerrainFileError", "TerrainMap", "relief_from_dem", "load_terrain_map",
    "x_mm_from_lon", "y_mm_from_lat", "lon_from_x_mm", "lat_from_y_mm", "z_mm_from_elevation_m",
    "elevation_m_from_z_mm", "tap_indenter",
]

# ----- the map's dimensions and scales ------------------------------------------------------

MAP_WIDTH_MM = 320.0          # 360 deg of longitude
MAP_DEPTH_MM = 160.0          # 180 deg of latitude
MAP_HEIGHT_MM = 9.7           # the printed model's total height, base slab included
MM_PER_DEG = MAP_WIDTH_MM / 360.0   # = MAP_DEPTH_MM / 180 = 0.8889 mm per degree on both axes
OCEAN_FLOOR_M = -3000.0       # the paper's flattened ocean floor
SEA_LEVEL_MM = 2.0            # height of 0 m above the ocean floor (the paper's global origin)
M_PER_MM = (0.0 - OCEAN_FLOOR_M) / SEA_LEVEL_MM   # 1500 m per mm: -3000 m -> 0 mm, 0 m -> 2 mm
EVEREST_M = 8848.0
BASE_MM = MAP_HEIGHT_MM - (SEA_LEVEL_MM + EVEREST_M / M_PER_MM)   # 1.80 mm slab under the ocean floor

ASSET_PACKAGE = "sim_assets.terrain"
ASSET_NAME = "relief.npz"
MAX_GRID_SIDE = 100_000      # cells per axis of a relief grid (a 0.004 deg global grid)


# ----- coordinate conversions ---------------------------------------------------------------

def x_mm_from_lon(lon_deg) -> np.ndarray:
    """Map x (mm, 0..320) of a longitude (deg, any branch): ``((lon - 180) mod 360) * 320/360``."""
    return np.mod(np.asarray(lon_deg, dtype=np.float64) - 180.0, 360.0) * MM_PER_DEG


def y_mm_from_lat(lat_deg) -> np.ndarray:
    """Map y (mm, 0..160) of a latitude (deg): ``(lat + 90) * 160/180``."""
    return (np.asarray(lat_deg, dtype=np.float64) + 90.0) * MM_PER_DEG


def lon_from_x_mm(x_mm) -> np.ndarray:
    """Longitude in [-180, 180) deg of a map x (mm)."""
    return np.mod(np.asarray(x_mm, dtype=np.float64) / MM_PER_DEG, 360.0) - 180.0


def lat_from_y_mm(y_mm) -> np.ndarray:
    """Latitude (deg) of a map y (mm)."""
    return np.asarray(y_mm, dtype=np.float64) / MM_PER_DEG - 90.0


def z_mm_from_elevation_m(elevation_m) -> np.ndarray:
    """Map height (mm above the ocean floor) of an elevation (m): ``2 + h / 1500``."""
    return SEA_LEVEL_MM + np.asarray(elevation_m, dtype=np.float64) / M_PER_MM


def elevation_m_from_z_mm(z_mm) -> np.ndarray:
    """Elevation (m) of a map height (mm above the ocean floor)."""
    return (np.asarray(z_mm, dtype=np.float64) - SEA_LEVEL_MM) * M_PER_MM


# ----- the relief map -----------------------------------------------------------------------

@dataclass(frozen=True)
class TerrainMap:
    """The printed world relief in the map frame (module docstring).

    Parameters
    ----------
    lat_deg : (H,) cell-centre latitudes, south to north, regular
    lon_deg : (W,) cell-centre longitudes in [-180, 180), west to east, regular
    elevation_m : (H, W) float32, land relief in metres; ocean cells hold exactly OCEAN_FLOOR_M
    land : (H, W) bool land mask used for the flattening
    source : provenance string
    """

    lat_deg: np.ndarray
    lon_deg: np.ndarray
    elevation_m: np.ndarray
    land: np.ndarray
    source: str = ""

    # --- grids in mm ---
    @property
    def x_mm(self) -> np.ndarray:
        """(W,) cell-centre x (mm), increasing: longitudes in [-180, 180) map to x in [0, 320)."""
        return x_mm_from_lon(self.lon_deg)

    @property
    def y_mm(self) -> np.ndarray:
        return y_mm_from_lat(self.lat_deg)

    @property
    def z_mm(self) -> np.ndarray:
        """(H, W) float64 map heights above the ocean floor (mm): ocean 0, sea level 2."""
        return z_mm_from_elevation_m(self.elevation_m)

    @property
    def step_mm(self) -> float:
        return float(np.mean(np.diff(self.x_mm)))

    def height_map(self, *, frame: str = "map") -> HeightMap:
        """The whole relief as a :class:`HeightMap`: ``frame='map'`` heights above the ocean floor,
        ``frame='global'`` heights above sea level (the paper's O_global, z = z_map - 2 mm)."""
        z = self.z_mm - (SEA_LEVEL_MM if frame == "global" else 0.0)
        if frame not in ("map", "global"):
            raise ValueError(f"frame must be 'map' or 'global', got {frame!r}")
        return HeightMap(self.x_mm, self.y_mm, z)

    def sample_z_mm(self, x_mm, y_mm, *, frame: str = "map") -> np.ndarray:
        """Bilinear map height at map points (mm); periodic in x (the map wraps at the antimeridian
        only in the DEM sense: points off the print are still given the relief they would have)."""
        x = np.asarray(x_mm, dtype=np.float64)
        y = np.asarray(y_mm, dtype=np.float64)
        dem = Dem(self.lat_deg, self.lon_deg, self.elevation_m, self.source)
        h = _bilinear_periodic(dem, lat_from_y_mm(y).ravel(), lon_from_x_mm(x).ravel()).reshape(np.broadcast(x, y).shape)
        z = z_mm_from_elevation_m(h)
        return z - SEA_LEVEL_MM if frame == "global" else z

    def crop(self, box_mm: tuple[float, float, float, float], *, frame: str = "global") -> HeightMap:
        """The relief inside ``(x0, x1, y0, y1)`` mm on the map's own grid (no interpolation)."""
        x0, x1, y0, y1 = box_mm
        xs, ys = self.x_mm, self.y_mm
        jx = np.flatnonzero((xs >= x0) & (xs <= x1))
        iy = np.flatnonzero((ys >= y0) & (ys <= y1))
        if len(jx) == 0 or len(iy) == 0:
            raise ValueError(f"box {box_mm} mm holds no map cell")
        z = self.z_mm[np.ix_(iy, jx)] - (SEA_LEVEL_MM if frame == "global" else 0.0)
        return HeightMap(xs[jx], ys[iy], z)

    # --- persistence (the packaged asset) ---
    def save_npz(self, path: str | Path, *, extra: dict | None = None) -> None:
        """Compact asset: int16 metres (ocean = -3000), packed land bits, the grid definition (atomic)."""
        from pipeline.io.atomic import atomic_open

        with atomic_open(path, "wb") as fh:
            self._savez(fh, extra)

    def _savez(self, fh, extra: dict | None) -> None:
        np.savez_compressed(
            fh,  # (file handle from atomic_open)
            elevation_m=np.round(self.elevation_m).astype(np.int16),
            land_bits=np.packbits(self.land, axis=None),
            shape=np.array(self.land.shape, dtype=np.int64),
            lat0_deg=np.float64(self.lat_deg[0]), lon0_deg=np.float64(self.lon_deg[0]),
            step_deg=np.float64(np.mean(np.diff(self.lon_deg))),
            source=np.array(self.source),
            **{k: np.array(v) for k, v in (extra or {}).items()},
        )

    @classmethod
    def load_npz(cls, file) -> "TerrainMap":
        """Read :meth:`save_npz`'s asset; a missing, empty, truncated or inconsistent file raises
        :class:`TerrainFileError` naming it and what is wrong (never a zip or numpy error)."""
        where = f"terrain asset {getattr(file, 'name', None) or file}"
        try:
            # our own handle for a path: np.load leaves a file it opened itself open on a truncated zip
            with (open(file, "rb") if isinstance(file, (str, Path)) else contextlib.nullcontext(file)) as fh, \
                    np.load(fh, allow_pickle=False) as f:
                shape = tuple(int(v) for v in np.asarray(f["shape"]).reshape(-1))
                step = float(f["step_deg"])
                lat0, lon0 = float(f["lat0_deg"]), float(f["lon0_deg"])
                bits = np.asarray(f["land_bits"])
                elev = np.asarray(f["elevation_m"])
                src = str(f["source"])
        except (OSError, KeyError, ValueError, TypeError, EOFError, zipfile.BadZipFile, zlib.error) as exc:
            raise TerrainFileError(f"{where}: unreadable, truncated or not an asset npz "
                                   f"({type(exc).__name__}: {str(exc)[:120]})") from None
        if len(shape) != 2 or not all(2 <= n <= MAX_GRID_SIDE for n in shape):
            raise TerrainFileError(f"{where}: shape must be two sizes in [2, {MAX_GRID_SIDE}], got {shape}")
        if elev.shape != shape or elev.dtype.kind not in "iuf" or not np.all(np.isfinite(elev)):
            raise TerrainFileError(f"{where}: elevation_m must be a finite {shape} number grid, got "
                                   f"{elev.shape} {elev.dtype}")
        if not (math.isfinite(step) and 0 < step and step * shape[1] <= 360.0 + 1e-6
                and step * shape[0] <= 180.0 + 1e-6):
            raise TerrainFileError(f"{where}: step_deg = {step!r} does not fit {shape[1]} x {shape[0]} cells in "
                                   "360 x 180 deg")
        if not (math.isfinite(lat0) and math.isfinite(lon0) and -90.0 <= lat0 and lat0 + step * (shape[0] - 1) <= 90.0
                and -180.0 <= lon0 and lon0 + step * (shape[1] - 1) < 180.0):
            raise TerrainFileError(f"{where}: grid origin ({lat0!r}, {lon0!r}) deg puts cells outside "
                                   "latitude [-90, 90] / longitude [-180, 180)")
        if bits.dtype != np.uint8 or bits.size * 8 < shape[0] * shape[1]:
            raise TerrainFileError(f"{where}: land_bits holds {bits.size * 8} bits for {shape[0] * shape[1]} cells")
        lat = lat0 + step * np.arange(shape[0])
        lon = lon0 + step * np.arange(shape[1])
        land = np.unpackbits(bits.reshape(-1), count=shape[0] * shape[1]).reshape(shape).astype(bool)
        return cls(lat, lon, elev.astype(np.float32), land, src)

    # --- export ---
    def to_mesh(self, *, stride: int = 1, base_mm: float = BASE_MM):
        """Watertight trimesh of the print: the relief on top (map frame), a base slab below z = 0
        down to ``-base_mm``, vertical walls on the four sides. ``stride`` decimates the grid."""
        x, y, z = self.x_mm[::stride], self.y_mm[::stride], self.z_mm[::stride, ::stride]
        # stretch the outermost cell centres onto the print's edges so the mesh is 320 x 160
        x = x.copy(); y = y.copy()
        x[0], x[-1], y[0], y[-1] = 0.0, MAP_WIDTH_MM, 0.0, MAP_DEPTH_MM
        return heightfield_mesh(x, y, z, bottom_mm=-base_mm)

    def to_stl(self, path: str | Path, *, stride: int = 2, base_mm: float = BASE_MM) -> Path:
        """Write the printable binary STL (mm, map frame with the base slab below z = 0)."""
        from pipeline.io.atomic import atomic_write_bytes

        mesh = self.to_mesh(stride=stride, base_mm=base_mm)
        path = Path(path)
        atomic_write_bytes(path, mesh.export(file_type="stl"))
        return path


def heightfield_mesh(x_mm: np.ndarray, y_mm: np.ndarray, z_mm: np.ndarray, *, bottom_mm: float):
    """Watertight solid under a height field: top grid, flat bottom at ``bottom_mm``, four walls.

    x (W,), y (H,) increasing; z (H, W). Faces are oriented outward (top normals +z)."""
    import trimesh

    H, W = z_mm.shape
    X, Y = np.meshgrid(x_mm, y_mm)
    top = np.column_stack([X.ravel(), Y.ravel(), z_mm.ravel()])
    idx = np.arange(H * W).reshape(H, W)
    a, b, c, d = idx[:-1, :-1].ravel(), idx[:-1, 1:].ravel(), idx[1:, 1:].ravel(), idx[1:, :-1].ravel()
    faces = [np.column_stack([a, b, c]), np.column_stack([a, c, d])]
    # boundary ring of the top, counter-clockwise seen from +z
    ring = np.concatenate([idx[0, :], idx[1:, -1], idx[-1, -2::-1], idx[-2:0:-1, 0]])
    n_top = len(top)
    bottom = top[ring].copy()
    bottom[:, 2] = bottom_mm
    ring_b = n_top + np.arange(len(ring))
    centre = n_top + len(ring)
    verts = np.vstack([top, bottom, [[x_mm.mean(), y_mm.mean(), bottom_mm]]])
    nxt = np.roll(np.arange(len(ring)), -1)
    # walls: outward for a CCW ring
    faces.append(np.column_stack([ring, ring_b, ring_b[nxt]]))
    faces.append(np.column_stack([ring, ring_b[nxt], ring[nxt]]))
    # bottom fan, facing -z (clockwise seen from +z)
    faces.append(np.column_stack([np.full(len(ring), centre), ring_b[nxt], ring_b]))
    return trimesh.Trimesh(vertices=verts, faces=np.vstack(faces), process=False)


def relief_from_dem(dem: Dem, *, step_deg: float = 0.2, mask: np.ndarray | None = None,
                    progress: bool = False) -> TerrainMap:
    """Build the relief map: resample to ``step_deg``, keep land, flatten the sea to -3000 m.

    Land cells keep the DEM value clipped to [-3000 m, +inf) (a coarse DEM can put ocean depths
    under mask-land along steep coasts; the clip keeps them no lower than the ocean floor). NaN land
    cells (missing data) become sea level. ``mask`` overrides the GLOBE land mask (tests).
    """
    grid = resample_dem(dem, step_deg, progress=progress)
    land = land_mask(grid.lat_deg, grid.lon_deg) if mask is None else np.asarray(mask, dtype=bool)
    if land.shape != grid.elevation_m.shape:
        raise ValueError(f"mask shape {land.shape} != grid shape {grid.elevation_m.shape}")
    elev = np.nan_to_num(grid.elevation_m.astype(np.float64), nan=0.0)
    elev = np.where(land, np.maximum(elev, OCEAN_FLOOR_M), OCEAN_FLOOR_M)
    return TerrainMap(grid.lat_deg, grid.lon_deg, elev.astype(np.float32), land, source=dem.source)


_CACHE: dict[str, TerrainMap] = {}


def load_terrain_map() -> TerrainMap:
    """The packaged relief (``sim_assets/terrain/relief.npz``, see its PROVENANCE.md), cached."""
    if ASSET_NAME not in _CACHE:
        ref = resources.files(ASSET_PACKAGE).joinpath(ASSET_NAME)
        if not ref.is_file():
            raise TerrainFileError(f"terrain asset {ASSET_PACKAGE}/{ASSET_NAME} is missing; regenerate it with "
                                   "python sim_assets/terrain/make_relief.py ETOPO_FILE")
        with ref.open("rb") as fh:
            buf = io.BytesIO(fh.read())
        buf.name = f"{ASSET_PACKAGE}/{ASSET_NAME}"   # for error messages
        _CACHE[ASSET_NAME] = TerrainMap.load_npz(buf)
    return _CACHE[ASSET_NAME]


def file_sha256(path: str | Path) -> str:
    h = hashlib.sha256()
    with open(path, "rb") as fh:
        for chunk in iter(lambda: fh.read(1 << 20), b""):
            h.update(chunk)
    return h.hexdigest()


# ----- the tap ------------------------------------------------------------------------------

APPROACH_Z_MM = 8.0      # start height of every tap above sea level (global z), clears Everest (5.9 mm)
TAP_Z_MM = 0.0           # the paper taps down to global z = 0 (sea level)


def tap_indenter(tmap: TerrainMap, centre_xy_mm: Sequence[float], *, skin_z_mm: float = TAP_Z_MM,
                 radius_mm: float = 22.0, spacing_mm: float = 0.2) -> HeightMap:
    """The terrain under a downward-facing sensor, as an indenter surface in the SENSOR frame.

    The sensor looks down on the map (sensor +z = global -z, sensor x = global x, sensor y = global
    -y: a rotation of 180 deg about x), its undeformed outer skin centred at global
    ``(cx, cy, skin_z_mm)``. A terrain point at global height h then sits at sensor
    ``z = skin_z_mm - h``: positive means still in front of the skin, negative means the relief
    pushes into the rest skin by that much.

    Returns
    -------
    HeightMap on a square grid of half-width ``radius_mm`` and ``spacing_mm``, sensor frame (mm).
    """
    cx, cy = (float(v) for v in centre_xy_mm)
    n = int(round(radius_mm / spacing_mm))
    s = np.arange(-n, n + 1) * spacing_mm
    XS, YS = np.meshgrid(s, s)
    h = tmap.sample_z_mm(cx + XS, cy - YS, frame="global")
    return HeightMap(s, s, skin_z_mm - h)


def sensor_to_global_rotation() -> np.ndarray:
    """3x3 rotation global_from_sensor of a sensor facing down (180 deg about x)."""
    return np.diag([1.0, -1.0, -1.0])
