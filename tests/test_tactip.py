"""The monocular TacTip in the twin: design schema, tap physics, render, identification by reference.
fit-twin and validate (their searches, baselines, goals and the real-frame runs) are tests/test_tactip_fit.py."""

from __future__ import annotations

import sys

import numpy as np
import pytest

from pipeline.design import DesignError, design_from_dict, list_designs, load_design, to_dict, to_toml
from pipeline.vision.detection import detect_markers
from pipeline.vision.tactip_id import identify_by_reference

if sys.version_info >= (3, 11):
    import tomllib
else:  # pragma: no cover
    import tomli as tomllib


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
