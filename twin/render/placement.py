"""Optics placement: where the scene appears to each camera, and where the cameras and boards are.

Every vertex behind the acrylic/gel stack is moved to its *apparent* position for one camera
(:func:`twin.optics.apparent_points`, exact Snell per vertex), so a plain pinhole render of the moved
mesh shows what the camera sees through the refracting stack; each camera has its own vertex buffers.
Also here: the calibration that is exactly true for the twin's cameras, and chessboard poses that are
fully in view of both (the skin-less calibration set-up).
"""

from __future__ import annotations

import math

import cv2
import numpy as np

from pipeline.design import SensorDesign
from pipeline.types import StereoCalibration, nominal_calibration
from twin.gl import RenderError
from twin.optics import FlatStack, apparent_points, project_exact
from twin.render.scene import ChessboardSpec, chessboard_corners_mm


def apparent(pts: np.ndarray, camera_centre: np.ndarray, stack: FlatStack, through_stack: bool) -> np.ndarray:
    """``pts`` (N, 3) where the camera at ``camera_centre`` sees them (unchanged when not behind the stack)."""
    # (a warm start from the previous frame's rays was measured: no gain, Newton needs ~4 steps anyway)
    if not through_stack:
        return pts
    return apparent_points(pts, camera_centre, stack)


def true_calibration(design: SensorDesign) -> StereoCalibration:
    """The stereo calibration that is exactly true for the twin's cameras (OpenCV conventions): the twin
    places its cameras at the design's nominal poses, so it is :func:`pipeline.types.nominal_calibration`."""
    return nominal_calibration(design)


def _board_in_view(design: SensorDesign, T: np.ndarray, spec: ChessboardSpec, margin_px: float) -> bool:
    pts = chessboard_corners_mm(spec)
    # add a ring of points half a square beyond the inner corners: the detector needs the outer squares
    cols, rows = spec.squares
    hx, hy = cols * spec.square_mm / 2.0, rows * spec.square_mm / 2.0
    outline = np.array([[sx * hx, sy * hy, 0.0] for sx in (-1, 1) for sy in (-1, 1)])
    P = np.vstack([pts, outline]) @ T[:3, :3].T + T[:3, 3]
    w, h = design.cameras.width_px, design.cameras.height_px
    for side, pose in design.camera_poses().items():
        depth = (P - pose[:3, 3]) @ pose[:3, 2]
        if np.any(depth <= 5.0):
            return False
        # the board faces the camera (its -z normal points toward the camera centre)
        normal = -T[:3, 2]
        if np.dot(pose[:3, 3] - T[:3, 3], normal) <= 0:
            return False
        uv = project_exact(P, design, side, through_stack=False)
        if np.any(uv < margin_px) or np.any(uv[:, 0] > w - 1 - margin_px) or np.any(uv[:, 1] > h - 1 - margin_px):
            return False
    return True


def chessboard_poses(n: int, rng: np.random.Generator, *, design: SensorDesign | None = None,
                     spec: ChessboardSpec = ChessboardSpec(), distance_mm: tuple[float, float] = (20.0, 60.0),
                     max_tilt_deg: float = 30.0, margin_px: float = 12.0) -> list[np.ndarray]:
    """``n`` varied chessboard poses (sensor_from_board, 4x4 mm) fully visible in both cameras.

    Board centre at a distance drawn uniformly from ``distance_mm`` above the midpoint of the cameras,
    shifted sideways, rotated about z by any angle and tilted up to ``max_tilt_deg`` about a random
    horizontal axis; poses whose board (corners plus outer squares) leaves either image by less than
    ``margin_px`` are redrawn. The default design is ``hexagon127``.
    """
    from pipeline.design import DEFAULT_DESIGN, load_design  # noqa: PLC0415

    if n < 0:
        raise RenderError(f"n: expected >= 0, got {n}")
    design = design if design is not None else load_design(DEFAULT_DESIGN)
    cam_z = design.camera_z_mm
    poses: list[np.ndarray] = []
    tries = 0
    while len(poses) < n:
        tries += 1
        if tries > 2000 * max(n, 1):
            raise RenderError(f"chessboard_poses: could not place {n} boards in view (distance {distance_mm} mm, "
                              f"tilt {max_tilt_deg} deg); widen the distance range")
        dist = rng.uniform(*distance_mm)
        half_w = 0.35 * dist
        centre = np.array([rng.uniform(-half_w, half_w), rng.uniform(-0.7 * half_w, 0.7 * half_w), cam_z + dist])
        yaw = rng.uniform(-np.pi, np.pi)
        tilt = np.deg2rad(max_tilt_deg) * math.sqrt(rng.uniform(0.0, 1.0))
        tilt_dir = rng.uniform(-np.pi, np.pi)
        axis = np.array([math.cos(tilt_dir), math.sin(tilt_dir), 0.0])
        Rz = np.array([[math.cos(yaw), -math.sin(yaw), 0], [math.sin(yaw), math.cos(yaw), 0], [0, 0, 1.0]])
        Rt = cv2.Rodrigues(axis * tilt)[0]
        T = np.eye(4)
        T[:3, :3] = Rt @ Rz
        T[:3, 3] = centre
        if _board_in_view(design, T, spec, margin_px):
            poses.append(T)
    return poses
