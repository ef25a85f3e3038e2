"""Photometry: what the surfaces look like and how the sensor records their light.

Albedos of every surface (B, G, R order: OpenGL is given BGR colours, so the read-back RGB buffer is
already BGR), the LED shading (four point LEDs under the acrylic, irradiance on the marker plane) and
vignetting per output pixel, then per frame a Gaussian blur (σ = ``BLUR_SIGMA_PX``) and shot + read
noise seeded from the caller's rng.
"""

from __future__ import annotations

import cv2
import numpy as np

from pipeline.design import SensorDesign
from twin.optics import FlatStack, trace_forward


def _albedo(*bgr: float) -> tuple[float, float, float]:
    """An albedo as the 8-bit GL colour buffer stores it (k/255), so that references can use it exactly."""
    return tuple(round(255.0 * c) / 255.0 for c in bgr)


# Appearance. Albedos are floats in [0, 1], BGR order, snapped to k/255 (the render buffer is 8-bit: an
# unsnapped 0.06 would be stored as 15/255, 2 % darker than a reference computed with 0.06).
MARKER_BGR = _albedo(0.97, 0.90, 0.80)          # white paint, bluish under white LEDs (real frames)
MARKER_SIDE_BGR = _albedo(0.80, 0.74, 0.66)     # the marker's cylinder wall, less directly lit
PIN_BGR = _albedo(0.04, 0.035, 0.035)
SKIN_BGR = _albedo(0.075, 0.06, 0.06)           # black Agilus underside, slightly lifted by scatter
MOUNT_BGR = _albedo(0.72, 0.82, 0.86)           # cream mount around the gel
LED_BGR = (1.0, 1.0, 1.0)
BOARD_BLACK_BGR = _albedo(0.06, 0.06, 0.06)
BOARD_WHITE_BGR = _albedo(0.86, 0.86, 0.86)
BACKGROUND_BGR = _albedo(0.02, 0.02, 0.02)
LAB_BACKGROUND_BGR = _albedo(0.30, 0.30, 0.30)  # skin-less calibration: the lab behind the board

BLUR_SIGMA_PX = 0.8                      # optics + demosaicing blur of a cheap M12 lens (brief: 0.6-1 px)
SEAM_BLUR_RADIUS_PX = 4                  # >= the radius of OpenCV's float kernel for σ = 0.8 (ksize 7 -> 3)
SHOT_GAIN_DN_PER_E = 0.06                # DN per photo-electron: σ_shot = sqrt(0.06·I) ≈ 3.5 DN at 200 DN
READ_NOISE_DN = 1.5
VIGNETTE_POWER = 2.0                     # relative illumination cos^p(field angle)
LED_COUNT = 4
LED_RADIAL_GAP_MM = 2.5                  # LEDs sit this far outside the gel rim, just under the acrylic
LED_GAMMA = 0.35                         # compresses the 1/d^4 point-LED falloff (the gel diffuses light)
LED_SHADING_RANGE = (0.75, 1.2)


def led_positions(design: SensorDesign) -> np.ndarray:
    """The four LEDs (LED_COUNT, 3), sensor frame mm: just outside the gel rim, under the acrylic."""
    d = design
    r = d.gel.radius_mm + LED_RADIAL_GAP_MM
    ang = np.deg2rad(45.0 + 360.0 / LED_COUNT * np.arange(LED_COUNT))
    return np.column_stack([r * np.cos(ang), r * np.sin(ang), np.full(LED_COUNT, d.acrylic_air_z_mm - 0.5)])


