"""Indenter registry: analytic heights, validation, meshes, and the sensor-frame mounting."""

import math

import numpy as np
import pytest

from pipeline.errors import UserError
from pipeline.types import HeightMap
from twin.indenters import (IndenterError, indenter_params, list_indenters, make_indenter, parse_params,
                            sensor_to_indenter_xy)

INTERP_TOL_MM = 0.02   # linear interpolation of a 0.2 mm grid on slopes <= 1: error << 0.2 mm * slope / 4


def _terrain_hm():
    ax = np.arange(-21.0, 21.01, 0.2)
    gx, gy = np.meshgrid(ax, ax)
    z = 1.0 + 0.5 * np.sin(gx / 3.0) + 0.1 * gy          # sensor-frame rest surface, asymmetric in x and y
    return HeightMap(ax, ax, z - z.min())


def test_registry_builds_every_indenter_with_a_closed_mesh():
    assert {"gaussian", "sine", "letter", "terrain"} <= set(list_indenters())
    for name in list_indenters():
        ind = make_indenter(name, height_map=_terrain_hm()) if name == "terrain" else make_indenter(name)
        x, y, z = ind.grid(0.5)
        assert z.shape == (len(y), len(x)) and np.all(np.isfinite(z))
        assert np.nanmax(z) == pytest.approx(ind.top_mm, abs=0.05)
        m = ind.mesh(1.0)
        assert m.is_watertight
        assert m.bounds[1, 2] == pytest.approx(ind.top_mm, abs=0.05)


def test_analytic_shapes():
    g = make_indenter("gaussian", h_mm=5, sigma2_mm2=10)
    r2 = np.array([0.0, 10.0, 40.0])
    assert np.allclose(g.height(np.sqrt(r2), 0 * r2), 5 * np.exp(-r2 / 20.0))
    w = math.pi / 5
    s = make_indenter("sine", amplitude_mm=2.5, omega_rad_per_mm=w)
    x = np.linspace(-10, 10, 41)
    assert np.allclose(s.height(x, 3.0), 2.5 * np.sin(w * x))
    assert s.top_mm == pytest.approx(2.5, abs=1e-6)
    assert np.isnan(g.height(30.0, 0.0))             # off the part


def test_a_sine_plate_with_a_relief_radius_rounds_off_beyond_it():
    """Inside relief_radius_mm the plate is the sine; d mm beyond it, d^2 / (2 R) lower (a parabola of apex radius
    R = roll_off_radius_mm, slope and height continuous at the relief's edge); the top is the sine's."""
    w, r0, rho = 2 * math.pi / 15, 14.0, 1.5
    s = make_indenter("sine", amplitude_mm=2.5, omega_rad_per_mm=w, relief_radius_mm=r0, roll_off_radius_mm=rho)
    ang = np.linspace(0, 2 * math.pi, 13)
    for r in (0.0, 5.0, 13.99, 14.5, 17.0, 20.0):
        x, y = r * np.cos(ang), r * np.sin(ang)
        drop = max(r - r0, 0.0) ** 2 / (2 * rho)
        assert np.allclose(s.height(x, y), 2.5 * np.sin(w * x) - drop, atol=1e-12)
    assert s.top_mm == pytest.approx(2.5, abs=1e-6)
    # beyond the clamped rim of the built-in designs (20 mm) every crest has fallen 12 mm: the plate clears the mount
    assert s.height(20.0, 0.0) <= 2.5 - 12.0 + 1e-9
    with pytest.raises(IndenterError, match="roll_off_radius_mm"):
        make_indenter("sine", relief_radius_mm=14.0, roll_off_radius_mm=0.0)


def test_letter_o_has_a_hole_and_G_is_not_symmetric():
    o = make_indenter("letter", char="o")
    assert o.height(0.0, 0.0) == pytest.approx(0.0, abs=1e-6)           # counter of the "o"
    x, y, z = o.grid(0.1)
    assert np.nanmax(z) == pytest.approx(3.0, abs=1e-6)
    G = make_indenter("letter", char="G")
    x, y, z = G.grid(0.1)
    assert np.mean(np.abs(z - z[:, ::-1])) > 0.1                       # not mirror symmetric in x


def test_validation_errors_name_the_problem():
    with pytest.raises(IndenterError, match="unknown indenter 'cube'"):
        make_indenter("cube")
    with pytest.raises(IndenterError, match="unknown parameter 'radius'"):
        make_indenter("gaussian", radius=3)
    with pytest.raises(IndenterError, match="sigma2_mm2"):
        make_indenter("gaussian", sigma2_mm2=-1)
    with pytest.raises(IndenterError, match="char"):
        make_indenter("letter", char="X")
    with pytest.raises(IndenterError, match="required"):
        make_indenter("terrain")
    with pytest.raises(IndenterError, match="key=value"):
        parse_params("gaussian", ["sigma2"])
    assert issubclass(IndenterError, UserError)
    assert make_indenter("gaussian", **parse_params("gaussian", ["sigma2=5"])).params["sigma2_mm2"] == 5.0
    assert "h_mm" in indenter_params("gaussian")


def test_every_indenter_takes_the_skins_friction_on_its_material():
    """``friction`` is the skin's Coulomb coefficient on the part (not a shape parameter): None by default (the
    design's), validated like the design key, parsed from the CLI, and the same shape whatever its value."""
    assert make_indenter("sphere").friction is None
    resin = make_indenter("sphere", **parse_params("sphere", ["radius=8", "friction=0.35"]))
    assert resin.friction == 0.35 and resin.params == make_indenter("sphere", radius_mm=8).params
    assert make_indenter("letter", char="e", friction=0).friction == 0.0
    for bad in (-0.1, 11.0, "rough", float("nan")):
        with pytest.raises(IndenterError, match="friction"):
            make_indenter("sphere", friction=bad)


def test_sensor_heightmap_depth_and_yaw():
    g = make_indenter("gaussian", sigma2_mm2=10)
    hm = g.sensor_heightmap(0, 0, 3.0, 0.0)
    assert np.nanmin(hm.z_mm) == pytest.approx(-3.0, abs=1e-9)       # top at z = -depth
    s = make_indenter("sine", omega_rad_per_mm=math.pi / 5)
    hm0, hm90 = s.sensor_heightmap(0, 0, 0, 0), s.sensor_heightmap(0, 0, 0, 90)
    assert np.nanstd(hm0.z_mm, axis=0).max() < 1e-9                   # yaw 0: varies along x only
    assert np.nanstd(hm90.z_mm, axis=1).max() < 1e-9                  # yaw 90: varies along y only
    xi, yi = sensor_to_indenter_xy(np.array([1.0]), np.array([2.0]), 0, 0, 0)
    assert (xi[0], yi[0]) == (1.0, -2.0)                              # 180 deg about x


def test_terrain_round_trip_in_the_sensor_frame():
    hm = _terrain_hm()
    t = make_indenter("terrain", height_map=hm)
    back = t.sensor_heightmap(0, 0, 0.0, 0.0, half_mm=20.0, spacing_mm=0.2)
    i0 = np.searchsorted(hm.x_mm, back.x_mm[0] - 1e-9)
    ref = hm.z_mm[i0:i0 + len(back.y_mm), i0:i0 + len(back.x_mm)]
    assert np.nanmax(np.abs(back.z_mm - ref)) < INTERP_TOL_MM
