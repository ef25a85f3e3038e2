"""Data types passed between pipeline stages (and handed over by the twin).

Frozen dataclasses of numpy arrays, validated on construction: shape, dtype and finiteness. Empty
results keep their shape (``(0, 2)``, never ``None``). Units ride in names (``_mm``, ``_px``,
``_deg``, ``_s``). Pixels are OpenCV ``(u, v)`` = (column, row), origin at the centre of the top-left
pixel. 3-D output is in the sensor frame documented in :mod:`pipeline.design` (mm).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from pipeline.errors import UserError

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
]

FRAME_WIDTH_PX = 1280   # concatenated left | right
FRAME_HEIGHT_PX = 480


class DataError(UserError, ValueError):
    """An array handed to a data type has the wrong shape, dtype or non-finite values."""


def _arr(name: str, value, *, dtype, shape: tuple, finite: bool = True) -> np.ndarray:
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


def _same_len(owner: str, **arrays: np.ndarray) -> None:
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
        object.__setattr__(self, "xy_px", _arr("Blobs.xy_px", self.xy_px, dtype=np.float64, shape=(-1, 2)))
        object.__setattr__(self, "sigma_px", _arr("Blobs.sigma_px", self.sigma_px, dtype=np.float64, shape=(-1,)))
        object.__setattr__(self, "response", _arr("Blobs.response", self.response, dtype=np.float64, shape=(-1,)))
        _same_len("Blobs", xy_px=self.xy_px, sigma_px=self.sigma_px, response=self.response)

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
        object.__setattr__(self, "ids", _arr("MarkerMatches.ids", self.ids, dtype=np.int64, shape=(-1,)))
        object.__setattr__(self, "left_px", _arr("MarkerMatches.left_px", self.left_px, dtype=np.float64, shape=(-1, 2)))
        object.__setattr__(self, "right_px", _arr("MarkerMatches.right_px", self.right_px, dtype=np.float64, shape=(-1, 2)))
        object.__setattr__(self, "unmatched_ids", _arr("MarkerMatches.unmatched_ids", self.unmatched_ids,
                                                       dtype=np.int64, shape=(-1,)))
        _same_len("MarkerMatches", ids=self.ids, left_px=self.left_px, right_px=self.right_px)
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
        object.__setattr__(self, "ids", _arr("MarkerCloud.ids", self.ids, dtype=np.int64, shape=(-1,)))
        object.__setattr__(self, "xyz_mm", _arr("MarkerCloud.xyz_mm", self.xyz_mm, dtype=np.float64, shape=(-1, 3)))
        _same_len("MarkerCloud", ids=self.ids, xyz_mm=self.xyz_mm)

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
        object.__setattr__(self, "ids", _arr("SkinSurface.ids", self.ids, dtype=np.int64, shape=(-1,)))
        object.__setattr__(self, "xyz_mm", _arr("SkinSurface.xyz_mm", self.xyz_mm, dtype=np.float64, shape=(-1, 3)))
        object.__setattr__(self, "normals", _arr("SkinSurface.normals", self.normals, dtype=np.float64, shape=(-1, 3)))
        _same_len("SkinSurface", ids=self.ids, xyz_mm=self.xyz_mm, normals=self.normals)
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
        object.__setattr__(self, "x_mm", _arr("HeightMap.x_mm", self.x_mm, dtype=np.float64, shape=(-1,)))
        object.__setattr__(self, "y_mm", _arr("HeightMap.y_mm", self.y_mm, dtype=np.float64, shape=(-1,)))
        z = _arr("HeightMap.z_mm", self.z_mm, dtype=np.float64, shape=(len(self.y_mm), len(self.x_mm)), finite=False)
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


# ----- stereo calibration (OpenCV FileStorage YAML) ------------------------------------------

class CalibrationError(UserError, ValueError):
    """A calibration file is unreadable, incomplete or holds non-finite values."""


#: Physical-sense limits of a calibration (each camera of a tactile sensor, a few cm from its skin).
MAX_IMAGE_SIDE_PX = 16384
#: Focal length per image width: 0.05 is a 170 deg field of view, 100 a 0.6 deg telephoto.
FOCAL_PER_WIDTH_RANGE = (0.05, 100.0)
MAX_ABS_DISTORTION = 1e4
BASELINE_RANGE_MM = (0.1, 1000.0)
MAX_POSE_OFFSET_MM = 1e4
MAX_RMS_PX = 1e3


def lens_folds_over(K: np.ndarray, D: np.ndarray, size: tuple[int, int]) -> bool:
    """True if the radial lens model ``r_d = r (1 + k1 r^2 + k2 r^4 + k3 r^6)`` (OpenCV's, normalised
    coordinates) stops increasing before it reaches the image's farthest corner: then some pixels
    see no ray, or two rays, and undistortion has no unique answer (Newton diverges or lands on the
    wrong branch). Tangential terms are left out: at a few 1e-3 they do not change where it folds.
    Searched out to r = 20 (87 deg off axis; a pinhole model ends at 90 deg).

    Designs must pass it (the twin renders through the inverse model over the whole image). Measured
    calibrations are not held to it: a polynomial fitted to chessboard corners may fold just beyond
    the corners it saw (OpenCV's fit on the twin's chessboard set in tests/test_calibration.py does), and
    the pipeline's undistortion handles such pixels."""
    w, h = size
    cx, cy, fx, fy = K[0, 2], K[1, 2], K[0, 0], K[1, 1]
    corners = np.array([[0.0, 0.0], [w - 1.0, 0.0], [0.0, h - 1.0], [w - 1.0, h - 1.0]])
    rd_max = float(np.max(np.hypot((corners[:, 0] - cx) / fx, (corners[:, 1] - cy) / fy)))
    k1, k2, k3 = float(D[0]), float(D[1]), float(D[4])
    r = np.linspace(0.0, 20.0, 20001)
    r2 = r * r
    with np.errstate(over="ignore", invalid="ignore"):
        rd = r * (1.0 + r2 * (k1 + r2 * (k2 + r2 * k3)))
        slope = 1.0 + r2 * (3.0 * k1 + r2 * (5.0 * k2 + r2 * 7.0 * k3))
    reach = np.flatnonzero(rd >= rd_max)
    if len(reach) == 0:
        return True
    return bool(np.any(~(slope[: reach[0] + 1] > 0.0)))


