"""Independent checks of the two geometric cores against references written here from first principles.

* Refraction exists twice: the pipeline's correction (``pipeline.refraction.refract_stack_rays``: air
  rays carried forward through the planes with the vector Snell law) and the twin's optics
  (``twin.optics.solve_paths``: the ray parameter from camera to point by Newton's method). They share
  no refraction code (only ``pipeline.design`` for the stack's numbers); this file adds a third,
  scalar Snell trace by bisection that reads only the design's raw thicknesses and indices, and holds
  both implementations to it on random rays through random stacks.
* Triangulation against a stereo rig built here (intrinsics, toe-in, vertical offset; no lens
  distortion) with points projected by the pinhole formula written out: exact to 1e-9 mm.
"""

from __future__ import annotations

import math

import numpy as np
import pytest

from pipeline.design import load_design
from pipeline.refraction import refract_stack_rays
from pipeline.triangulation import triangulate
from pipeline.types import MarkerMatches, StereoCalibration
from twin.optics import FlatStack, solve_paths

# Points recovered by the pipeline from the reference's air ray: the bisection fixes the ray parameter
# to ~1e-16 and the planes are ~40 mm away, so agreement is ~1e-12 mm; 1e-6 mm is the contract.
REFRACTION_TOL_MM = 1e-6
# Unit air directions of the twin (Newton to 1e-11 mm of run) and the reference.
DIRECTION_TOL = 1e-9
TRIANGULATION_TOL_MM = 1e-9


def _random_stack(rng: np.random.Generator):
    """hexagon127 with random thicknesses and indices (all within the design's validity rules)."""
    base = load_design("hexagon127")
    return base.with_overrides({
        "optics.air_gap_mm": float(rng.uniform(10.0, 40.0)),
        "optics.acrylic_thickness_mm": float(rng.uniform(0.5, 4.0)),
        "optics.acrylic_n": float(rng.uniform(1.45, 1.65)),
        "optics.gel_thickness_mm": float(rng.uniform(6.0, 16.0)),
        "optics.gel_n": float(rng.uniform(1.33, 1.55)),
        "skin.thickness_mm": float(rng.uniform(0.5, 2.0)),
    })


def _raw_planes(design) -> tuple[float, float, float]:
    """(camera z, air/acrylic z, acrylic/gel z) from the raw thicknesses: skin top at z = 0, stack below."""
    o = design.optics
    z_gel = -(design.skin.thickness_mm + o.gel_thickness_mm)
    z_acr = z_gel - o.acrylic_thickness_mm
    return z_acr - o.air_gap_mm, z_acr, z_gel


def _reference_air_direction(C: np.ndarray, P: np.ndarray, z_acr: float, z_gel: float,
                             n_a: float, n_g: float) -> np.ndarray:
    """Unit direction in air of the ray from ``C`` (in air, below the stack) that reaches ``P`` (in the gel).

    Snell: p = sin(theta_air) = n_a sin(theta_acrylic) = n_g sin(theta_gel); a layer of thickness t and
    index n runs t p / sqrt(n^2 - p^2) horizontally; the runs sum to the horizontal distance rho. The run
    is increasing in p on [0, 1), so bisection finds p."""
    t = np.array([z_acr - C[2], z_gel - z_acr, P[2] - z_gel])
    n = np.array([1.0, n_a, n_g])
    v = P[:2] - C[:2]
    rho = math.hypot(*v)
    lo, hi = 0.0, 1.0
    for _ in range(200):
        p = 0.5 * (lo + hi)
        run = float(np.sum(t * p / np.sqrt(n * n - p * p)))
        lo, hi = (p, hi) if run < rho else (lo, p)
    p = 0.5 * (lo + hi)
    u = v / rho if rho > 0 else np.zeros(2)
    return np.array([p * u[0], p * u[1], math.sqrt(1.0 - p * p)])


def test_pipeline_and_twin_refraction_agree_with_an_independent_snell_trace():
    rng = np.random.default_rng(20261123)
    worst_pipe = worst_twin_dir = worst_twin_pipe = 0.0
    n_checked = 0
    for _ in range(25):
        design = _random_stack(rng)
        cam_z, z_acr, z_gel = _raw_planes(design)
        # the design's derived planes are the ones the reference assumes (else the comparison is moot)
        assert design.acrylic_air_z_mm == pytest.approx(z_acr, abs=1e-12)
        assert design.gel_acrylic_z_mm == pytest.approx(z_gel, abs=1e-12)
        n_a, n_g = design.optics.acrylic_n, design.optics.gel_n
        stack = FlatStack((z_acr, z_gel), (1.0, n_a, n_g))
        for _ in range(20):
            C = np.array([rng.uniform(-5, 5), rng.uniform(-5, 5), cam_z])
            # a point anywhere in the gel up to 45 deg off the camera's axis
            z = rng.uniform(z_gel + 1e-3, -design.skin.thickness_mm)
            r = rng.uniform(0, 1.0) * (z - cam_z)
            a = rng.uniform(0, 2 * np.pi)
            P = np.array([C[0] + r * math.cos(a), C[1] + r * math.sin(a), z])
            d_ref = _reference_air_direction(C, P, z_acr, z_gel, n_a, n_g)

            # pipeline: carry the reference's air ray through the stack, follow it to P's depth
            entry, d_gel = refract_stack_rays(C[None], d_ref[None], design)
            hit = entry[0] + (P[2] - entry[0, 2]) / d_gel[0, 2] * d_gel[0]
            worst_pipe = max(worst_pipe, float(np.linalg.norm(hit - P)))

            # twin: its air direction to P is the reference's
            d_twin = solve_paths(C, P[None], stack).direction_air[0]
            worst_twin_dir = max(worst_twin_dir, float(np.linalg.norm(d_twin - d_ref)))

            # and the pipeline carries the twin's ray to P (the two implementations agree directly)
            entry, d_gel = refract_stack_rays(C[None], d_twin[None], design)
            hit = entry[0] + (P[2] - entry[0, 2]) / d_gel[0, 2] * d_gel[0]
            worst_twin_pipe = max(worst_twin_pipe, float(np.linalg.norm(hit - P)))
            n_checked += 1
    assert n_checked == 500
    assert worst_pipe < REFRACTION_TOL_MM, worst_pipe
    assert worst_twin_dir < DIRECTION_TOL, worst_twin_dir
    assert worst_twin_pipe < REFRACTION_TOL_MM, worst_twin_pipe


