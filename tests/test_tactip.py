"""The monocular TacTip in the twin: design schema, tap physics, render, identification, fit/validate
inputs. Real-frame tests use the shared TacTip frames when present and skip with the reason otherwise."""

from __future__ import annotations

import json
import math
import shutil
import sys

import cv2
import numpy as np
import pytest

from pipeline.design import DesignError, design_from_dict, list_designs, load_design, to_dict, to_toml
from pipeline.vision.detection import detect_markers
from pipeline.vision.tactip_id import identify_by_reference

if sys.version_info >= (3, 11):
    import tomllib
else:  # pragma: no cover
    import tomli as tomllib

from pathlib import Path

DATA = Path(__file__).resolve().parents[2] / "shared" / "data" / "real_frames"
TARGETS = DATA / "tactip331_tap_targets.csv"
ROOT = Path(__file__).resolve().parents[1]
HAVE_REAL = TARGETS.is_file()


@pytest.fixture(scope="module")
def design():
    return load_design("tactip331")


@pytest.fixture(scope="module")
def skin(design):
    from twin.tactip import DomeSkin

    return DomeSkin(design)


# ----- design schema ------------------------------------------------------------------------

def test_tactip331_is_a_monocular_hemisphere_with_331_pins_on_the_dome(design):
    assert design.monocular and design.cameras is None
    assert design.marker_count == 331
    R = design.dome_radius_mm()
    assert R == pytest.approx(design.gel.radius_mm)  # a hemisphere
    p = design.rest_markers_mm()
    # every pin tip lies skin thickness + pin height inside the outer sphere (centre at z = -R)
    r = np.linalg.norm(p - [0, 0, -R], axis=1)
    np.testing.assert_allclose(r, R - design.marker_depth_mm, atol=1e-9)
    # and neighbouring rings are one separation apart along the outer surface: apex to ring 1
    assert p[-1] == pytest.approx([0, 0, -design.marker_depth_mm])


def test_every_design_round_trips_through_toml():
    for name in list_designs():
        d = load_design(name)
        assert design_from_dict(tomllib.loads(to_toml(d)), source=d.source_file) == d


def test_stereo_designs_keep_their_camera_pair():
    d = load_design("hexagon127")
    assert not d.monocular and d.cameras is not None
    with pytest.raises(DesignError, match="stereo design"):
        d.camera_pose()
    with pytest.raises(DesignError, match="monocular"):
        load_design("tactip331").camera_poses()


@pytest.mark.parametrize("edit, msg", [
    (lambda r: r.__setitem__("cameras", to_dict(load_design("hexagon127"))["cameras"]), "not both"),
    (lambda r: r.pop("camera"), "missing key 'cameras'"),
    (lambda r: r["pattern"].__setitem__("mapping", "spiral"), "mapping"),
    (lambda r: r.__setitem__("twin", {"stiffness": 1.0}), "unknown key 'stiffness'"),
    (lambda r: r.__setitem__("twin", {"marker_grey": 300.0}), "marker_grey"),
    (lambda r: r.__setitem__("twin", {"pin_rotation": 1.2}), "pin_rotation"),
    (lambda r: r.__setitem__("twin", {"pin_rotation": -0.1}), "pin_rotation"),
    (lambda r: r.__setitem__("twin", {"tap_friction": -0.1}), "tap_friction"),
    (lambda r: r["pattern"].__setitem__("separation_mm", 3.5), "does not fit on the dome"),
    (lambda r: r["camera"].__setitem__("fx_px", 5.0), "fx_px"),
])
def test_bad_monocular_designs_are_refused_by_key(design, edit, msg):
    raw = to_dict(design)
    edit(raw)
    with pytest.raises(DesignError, match=msg):
        design_from_dict(raw, source="t.toml")


# ----- tap physics --------------------------------------------------------------------------

def test_untouched_skin_stays_at_rest(design, skin):
    from twin.tactip import TapPose, tap_markers

    p, axis, info = tap_markers(skin, TapPose(0.0))
    assert info["converged"]
    # pin tips at rest: the mesh normals differ from the sphere's by the facet angle (< 0.1 mm here)
    assert np.max(np.linalg.norm(p - design.rest_markers_mm(), axis=1)) < 0.1


