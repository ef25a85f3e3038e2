"""Sensor designs: the built-in files load, counts follow the paper, bad files fail clearly."""

import math
from pathlib import Path

import numpy as np
import pytest

from pipeline.design import DesignError, design_path, list_designs, load_design, marker_layout, to_toml

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


def _standalone(name="hexagon127"):
    """A built-in design written out as one file, every key in it (no extends)."""
    return to_toml(load_design(name))


def test_unknown_key_names_file_and_key(tmp_path):
    text = _standalone().replace("[pins]\n", "[pins]\ncolour = 3\n")
    with pytest.raises(DesignError, match=r"bad\.toml.*pins.*colour"):
        load_design(_write(tmp_path, text))


def test_missing_field_names_file_and_key(tmp_path):
    text = _standalone().replace("height_mm = 1.5\n", "")
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


# ----- extends: designs built on a base --------------------------------------------------------

import dataclasses  # noqa: E402
import sys  # noqa: E402

from pipeline.design import Gel, Optics, design_digest, mapping_to_toml, to_dict  # noqa: E402
from pipeline.errors import UserError  # noqa: E402

if sys.version_info >= (3, 11):
    import tomllib
else:  # pragma: no cover
    import tomli as tomllib

BASE = "base/stereotactip_module"


def _refused(path, match):
    """load_design(path) raises a one-line DesignError (a UserError) matching ``match``; its text."""
    with pytest.raises(DesignError, match=match) as info:
        load_design(path)
    assert isinstance(info.value, UserError) and "\n" not in str(info.value)
    return str(info.value)


def _module_base(tmp_path, name="base.toml", **edits):
    """An abstract base written from hexagon127 without its name, description and pattern; ``edits``
    ``{"optics.gel_n": 1.5}`` change its values."""
    raw = to_dict(load_design("hexagon127"))
    for k in ("name", "description", "pattern"):
        raw.pop(k)
    for key, value in edits.items():
        sec, k = key.rsplit(".", 1)
        node = raw
        for part in sec.split("."):
            node = node[part]
        node[k] = value
    p = tmp_path / name
    p.write_text(mapping_to_toml({"abstract": True, **raw}))
    return p


PATTERN = '\n[pattern]\nkind = "hexagon"\nlayers = 7\nlinks = 12\nseparation_mm = 2.54\ndome_height_mm = 0.0\n'


def _child(tmp_path, extends, body="", name="child"):
    p = tmp_path / f"{name}.toml"
    p.write_text(f'name = "{name}"\ndescription = "test module"\nextends = "{extends}"\n{PATTERN}{body}')
    return p


def test_twin_friction_is_a_checked_design_key(tmp_path):
    """``[twin] friction`` (the twin's skin/indenter Coulomb coefficient) defaults to 1, can be set by an override
    even where the design has no [twin] section, survives writing the design out, and is refused outside [0, 10]."""
    d = load_design("hexagon127")
    assert d.twin_params()["friction"] == 1.0
    rough = d.with_overrides({"twin.friction": 0.8})
    assert rough.twin_params()["friction"] == 0.8
    path = tmp_path / "rough.toml"
    path.write_text(to_toml(rough))
    assert load_design(str(path)).twin_params()["friction"] == 0.8
    for bad in (-0.5, 11.0):
        with pytest.raises(DesignError, match=r"twin\.friction"):
            d.with_overrides({"twin.friction": bad})
    with pytest.raises(DesignError, match="unknown key|no section"):
        d.with_overrides({"twin.frictoin": 0.5})


def test_builtin_designs_equal_their_written_out_form(tmp_path):
    """Every built-in design that extends a base loads to the same design as its merged document written
    out as one standalone file (to_toml): inheritance changes where a value is written, never the value."""
    extending = []
    for name in list_designs():
        raw = tomllib.loads(design_path(name).read_text())
        if "extends" not in raw:
            continue
        extending.append(name)
        d = load_design(name)
        p = tmp_path / f"{name}.toml"
        p.write_text(to_toml(d))
        assert not {"extends", "abstract"} & set(tomllib.loads(p.read_text()))
        assert load_design(p) == dataclasses.replace(d, source_file=str(p))
        assert design_digest(load_design(p)) == design_digest(d)
    assert sorted(extending) == sorted(EXPECTED)          # the seven stereo modules; tactip331 stands alone


