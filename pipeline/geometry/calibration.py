"""Stage 2: chessboard stereo calibration and rectification.

The paper calibrates with a 9x7-square alumina chessboard (4 mm squares, 20 pairs, skin module
removed; RMS 0.12 px). Chessboard calibration recovers the two cameras and their relative pose but
cannot know where the sensor frame is, so ``sensor_from_left`` always comes from the design's nominal
camera pose (:meth:`pipeline.design.SensorDesign.camera_poses`).

References
----------
StereoTacTip paper, Sec. "Camera Calibration", Table II.
"""

from __future__ import annotations

import hashlib
from dataclasses import dataclass, field
from typing import Iterable, Sequence

import cv2
import numpy as np

from pipeline.types import CalibrationError, StereoCalibration, StereoFrame

__all__ = ["find_board", "board_points_mm", "calibrate_stereo", "CalibrationReport", "Rectification",
           "rectification", "MIN_PAIRS"]

MIN_PAIRS = 3  # a camera needs >= 3 views of a planar target to fix its intrinsics and distortion


def _grey(image: np.ndarray) -> np.ndarray:
    img = np.asarray(image)
    if img.dtype != np.uint8:
        raise CalibrationError(f"find_board: expected a uint8 image, got {img.dtype}")
    if img.ndim == 3:
        img = cv2.cvtColor(img, cv2.COLOR_BGR2GRAY)
    return img


def find_board(image: np.ndarray, board_squares: tuple[int, int] = (9, 7)) -> np.ndarray | None:
    """Find the inner chessboard corners in one camera image.

    Parameters
    ----------
    image : (H, W) or (H, W, 3) uint8
        One camera image (grey or BGR).
    board_squares : (cols, rows)
        Squares of the board; the inner-corner grid is (cols - 1, rows - 1), 8x6 for the 9x7 board.

    Returns
    -------
    (M, 2) float64 corner pixels (u, v) in OpenCV's row-major order, or None when the full board is
    not visible.
    """
    cols, rows = board_squares
    if cols < 3 or rows < 3:
        raise CalibrationError(f"board_squares {board_squares}: need at least 3x3 squares")
    grey = _grey(image)
    pattern = (cols - 1, rows - 1)
    found, corners = cv2.findChessboardCornersSB(grey, pattern, flags=cv2.CALIB_CB_ACCURACY)
    if not found:
        found, corners = cv2.findChessboardCorners(grey, pattern, flags=cv2.CALIB_CB_ADAPTIVE_THRESH
                                                   | cv2.CALIB_CB_NORMALIZE_IMAGE)
        if not found:
            return None
        corners = cv2.cornerSubPix(grey, corners, (5, 5), (-1, -1),
                                   (cv2.TERM_CRITERIA_EPS | cv2.TERM_CRITERIA_COUNT, 50, 1e-4))
    pts = corners.reshape(-1, 2).astype(np.float64)
    # An 8x6 inner-corner grid (both even) is symmetric under a 180 degree turn, so the detector may
    # return it in either order. Canonical order: the first row runs toward +u (its direction within
    # (-90, 90] degrees of the image's u axis). A stereo pair is made consistent in calibrate_stereo.
    return _orient_rows_toward_u(pts, pattern[0])


def _row_direction(pts: np.ndarray, per_row: int) -> np.ndarray:
    """Direction of the first corner row, (2,) px: last corner of row 0 minus the first."""
    return pts[per_row - 1] - pts[0]


def _orient_rows_toward_u(pts: np.ndarray, per_row: int) -> np.ndarray:
    d = _row_direction(pts, per_row)
    if d[0] < 0 or (d[0] == 0 and d[1] < 0):
        pts = pts[::-1].copy()
    return pts


def board_points_mm(board_squares: tuple[int, int] = (9, 7), square_mm: float = 4.0) -> np.ndarray:
    """Inner-corner positions on the board plane, (M, 3) float64 mm, z = 0, OpenCV corner order."""
    cols, rows = board_squares[0] - 1, board_squares[1] - 1
    gx, gy = np.meshgrid(np.arange(cols), np.arange(rows))
    return np.column_stack([gx.ravel(), gy.ravel(), np.zeros(cols * rows)]) * square_mm


@dataclass(frozen=True)
class CalibrationReport:
    """What :func:`calibrate_stereo` measured.

    ``rms_px`` stereo RMS reprojection error; ``rms_left_px`` / ``rms_right_px`` per-camera RMS;
    ``per_pair_rms_px`` {pair name: RMS over both views}; ``baseline_mm`` |T|; ``used`` pair names;
    ``skipped`` {pair name: reason} for pairs where the board was not found.
    """

    rms_px: float
    rms_left_px: float
    rms_right_px: float
    per_pair_rms_px: dict[str, float]
    baseline_mm: float
    used: tuple[str, ...]
    skipped: dict[str, str] = field(default_factory=dict)

    def summary(self) -> str:
        lines = [f"stereo RMS {self.rms_px:.3f} px (left {self.rms_left_px:.3f}, right {self.rms_right_px:.3f}); "
                 f"baseline {self.baseline_mm:.3f} mm; {len(self.used)} pairs used, {len(self.skipped)} skipped"]
        for name, rms in self.per_pair_rms_px.items():
            lines.append(f"  {name}: {rms:.3f} px")
        for name, why in self.skipped.items():
            lines.append(f"  skipped {name}: {why}")
        return "\n".join(lines)


