"""Frames, blobs, matches, clouds and surfaces: the arrays passed between the pipeline's stages.

Frozen dataclasses of numpy arrays, validated on construction: shape, dtype and finiteness. Empty
results keep their shape (``(0, 2)``, never ``None``). Pixels are OpenCV ``(u, v)`` = (column, row),
origin at the centre of the top-left pixel.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from pipeline.errors import UserError

FRAME_WIDTH_PX = 1280   # concatenated left | right
FRAME_HEIGHT_PX = 480


class DataError(UserError, ValueError):
    """An array handed to a data type has the wrong shape, dtype or non-finite values."""


def checked_array(name: str, value, *, dtype, shape: tuple, finite: bool = True) -> np.ndarray:
    """Coerce ``value`` to a read-only array of ``dtype`` and check its shape (-1 = any)."""
    a = np.asarray(value)
    if dtype is np.float64:
        if a.dtype.kind not in "fiu" and a.size:
            raise DataError(f"{name}: expected a numeric array, got dtype {a.dtype}")
        a = a.astype(np.float64, copy=True)
    elif dtype is np.int64:
        if a.size and a.dtype.kind not in "iu":
            raise DataError(f"{name}: expected an integer array, got dtype {a.dtype}")
        a = a.astype(np.int64, copy=True)
    elif dtype is np.bool_:
        a = a.astype(np.bool_, copy=True)
    if a.size == 0 and a.ndim != len(shape):
        a = a.reshape(tuple(0 if s == -1 else s for s in shape))
    if a.ndim != len(shape) or any(s != -1 and s != n for s, n in zip(shape, a.shape)):
        want = "(" + ", ".join("N" if s == -1 else str(s) for s in shape) + ")"
        raise DataError(f"{name}: expected shape {want}, got {a.shape}")
    if finite and a.dtype.kind == "f" and not np.all(np.isfinite(a)):
        raise DataError(f"{name}: contains NaN or inf")
    a.setflags(write=False)
    return a


def same_length(owner: str, **arrays: np.ndarray) -> None:
    lens = {k: len(v) for k, v in arrays.items()}
    if len(set(lens.values())) > 1:
        raise DataError(f"{owner}: arrays differ in length: {lens}")


@dataclass(frozen=True)
class StereoFrame:
    """One concatenated stereo frame exactly as the hardware delivers it.

    Parameters
    ----------
    image : (480, 1280, 3) uint8 BGR or (480, 1280) uint8 grey
        Left image in columns 0..639, right image in columns 640..1279.
    timestamp_s : float
        Capture time in seconds (monotonic clock of the source, or simulated time).
    index : int
        Frame number within its source.
    source : str
        Human-readable name of where the frame came from (for error messages).
    """

    image: np.ndarray
    timestamp_s: float = 0.0
    index: int = 0
    source: str = ""

    def __post_init__(self) -> None:
        img = np.asarray(self.image)
        where = f"StereoFrame from {self.source or '<unknown source>'}"
        if img.dtype != np.uint8:
            raise DataError(f"{where}: expected uint8 pixels, got {img.dtype}")
        if img.ndim == 3 and img.shape[2] == 1:
            img = img[:, :, 0]
        if img.ndim not in (2, 3) or (img.ndim == 3 and img.shape[2] != 3):
            raise DataError(f"{where}: expected a grey (H, W) or BGR (H, W, 3) image, got shape {img.shape}")
        if img.shape[:2] != (FRAME_HEIGHT_PX, FRAME_WIDTH_PX):
            raise DataError(f"{where}: expected {FRAME_WIDTH_PX}x{FRAME_HEIGHT_PX} (left|right), "
                            f"got {img.shape[1]}x{img.shape[0]}")
        if not math.isfinite(self.timestamp_s):
            raise DataError(f"{where}: timestamp_s must be finite")
        img = np.ascontiguousarray(img)
        img.setflags(write=False)
        object.__setattr__(self, "image", img)

    @property
    def left(self) -> np.ndarray:
        return self.image[:, : FRAME_WIDTH_PX // 2]

    @property
    def right(self) -> np.ndarray:
        return self.image[:, FRAME_WIDTH_PX // 2:]

    @classmethod
    def from_pair(cls, left: np.ndarray, right: np.ndarray, **kw) -> "StereoFrame":
        left, right = np.asarray(left), np.asarray(right)
        if left.shape != right.shape:
            raise DataError(f"StereoFrame.from_pair: left {left.shape} and right {right.shape} differ")
        return cls(np.concatenate([left, right], axis=1), **kw)


@dataclass(frozen=True)
class Blobs:
    """Detected blobs in one image. ``xy_px`` (N, 2) float64 (u, v); ``sigma_px`` (N,) scale;
    ``response`` (N,) detector response (larger = stronger)."""

    xy_px: np.ndarray
    sigma_px: np.ndarray
    response: np.ndarray

    def __post_init__(self) -> None:
        object.__setattr__(self, "xy_px", checked_array("Blobs.xy_px", self.xy_px, dtype=np.float64, shape=(-1, 2)))
        object.__setattr__(self, "sigma_px", checked_array("Blobs.sigma_px", self.sigma_px,
                                                           dtype=np.float64, shape=(-1,)))
        object.__setattr__(self, "response", checked_array("Blobs.response", self.response,
                                                           dtype=np.float64, shape=(-1,)))
        same_length("Blobs", xy_px=self.xy_px, sigma_px=self.sigma_px, response=self.response)

    def __len__(self) -> int:
        return len(self.xy_px)

    @classmethod
    def empty(cls) -> "Blobs":
        return cls(np.empty((0, 2)), np.empty(0), np.empty(0))


@dataclass(frozen=True)
class MarkerMatches:
    """Markers identified in both views.

    ``ids`` (N,) int64 canonical marker ids (see :mod:`pipeline.design`); ``left_px`` / ``right_px``
    (N, 2) float64 (u, v) in each half image (right coordinates relative to the right half);
    ``unmatched_ids`` (M,) int64 design ids that could not be identified consistently in this frame.
    """

    ids: np.ndarray
    left_px: np.ndarray
    right_px: np.ndarray
    unmatched_ids: np.ndarray = field(default_factory=lambda: np.empty(0, dtype=np.int64))

    def __post_init__(self) -> None:
        object.__setattr__(self, "ids", checked_array("MarkerMatches.ids", self.ids, dtype=np.int64, shape=(-1,)))
        object.__setattr__(self, "left_px", checked_array("MarkerMatches.left_px", self.left_px,
                                                          dtype=np.float64, shape=(-1, 2)))
        object.__setattr__(self, "right_px", checked_array("MarkerMatches.right_px", self.right_px,
                                                           dtype=np.float64, shape=(-1, 2)))
        object.__setattr__(self, "unmatched_ids", checked_array("MarkerMatches.unmatched_ids", self.unmatched_ids,
                                                       dtype=np.int64, shape=(-1,)))
        same_length("MarkerMatches", ids=self.ids, left_px=self.left_px, right_px=self.right_px)
        if len(np.unique(self.ids)) != len(self.ids):
            raise DataError("MarkerMatches.ids: duplicate ids")

    def __len__(self) -> int:
        return len(self.ids)


@dataclass(frozen=True)
class MarkerCloud:
    """Marker positions in 3-D: ``ids`` (N,) int64, ``xyz_mm`` (N, 3) float64, sensor frame."""

    ids: np.ndarray
    xyz_mm: np.ndarray

    def __post_init__(self) -> None:
        object.__setattr__(self, "ids", checked_array("MarkerCloud.ids", self.ids, dtype=np.int64, shape=(-1,)))
        object.__setattr__(self, "xyz_mm", checked_array("MarkerCloud.xyz_mm", self.xyz_mm,
                                                         dtype=np.float64, shape=(-1, 3)))
        same_length("MarkerCloud", ids=self.ids, xyz_mm=self.xyz_mm)

    def __len__(self) -> int:
        return len(self.ids)


@dataclass(frozen=True)
class SkinSurface:
    """Skin points recovered from markers: ``ids`` (N,), ``xyz_mm`` (N, 3) points on the outer skin
    surface, ``normals`` (N, 3) unit normals of the marker surface (pointing +z-ish, out of the skin)."""

    ids: np.ndarray
    xyz_mm: np.ndarray
    normals: np.ndarray

    def __post_init__(self) -> None:
        object.__setattr__(self, "ids", checked_array("SkinSurface.ids", self.ids, dtype=np.int64, shape=(-1,)))
        object.__setattr__(self, "xyz_mm", checked_array("SkinSurface.xyz_mm", self.xyz_mm,
                                                         dtype=np.float64, shape=(-1, 3)))
        object.__setattr__(self, "normals", checked_array("SkinSurface.normals", self.normals,
                                                          dtype=np.float64, shape=(-1, 3)))
        same_length("SkinSurface", ids=self.ids, xyz_mm=self.xyz_mm, normals=self.normals)
        if len(self.normals) and not np.allclose(np.linalg.norm(self.normals, axis=1), 1.0, atol=1e-6):
            raise DataError("SkinSurface.normals: not unit vectors")

    def __len__(self) -> int:
        return len(self.ids)


@dataclass(frozen=True)
class HeightMap:
    """A regular grid of heights: ``x_mm`` (W,), ``y_mm`` (H,) increasing axes; ``z_mm`` (H, W) with
    NaN where there is no data (outside the sensed area). Row i is y_mm[i], column j is x_mm[j]."""

    x_mm: np.ndarray
    y_mm: np.ndarray
    z_mm: np.ndarray

    def __post_init__(self) -> None:
        object.__setattr__(self, "x_mm", checked_array("HeightMap.x_mm", self.x_mm, dtype=np.float64, shape=(-1,)))
        object.__setattr__(self, "y_mm", checked_array("HeightMap.y_mm", self.y_mm, dtype=np.float64, shape=(-1,)))
        z = checked_array("HeightMap.z_mm", self.z_mm,
                          dtype=np.float64, shape=(len(self.y_mm), len(self.x_mm)), finite=False)
        if np.any(np.isinf(z)):
            raise DataError("HeightMap.z_mm: contains inf (use NaN for no data)")
        object.__setattr__(self, "z_mm", z)
        for name, ax in (("x_mm", self.x_mm), ("y_mm", self.y_mm)):
            if len(ax) > 1 and not np.all(np.diff(ax) > 0):
                raise DataError(f"HeightMap.{name}: must be strictly increasing")

    def save_npz(self, path: str | Path) -> None:
        """Write ``x_mm``, ``y_mm``, ``z_mm`` to a compressed ``.npz`` (atomically)."""
        from pipeline.io.atomic import atomic_open

        with atomic_open(path, "wb") as fh:
            np.savez_compressed(fh, x_mm=self.x_mm, y_mm=self.y_mm, z_mm=self.z_mm)

    @classmethod
    def load_npz(cls, path: str | Path) -> "HeightMap":
        """Read :meth:`save_npz`'s file; a missing, truncated or malformed one is a :class:`DataError`
        naming it."""
        import zipfile
        import zlib

        try:
            with open(path, "rb") as fh, np.load(fh, allow_pickle=False) as f:
                return cls(f["x_mm"], f["y_mm"], f["z_mm"])
        except DataError as exc:
            raise DataError(f"height map file {path}: {exc}") from None
        except (OSError, KeyError, ValueError, EOFError, zipfile.BadZipFile, zlib.error) as exc:
            raise DataError(f"height map file {path}: unreadable or truncated ({type(exc).__name__})") from None