def shading_maps(design: SensorDesign, stack: FlatStack, pose: np.ndarray,
                 xy_ideal: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Per output pixel: (LED shading × vignetting, vignetting), each (H, W, 1) float32 (at render scale).

    ``xy_ideal`` (H, W, 2): the ideal normalised ray of each output pixel of the camera at ``pose``.
    """
    d = design
    H, W = xy_ideal.shape[:2]
    rays_cam = np.concatenate([xy_ideal, np.ones((H, W, 1))], axis=2).reshape(-1, 3)
    cos_field = 1.0 / np.linalg.norm(rays_cam, axis=1)
    vignette = cos_field**VIGNETTE_POWER
    d_sensor = rays_cam @ pose[:3, :3].T
    z_marker = -d.marker_depth_mm
    pts, _ = trace_forward(pose[:3, 3], d_sensor, stack, z_marker)
    leds = led_positions(d)
    E = np.zeros(len(pts))
    for L in leds:
        v = pts - L
        d2 = np.sum(v * v, axis=1)
        E += v[:, 2] ** 2 / d2**2            # Lambertian LED (cos) × Lambertian face (cos) / d²
    centre = np.array([[0.0, 0.0, z_marker]])
    E0 = sum(float((centre[0, 2] - L[2]) ** 2 / np.sum((centre[0] - L) ** 2) ** 2) for L in leds)
    led = np.clip((E / E0) ** LED_GAMMA, *LED_SHADING_RANGE)
    module = (led * vignette).reshape(H, W, 1).astype(np.float32)
    lab = vignette.reshape(H, W, 1).astype(np.float32)
    return module, lab


class SensorResponse:
    """Blur and noise of the image sensor for (H, 2W) side-by-side pairs of views ``width_px`` wide."""

    def __init__(self, width_px: int, height_px: int) -> None:
        self._w = width_px
        self._noise_z = np.empty((height_px, 2 * width_px), np.float32)
        self._sigma_lut = np.sqrt(SHOT_GAIN_DN_PER_E * np.arange(256) + READ_NOISE_DN**2).astype(np.float32)[None]

    def apply(self, pair: np.ndarray, rng: np.random.Generator | None, scratch) -> np.ndarray:
        """Shaded float DN pair -> blurred 8-bit BGR pair, with noise drawn from ``rng`` (None: noise-free).

        ``scratch(name, shape, dtype)`` lends reusable buffers.
        """
        W = self._w
        img = cv2.GaussianBlur(pair, (0, 0), BLUR_SIGMA_PX, dst=scratch("blur", pair.shape, np.float32))
        # the pair was blurred as one image: redo the columns next to the seam from each view alone
        # (kernel radius r = SEAM_BLUR_RADIUS_PX; a 2r + 1 wide strip has the view's own edge handling)
        r = SEAM_BLUR_RADIUS_PX
        img[:, W - r:W] = cv2.GaussianBlur(np.ascontiguousarray(pair[:, W - 2 * r - 1:W]), (0, 0),
                                           BLUR_SIGMA_PX)[:, -r:]
        img[:, W:W + r] = cv2.GaussianBlur(np.ascontiguousarray(pair[:, W:W + 2 * r + 1]), (0, 0),
                                           BLUR_SIGMA_PX)[:, :r]
        if rng is None:
            return cv2.add(img, 0.0, dtype=cv2.CV_8U)
        # One normal field per frame shared by the channels of a pixel (a demosaiced Bayer sensor's
        # channels share most of their noise), scaled by the signal-dependent σ² = g·I + σ_read², I the
        # blurred level (σ looked up at the rounded level: |Δσ| ≤ g/(4σ) ≈ 0.004 DN). The field comes
        # from OpenCV's generator seeded by the caller's rng (one draw per frame): deterministic for a
        # seeded rng, different for different seeds, ~6x faster than numpy's normal sampler.
        cv2.setRNGSeed(int(rng.integers(0, 2**31 - 1)))
        cv2.randn(self._noise_z, 0.0, 1.0)
        level = cv2.convertScaleAbs(img, dst=scratch("level", img.shape, np.uint8))
        sigma = cv2.LUT(level, self._sigma_lut, dst=scratch("sigma", img.shape, np.float32))
        z3 = cv2.merge([self._noise_z, self._noise_z, self._noise_z], dst=scratch("z3", img.shape, np.float32))
        # the sum is saturate_cast straight to 8 bits: rounded to nearest, clipped to [0, 255]
        return cv2.add(img, cv2.multiply(z3, sigma, dst=z3), dtype=cv2.CV_8U)
