"""Sensor designs: the built-in files load, counts follow the paper, bad files fail clearly."""

import math

import numpy as np
import pytest

from pipeline.design import DesignError, list_designs, load_design, marker_layout

# (design, markers, layers, links) — paper Sec. II and Table III; separations 1.80/2.54/3.54 mm.
EXPECTED = {
    "hexagon127": (127, 7, 12),
    "hexagon127_skin050": (127, 7, 12),
    "hexagon127_skin150": (127, 7, 12),
    "hexagon61_sep354": (61, 5, 12),
    "hexagon217_sep180": (217, 9, 12),
    "circular217_dome": (217, 9, 12),
    "square121": (121, 6, 16),
}


def test_all_builtin_designs_are_listed():
    assert set(EXPECTED) <= set(list_designs())


@pytest.mark.parametrize("name", sorted(EXPECTED))
def test_builtin_design_counts(name):
    d = load_design(name)
    n, layers, links = EXPECTED[name]
    assert d.marker_count == n
    assert d.pattern.layers == layers and d.pattern.links == links
    xyz = d.rest_markers_mm()
    assert xyz.shape == (n, 3) and np.all(np.isfinite(xyz))
    # nearest-neighbour spacing equals the design separation (to float precision)
    dist = np.linalg.norm(xyz[:, None, :2] - xyz[None, :, :2], axis=2) + np.eye(n) * 1e9
    assert np.min(dist) == pytest.approx(d.pattern.separation_mm, rel=1e-9)


def test_separation_designs_cover_the_same_area():
    radii = [load_design(n).pattern_radius_mm() for n in ("hexagon61_sep354", "hexagon127", "hexagon217_sep180")]
    # each within one 1.80 mm spacing of the default hexagon's 15.24 mm radius
    assert max(radii) - min(radii) < 1.80


def test_canonical_order_outer_ring_first_ccw_from_plus_x():
    d = load_design("hexagon127")
    xy = d.rest_markers_mm()[:, :2]
    layers = d.marker_layers()
    assert layers[0] == 6 and layers[-1] == 0 and np.all(np.diff(layers) <= 0)
    assert xy[0] == pytest.approx([6 * 2.54, 0.0])
    ang = np.unwrap(np.arctan2(xy[layers == 6, 1], xy[layers == 6, 0]))
    assert np.all(np.diff(ang) > 0)  # counter-clockwise


def test_camera_poses_follow_table_ii():
    d = load_design("hexagon127")
    poses = d.camera_poses()
    base = poses["right"][:3, 3] - poses["left"][:3, 3]
    assert np.linalg.norm(base) == pytest.approx(12.5)
    zl, zr = poses["left"][:3, 2], poses["right"][:3, 2]
    assert math.degrees(math.acos(zl @ zr)) == pytest.approx(8.94, abs=1e-9)
    assert zl[0] > 0 > zr[0]  # toe-in: each camera looks toward the centre


def test_square_ring_sizes():
    d = load_design("square121")
    _, layers = marker_layout(d.pattern)
    assert [int(np.sum(layers == k)) for k in range(6)] == [1, 8, 16, 24, 32, 40]


def _write(tmp_path, text):
    p = tmp_path / "bad.toml"
    p.write_text(text)
    return p


def test_unknown_key_names_file_and_key(tmp_path):
    from pipeline.design import design_path

    text = design_path("hexagon127").read_text().replace("[pins]\n", "[pins]\ncolour = 3\n")
    with pytest.raises(DesignError, match=r"bad\.toml.*pins.*colour"):
        load_design(_write(tmp_path, text))


def test_missing_field_names_file_and_key(tmp_path):
    from pipeline.design import design_path

    text = design_path("hexagon127").read_text().replace("height_mm = 1.5\n", "")
    with pytest.raises(DesignError, match=r"bad\.toml.*pins.*height_mm"):
        load_design(_write(tmp_path, text))


def test_unknown_design_name_lists_builtins():
    with pytest.raises(DesignError, match="hexagon127"):
        load_design("no_such_design")


def test_overrides_revalidate():
    d = load_design("hexagon127").with_overrides({"skin.thickness_mm": 0.5})
    assert d.skin.thickness_mm == 0.5 and d.marker_depth_mm == pytest.approx(2.0)
    with pytest.raises(DesignError):
        load_design("hexagon127").with_overrides({"skin.thickness_mm": -1.0})
