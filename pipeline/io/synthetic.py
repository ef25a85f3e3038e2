"""Analytic synthetic stereo frames (no physics, no renderer) for the latency benchmark and tests.

Markers at known 3-D positions are projected through the exact flat refraction stack
(:func:`pipeline.geometry.refraction.project_through_stack`) and drawn as anti-aliased bright discs on a dark
background with OpenCV. This is the pipeline's own analytic check; the digital twin (``twin/``) is
the independent, physically rendered one.
"""

from __future__ import annotations

import cv2
import numpy as np

from pipeline.design import SensorDesign
from pipeline.geometry.refraction import project_through_stack
from pipeline.types import FRAME_HEIGHT_PX, FRAME_WIDTH_PX, StereoCalibration, StereoFrame, nominal_calibration

__all__ = ["nominal_calibration", "synth_stereo_frame", "gaussian_press_markers", "disc_grid_image",
           "BACKGROUND_GREY", "MARKER_GREY"]

BACKGROUND_GREY = 25
MARKER_GREY = 225
_SHIFT_BITS = 4            # cv2 drawing sub-pixel precision: 1/16 px
_BLUR_SIGMA_PX = 0.7       # "a touch of blur": optics are never perfectly sharp


def gaussian_press_markers(design: SensorDesign, depth_mm: float, *, sigma_mm: float = 4.0,
                           centre_xy_mm: tuple[float, float] = (0.0, 0.0), lateral: float = 0.0) -> np.ndarray:
    """Rest markers displaced by an analytic Gaussian press, (N, 3) float64, sensor frame, mm.

    dz = -depth exp(-r^2 / 2 sigma^2) (toward the cameras); optional outward lateral displacement
    ``lateral * depth * (r / sigma) exp(-r^2 / 2 sigma^2)`` along the radial direction.
    """
    rest = design.rest_markers_mm()
    d = rest[:, :2] - np.asarray(centre_xy_mm, dtype=np.float64)
    r = np.hypot(d[:, 0], d[:, 1])
    g = np.exp(-0.5 * (r / sigma_mm) ** 2)
    out = rest.copy()
    out[:, 2] -= depth_mm * g
    with np.errstate(invalid="ignore", divide="ignore"):
        u = np.where(r[:, None] > 0, d / r[:, None], 0.0)
    out[:, :2] += (lateral * depth_mm * (r / sigma_mm) * g)[:, None] * u
    return out


def _marker_radii_px(design: SensorDesign, calib: StereoCalibration, xyz: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    r_mm = design.markers.diameter_mm / 2.0
    left, right = project_through_stack(xyz, calib, design)
    edge = xyz + np.array([r_mm, 0.0, 0.0])
    el, er = project_through_stack(edge, calib, design)
    edge_y = xyz + np.array([0.0, r_mm, 0.0])
    fl, fr = project_through_stack(edge_y, calib, design)
    rl = 0.5 * (np.linalg.norm(el - left, axis=1) + np.linalg.norm(fl - left, axis=1))
    rr = 0.5 * (np.linalg.norm(er - right, axis=1) + np.linalg.norm(fr - right, axis=1))
    return rl, rr


def _draw(shape: tuple[int, int], px: np.ndarray, radii: np.ndarray) -> np.ndarray:
    img = np.full(shape, BACKGROUND_GREY, dtype=np.uint8)
    scale = 1 << _SHIFT_BITS
    h, w = shape
    for (u, v), r in zip(px, radii):
        if not (-r <= u < w + r and -r <= v < h + r):
            continue
        cv2.circle(img, (int(round(u * scale)), int(round(v * scale))), max(int(round(r * scale)), 1),
                   MARKER_GREY, thickness=-1, lineType=cv2.LINE_AA, shift=_SHIFT_BITS)
    return img


def synth_stereo_frame(design: SensorDesign, calib: StereoCalibration, marker_xyz_mm: np.ndarray, *,
                       marker_radius_px: float | None = None, rng: np.random.Generator | None = None,
                       noise_grey: float = 2.0, index: int = 0, timestamp_s: float = 0.0) -> StereoFrame:
    """Draw markers at known 3-D positions into a 1280x480 grey stereo frame.

    Parameters
    ----------
    design : SensorDesign
        Optical stack and marker diameter.
    calib : StereoCalibration
        Cameras to project with (e.g. :func:`nominal_calibration`).
    marker_xyz_mm : (N, 3) float64
        Marker face centres in the gel, sensor frame, mm.
    marker_radius_px : float, optional
        Disc radius in px; default: the marker diameter projected through the stack at each marker.
    rng : numpy.random.Generator, optional
        If given, adds Gaussian pixel noise of ``noise_grey`` grey levels.

    Returns
    -------
    StereoFrame (grey), markers bright (225) on dark (25), Gaussian blur sigma 0.7 px.

    Notes
    -----
    Discs, not the true ellipses of oblique views: the centroid of a disc drawn at the projected centre
    is the projected centre, which is what the tests need. Markers are drawn at sub-pixel precision
    (1/16 px).
    """
    xyz = np.asarray(marker_xyz_mm, dtype=np.float64).reshape(-1, 3)
    left_px, right_px = project_through_stack(xyz, calib, design)
    if marker_radius_px is None:
        rl, rr = _marker_radii_px(design, calib, xyz)
    else:
        rl = rr = np.full(len(xyz), float(marker_radius_px))
    h, w = FRAME_HEIGHT_PX, FRAME_WIDTH_PX // 2
    halves = []
    for px, r in ((left_px, rl), (right_px, rr)):
        img = _draw((h, w), px, r)
        img = cv2.GaussianBlur(img, (0, 0), _BLUR_SIGMA_PX)
        if rng is not None and noise_grey > 0:
            img = np.clip(img + rng.normal(0.0, noise_grey, img.shape), 0, 255).astype(np.uint8)
        halves.append(img)
    return StereoFrame.from_pair(halves[0], halves[1], index=index, timestamp_s=timestamp_s, source="synthetic")


def disc_grid_image(radius_px: float, rng: np.random.Generator, *, noise: float = 0.0, value: int = 200,
                    pitch: int = 40, shape: tuple[int, int] = (480, 640)) -> tuple[np.ndarray, np.ndarray]:
    """A grey image of anti-aliased bright discs of ``radius_px`` on black, one per ``pitch``-px grid cell,
    each centre jittered uniformly by up to half a pixel; optional Gaussian noise of ``noise`` grey levels.

    Returns the uint8 image and the true centres (N, 2) px. ``cv2.circle`` (LINE_AA, 8 fractional bits)
    places a centre to 1/256 px, so the image of each disc has a known sub-pixel centre: the analytic check
    of the detector's centres.
    """
    pts = []
    for y in range(pitch, shape[0] - pitch // 2, pitch):
        for x in range(pitch, shape[1] - pitch // 2, pitch):
            pts.append(np.array([x, y]) + rng.uniform(-0.5, 0.5, 2))
    canvas = np.zeros(shape, np.uint8)
    for c in pts:
        cv2.circle(canvas, (int(round(c[0] * 256)), int(round(c[1] * 256))), int(round(radius_px * 256)),
                   value, -1, cv2.LINE_AA, 8)
    img = canvas.astype(np.float64) + (rng.normal(0, noise, shape) if noise else 0)
    return np.clip(np.rint(img), 0, 255).astype(np.uint8), np.asarray(pts)