def _is_rotation(R: np.ndarray) -> bool:
    return bool(np.allclose(R @ R.T, np.eye(3), atol=1e-6) and abs(np.linalg.det(R) - 1.0) < 1e-6)


def _check_intrinsics(key: str, K: np.ndarray, w: int, h: int) -> None:
    lo, hi = FOCAL_PER_WIDTH_RANGE[0] * w, FOCAL_PER_WIDTH_RANGE[1] * w
    for name, f in (("fx", K[0, 0]), ("fy", K[1, 1])):
        if not lo <= f <= hi:
            raise CalibrationError(f"{key}: focal length {name} = {f:.6g} px is outside [{lo:g}, {hi:g}] px "
                                   f"({FOCAL_PER_WIDTH_RANGE[0]:g}-{FOCAL_PER_WIDTH_RANGE[1]:g} x image_width {w})")
    if not (0.0 <= K[0, 2] <= w and 0.0 <= K[1, 2] <= h):
        raise CalibrationError(f"{key}: principal point ({K[0, 2]:.6g}, {K[1, 2]:.6g}) px lies outside the "
                               f"{w}x{h} image")
    if K[1, 0] != 0.0 or not np.allclose(K[2], [0.0, 0.0, 1.0], atol=1e-9) or abs(K[0, 1]) > 0.1 * K[0, 0]:
        raise CalibrationError(f"{key}: not an intrinsic matrix (needs [[fx s cx] [0 fy cy] [0 0 1]], "
                               f"|skew s| <= 0.1 fx)")


