"""Refraction: exact ray tracing vs the analytic forward projection; the paper's linear model's error."""

import cv2
import numpy as np
import pytest

from benchmarks.experiments.accuracy import EXACT_TOL_MM, refraction_rows
from pipeline.design import load_design
from pipeline.geometry.index_fit import fit_refractive_index
from pipeline.geometry.refraction import (RefractionError, correct_exact, correct_linear, project_through_stack,
                                          refract_stack_rays, snell)
from pipeline.io.synthetic import gaussian_press_markers, nominal_calibration
from pipeline.geometry.triangulation import camera_poses, triangulate
from pipeline.types import MarkerCloud, MarkerMatches



def _apparent(points, calib, design):
    left, right = project_through_stack(points, calib, design)
    return triangulate(MarkerMatches(np.arange(len(points)), left, right), calib)


def test_snell_angles_and_normal_incidence():
    up = np.array([0.0, 0.0, -1.0])
    th = np.radians([0.0, 10.0, 30.0, 60.0])
    d = np.column_stack([np.sin(th), np.zeros(4), np.cos(th)])
    t = snell(d, up, 1.0 / 1.5)
    assert np.allclose(np.linalg.norm(t, axis=1), 1.0)
    assert np.allclose(np.sin(th), 1.5 * np.hypot(t[:, 0], t[:, 1]))  # n1 sin(th1) = n2 sin(th2)
    assert np.allclose(t[0], [0, 0, 1])
    tir = snell(d, up, 1.5)  # from dense to thin at 60 deg: total internal reflection
    assert np.isnan(tir[3]).all() and np.isfinite(tir[0]).all()


@pytest.mark.parametrize("design_name", ["hexagon127", "square121", "circular217_dome"])
@pytest.mark.parametrize("depth_mm", [0.0, 3.0, 6.0])
def test_exact_correction_inverts_forward_projection(design_name, depth_mm):
    design = load_design(design_name)
    calib = nominal_calibration(design)
    truth = gaussian_press_markers(design, depth_mm, sigma_mm=5.0, lateral=0.3)
    left, right = project_through_stack(truth, calib, design)
    cloud = correct_exact(MarkerMatches(np.arange(len(truth)), left, right), calib, design)
    assert np.array_equal(cloud.ids, np.arange(len(truth)))
    assert np.max(np.abs(cloud.xyz_mm - truth)) < EXACT_TOL_MM
    apparent = _apparent(truth, calib, design)
    assert np.all(apparent.xyz_mm[:, 2] < truth[:, 2] - 1.0)  # refraction makes markers look > 1 mm shallower


def test_forward_projection_without_refraction_is_a_pinhole_projection():
    design = load_design("hexagon127")
    calib = nominal_calibration(design)
    pts = gaussian_press_markers(design, 2.0)
    left, right = project_through_stack(pts, calib, design, n_gel=1.0, n_acrylic=1.0)
    for px, pose, K, D in zip((left, right), camera_poses(calib), (calib.K1, calib.K2), (calib.D1, calib.D2)):
        cam = np.linalg.inv(pose)
        ref, _ = cv2.Rodrigues(cam[:3, :3])
        want, _ = cv2.projectPoints(pts.reshape(-1, 1, 3), ref, cam[:3, 3], K, D)
        assert np.max(np.abs(px - want.reshape(-1, 2))) < 1e-8


def test_refracted_rays_obey_snell_at_both_interfaces():
    design = load_design("hexagon127")
    o = np.zeros((3, 3)) + [0, 0, design.camera_z_mm]
    th = np.radians([0.0, 15.0, 35.0])
    d = np.column_stack([np.sin(th), np.zeros(3), np.cos(th)])
    p, g = refract_stack_rays(o, d, design)
    assert np.allclose(p[:, 2], design.gel_acrylic_z_mm)
    assert np.allclose(np.sin(th), design.optics.gel_n * np.hypot(g[:, 0], g[:, 1]))
    # lateral offset: air + acrylic legs
    sin_a = np.sin(th) / design.optics.acrylic_n
    want = design.optics.air_gap_mm * np.tan(th) + design.optics.acrylic_thickness_mm * sin_a / np.sqrt(1 - sin_a**2)
    assert np.allclose(p[:, 0], want)