@pytest.mark.parametrize("depth, tilt", [(3.0, (0.0, 0.0)), (4.0, (12.0, -8.0))])
def test_tap_respects_the_plane_and_keeps_the_gel_volume(skin, design, depth, tilt):
    from twin.tactip import TapPose

    pose = TapPose(depth, *tilt)
    params = design.twin_params()
    X, info = skin.tap(pose, params)
    m, c = skin.plane(pose, params)
    assert info["converged"]
    assert np.max(X @ m - c) < 2e-3                    # penalty contact: < 2 µm inside the surface
    assert abs(info["volume_change"]) < 5e-3            # incompressible fill: < 0.5 % volume change
    # the contact patch is flat: nodes in contact lie on the plane within 2 µm
    on = np.abs(X @ m - c) < 2e-3
    assert on.sum() >= 10
    # a vertical tap pushes the apex pin straight in by the depth (flat patch, rigid pin)
    if tilt == (0.0, 0.0):
        p, _ = skin.markers(X)
        assert p[-1] == pytest.approx([0, 0, -design.marker_depth_mm - depth], abs=0.02)


@pytest.fixture(scope="module")
def tilted_tap(skin, design):
    from twin.tactip import TapPose

    X, info = skin.tap(TapPose(3.5, 8.0, -6.0), design.twin_params())
    assert info["converged"]
    return X


def test_pins_held_normal_to_the_skin_are_the_default_placement_bit_for_bit(skin, design, tilted_tap):
    """pin_rotation = 1 (the default) is a pin normal to the deformed skin: each tip skin thickness + pin
    height inside the outer surface along the deformed normal, exactly as before the pin rotation existed."""
    X = tilted_tap
    assert design.twin_params()["pin_rotation"] == 1.0
    n = skin.normals(X)[: skin.n_markers]
    old_tips, old_axes = X[: skin.n_markers] - design.marker_depth_mm * n, -n
    for p, ax in (skin.markers(X), skin.markers(X, 1.0)):
        np.testing.assert_array_equal(p, old_tips)
        np.testing.assert_array_equal(ax, old_axes)


def test_pins_that_do_not_rotate_keep_their_rest_direction(skin, design, tilted_tap):
    """pin_rotation = 0: the pin's base follows the skin (skin thickness inside it, along its deformed normal)
    and the pin keeps its rest direction, so the tip is base - pin height x rest normal."""
    X = tilted_tap
    n = skin.normals(X)[: skin.n_markers]
    n0 = skin.normals(skin.X0)[: skin.n_markers]
    p, ax = skin.markers(X, 0.0)
    np.testing.assert_allclose(ax, -n0, atol=1e-12)
    base = X[: skin.n_markers] - design.skin.thickness_mm * n
    np.testing.assert_allclose(p, base - design.pins.height_mm * n0, atol=1e-12)
    # at rest the fraction does not matter: no rotation to follow
    for a in (0.0, 0.37, 1.0):
        np.testing.assert_allclose(skin.markers(skin.X0, a)[0], skin.markers(skin.X0)[0], atol=1e-12)


def test_a_pin_turns_by_its_fraction_of_the_skin_rotation_about_the_same_axis(skin, tilted_tap):
    """Analytic: a normal turned by theta about x gives, at fraction alpha, the rest normal turned by
    alpha x theta about x; on a tapped skin every pin's angle from rest is alpha x the normal's, in the
    plane of the two normals. Pins that follow less of the rotation move their markers less."""
    from twin.tactip import pin_axes

    th = np.radians([0.0, 1e-10, 5.0, 40.0, 120.0])
    n0 = np.tile([0.0, 0.0, 1.0], (len(th), 1))
    turn = lambda t: np.column_stack([np.zeros_like(t), -np.sin(t), np.cos(t)])  # noqa: E731 - about x
    for a in (0.0, 0.25, 0.5, 1.0):
        np.testing.assert_allclose(pin_axes(n0, turn(th), a), turn(a * th), atol=1e-12)
    X = tilted_tap
    n0 = skin.normals(skin.X0)[: skin.n_markers]
    n = skin.normals(X)[: skin.n_markers]
    ang = lambda u, v: np.arctan2(np.linalg.norm(np.cross(u, v), axis=1), np.einsum("ij,ij->i", u, v))  # noqa: E731
    moved = ang(n0, n) > 1e-3
    assert moved.sum() > 50
    prev = None
    for a in (0.0, 0.3, 0.7, 1.0):
        p, ax = skin.markers(X, a)
        np.testing.assert_allclose(ang(n0, -ax)[moved], a * ang(n0, n)[moved], atol=1e-9)
        coplanar = np.einsum("ij,ij->i", np.cross(n0, n), -ax)
        np.testing.assert_allclose(coplanar, 0.0, atol=1e-12)
        motion = np.linalg.norm(p - skin.markers(skin.X0)[0], axis=1)[moved].mean()
        assert prev is None or motion > prev
        prev = motion