@dataclass(frozen=True)
class StereoCalibration:
    """Stereo calibration in OpenCV conventions (``cv2.stereoCalibrate``: X_right = R X_left + T).

    Parameters
    ----------
    K1, K2 : (3, 3) float64 intrinsics (px); D1, D2 : (5,) distortion (k1, k2, p1, p2, k3)
    R : (3, 3) rotation left→right; T : (3,) translation left→right, mm
    image_size : (width, height) of ONE camera image, px
    sensor_from_left : (4, 4) pose of the left camera in the sensor frame (mm); identity if unknown
    rms_px : RMS reprojection error reported by the calibration that produced this file (NaN unknown)
    """

    K1: np.ndarray
    D1: np.ndarray
    K2: np.ndarray
    D2: np.ndarray
    R: np.ndarray
    T: np.ndarray
    image_size: tuple[int, int] = (640, 480)
    sensor_from_left: np.ndarray = field(default_factory=lambda: np.eye(4))
    rms_px: float = float("nan")

    def __post_init__(self) -> None:
        for name, shape in (("K1", (3, 3)), ("K2", (3, 3)), ("D1", (5,)), ("D2", (5,)), ("R", (3, 3)),
                            ("T", (3,)), ("sensor_from_left", (4, 4))):
            try:
                value = np.asarray(getattr(self, name), dtype=np.float64)
            except (TypeError, ValueError):
                raise CalibrationError(f"StereoCalibration.{name}: expected numbers") from None
            if name in ("D1", "D2", "T"):
                value = value.reshape(-1)
            try:
                object.__setattr__(self, name, _arr(f"StereoCalibration.{name}", value, dtype=np.float64, shape=shape))
            except DataError as exc:
                raise CalibrationError(str(exc)) from None
        size = tuple(self.image_size) if isinstance(self.image_size, (tuple, list, np.ndarray)) else ()
        if len(size) != 2:
            raise CalibrationError(f"StereoCalibration.image_size: expected (width, height), got {self.image_size!r}")
        wh = []
        for key, v in zip(("image_width", "image_height"), size):
            try:
                f = float(v)
            except (TypeError, ValueError):
                raise CalibrationError(f"{key}: expected an integer number of pixels, got {v!r}") from None
            if not (math.isfinite(f) and f == int(f) and 1 <= f <= MAX_IMAGE_SIDE_PX):
                raise CalibrationError(f"{key}: must be an integer in [1, {MAX_IMAGE_SIDE_PX}] px, got {v!r}")
            wh.append(int(f))
        w, h = wh
        object.__setattr__(self, "image_size", (w, h))
        for cam in ("1", "2"):
            _check_intrinsics(f"K{cam}", self.__dict__[f"K{cam}"], w, h)
            d = self.__dict__[f"D{cam}"]
            if np.max(np.abs(d)) > MAX_ABS_DISTORTION:
                raise CalibrationError(f"D{cam}: distortion coefficients must lie in [-{MAX_ABS_DISTORTION:g}, "
                                       f"{MAX_ABS_DISTORTION:g}], got {d.tolist()}")
        if not _is_rotation(self.R):
            raise CalibrationError("R: not a rotation matrix (needs R R^T = I and det R = +1 within 1e-6)")
        b = float(np.linalg.norm(self.T))
        if not BASELINE_RANGE_MM[0] <= b <= BASELINE_RANGE_MM[1]:
            raise CalibrationError(f"T: baseline |T| = {b:.6g} mm is outside [{BASELINE_RANGE_MM[0]:g}, "
                                   f"{BASELINE_RANGE_MM[1]:g}] mm")
        P = self.sensor_from_left
        if not (np.allclose(P[3], [0.0, 0.0, 0.0, 1.0], atol=1e-9) and _is_rotation(P[:3, :3])
                and np.all(np.abs(P[:3, 3]) <= MAX_POSE_OFFSET_MM)):
            raise CalibrationError("sensor_from_left: not a rigid pose (needs a rotation block, last row "
                                   f"[0 0 0 1] and a translation within {MAX_POSE_OFFSET_MM:g} mm)")
        rms = float(self.rms_px)
        if not (math.isnan(rms) or 0.0 <= rms <= MAX_RMS_PX):
            raise CalibrationError(f"rms_px: must be in [0, {MAX_RMS_PX:g}] px (or unknown), got {self.rms_px!r}")

    def check_fits_frame(self, where: str = "calibration") -> None:
        """Raise :class:`CalibrationError` unless each camera image is one half of a 1280x480 frame."""
        want = (FRAME_WIDTH_PX // 2, FRAME_HEIGHT_PX)
        if tuple(self.image_size) != want:
            raise CalibrationError(f"{where}: image_width x image_height is {self.image_size[0]}x{self.image_size[1]}, "
                                   f"but each view of a {FRAME_WIDTH_PX}x{FRAME_HEIGHT_PX} stereo frame is "
                                   f"{want[0]}x{want[1]}")

    @property
    def baseline_mm(self) -> float:
        return float(np.linalg.norm(self.T))

    def save_yaml(self, path: str | Path) -> None:
        """Write OpenCV FileStorage YAML (readable with ``cv2.FileStorage(path, READ)``)."""
        import cv2

        from pipeline.io.atomic import atomic_write_text

        # built in memory, then written atomically: an interrupted write never leaves half a calibration
        fs = cv2.FileStorage(".yaml", cv2.FILE_STORAGE_WRITE | cv2.FILE_STORAGE_MEMORY)
        if not fs.isOpened():  # pragma: no cover - memory storage always opens
            raise CalibrationError(f"cannot write calibration file {path}")
        try:
            fs.write("image_width", int(self.image_size[0]))
            fs.write("image_height", int(self.image_size[1]))
            fs.write("K1", self.K1)
            fs.write("D1", self.D1.reshape(1, 5))
            fs.write("K2", self.K2)
            fs.write("D2", self.D2.reshape(1, 5))
            fs.write("R", self.R)
            fs.write("T", self.T.reshape(3, 1))
            fs.write("sensor_from_left", self.sensor_from_left)
            fs.write("rms_px", float(self.rms_px) if math.isfinite(self.rms_px) else -1.0)
            fs.write("units", "mm")
            # derived, for OpenCV users (as OpenCV's stereo_calib sample writes them); not read back:
            # essential / fundamental matrices and the rectification (stereoRectify, zero disparity, alpha 0)
            tx = np.array([[0, -self.T[2], self.T[1]], [self.T[2], 0, -self.T[0]], [-self.T[1], self.T[0], 0]])
            E = tx @ self.R
            F = np.linalg.inv(self.K2).T @ E @ np.linalg.inv(self.K1)
            fs.write("E", E)
            fs.write("F", F / F[2, 2] if abs(F[2, 2]) > 1e-12 else F)
            R1, R2, P1, P2, Q, _, _ = cv2.stereoRectify(self.K1, self.D1, self.K2, self.D2, tuple(self.image_size),
                                                        self.R, self.T.reshape(3, 1),
                                                        flags=cv2.CALIB_ZERO_DISPARITY, alpha=0)
            for key, val in (("R1", R1), ("R2", R2), ("P1", P1), ("P2", P2), ("Q", Q)):
                fs.write(key, val)
            text = fs.releaseAndGetString()
        finally:
            fs.release()
        try:
            atomic_write_text(path, text)
        except OSError as exc:
            raise CalibrationError(f"cannot write calibration file {path}: {exc.strerror or exc}") from None

    @classmethod
    def load_yaml(cls, path: str | Path) -> "StereoCalibration":
        """Read a file written by :meth:`save_yaml` (or by OpenCV with the same key names).

        Every way a file can be wrong is a :class:`CalibrationError` naming the file and the key:
        missing, empty, binary or not OpenCV YAML/JSON; a key missing, not a matrix of numbers, of the
        wrong shape or holding NaN/inf; values without physical sense (see ``__post_init__``).
        """
        import cv2

        path = Path(path)
        where = f"calibration file {path}"
        if not path.is_file():
            raise CalibrationError(f"{where} does not exist")
        try:
            raw = path.read_bytes()
        except OSError as exc:
            raise CalibrationError(f"{where}: cannot be read ({exc.strerror or exc})") from None
        if not raw.strip():
            raise CalibrationError(f"{where}: is empty")
        if len(raw) > MAX_CALIB_FILE_BYTES:
            raise CalibrationError(f"{where}: {len(raw)} bytes; a calibration file is a few kB "
                                   f"(limit {MAX_CALIB_FILE_BYTES} bytes)")
        try:
            text = raw.decode("utf-8")
        except UnicodeDecodeError:
            text = ""
        if not text or "\x00" in text:
            raise CalibrationError(f"{where}: not a text file (binary data); expected OpenCV YAML/JSON")
        # cv2.FileStorage fails on odd input with cv2.error, SystemError (a bare tag document) or
        # others; anything it raises means the same thing to the user
        unreadable = (cv2.error, SystemError, ValueError, TypeError, OverflowError)
        try:
            fs = cv2.FileStorage(str(path), cv2.FILE_STORAGE_READ)
            opened = fs.isOpened()
        except unreadable as exc:
            raise CalibrationError(f"{where}: not readable as OpenCV YAML/JSON ({_first_line(exc)})") from None
        if not opened:
            raise CalibrationError(f"{where}: not readable as OpenCV YAML/JSON")
        key = ""
        try:
            def node(k: str, required: bool = True):
                nonlocal key
                key = k
                n = fs.getNode(k)
                if n.empty() or n.isNone():
                    if required:
                        raise CalibrationError(f"{where}: missing key {k!r}")
                    return None
                return n

            def mat(k: str, required: bool = True):
                n = node(k, required)
                if n is None:
                    return None
                if not n.isMap():
                    raise CalibrationError(f"{where}: key {k!r} is not a matrix (expected !!opencv-matrix "
                                           f"with rows, cols, dt and data)")
                m = n.mat()
                if m is None or m.size == 0:
                    raise CalibrationError(f"{where}: key {k!r} is not a matrix")
                m = np.asarray(m, dtype=np.float64)
                if not np.all(np.isfinite(m)):
                    raise CalibrationError(f"{where}: key {k!r} contains NaN or inf")
                return m

            def num(k: str, required: bool = True):
                n = node(k, required)
                if n is None:
                    return None
                if not (n.isInt() or n.isReal()):
                    raise CalibrationError(f"{where}: key {k!r} must be a number, got {_node_text(n)}")
                return n.real()

            kw = {k: mat(k) for k in ("K1", "D1", "K2", "D2", "R", "T")}
            sfl = mat("sensor_from_left", required=False)
            rms = num("rms_px", required=False)
            size = (num("image_width"), num("image_height"))
        except CalibrationError:
            raise
        except unreadable as exc:
            raise CalibrationError(f"{where}: key {key!r} is not a readable matrix (rows x cols must match "
                                   f"the data, dt one of u, c, w, s, i, f, d: {_first_line(exc)})") from None
        finally:
            fs.release()
        if rms is None or rms == -1.0:  # save_yaml writes -1 for "unknown"
            rms = float("nan")
        try:
            return cls(**kw, image_size=size, sensor_from_left=np.eye(4) if sfl is None else sfl, rms_px=rms)
        except CalibrationError as exc:
            raise CalibrationError(f"{where}: {exc}") from None


MAX_CALIB_FILE_BYTES = 1 << 20


def _first_line(exc: BaseException) -> str:
    """The useful part of a library's message: OpenCV's ``error: (-215:...) what in function f``
    becomes ``what``; an exception without text gives its type name."""
    lines = str(exc).strip().splitlines()
    text = lines[-1] if lines else ""
    if "error: (" in text:
        text = text.split("error: (", 1)[1].split(")", 1)[-1].split(" in function ")[0].strip()
    if "returned a result with an exception set" in text or not text:
        text = "no key/value document"
    return text[:200]


def _node_text(n) -> str:
    try:
        if n.isString():
            return repr(n.string())[:60]
    except Exception:  # noqa: BLE001 - only for the message
        pass
    return "a non-numeric value"