def test_fused_stack_midpoints_are_refract_stack_rays_then_closest_points():
    """correct_exact's one-pass kernel computes what the two documented steps compute, ray by ray:
    the same markers kept (rays that miss the stack, total internal reflection, parallel pairs drop
    out alike) and the same points and gaps (identical with numpy's einsum order on x86-64; 1e-12
    mm allowed for a numpy that sums the three products of a dot product in another order)."""
    from pipeline.geometry.refraction import N_AIR, _indices, _stack_midpoints
    from pipeline.geometry.triangulation import closest_points

    rng = np.random.default_rng(3)
    for trial in range(60):
        design = load_design(("hexagon127", "circular217_dome", "square121")[trial % 3])
        n = int(rng.integers(1, 300))
        o1 = rng.normal(0, 5, (n, 3))
        o1[:, 2] = rng.uniform(-30, -5, n)
        o2 = o1 + rng.normal(0, 3, (n, 3))
        d1, d2 = rng.normal(0, 0.3, (2, n, 3))
        d1[:, 2], d2[:, 2] = rng.uniform(-0.1, 1, (2, n))     # some rays go away from the stack
        d1[:3, 0] = 0.999                                       # grazing: total internal reflection
        d1 /= np.linalg.norm(d1, axis=1, keepdims=True)
        d2 /= np.linalg.norm(d2, axis=1, keepdims=True)
        d2[3:5] = d1[3:5]                                       # parallel pairs
        n_gel = float(rng.uniform(1.3, 1.6)) if trial % 2 else None
        p1, g1 = refract_stack_rays(o1, d1, design, n_gel=n_gel)
        p2, g2 = refract_stack_rays(o2, d2, design, n_gel=n_gel)
        with np.errstate(invalid="ignore"):
            want, want_gap = closest_points(p1, g1, p2, g2)
        n_a, n_g = _indices(design, n_gel, None)
        got, got_gap = np.empty((n, 3)), np.empty(n)
        _stack_midpoints(o1, d1, o2, d2, float(design.acrylic_air_z_mm), float(design.gel_acrylic_z_mm), N_AIR / n_a,
                         n_a / n_g, got, got_gap)
        ok = np.all(np.isfinite(want), axis=1)
        np.testing.assert_array_equal(np.all(np.isfinite(got), axis=1), ok)
        np.testing.assert_allclose(got[ok], want[ok], rtol=0, atol=1e-12)
        np.testing.assert_allclose(got_gap[ok], want_gap[ok], rtol=0, atol=1e-12)


def test_points_outside_the_gel_are_rejected():
    design = load_design("hexagon127")
    calib = nominal_calibration(design)
    with pytest.raises(RefractionError, match="must lie in the gel"):
        project_through_stack(np.array([[0.0, 0.0, design.gel_acrylic_z_mm - 0.5]]), calib, design)