def test_tilt_moves_the_contact_towards_the_tilt(skin, design):
    from twin.tactip import TapPose

    params = design.twin_params()
    X, _ = skin.tap(TapPose(3.0, 0.0, 10.0), params)
    m, c = skin.plane(TapPose(3.0, 0.0, 10.0), params)
    contact = X[np.abs(X @ m - c) < 2e-3]
    # the plane's normal leans along +x: the patch centre sits at R sin(10 deg) ~ 3.5 mm on that side
    centroid = contact[:, :2].mean(axis=0)
    assert np.sign(centroid[0]) == np.sign(m[0]) and abs(centroid[0]) > 1.5


def test_the_tilt_pivot_sets_how_deep_a_tilted_surface_reaches(skin, design):
    """Analytic: a surface tilted about the dome's centre of curvature (pivot 0, the default) is tangent to
    the rest dome at depth 0; tilted about the apex (pivot = dome radius) it passes through the apex pressed
    in by the depth; in between it reaches pivot x (1 - cos tilt) deeper along its normal. Untilted, the
    pivot does not matter."""
    from twin.tactip import TapPose

    params = design.twin_params()
    assert params["tilt_pivot_mm"] == 0.0
    R = skin.R
    tilted = TapPose(0.0, 12.0, -8.0)
    m, c = skin.plane(tilted, params)
    sphere = np.array([0.0, 0.0, -R]) + R * m              # the rest dome's point whose normal is m
    assert m @ sphere == pytest.approx(c, abs=1e-12)
    d = 2.5
    m, c_apex = skin.plane(TapPose(d, 12.0, -8.0), {**params, "tilt_pivot_mm": R})
    assert m @ np.array([0.0, 0.0, -d]) == pytest.approx(c_apex, abs=1e-12)
    _, c0 = skin.plane(TapPose(d, 12.0, -8.0), params)
    _, c7 = skin.plane(TapPose(d, 12.0, -8.0), {**params, "tilt_pivot_mm": 7.0})
    assert c0 - c7 == pytest.approx(7.0 * (1.0 - m[2]), abs=1e-12)
    assert skin.plane(TapPose(d), params)[1] == skin.plane(TapPose(d), {**params, "tilt_pivot_mm": 15.0})[1]


class _PivotScores:
    """A stand-in fit context whose displacement error is a known bowl in (pivot height, depth offset): the
    offset that suits a height falls with it, as a deeper-reaching tilted tap asks."""

    train, ref = [0, 1, 2], 0

    def __init__(self, h_best):
        self.h_best, self.calls = h_best, 0

    def displacement_rms(self, design, idx, twin):
        self.calls += 1
        h, off = twin["tilt_pivot_mm"], twin["depth_offset_mm"]
        return 1.7 + 1e-3 * (h - self.h_best) ** 2 + 4.0 * (off + 0.26 + 0.022 * h) ** 2


@pytest.mark.parametrize("h_best", [7.0, 27.0])
def test_the_tilt_pivot_search_refines_between_grid_heights_and_past_the_apex(h_best):
    from types import SimpleNamespace

    from benchmarks.tactip_fit import TILT_PIVOTS_MM, _fit_tilt_pivot

    ctx, twin = _PivotScores(h_best), {"tilt_pivot_mm": 0.0, "depth_offset_mm": -0.26}
    h, rows = _fit_tilt_pivot(ctx, None, [0, 1], twin, SimpleNamespace(update=lambda n: None))
    assert max(TILT_PIVOTS_MM) > 20.0  # the search reaches beyond the 20 mm dome's apex
    assert [r[0] for r in rows[:len(TILT_PIVOTS_MM)]] == list(TILT_PIVOTS_MM)
    assert len(rows) == len(TILT_PIVOTS_MM) + 1  # one parabolic step off the grid
    assert h == pytest.approx(h_best, abs=0.5)  # the bowl is a parabola in h: the step lands on it
    assert twin["depth_offset_mm"] == pytest.approx(-0.26 - 0.022 * h, abs=0.02)


