"""The DEM readers of the terrain demonstration: ETOPO-family relief grids in latitude-longitude.

:func:`load_etopo` reads a netCDF-3 (Ferret ETOPO5/20/60, ETOPO1; scipy) or netCDF-4/HDF5 (ETOPO 2022;
``h5py`` when installed) grid into a :class:`Dem` (latitudes south to north, longitudes in [-180, 180)),
:func:`resample_dem` area-averages or interpolates it onto a global cell-centred grid, and
:func:`land_mask` decides land by a real land mask (``global_land_mask``, 1 km GLOBE), not by ``z > 0``.
Everything here is in degrees and metres; the printed map's frame (mm) is :mod:`twin.terrain`'s, which
builds the relief map from these (:func:`twin.terrain.relief_from_dem`).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path
from typing import Iterable

import numpy as np

from pipeline.types import DataError

__all__ = ["TerrainFileError", "Dem", "load_etopo", "resample_dem", "land_mask"]

# variable names of the relief in the ETOPO family (Ferret ETOPO5/20/60: ROSE; ETOPO1/2022: z)
_RELIEF_VARIABLES = ("ROSE", "z", "elevation", "Band1", "topo", "altitude", "height")


class TerrainFileError(DataError):
    """A DEM file is missing, corrupt, truncated, or lacks a relief variable / lat-lon axes."""


@dataclass(frozen=True)
class Dem:
    """A regular latitude-longitude elevation grid.

    Parameters
    ----------
    lat_deg : (H,) float64, strictly increasing (south to north), cell centres
    lon_deg : (W,) float64, strictly increasing within [-180, 180), cell centres, no repeated wrap column
    elevation_m : (H, W) float32, metres above sea level; row i is lat_deg[i], column j lon_deg[j]
    source : where it came from (file name), for messages and provenance
    """

    lat_deg: np.ndarray
    lon_deg: np.ndarray
    elevation_m: np.ndarray
    source: str = ""

    def __post_init__(self) -> None:
        lat = np.asarray(self.lat_deg, dtype=np.float64)
        lon = np.asarray(self.lon_deg, dtype=np.float64)
        z = np.asarray(self.elevation_m, dtype=np.float32)
        if lat.ndim != 1 or lon.ndim != 1 or z.shape != (len(lat), len(lon)):
            raise TerrainFileError(f"{self.source or 'DEM'}: elevation shape {z.shape} does not match "
                                   f"the axes ({len(lat)} latitudes, {len(lon)} longitudes)")
        if len(lat) < 2 or len(lon) < 2 or np.any(np.diff(lat) <= 0) or np.any(np.diff(lon) <= 0):
            raise TerrainFileError(f"{self.source or 'DEM'}: latitude/longitude axes must be strictly increasing")
        for name, value in (("lat_deg", lat), ("lon_deg", lon), ("elevation_m", z)):
            value.setflags(write=False)
            object.__setattr__(self, name, value)

    @property
    def step_deg(self) -> float:
        """Mean longitude spacing (deg)."""
        return float(np.mean(np.diff(self.lon_deg)))


def load_etopo(path: str | Path, *, variable: str | None = None) -> Dem:
    """Read an ETOPO-family netCDF relief grid into a :class:`Dem`.

    Parameters
    ----------
    path : a netCDF-3 file (Ferret ETOPO5/20/60, ETOPO1) read with scipy; a netCDF-4/HDF5 file
        (ETOPO 2022) is read with ``h5py`` when that package is installed.
    variable : name of the relief variable; by default the first of ROSE, z, elevation, Band1, ...

    Returns
    -------
    Dem with latitudes south to north and longitudes wrapped into [-180, 180), sorted, the
    repeated wrap column (etopo20 repeats one) dropped. Missing values (``_FillValue`` /
    ``missing_value``) become NaN.

    Raises
    ------
    TerrainFileError
        naming the file: missing, not netCDF, truncated (data shorter than its header says),
        no relief variable, no 1-D latitude/longitude axes, or no finite value at all.
    """
    path = Path(path)
    if not path.is_file():
        raise TerrainFileError(f"DEM file {path} does not exist")
    with open(path, "rb") as fh:
        magic = fh.read(8)
    if magic[:3] == b"CDF":
        lat, lon, z, fill = _read_netcdf3(path, variable)
    elif magic == b"\x89HDF\r\n\x1a\n":
        lat, lon, z, fill = _read_hdf5(path, variable)
    else:
        raise TerrainFileError(f"DEM file {path}: not a netCDF file (first bytes {magic[:4]!r})")
    z = np.array(z, dtype=np.float32)
    for f in fill:
        if f is not None and np.isfinite(f):
            z[z == np.float32(f)] = np.nan
    z[np.abs(z) > 1e5] = np.nan  # -1e34 style fills without an attribute
    if not np.any(np.isfinite(z)):
        raise TerrainFileError(f"DEM file {path}: relief variable holds no finite value")
    lat = np.asarray(lat, dtype=np.float64)
    lon = np.asarray(lon, dtype=np.float64)
    if z.shape != (len(lat), len(lon)):
        if z.shape == (len(lon), len(lat)):
            z = z.T
        else:
            raise TerrainFileError(f"DEM file {path}: relief shape {z.shape} does not match the axes "
                                   f"({len(lat)} latitudes, {len(lon)} longitudes)")
    if lat[0] > lat[-1]:
        lat, z = lat[::-1], z[::-1]
    lon_w = np.mod(lon + 180.0, 360.0) - 180.0
    lon_w = np.round(lon_w, 9)
    order = np.argsort(lon_w, kind="stable")
    lon_w, z = lon_w[order], z[:, order]
    d = np.diff(lon_w)
    # drop the repeated wrap column (etopo20's 380.1666307 deg is 20.1666667 deg to 4e-5 deg)
    keep = np.concatenate([[True], d > 0.01 * np.median(d)]) if len(d) else np.ones(1, bool)
    return Dem(lat, lon_w[keep], z[:, keep], source=str(path))


def _pick_variable(names: Iterable[str], variable: str | None, path: Path) -> str:
    names = list(names)
    if variable is not None:
        if variable not in names:
            raise TerrainFileError(f"DEM file {path}: no variable {variable!r} (has {', '.join(names)})")
        return variable
    for cand in _RELIEF_VARIABLES:
        if cand in names:
            return cand
    raise TerrainFileError(f"DEM file {path}: no relief variable (looked for {', '.join(_RELIEF_VARIABLES)}; "
                           f"file has {', '.join(names) or 'none'})")


def _axis_kind(name: str, attrs: dict) -> str | None:
    units = attrs.get("units", b"")
    units = units.decode("latin-1") if isinstance(units, bytes) else str(units)
    units, lname = units.lower(), name.lower()
    if "degrees_north" in units or "degree_north" in units or lname.startswith("lat") or lname.endswith("y"):
        return "lat"
    if "degrees_east" in units or "degree_east" in units or lname.startswith("lon") or "x" in lname:
        return "lon"
    return None


def _read_netcdf3(path: Path, variable: str | None):
    from scipy.io import netcdf_file

    try:
        with netcdf_file(str(path), "r", mmap=False) as f:
            name = _pick_variable(f.variables, variable, path)
            var = f.variables[name]
            if var.data.ndim != 2:
                raise TerrainFileError(f"DEM file {path}: variable {name!r} is {var.data.ndim}-D, expected 2-D (lat, lon)")
            axes = {}
            for dim in var.dimensions:
                if dim not in f.variables:
                    raise TerrainFileError(f"DEM file {path}: dimension {dim!r} of {name!r} has no coordinate variable")
                kind = _axis_kind(dim, f.variables[dim]._attributes)
                if kind is None:
                    raise TerrainFileError(f"DEM file {path}: cannot tell whether axis {dim!r} is latitude or longitude")
                axes[kind] = np.array(f.variables[dim].data, dtype=np.float64)
            if set(axes) != {"lat", "lon"}:
                raise TerrainFileError(f"DEM file {path}: variable {name!r} needs one latitude and one longitude axis")
            z = np.array(var.data, dtype=np.float32)
            if _axis_kind(var.dimensions[0], f.variables[var.dimensions[0]]._attributes) == "lon":
                z = z.T
            fill = [var._attributes.get("_FillValue"), var._attributes.get("missing_value")]
            fill = [float(np.asarray(v).ravel()[0]) if v is not None else None for v in fill]
    except TerrainFileError:
        raise
    except (TypeError, ValueError, OSError, IndexError, KeyError, EOFError, AttributeError) as exc:
        raise TerrainFileError(f"DEM file {path}: corrupt or truncated netCDF ({type(exc).__name__}: {exc})") from None
    return axes["lat"], axes["lon"], z, fill


def _read_hdf5(path: Path, variable: str | None):
    try:
        import h5py  # optional: only for netCDF-4 grids such as ETOPO 2022
    except ImportError:
        raise TerrainFileError(f"DEM file {path}: netCDF-4/HDF5 needs the 'h5py' package "
                               "(pip install h5py), or convert it to netCDF-3 first") from None
    try:
        with h5py.File(path, "r") as f:
            name = _pick_variable([k for k in f.keys() if getattr(f[k], "ndim", 0) == 2], variable, path)
            lat_name = next((k for k in ("lat", "latitude", "y") if k in f), None)
            lon_name = next((k for k in ("lon", "longitude", "x") if k in f), None)
            if lat_name is None or lon_name is None:
                raise TerrainFileError(f"DEM file {path}: no lat/lon coordinate variables")
            z = np.asarray(f[name][...], dtype=np.float32)
            fill = [f[name].attrs.get("_FillValue"), f[name].attrs.get("missing_value")]
            fill = [float(np.asarray(v).ravel()[0]) if v is not None else None for v in fill]
            return np.asarray(f[lat_name][...]), np.asarray(f[lon_name][...]), z, fill
    except TerrainFileError:
        raise
    except (OSError, ValueError, KeyError, TypeError) as exc:
        raise TerrainFileError(f"DEM file {path}: corrupt or truncated HDF5 ({type(exc).__name__}: {exc})") from None


# ----- resampling and land mask --------------------------------------------------------------

def _cell_centres(lo: float, hi: float, step: float) -> np.ndarray:
    n = int(round((hi - lo) / step))
    return lo + step * (np.arange(n) + 0.5)


def _bilinear_periodic(dem: Dem, lat: np.ndarray, lon: np.ndarray) -> np.ndarray:
    """Bilinear DEM value at points (deg), periodic in longitude, clamped in latitude; NaN-aware."""
    la, lo, z = dem.lat_deg, dem.lon_deg, dem.elevation_m.astype(np.float64)
    W = len(lo)
    # longitude: extend periodically by one column either side
    lo_ext = np.concatenate([[lo[-1] - 360.0], lo, [lo[0] + 360.0]])
    z_ext = np.concatenate([z[:, -1:], z, z[:, :1]], axis=1)
    lon = np.mod(lon - lo_ext[0], 360.0) + lo_ext[0]
    j = np.clip(np.searchsorted(lo_ext, lon, side="right") - 1, 0, W)
    tx = (lon - lo_ext[j]) / (lo_ext[j + 1] - lo_ext[j])
    latc = np.clip(lat, la[0], la[-1])
    i = np.clip(np.searchsorted(la, latc, side="right") - 1, 0, len(la) - 2)
    ty = (latc - la[i]) / (la[i + 1] - la[i])
    v00, v01 = z_ext[i, j], z_ext[i, j + 1]
    v10, v11 = z_ext[i + 1, j], z_ext[i + 1, j + 1]
    return (1 - ty) * ((1 - tx) * v00 + tx * v01) + ty * ((1 - tx) * v10 + tx * v11)


def resample_dem(dem: Dem, step_deg: float, *, progress: bool = False) -> Dem:
    """Resample to the global cell-centred grid of ``step_deg`` (lon -180.., lat -90..).

    Each output cell is the mean of k x k bilinear samples of the source inside it, k = the number
    of source cells per output cell rounded up (k = 1 when upsampling): an area mean when
    downsampling (e.g. ETOPO 2022 30" -> 0.2 deg), plain bilinear interpolation when upsampling.
    """
    if not 0 < step_deg <= 10:
        raise TerrainFileError(f"step_deg must be in (0, 10], got {step_deg!r}")
    lat = _cell_centres(-90.0, 90.0, step_deg)
    lon = _cell_centres(-180.0, 180.0, step_deg)
    k = max(1, int(math.ceil(step_deg / dem.step_deg - 1e-9)))
    off = (np.arange(k) + 0.5) / k * step_deg - step_deg / 2
    out = np.zeros((len(lat), len(lon)), dtype=np.float64)
    rows = range(len(lat))
    if progress:
        from tqdm import tqdm
        rows = tqdm(rows, desc="resample DEM", unit="row", leave=False)
    LO = (lon[None, :] + off[:, None]).ravel()
    for r in rows:
        acc = np.zeros(len(lon))
        for dy in off:
            v = _bilinear_periodic(dem, np.full(LO.shape, lat[r] + dy), LO)
            acc += v.reshape(k, len(lon)).mean(axis=0)
        out[r] = acc / k
    return Dem(lat, lon, out.astype(np.float32), source=f"{dem.source} resampled to {step_deg} deg")


def land_mask(lat_deg: np.ndarray, lon_deg: np.ndarray, *, subsamples: int = 3) -> np.ndarray:
    """Land (True) / sea of grid cells centred on ``lat_deg`` (H,) x ``lon_deg`` (W,), from GLOBE.

    A cell is land when at least half of ``subsamples``^2 points spread over it are land in the
    1 km ``global_land_mask`` (majority vote, so a coastline cell goes to whichever side covers more
    of it). Inland seas the mask calls land (Caspian) stay land; the Black Sea is sea.
    """
    from global_land_mask import globe

    lat = np.asarray(lat_deg, dtype=np.float64)
    lon = np.asarray(lon_deg, dtype=np.float64)
    dlat = float(np.mean(np.diff(lat))) if len(lat) > 1 else 0.0
    dlon = float(np.mean(np.diff(lon))) if len(lon) > 1 else 0.0
    off = (np.arange(subsamples) + 0.5) / subsamples - 0.5
    votes = np.zeros((len(lat), len(lon)), dtype=np.int32)
    for oy in off:
        la = np.clip(lat + oy * dlat, -89.999, 89.999)
        for ox in off:
            lo = np.mod(lon + ox * dlon + 180.0, 360.0) - 180.0
            LA, LO = np.meshgrid(la, np.clip(lo, -180.0, 179.999), indexing="ij")
            votes += globe.is_land(LA, LO)
    return votes * 2 >= subsamples * subsamples
