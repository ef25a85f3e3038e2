"""Analytic synthetic inputs for the geometry tests.

Stereo marker frames come from the product's own :mod:`pipeline.io.synthetic` (re-exported here);
chessboard views for calibration are rendered analytically: every pixel (2x2 supersampled) is
undistorted to a viewing ray, intersected with the board plane and coloured by its square.
"""

from __future__ import annotations

import math

import cv2
import numpy as np

from pipeline.io.synthetic import gaussian_press_markers, nominal_calibration, synth_stereo_frame
from pipeline.geometry.triangulation import UNDISTORT_CRITERIA, camera_poses
from pipeline.types import StereoCalibration

__all__ = ["nominal_calibration", "synth_stereo_frame", "gaussian_press_markers", "render_chessboard",
           "chessboard_pairs", "rot_xyz"]

_SUPER = 2
_GRID_CACHE: dict[bytes, np.ndarray] = {}


def rot_xyz(ax_deg: float, ay_deg: float, az_deg: float) -> np.ndarray:
    """Rotation Rz @ Ry @ Rx (3, 3) from angles in degrees."""
    a, b, c = (math.radians(v) for v in (ax_deg, ay_deg, az_deg))
    Rx = np.array([[1, 0, 0], [0, math.cos(a), -math.sin(a)], [0, math.sin(a), math.cos(a)]])
    Ry = np.array([[math.cos(b), 0, math.sin(b)], [0, 1, 0], [-math.sin(b), 0, math.cos(b)]])
    Rz = np.array([[math.cos(c), -math.sin(c), 0], [math.sin(c), math.cos(c), 0], [0, 0, 1]])
    return Rz @ Ry @ Rx


def _normalized_grid(K: np.ndarray, D: np.ndarray, size: tuple[int, int]) -> np.ndarray:
    key = K.tobytes() + D.tobytes() + bytes(str(size), "ascii")
    if key not in _GRID_CACHE:
        w, h = size
        offs = (np.arange(_SUPER) + 0.5) / _SUPER - 0.5
        u = (np.arange(w)[None, :, None] + offs[None, None, :]).repeat(h, 0)
        v = (np.arange(h)[:, None, None] + offs[None, None, :]).repeat(w, 1)
        uu = np.broadcast_to(u[:, :, :, None], (h, w, _SUPER, _SUPER))
        vv = np.broadcast_to(v[:, :, None, :], (h, w, _SUPER, _SUPER))
        px = np.stack([uu, vv], axis=-1).reshape(-1, 1, 2).astype(np.float64)
        xy = cv2.undistortPoints(px, K, D, criteria=UNDISTORT_CRITERIA).reshape(h, w, _SUPER * _SUPER, 2)
        _GRID_CACHE[key] = xy
    return _GRID_CACHE[key]


def render_chessboard(K: np.ndarray, D: np.ndarray, cam_from_board: np.ndarray, *, size=(640, 480),
                      board_squares=(9, 7), square_mm=4.0) -> np.ndarray:
    """Grey image (H, W) uint8 of a chessboard seen by a distorted camera.

    The board frame has the inner corner (0, 0) at its origin and inner corners at (i, j) * square_mm,
    matching :func:`pipeline.geometry.calibration.board_points_mm`; a one-square white margin surrounds it.
    """
    xy = _normalized_grid(K, D, size)
    R, t = cam_from_board[:3, :3], cam_from_board[:3, 3]
    d = np.concatenate([xy, np.ones(xy.shape[:-1] + (1,))], axis=-1)
    n = R[:, 2]
    s = (n @ t) / (d @ n)
    Xc = s[..., None] * d
    Xb = (Xc - t) @ R
    bx, by = Xb[..., 0] / square_mm, Xb[..., 1] / square_mm
    cols, rows = board_squares
    on_board = (bx >= -1) & (bx < cols - 1) & (by >= -1) & (by < rows - 1)
    margin = (bx >= -2) & (bx < cols) & (by >= -2) & (by < rows)
    dark = ((np.floor(bx) + np.floor(by)) % 2 == 0) & on_board
    val = np.where(margin, 215.0, 110.0)
    val = np.where(dark, 35.0, val)
    val = np.where(s > 0, val, 110.0)
    return np.clip(val.mean(axis=-1), 0, 255).astype(np.uint8)


def chessboard_pairs(calib: StereoCalibration, n_pairs: int, rng: np.random.Generator, *,
                     board_squares=(9, 7), square_mm=4.0, in_plane_deg: float = 0.0,
                     in_plane_spread_deg: float = 20.0) -> list[tuple[str, np.ndarray, np.ndarray]]:
    """``n_pairs`` (name, left, right) views of a board at 38-55 mm, tilted up to ±25° and turned in its
    plane by ``in_plane_deg`` ± ``in_plane_spread_deg``, seen by both cameras of ``calib`` (poses of the
    left camera frame; the right view uses R, T)."""
    cols, rows = board_squares
    centre_b = np.array([(cols - 2) / 2 * square_mm, (rows - 2) / 2 * square_mm, 0.0])
    out = []
    left_from_right = np.linalg.inv(camera_poses(calib)[0]) @ camera_poses(calib)[1]
    mid_x = left_from_right[0, 3] / 2
    for k in range(n_pairs):
        R = rot_xyz(rng.uniform(-25, 25), rng.uniform(-25, 25),
                    in_plane_deg + rng.uniform(-in_plane_spread_deg, in_plane_spread_deg))
        c = np.array([mid_x + rng.uniform(-4, 4), rng.uniform(-3, 3), rng.uniform(38, 55)])
        T = np.eye(4)
        T[:3, :3] = R
        T[:3, 3] = c - R @ centre_b
        right_from_board = np.linalg.inv(left_from_right) @ T
        left = render_chessboard(calib.K1, calib.D1, T, size=calib.image_size, board_squares=board_squares,
                                 square_mm=square_mm)
        right = render_chessboard(calib.K2, calib.D2, right_from_board, size=calib.image_size,
                                  board_squares=board_squares, square_mm=square_mm)
        out.append((f"pair{k:02d}", left, right))
    return out