class _TiltFrameScores:
    """A stand-in fit context whose displacement error is a known bowl in (tilt frame, depth offset) and whose
    taps differ in tilt, so the re-search can be checked on which taps it scores and where it lands."""

    def __init__(self, psi_best, off_best):
        from types import SimpleNamespace

        from twin.tactip import TapPose

        self.psi_best, self.off_best = psi_best, off_best
        tilts = [(0.0, 0.0)] + [(1.0 * k, -0.5 * k) for k in range(1, 15)]
        self.frames = [SimpleNamespace(pose=TapPose(3.0, tx, ty), path=Path(f"tap_{k}.png"))
                       for k, (tx, ty) in enumerate(tilts)]
        self.train, self.ref = list(range(len(tilts))), 0
        self.real_xy = [np.zeros((5, 2)) for _ in tilts]
        self.scored: list[set] = []

    def displacement_rms(self, design, idx, twin):
        self.scored.append(set(idx))
        dpsi = (twin["tilt_frame_deg"] - self.psi_best + 180.0) % 360.0 - 180.0   # an angle: one turn is nothing
        return 1.0 + 1e-3 * dpsi ** 2 + 4.0 * (twin["depth_offset_mm"] - self.off_best) ** 2


@pytest.mark.parametrize("psi_best", [-181.0, -150.0])
def test_the_tilt_frame_is_re_searched_on_the_most_tilted_taps_after_the_skin(psi_best):
    """The first tilt-frame fit (pivot at the dome's centre, nominal skin) ended 18-24 degrees off on the real
    taps; the re-search finds the bowl's bottom within its half-width of the first fit, scores it on the most
    tilted training taps only (never the reference), and re-fits the depth offset after it."""
    from benchmarks.tactip_fit_skin import TILT_REFIT_FRAMES, TILT_REFIT_HALF_DEG, _refit_tilt_frame

    ctx = _TiltFrameScores(psi_best, -0.5)
    twin = {"tilt_frame_deg": -160.4, "depth_offset_mm": -0.6}
    assert abs(psi_best - twin["tilt_frame_deg"]) < TILT_REFIT_HALF_DEG
    rep = _refit_tilt_frame(ctx, None, [1, 2, 3], twin)
    assert -180.0 <= twin["tilt_frame_deg"] < 180.0       # kept in one turn: -181 is written as 179
    assert (twin["tilt_frame_deg"] - psi_best + 180.0) % 360.0 - 180.0 == pytest.approx(0.0, abs=1.0)
    assert twin["depth_offset_mm"] == pytest.approx(-0.5, abs=0.02)
    most_tilted = set(range(len(ctx.frames) - TILT_REFIT_FRAMES, len(ctx.frames)))
    assert set(rep["frames"]) == most_tilted and ctx.ref not in rep["frames"]
    assert {frozenset(s) for s in ctx.scored} == {frozenset(most_tilted), frozenset({1, 2, 3})}
    assert rep["rms_px"] < rep["rms_px_before"]
    assert rep["n_obs"] == 5 * TILT_REFIT_FRAMES


def test_a_tilt_frame_re_search_that_finds_nothing_better_keeps_the_first_fit():
    from benchmarks.tactip_fit_skin import _refit_tilt_frame

    ctx = _TiltFrameScores(-160.4, -0.6)
    twin = {"tilt_frame_deg": -160.4, "depth_offset_mm": -0.6}
    _refit_tilt_frame(ctx, None, [1, 2, 3], twin)
    assert twin == {"tilt_frame_deg": pytest.approx(-160.4, abs=0.5), "depth_offset_mm": pytest.approx(-0.6, abs=0.02)}


def test_rendered_markers_are_detected_where_they_are_projected(design, skin):
    from twin.tactip import TapPose, project_markers, render_frame, tap_markers

    p, axis, _ = tap_markers(skin, TapPose(2.0))
    d = design
    img = render_frame(d, p, axis, seed=3)
    uv = project_markers(d, p)
    inside = (uv[:, 0] > 10) & (uv[:, 0] < 630) & (uv[:, 1] > 10) & (uv[:, 1] < 470)
    blobs = detect_markers(img)
    idx = identify_by_reference(blobs.xy_px, uv[inside])
    # the central pins (seen face-on) are all found, within 0.3 px of their projection
    central = np.linalg.norm(p[inside, :2], axis=1) < 10.0
    found = idx[central] >= 0
    assert found.mean() > 0.95
    err = np.linalg.norm(blobs.xy_px[idx[central][found]] - uv[inside][central][found], axis=1)
    assert np.sqrt(np.mean(err**2)) < 0.3