def test_linear_model_error_grows_with_incidence_angle_and_depth():
    """Paper Sec. Depth Correction Model: |P P'| ratio = n (1 + E), E = O(theta^2); E ~ 1 % near 10 deg."""
    design = load_design("hexagon127")
    calib = nominal_calibration(design)
    rest = design.rest_markers_mm()
    reference = _apparent(rest, calib, design)
    assert np.allclose(correct_linear(reference, reference, design.optics.gel_n, design).xyz_mm[:, 2], rest[:, 2])
    rel = {}
    for row in refraction_rows(design):     # pure depth moves of the rest pattern, 1 / 4 / 8 mm
        assert row["exact_error_max_mm"] < EXACT_TOL_MM
        rel[row["depth_mm"]] = np.array(row["linear_rel_error_per_ring"])
    assert sorted(rel) == [1.0, 4.0, 8.0]
    for dz, per_layer in rel.items():
        # the centre marker is seen at ~12 deg by each camera (half baseline + toe-in): ~1 % like Fig. 7
        assert per_layer[0] < 0.02, (dz, per_layer)
        # off-axis rings see larger angles: the error grows ring by ring (allow tiny non-monotone wiggles)
        assert np.all(np.diff(per_layer) > -0.002), (dz, per_layer)
        assert per_layer[-1] > 5 * per_layer[0]
    assert rel[8.0][0] > rel[4.0][0] > rel[1.0][0]  # deeper presses raise the angles in the gel too


def test_correct_linear_drops_ids_missing_from_reference_and_validates():
    design = load_design("hexagon127")
    ref = MarkerCloud(np.array([0, 1, 2]), np.zeros((3, 3)) - [0, 0, 6.0])
    cur = MarkerCloud(np.array([1, 2, 5]), np.zeros((3, 3)) - [0, 0, 6.5])
    out = correct_linear(cur, ref, 1.5, design)
    assert out.ids.tolist() == [1, 2]
    assert np.allclose(out.xyz_mm[:, 2], -design.marker_depth_mm - 0.75)
    with pytest.raises(RefractionError, match="n_gel"):
        correct_linear(cur, ref, 0.5, design)
    with pytest.raises(RefractionError, match="ids outside"):
        correct_linear(MarkerCloud(np.array([999]), np.zeros((1, 3))), ref, 1.5, design)


def test_fit_refractive_index_recovers_slope():
    rng = np.random.default_rng(4)
    true = np.repeat(np.arange(0.0, 9.0), 5)
    apparent = true / 1.51 + rng.normal(0, 0.01, true.shape)
    fit = fit_refractive_index(true, apparent)
    # 45 samples with 0.01 mm noise over 0..5.3 mm apparent: slope SE ~ 1.51 * 0.01 / sqrt(sum a^2) ~ 7e-4
    assert abs(fit.n - 1.51) < 0.005
    assert abs(fit.intercept) < 0.02 and abs(fit.slope_with_intercept - 1.51) < 0.01
    assert fit.r2 > 0.999 and 0.005 < fit.residual_rms_mm < 0.03
    offset = fit_refractive_index(true + 0.3, true / 1.4)
    assert offset.intercept == pytest.approx(0.3) and offset.slope_with_intercept == pytest.approx(1.4)
    with pytest.raises(RefractionError):
        fit_refractive_index([1.0, 2.0], [1.0])
    with pytest.raises(RefractionError):
        fit_refractive_index([1.0, 2.0], [1.0, 1.0])


def test_fit_on_simulated_skinless_press_gives_gel_index_near_axis():
    """The paper's calibration (a board pressed 0-8 mm): near-axis markers give n close to n_gel."""
    design = load_design("hexagon127")
    calib = nominal_calibration(design)
    rest = design.rest_markers_mm()
    near = np.hypot(rest[:, 0], rest[:, 1]) < 3.0
    ref = _apparent(rest, calib, design)
    true_dz, app_dz = [], []
    for step in range(9):
        a = _apparent(rest - [0.0, 0.0, float(step)], calib, design)
        true_dz.append(np.full(near.sum(), float(step)))
        app_dz.append(ref.xyz_mm[near, 2] - a.xyz_mm[near, 2])
    fit = fit_refractive_index(np.concatenate(true_dz), np.concatenate(app_dz))
    # paraxial ratio is n_gel; the ~12 deg viewing angle adds E ~ +1-2 % (see the test above)
    assert design.optics.gel_n * 0.97 < fit.n < design.optics.gel_n * 1.03
    assert fit.r2 > 0.999