def test_reference_trace_itself_obeys_snell_and_bends_away_from_the_normal():
    """The reference is not trusted blindly: straight down stays straight, and an oblique ray's gel
    angle is smaller than its air angle by exactly Snell's ratio."""
    C = np.array([0.0, 0.0, -40.0])
    d = _reference_air_direction(C, np.array([0.0, 0.0, -5.0]), -16.0, -15.0, 1.5, 1.4)
    assert np.allclose(d, [0, 0, 1], atol=1e-15)
    P = np.array([6.0, 0.0, -5.0])
    d = _reference_air_direction(C, P, -16.0, -15.0, 1.5, 1.4)
    sin_air = d[0]
    # rebuild the path: air to z = -16, acrylic to -15, gel to P; the gel segment's sine is sin_air / 1.4
    x1 = C[0] + 24.0 * sin_air / math.sqrt(1 - sin_air**2)
    s_a = sin_air / 1.5
    x2 = x1 + 1.0 * s_a / math.sqrt(1 - s_a**2)
    s_g = (P[0] - x2) / math.hypot(P[0] - x2, 10.0)
    assert s_g == pytest.approx(sin_air / 1.4, abs=1e-12)
    assert s_g < sin_air          # the ray in the denser gel is steeper than in air


def _rig() -> tuple[StereoCalibration, list[np.ndarray], list[np.ndarray]]:
    """A stereo rig written out by hand: different intrinsics, 3 deg toe-in each side, 0.4 mm vertical
    offset of the right camera, left camera at (−9, 0, −40) mm in the sensor frame looking up +z."""
    K1 = np.array([[610.0, 0.0, 321.5], [0.0, 605.0, 238.0], [0.0, 0.0, 1.0]])
    K2 = np.array([[598.0, 0.0, 317.0], [0.0, 601.0, 243.5], [0.0, 0.0, 1.0]])

    def rot_y(deg: float) -> np.ndarray:
        a = math.radians(deg)
        return np.array([[math.cos(a), 0, math.sin(a)], [0, 1, 0], [-math.sin(a), 0, math.cos(a)]])

    sensor_from = []
    for x, y, toe in ((-9.0, 0.0, 3.0), (9.0, 0.4, -3.0)):
        T = np.eye(4)
        T[:3, :3] = rot_y(toe)          # toe-in: each optical axis turned toward the middle
        T[:3, 3] = [x, y, -40.0]
        sensor_from.append(T)
    right_from_left = np.linalg.inv(sensor_from[1]) @ sensor_from[0]
    calib = StereoCalibration(K1=K1, D1=np.zeros(5), K2=K2, D2=np.zeros(5), R=right_from_left[:3, :3],
                              T=right_from_left[:3, 3], image_size=(640, 480), sensor_from_left=sensor_from[0])
    return calib, [K1, K2], sensor_from


def test_triangulation_is_exact_on_an_analytic_rig():
    calib, Ks, poses = _rig()
    rng = np.random.default_rng(7)
    pts = np.column_stack([rng.uniform(-8, 8, 300), rng.uniform(-6, 6, 300), rng.uniform(-20, 5, 300)])
    px = []
    for K, pose in zip(Ks, poses):
        cam = (pts - pose[:3, 3]) @ pose[:3, :3]          # sensor -> camera: R^T (X - t)
        assert np.all(cam[:, 2] > 0)                      # every point is in front of both cameras
        uv = cam @ K.T
        px.append(uv[:, :2] / uv[:, 2:3])                 # pinhole: u = fx x/z + cx, v = fy y/z + cy
    inside = np.all((px[0] >= 0) & (px[0] < [640, 480]) & (px[1] >= 0) & (px[1] < [640, 480]), axis=1)
    assert inside.sum() > 200
    m = MarkerMatches(np.arange(inside.sum()), px[0][inside], px[1][inside])
    cloud = triangulate(m, calib, method="general")
    assert np.array_equal(cloud.ids, np.arange(inside.sum()))
    err = np.max(np.abs(cloud.xyz_mm - pts[inside]))
    assert err < TRIANGULATION_TOL_MM, err