def test_identification_by_reference_follows_small_moves_and_refuses_large_ones():
    rng = np.random.default_rng(0)
    g = np.stack(np.meshgrid(np.arange(10), np.arange(10)), -1).reshape(-1, 2) * 16.0 + 50
    moved = g + rng.uniform(-4, 4, g.shape)          # < half the 16 px spacing
    perm = rng.permutation(len(g))
    idx = identify_by_reference(moved[perm], g)
    np.testing.assert_array_equal(perm[idx], np.arange(len(g)))
    idx = identify_by_reference(g + [7.5, 0.0], g)    # just under half a spacing: still right
    np.testing.assert_array_equal(idx, np.arange(len(g)))
    # past half a spacing the method's stated limit is reached: markers take their neighbour's id
    idx = identify_by_reference(g + [9.0, 0.0], g)
    row_start = np.arange(len(g)) % 10 == 0
    assert np.all(idx[row_start] == -1)
    np.testing.assert_array_equal(idx[~row_start], np.arange(len(g))[~row_start] - 1)


def test_ridge_baseline_recovers_a_quadratic_pose_model():
    from twin.tactip import TapPose
    from benchmarks.tactip_validate import baselines

    rng = np.random.default_rng(1)
    poses = [TapPose(rng.uniform(2, 5), rng.uniform(-15, 15), rng.uniform(-15, 15)) for _ in range(24)]
    base = rng.uniform(100, 500, (5, 2))

    def truth(p):
        return base + np.array([[p.depth_mm * 2.0 + 0.1 * p.tilt_x_deg, -0.05 * p.tilt_y_deg * p.depth_mm]])

    real = [truth(p) for p in poses]
    train, held = np.arange(18), np.arange(18, 24)
    b = baselines(real, poses, train, held)
    for k, i in enumerate(held):
        np.testing.assert_allclose(b["ridge"][k], real[i], atol=0.05)
        assert np.abs(b["static"][k] - real[i]).max() > 0.5   # the static baseline cannot follow the pose


def test_validate_goals_are_decided_from_the_held_out_rms_and_the_image_statistics():
    """The twin within half the static baseline and 1.5× the ridge; the image statistics within 10 %: a statistic
    the twin matches exactly meets it, one without a value does not. The summary's twin parameter groups add up to
    the fitted position parameters."""
    from benchmarks.tactip_fit import FITTED_POSITION_GROUPS, FITTED_POSITION_PARAMETERS
    from benchmarks.tactip_validate import GOAL_IMAGE_KEYS, _goals

    stats = {k: {"real": 10.0, "twin": 10.0, "relative_difference": 0.0} for k in GOAL_IMAGE_KEYS}
    goals = _goals({"twin": 2.0, "static": 4.0, "ridge": 1.4}, stats)
    assert goals == {"twin_le_half_static": True, "twin_within_1p5_ridge": True, "image_stats_within_10pct": True}
    goals = _goals({"twin": 2.01, "static": 4.0, "ridge": 1.3}, {**stats, "contrast": {**stats["contrast"],
                                                                                      "relative_difference": 0.11}})
    assert not any(goals.values())
    assert not _goals({"twin": None, "static": 4.0, "ridge": 1.3},
                      {**stats, "count": {"real": None, "twin": 3.0, "relative_difference": None}})[
        "image_stats_within_10pct"]
    assert sum(FITTED_POSITION_GROUPS.values()) == FITTED_POSITION_PARAMETERS == 17


# ----- real frames --------------------------------------------------------------------------

needs_real = pytest.mark.skipif(not HAVE_REAL, reason=f"real TacTip frames not found in {DATA}")


@needs_real
def test_bad_tap_inputs_give_clear_errors(tmp_path, design):
    from benchmarks.tapdata import TapDataError, load_tap_frames

    with pytest.raises(TapDataError, match="no row"):
        load_tap_frames(DATA, TARGETS, design)                    # the raw frame has no label
    frames = load_tap_frames(DATA, TARGETS, design, skip_unlabelled=True)
    assert len(frames) == 40
    bad = tmp_path / "t.csv"
    bad.write_text(TARGETS.read_text().replace("pose_5", "pose_five", 1))
    with pytest.raises(TapDataError, match="unknown column 'pose_five'"):
        load_tap_frames(DATA, bad, design, skip_unlabelled=True)
    small = tmp_path / "frames"
    small.mkdir()
    for k in range(1, 5):
        img = cv2.imread(str(DATA / f"tactip331_tap_{k}.png"))
        cv2.imwrite(str(small / f"tactip331_tap_{k}.png"), cv2.resize(img, (320, 240)) if k == 2 else img)
    from stereotactip.cli import main

    assert main(["validate", str(small), "--targets", str(TARGETS), "--design", "tactip331",
                 "--out", str(tmp_path / "v"), "--no-progress"]) == 2