def _as_pair(item) -> tuple[str, np.ndarray, np.ndarray]:
    if isinstance(item, StereoFrame):
        return item.source or f"frame {item.index}", item.left, item.right
    if isinstance(item, tuple) and len(item) == 3:
        return str(item[0]), np.asarray(item[1]), np.asarray(item[2])
    if isinstance(item, tuple) and len(item) == 2:
        return "", np.asarray(item[0]), np.asarray(item[1])
    raise CalibrationError("calibrate_stereo: each pair must be a StereoFrame, (left, right) or (name, left, right)")


def _view_rms(obj, img_pts, K, D, rvec, tvec) -> float:
    proj, _ = cv2.projectPoints(obj, rvec, tvec, K, D)
    return float(np.sqrt(np.mean(np.sum((proj.reshape(-1, 2) - img_pts) ** 2, axis=1))))


def calibrate_stereo(pairs: Iterable, *, board_squares: tuple[int, int] = (9, 7), square_mm: float = 4.0,
                     sensor_from_left: np.ndarray | None = None) -> tuple[StereoCalibration, CalibrationReport]:
    """Calibrate a stereo pair from chessboard views.

    Parameters
    ----------
    pairs : iterable of StereoFrame, (left, right) or (name, left, right)
        Chessboard views; left/right are uint8 images of one camera each.
    board_squares : (cols, rows)
        Squares of the board (9x7 in the paper, i.e. 8x6 inner corners).
    square_mm : float
        Side of one square, mm.
    sensor_from_left : (4, 4), optional
        Pose of the left camera in the sensor frame (use the design's nominal pose); identity if None.

    Returns
    -------
    (StereoCalibration, CalibrationReport)
        ``cv2.calibrateCamera`` per camera, then ``cv2.stereoCalibrate`` with ``CALIB_FIX_INTRINSIC``.

    Raises
    ------
    CalibrationError
        Fewer than :data:`MIN_PAIRS` pairs show the whole board in both views (the message names the
        skipped pairs), or images of different sizes.

    Notes
    -----
    Runs with OpenCV (and BLAS) at one thread (:func:`pipeline.threads.one_thread`): with OpenCV's thread pool the
    same 20 chessboard pairs calibrated to an RMS and focal lengths that differed from run to run in the tenth to
    eighth significant digit (measured on the twin's renders), enough to move benchmark figures downstream; at one
    thread every run gives the same numbers.
    """
    from pipeline.threads import one_thread

    with one_thread():
        return _calibrate_stereo(pairs, board_squares, square_mm, sensor_from_left)


def _calibrate_stereo(pairs: Iterable, board_squares: tuple[int, int], square_mm: float,
                      sensor_from_left: np.ndarray | None) -> tuple[StereoCalibration, CalibrationReport]:
    if not square_mm > 0:
        raise CalibrationError(f"square_mm must be > 0, got {square_mm}")
    obj = board_points_mm(board_squares, square_mm).astype(np.float32)
    used, skipped, pts_l, pts_r = [], {}, [], []
    size = None
    for i, item in enumerate(pairs):
        name, left, right = _as_pair(item)
        name = name or f"pair {i}"
        if left.shape[:2] != right.shape[:2]:
            raise CalibrationError(f"{name}: left {left.shape[:2]} and right {right.shape[:2]} image sizes differ")
        s = (left.shape[1], left.shape[0])
        if size is None:
            size = s
        elif s != size:
            raise CalibrationError(f"{name}: image size {s} differs from the first pair's {size}")
        cl, cr = find_board(left, board_squares), find_board(right, board_squares)
        if cl is None or cr is None:
            which = "both views" if cl is None and cr is None else ("left view" if cl is None else "right view")
            skipped[name] = f"{board_squares[0]}x{board_squares[1]} board not found in the {which}"
            continue
        # The two cameras of a near-parallel rig see the board turned alike: if the canonical orders
        # still disagree (rows close to vertical in the image), turn the right view's order round.
        per_row = board_squares[0] - 1
        if float(_row_direction(cl, per_row) @ _row_direction(cr, per_row)) < 0:
            cr = cr[::-1].copy()
        used.append(name)
        pts_l.append(cl.astype(np.float32))
        pts_r.append(cr.astype(np.float32))
    if len(used) < MIN_PAIRS:
        names = ", ".join(skipped) or "none"
        raise CalibrationError(f"calibrate_stereo: only {len(used)} usable pair(s), need at least {MIN_PAIRS} "
                               f"(board {board_squares[0]}x{board_squares[1]} squares not found in: {names})")
    objs = [obj] * len(used)
    crit = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 200, 1e-12)
    rms_l, K1, D1, rv_l, tv_l = cv2.calibrateCamera(objs, pts_l, size, None, None, criteria=crit)
    rms_r, K2, D2, rv_r, tv_r = cv2.calibrateCamera(objs, pts_r, size, None, None, criteria=crit)
    rms, K1, D1, K2, D2, R, T, _E, _F = cv2.stereoCalibrate(
        objs, pts_l, pts_r, K1, D1, K2, D2, size, flags=cv2.CALIB_FIX_INTRINSIC, criteria=crit)
    per_pair = {}
    for k, name in enumerate(used):
        e_l = _view_rms(obj, pts_l[k].astype(np.float64), K1, D1, rv_l[k], tv_l[k])
        # right view through the stereo extrinsics: right_from_board = [R|T] @ left_from_board
        R_lb, _ = cv2.Rodrigues(rv_l[k])
        R_rb = R @ R_lb
        t_rb = R @ tv_l[k].reshape(3) + T.reshape(3)
        e_r = _view_rms(obj, pts_r[k].astype(np.float64), K2, D2, cv2.Rodrigues(R_rb)[0], t_rb)
        per_pair[name] = float(np.sqrt(0.5 * (e_l**2 + e_r**2)))
    calib = StereoCalibration(K1=K1, D1=D1.reshape(-1)[:5], K2=K2, D2=D2.reshape(-1)[:5], R=R, T=T.reshape(3),
                              image_size=size, sensor_from_left=np.eye(4) if sensor_from_left is None
                              else sensor_from_left, rms_px=float(rms))
    report = CalibrationReport(rms_px=float(rms), rms_left_px=float(rms_l), rms_right_px=float(rms_r),
                               per_pair_rms_px=per_pair, baseline_mm=calib.baseline_mm, used=tuple(used),
                               skipped=skipped)
    return calib, report