def test_stereo_designs_take_the_module_from_the_base():
    base = tomllib.loads(design_path(BASE).read_text())
    assert base["abstract"] is True and BASE not in list_designs() and "stereotactip_module" not in list_designs()
    for name in EXPECTED:
        d = load_design(name)
        assert d.optics == Optics(**base["optics"]) and d.gel == Gel(**base["gel"])
        assert d.pins.height_mm == base["pins"]["height_mm"] and d.skin.material == base["skin"]["material"]
        assert d.cameras.left.dist == tuple(base["cameras"]["left"]["dist"])
        assert d.cameras.baseline_mm == base["cameras"]["baseline_mm"]
    # a child's value wins over the base's, its siblings stay the base's
    thin = load_design("hexagon127_skin050")
    assert thin.skin.thickness_mm == 0.5 != base["skin"]["thickness_mm"]
    assert thin.skin.youngs_modulus_mpa == base["skin"]["youngs_modulus_mpa"]
    dense = load_design("hexagon217_sep180")
    assert dense.markers.diameter_mm == 0.9 and dense.markers.thickness_mm == base["markers"]["thickness_mm"]


def test_loading_a_base_as_a_design_is_refused():
    msg = _refused(BASE, r"stereotactip_module\.toml: is a base \(abstract = true\), not a design")
    assert "extends = 'base/stereotactip_module'" in msg


def test_child_overrides_a_nested_key(tmp_path):
    base = _module_base(tmp_path)
    child = _child(tmp_path, "base.toml", "\n[cameras.left]\nfx_px = 450.0\n\n[cameras.right]\n"
                   "dist = [-0.2, 0.05, 0.0, 0.0, 0.0]\n\n[optics]\ngel_n = 1.41\n")
    ref, d = load_design("hexagon127"), load_design(child)
    assert d.cameras.left.fx_px == 450.0                                        # the child's key wins
    assert dataclasses.replace(d.cameras.left, fx_px=ref.cameras.left.fx_px) == ref.cameras.left  # siblings kept
    assert d.cameras.right.dist == (-0.2, 0.05, 0.0, 0.0, 0.0)                  # an array replaces whole
    assert d.cameras.right.fx_px == ref.cameras.right.fx_px
    assert d.optics == dataclasses.replace(ref.optics, gel_n=1.41)
    assert (d.skin, d.pins, d.markers, d.gel) == (ref.skin, ref.pins, ref.markers, ref.gel)
    assert d.name == "child" and str(child) == d.source_file
    # two levels: a base of a base, the nearer file winning
    mid = tmp_path / "mid.toml"
    mid.write_text('abstract = true\nextends = "base.toml"\n\n[optics]\nair_gap_mm = 20.0\ngel_n = 1.45\n')
    d2 = load_design(_child(tmp_path, "mid.toml", "\n[optics]\ngel_n = 1.42\n", name="grandchild"))
    assert (d2.optics.air_gap_mm, d2.optics.gel_n, d2.optics.gel_thickness_mm) == (20.0, 1.42, 10.0)
    assert base.is_file()


def test_a_base_edit_reaches_every_design_and_its_digest(tmp_path):
    """A tolerance study edits one place: the base. Every design extending it changes, and so does the
    content digest the caches key on (the children's own bytes did not change)."""
    _module_base(tmp_path)
    a, b = _child(tmp_path, "base.toml", name="a"), _child(tmp_path, "base.toml", "\n[skin]\nthickness_mm = 0.5\n",
                                                          name="b")
    before = {p: (load_design(p), design_digest(load_design(p))) for p in (a, b)}
    _module_base(tmp_path, **{"optics.gel_thickness_mm": 10.2, "optics.gel_n": 1.39})
    for p in (a, b):
        d = load_design(p)
        assert (d.optics.gel_thickness_mm, d.optics.gel_n) == (10.2, 1.39)
        assert design_digest(d) != before[p][1]
        assert d == dataclasses.replace(before[p][0], optics=dataclasses.replace(before[p][0].optics,
                                                                                 gel_thickness_mm=10.2, gel_n=1.39))


def test_extends_cycle_is_refused_naming_the_chain(tmp_path):
    a = _child(tmp_path, "b.toml", name="a")
    (tmp_path / "b.toml").write_text('abstract = true\nextends = "a.toml"\n')
    msg = _refused(a, r"a\.toml: extends cycle: .*a\.toml -> .*b\.toml -> .*a\.toml")
    assert msg.count("->") == 2
    _refused(_child(tmp_path, "self.toml", name="self"), r"self\.toml: extends cycle")


