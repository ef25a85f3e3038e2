"""The monocular TacTip twin's camera frame (:mod:`twin.tactip`): the pin-tip markers projected and drawn.

Rendering: each marker is a disc (the pin tip) facing along its pin; its outline is projected through the
camera (OpenCV model, distortion included; the flat acrylic window's refraction is folded into the fitted
intrinsics), filled at 4x supersampling, blurred by the edge width, shaded and noised. Appearance numbers
come from the design's ``[twin]`` section.
"""

from __future__ import annotations

import cv2
import numpy as np

from pipeline.design import SensorDesign

__all__ = ["SUPERSAMPLE", "camera_extrinsics", "project_markers", "render_frame"]

SUPERSAMPLE = 4          # markers are filled on a grid this many times finer, then area-averaged


def camera_extrinsics(design: SensorDesign) -> tuple[np.ndarray, np.ndarray]:
    """OpenCV rvec, tvec (camera_from_sensor) of a monocular design's camera."""
    T = np.linalg.inv(design.camera_pose())
    rvec, _ = cv2.Rodrigues(T[:3, :3])
    return rvec.ravel(), T[:3, 3].copy()


def project_markers(design: SensorDesign, points_mm: np.ndarray) -> np.ndarray:
    """Image positions (N, 2) px of sensor-frame points through the design's camera."""
    rvec, tvec = camera_extrinsics(design)
    uv, _ = cv2.projectPoints(np.asarray(points_mm, np.float64).reshape(-1, 1, 3), rvec, tvec,
                              design.camera.K, design.camera.D)
    return uv.reshape(-1, 2)


def render_frame(design: SensorDesign, centres: np.ndarray, axes: np.ndarray, *,
                 seed: int = 0, n_outline: int = 16) -> np.ndarray:
    """The camera's 8-bit grey frame of the markers (discs of the design's marker diameter x
    ``marker_scale`` at ``centres``, facing along ``axes``)."""
    cam = design.camera
    tp = design.twin_params()
    w, h = cam.width_px, cam.height_px
    rad = 0.5 * design.markers.diameter_mm * tp["marker_scale"]
    # outline of each disc: two unit vectors spanning its plane
    a = np.asarray(axes, np.float64)
    ref = np.where(np.abs(a[:, [2]]) < 0.9, np.array([[0.0, 0.0, 1.0]]), np.array([[1.0, 0.0, 0.0]]))
    e1 = np.cross(a, ref)
    e1 /= np.linalg.norm(e1, axis=1, keepdims=True)
    e2 = np.cross(a, e1)
    t = 2 * np.pi * np.arange(n_outline) / n_outline
    ring = (centres[:, None, :] + rad * (np.cos(t)[None, :, None] * e1[:, None, :]
                                         + np.sin(t)[None, :, None] * e2[:, None, :]))
    uv = project_markers(design, ring.reshape(-1, 3)).reshape(len(centres), n_outline, 2)
    uvc = project_markers(design, centres)
    # camera-frame depth: draw far markers first
    T = np.linalg.inv(design.camera_pose())
    depth = (centres @ T[:3, :3].T + T[:3, 3])[:, 2]
    rho2 = ((uvc[:, 0] - cam.cx_px) ** 2 + (uvc[:, 1] - cam.cy_px) ** 2) / (0.5 * h) ** 2
    grey = np.clip(tp["marker_grey"] * (1.0 + tp["marker_shading"] * rho2), 0, 255)
    S = SUPERSAMPLE
    canvas = np.full((h * S, w * S), 0, np.uint8)
    shift = 4
    for k in np.argsort(-depth):
        if depth[k] <= 0:
            continue
        poly = np.rint((uv[k] + 0.5) * S * (1 << shift) - 0.5 * (1 << shift)).astype(np.int32)
        cv2.fillPoly(canvas, [poly], int(round(grey[k])), lineType=cv2.LINE_8, shift=shift)
    img = cv2.resize(canvas.astype(np.float32), (w, h), interpolation=cv2.INTER_AREA)
    mask = cv2.resize((canvas > 0).astype(np.float32), (w, h), interpolation=cv2.INTER_AREA)
    if tp["edge_px"] > 0.05:
        img = cv2.GaussianBlur(img, (0, 0), tp["edge_px"])
        mask = cv2.GaussianBlur(mask, (0, 0), tp["edge_px"])
    img = img + tp["background_grey"] * (1.0 - mask)
    if tp["noise_grey"] > 0:
        img = img + np.random.default_rng(seed).normal(0.0, tp["noise_grey"], img.shape)
    return np.clip(np.rint(img), 0, 255).astype(np.uint8)