@dataclass(frozen=True)
class Rectification:
    """``cv2.stereoRectify`` output for one calibration.

    ``R1``, ``R2`` (3, 3) rectified_from_camera rotations; ``P1``, ``P2`` (3, 4) rectified projections
    (P2[0, 3] = -f b); ``Q`` (4, 4) disparity-to-depth; ``maps_left`` / ``maps_right`` the
    ``cv2.initUndistortRectifyMap`` (map_x, map_y) float32 pairs (None when built without maps).
    """

    R1: np.ndarray
    R2: np.ndarray
    P1: np.ndarray
    P2: np.ndarray
    Q: np.ndarray
    maps_left: tuple[np.ndarray, np.ndarray] | None = None
    maps_right: tuple[np.ndarray, np.ndarray] | None = None

    def rectify(self, frame: StereoFrame) -> tuple[np.ndarray, np.ndarray]:
        """Rectified (left, right) images of one frame (needs the maps)."""
        if self.maps_left is None or self.maps_right is None:
            raise CalibrationError("Rectification was built without maps; call rectification(calib, with_maps=True)")
        left = cv2.remap(frame.left, *self.maps_left, cv2.INTER_LINEAR)
        right = cv2.remap(frame.right, *self.maps_right, cv2.INTER_LINEAR)
        return left, right


_CACHE: dict[tuple[bytes, bool], Rectification] = {}
_CACHE_MAX = 8


def _key(calib: StereoCalibration) -> bytes:
    h = hashlib.sha1()
    for a in (calib.K1, calib.D1, calib.K2, calib.D2, calib.R, calib.T):
        h.update(np.ascontiguousarray(a).tobytes())
    h.update(np.asarray(calib.image_size, dtype=np.int64).tobytes())
    return h.digest()


def rectification(calib: StereoCalibration, *, with_maps: bool = True) -> Rectification:
    """Rectifying transforms (``cv2.stereoRectify`` with ``CALIB_ZERO_DISPARITY``, alpha 0), cached per
    calibration; maps from ``cv2.initUndistortRectifyMap`` when ``with_maps``."""
    key = (_key(calib), with_maps)
    hit = _CACHE.get(key) or (_CACHE.get((key[0], True)) if not with_maps else None)
    if hit is not None:
        return hit
    R1, R2, P1, P2, Q, _roi1, _roi2 = cv2.stereoRectify(calib.K1, calib.D1, calib.K2, calib.D2, calib.image_size,
                                                        calib.R, calib.T.reshape(3, 1),
                                                        flags=cv2.CALIB_ZERO_DISPARITY, alpha=0)
    maps_l = maps_r = None
    if with_maps:
        maps_l = cv2.initUndistortRectifyMap(calib.K1, calib.D1, R1, P1, calib.image_size, cv2.CV_32FC1)
        maps_r = cv2.initUndistortRectifyMap(calib.K2, calib.D2, R2, P2, calib.image_size, cv2.CV_32FC1)
    rect = Rectification(R1, R2, P1, P2, Q, maps_l, maps_r)
    if len(_CACHE) >= _CACHE_MAX:
        _CACHE.pop(next(iter(_CACHE)))
    _CACHE[key] = rect
    return rect


def pairs_from_frames(frames: Sequence[StereoFrame]) -> list[tuple[str, np.ndarray, np.ndarray]]:
    """(name, left, right) triples from concatenated frames (convenience for the CLI)."""
    return [(f.source or f"frame {f.index}", f.left, f.right) for f in frames]
