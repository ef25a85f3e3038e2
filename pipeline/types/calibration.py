"""Stereo calibration: :class:`StereoCalibration`, its physical-sense checks and its OpenCV FileStorage
YAML reading and writing."""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from pipeline.errors import UserError
from pipeline.types.frames import FRAME_HEIGHT_PX, FRAME_WIDTH_PX, DataError, checked_array

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
                object.__setattr__(self, name, checked_array(f"StereoCalibration.{name}", value,
                                                             dtype=np.float64, shape=shape))
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


def nominal_calibration(design) -> StereoCalibration:
    """The calibration the design's nominal cameras have: exactly the twin's cameras, and what a sensor
    built to its drawing would be calibrated to.

    K, D from ``design.cameras``; (R, T) with X_right = R X_left + T from the two nominal
    ``design.camera_poses()`` (sensor_from_camera); ``sensor_from_left`` = the nominal left pose;
    ``rms_px`` = 0. (``design``: a :class:`pipeline.design.SensorDesign`, read by attribute: the types sit
    below the design package and do not import it.)
    """
    poses = design.camera_poses()
    right_from_left = np.linalg.inv(poses["right"]) @ poses["left"]
    c = design.cameras
    return StereoCalibration(K1=c.left.K, D1=c.left.D, K2=c.right.K, D2=c.right.D, R=right_from_left[:3, :3],
                             T=right_from_left[:3, 3], image_size=(c.width_px, c.height_px),
                             sensor_from_left=poses["left"], rms_px=0.0)


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