@needs_real
def test_camera_fit_on_a_real_tap_matches_most_pins(design, monkeypatch):
    """The reference-tap camera fit (stage 1 of fit-twin) on the real frames at a pin spacing near the one
    fit-twin selects (2.1 mm in the measured run; 2.2 mm scored 2.72 against 2.66 px there): 309 of 331 pins
    matched at 3.0 px RMS when measured without k3, the bounds below leave room for the k3 variant."""
    from benchmarks.tactip_fit import FitContext, apply_params, fit_camera_reference

    d = apply_params(design, {"separation_mm": 2.2})
    ctx = FitContext(DATA, TARGETS, d, progress=False, skip_unlabelled=True, log=lambda *a: None)
    # a fit cached under another meaning of a tap is not reused: the twin's tap model is in the stages' key
    import benchmarks.tactip_fit as tf

    key = ctx.key()
    monkeypatch.setattr(tf, "TAP_MODEL", tf.TAP_MODEL + " (changed)")
    assert ctx.key() != key
    monkeypatch.undo()
    # ... nor one cached under another placement of the markers on the skin
    monkeypatch.setattr(tf, "PIN_MODEL", tf.PIN_MODEL + " (changed)")
    assert ctx.key() != key
    monkeypatch.undo()
    assert ctx.key() == key
    fitted, ref_xy, rep = fit_camera_reference(ctx, d.twin_params())
    assert rep["matched"] >= 290
    assert rep["rms_px"] < 4.0
    # the chain identification carries the ids to every frame
    ctx.set_reference(ref_xy)
    counts = [int(np.isfinite(x[:, 0]).sum()) for x in ctx.real_xy]
    assert min(counts) >= 250
    # the pin-rotation search reuses one skin solve per tap: another fraction is a new placement only
    tw = d.twin_params()
    p1, _ = ctx.tap(ctx.ref, tw)
    solves = len(ctx._skins)
    p0, _ = ctx.tap(ctx.ref, {**tw, "pin_rotation": 0.0})
    assert len(ctx._skins) == solves and not np.allclose(p0, p1)
    assert ctx.displacement_rms(fitted, [ctx.ref], {**tw, "pin_rotation": 0.3}) == pytest.approx(0.0, abs=1e-9)


@needs_real
@pytest.mark.slow
def test_validate_runs_every_real_frame_through_the_executor(tmp_path):
    """validate end to end on the shared taps with the fitted design kept in the records, the twin's frames as
    cells on two local workers: a report per frame, the held-out split (every 4th of 40), both baselines. The
    data-driven ridge must beat the static baseline on held-out frames (the taps do move the markers), and the
    fitted twin must meet both goals (measured 2026-11-27: twin 1.24, static 4.92, ridge 1.14 px; the built-in
    design, whose twin is not fitted, errs 10.3 px)."""
    from benchmarks.tactip_validate import GOAL_RIDGE, GOAL_STATIC
    from stereotactip.cli import main

    out = tmp_path / "v"
    fitted = ROOT / "docs" / "records" / "tactip-validation" / "fitted.toml"
    assert main(["validate", str(DATA), "--targets", str(TARGETS), "--design", str(fitted), "--out", str(out),
                 "--skip-unlabelled", "--no-progress", "--workers", "2"]) == 0
    s = json.loads((out / "summary.json").read_text())
    assert s["frames"] == 40 and s["held_out"] == 10 and len(s["per_frame"]) == 40
    assert len(s["commit"]) == 40 and sum(s["fitted_position_parameter_groups"].values()) == \
        s["fitted_position_parameters"]["twin"]
    assert len(list(out.glob("overlay_*.png"))) == 40
    rms = s["held_out_rms_px"]
    assert all(math.isfinite(rms[k]) for k in ("twin", "static", "ridge"))
    assert rms["ridge"] < rms["static"]
    common = s["held_out_rms_px_common_markers"]
    assert common["twin"] <= GOAL_STATIC * common["static"] and common["twin"] <= GOAL_RIDGE * common["ridge"]
    assert s["goals"] == {"twin_le_half_static": True, "twin_within_1p5_ridge": True, "image_stats_within_10pct": True}
    assert (out / "report.html").is_file() and (out / "errors.png").is_file()