def test_extends_chain_depth_is_limited(tmp_path):
    _module_base(tmp_path, name="level0.toml")
    for i in range(1, 9):
        (tmp_path / f"level{i}.toml").write_text(f'abstract = true\nextends = "level{i - 1}.toml"\n')
    assert load_design(_child(tmp_path, "level6.toml", name="deep7")).optics.gel_n == 1.40   # 8 files
    _refused(_child(tmp_path, "level7.toml", name="deep8"), r"deep8\.toml: extends chain longer than 8 files")


def test_missing_base_is_refused(tmp_path):
    _refused(_child(tmp_path, "base/no_such_module"), r"child\.toml: extends: no design or base 'base/no_such_module'")
    _refused(_child(tmp_path, "missing.toml"), r"child\.toml: extends: no design or base 'missing\.toml'")
    _refused(_child(tmp_path, "x" * 300 + ".toml"), r"child\.toml: extends: no design or base 'x{200}\.\.\.'")
    p = tmp_path / "n.toml"
    p.write_text('name = "n"\ndescription = "x"\nextends = 3\n' + PATTERN)
    _refused(p, r"n\.toml: extends: expected a design name or a \.toml path, got 3")


def test_unknown_key_in_a_child_or_base_names_its_file(tmp_path):
    _refused(_child(tmp_path, BASE, "\n[optics]\nfocus_mm = 3.0\n"), r"child\.toml: optics: unknown key 'focus_mm'")
    _refused(_child(tmp_path, BASE, "\n[cameras.left]\nfov_deg = 90.0\n"),
             r"child\.toml: cameras\.left: unknown key 'fov_deg'")
    _refused(_child(tmp_path, BASE, "\n[lighting]\ncolour = 'white'\n"), r"child\.toml: unknown key 'lighting'")
    base = _module_base(tmp_path)
    base.write_text(base.read_text().replace("[gel]\n", "[gel]\nhardness = 3\n"))
    msg = _refused(_child(tmp_path, "base.toml"), r"base\.toml: gel: unknown key 'hardness'")
    assert "child.toml" not in msg
    # a missing key or a non-physical value is found in the merged document, named by the design and its bases
    _module_base(tmp_path)
    _refused(_child(tmp_path, "base.toml", "\n[optics]\ngel_thickness_mm = -1.0\n"),
             r"child\.toml \(extends .*base\.toml\): optics\.gel_thickness_mm: must be in \(0,")
    (tmp_path / "partial.toml").write_text('abstract = true\n\n[optics]\ngel_n = 1.4\n')
    _refused(_child(tmp_path, "partial.toml"), r"child\.toml \(extends .*partial\.toml\): missing key 'skin'")


def test_extends_a_file_that_is_not_a_design(tmp_path):
    import benchmarks

    thresholds = Path(benchmarks.__file__).parent / "thresholds.toml"
    _refused(_child(tmp_path, str(thresholds)),
             r"child\.toml: extends '.*thresholds\.toml', which is neither a design nor a base \(abstract = true\)")
    (tmp_path / "notes.toml").write_text("these are notes, not TOML\n")
    _refused(_child(tmp_path, "notes.toml"), r"notes\.toml: not valid TOML")
    (tmp_path / "stack.toml").write_text("[optics]\ngel_n = 1.4\n")      # design keys, but neither whole nor abstract
    _refused(_child(tmp_path, "stack.toml"), r"child\.toml: extends 'stack\.toml', which is neither a design nor a "
                                             r"base .*stack\.toml: missing key 'name'")


def test_a_whole_design_can_serve_as_a_base(tmp_path):
    d = load_design(_child(tmp_path, "hexagon127", "\n[skin]\nthickness_mm = 0.5\n", name="thin"))
    ref = load_design("hexagon127_skin050")
    assert dataclasses.replace(d, name=ref.name, description=ref.description, source_file=ref.source_file) == ref
    assert d.name == "thin"                                   # name and description are never inherited
    p = tmp_path / "anon.toml"
    p.write_text('extends = "hexagon127"\n')
    _refused(p, r"anon\.toml \(extends .*hexagon127\.toml.*\): missing key 'name'")


def test_a_parsed_mapping_cannot_extend():
    from pipeline.design import design_from_dict

    raw = {**to_dict(load_design("hexagon127")), "extends": BASE}
    with pytest.raises(DesignError, match=r"t\.toml: extends: a base is merged in when a design file is loaded"):
        design_from_dict(raw, source="t.toml")
    raw = {**to_dict(load_design("hexagon127")), "abstract": True}
    with pytest.raises(DesignError, match=r"t\.toml: is a base"):
        design_from_dict(raw, source="t.toml")
