"""Readers refuse files without physical sense with one line naming the file, the key and the range.

Each case is one a user can hand the CLI: it must give exit code 2 and a clear line, never a library's
traceback and never a silently wrong result.
"""

import re
import time

import numpy as np
import pytest

from pipeline.design import DesignError, load_design, to_toml
from pipeline.types import CalibrationError, StereoCalibration

# ----- calibration files ---------------------------------------------------------------------


@pytest.fixture(scope="module")
def calib_text(tmp_path_factory):
    from pipeline.io.synthetic import nominal_calibration

    p = tmp_path_factory.mktemp("cal") / "good.yaml"
    nominal_calibration(load_design("hexagon127")).save_yaml(p)
    return p.read_text()


def _matrix_data(text, key):
    m = re.search(rf"(?m)^{key}: !!opencv-matrix\n   rows: \d+\n   cols: \d+\n   dt: d\n   data: \[([^\]]*)\]", text)
    assert m, key
    return m


def _with_matrix(text, key, values):
    m = _matrix_data(text, key)
    fmt = lambda v: ".nan" if np.isnan(v) else repr(float(v))   # YAML's spelling of NaN
    return text[:m.start(1)] + " " + ", ".join(fmt(v) for v in values) + " " + text[m.end(1):]


def _k1(text):
    return [float(v) for v in _matrix_data(text, "K1").group(1).split(",")]


CALIB_CASES = {
    # name: (edit of the good file's text (or bytes), expected message fragment)
    "empty": (lambda t: "", "is empty"),
    "whitespace": (lambda t: "  \n\n", "is empty"),
    "binary": (lambda t: bytes(range(256)) * 4, "not a text file"),
    "bare_tag": (lambda t: "%YAML:1.0\n---\n!!opencv-matrix\n", "not readable as OpenCV YAML"),
    "nan_width": (lambda t: re.sub(r"image_width: \d+", "image_width: .nan", t), r"image_width.*\[1, 16384\]"),
    "inf_width": (lambda t: re.sub(r"image_width: \d+", "image_width: .inf", t), r"image_width.*\[1, 16384\]"),
    "text_width": (lambda t: re.sub(r"image_width: \d+", "image_width: abc", t), "'image_width' must be a number"),
    "fraction_width": (lambda t: re.sub(r"image_width: \d+", "image_width: 640.5", t), "image_width.*integer"),
    "K1_text": (lambda t: re.sub(r"K1: !!opencv-matrix\n(   .*\n)+", "K1: hello\n", t, count=1), "'K1' is not a matrix"),
    "rows_mismatch": (lambda t: t.replace("K1: !!opencv-matrix\n   rows: 3", "K1: !!opencv-matrix\n   rows: 4", 1),
                      "'K1' is not a readable matrix"),
    "bad_dt": (lambda t: t.replace("dt: d", "dt: q", 1), "'K1' is not a readable matrix"),
    "zero_K": (lambda t: _with_matrix(t, "K1", [0] * 9), r"K1: focal length fx = 0 px is outside \[32, 64000\]"),
    "huge_fx": (lambda t: _with_matrix(t, "K1", [1e308] + _k1(t)[1:]), "K1: focal length fx = 1e\\+308"),
    "negative_fy": (lambda t: _with_matrix(t, "K2", _k1(t)[:4] + [-440.0] + _k1(t)[5:]), "K2: focal length fy"),
    "principal_point_outside": (lambda t: _with_matrix(t, "K1", _k1(t)[:2] + [5000.0] + _k1(t)[3:]),
                                "principal point"),
    "not_intrinsic": (lambda t: _with_matrix(t, "K1", _k1(t)[:6] + [1.0, 0.0, 1.0]), "not an intrinsic matrix"),
    "scaled_R": (lambda t: _with_matrix(t, "R", [2, 0, 0, 0, 2, 0, 0, 0, 2]), "R: not a rotation"),
    "reflection_R": (lambda t: _with_matrix(t, "R", [-1, 0, 0, 0, 1, 0, 0, 0, 1]), "R: not a rotation"),
    "zero_baseline": (lambda t: _with_matrix(t, "T", [0, 0, 0]), r"T: baseline .* outside \[0.1, 1000\] mm"),
    "nan_T": (lambda t: _with_matrix(t, "T", [np.nan, 0, 0]), "'T' contains NaN or inf"),
    "short_D1": (lambda t: t.replace("D1: !!opencv-matrix\n   rows: 1\n   cols: 5", "D1: !!opencv-matrix\n   rows: 1\n   cols: 4", 1)
                 .replace(_matrix_data(t, "D1").group(1), " 0., 0., 0., 0. ", 1), r"D1: expected shape \(5\)"),
    "bad_pose": (lambda t: _with_matrix(t, "sensor_from_left", [2, 0, 0, 0, 0, 1, 0, 0, 0, 0, 1, 0, 0, 0, 0, 1]),
                 "sensor_from_left: not a rigid pose"),
    "negative_rms": (lambda t: re.sub(r"rms_px: \S+", "rms_px: -5.", t), "rms_px"),
    "text_rms": (lambda t: re.sub(r"rms_px: \S+", "rms_px: good", t), "'rms_px' must be a number"),
}


@pytest.mark.parametrize("case", sorted(CALIB_CASES))
def test_bad_calibration_files_are_one_clear_error(case, calib_text, tmp_path):
    edit, message = CALIB_CASES[case]
    p = tmp_path / f"{case}.yaml"
    content = edit(calib_text)
    assert content != calib_text, "the edit must change the file"
    (p.write_bytes if isinstance(content, bytes) else p.write_text)(content)
    with pytest.raises(CalibrationError, match=message) as info:
        StereoCalibration.load_yaml(p)
    text = str(info.value)
    assert str(p) in text and "\n" not in text


def test_good_calibration_still_loads_and_unknown_rms_round_trips(calib_text, tmp_path):
    import dataclasses

    p = tmp_path / "c.yaml"
    p.write_text(calib_text)
    c = StereoCalibration.load_yaml(p)
    assert c.image_size == (640, 480) and c.rms_px == 0.0
    c.check_fits_frame()
    dataclasses.replace(c, rms_px=float("nan")).save_yaml(p)   # "unknown" is written as -1
    assert np.isnan(StereoCalibration.load_yaml(p).rms_px)


def test_calibration_for_other_image_sizes_does_not_fit_the_frame(calib_text, tmp_path):
    from pipeline.runner import Reconstructor

    p = tmp_path / "short.yaml"
    p.write_text(re.sub(r"image_height: \d+", "image_height: 360", calib_text))
    calib = StereoCalibration.load_yaml(p)   # a valid calibration of some camera ...
    with pytest.raises(CalibrationError, match=r"640x360.*each view .* 640x480"):
        Reconstructor(load_design("hexagon127"), calib)   # ... but not of this sensor's frames


def test_cli_bad_calibration_exit_code_2(calib_text, tmp_path, capsys):
    from stereotactip.cli import main

    p = tmp_path / "zero.yaml"
    p.write_text(_with_matrix(calib_text, "K1", [0] * 9))
    frames = tmp_path / "frames"
    frames.mkdir()
    import cv2

    cv2.imwrite(str(frames / "frame_0000.png"), np.zeros((480, 1280), np.uint8))
    rc = main(["reconstruct", str(frames), "--calib", str(p), "--out", str(tmp_path / "out")])
    err = capsys.readouterr().err.strip().splitlines()
    assert rc == 2 and len(err) == 1 and "zero.yaml" in err[0] and "K1" in err[0]


# ----- design files --------------------------------------------------------------------------

def _design_text():
    """hexagon127 written out as one standalone file (the shipped file extends a base)."""
    return to_toml(load_design("hexagon127"))


def _set(section, key, value):
    """Edit of the written-out hexagon127: ``key = value`` in ``[section]``."""
    def edit(text):
        head = f"[{section}]\n"
        i = text.index(head) + len(head)
        j = text.find("\n[", i)
        j = len(text) if j < 0 else j
        body, n = re.subn(rf"(?m)^{re.escape(key)} = .*$", f"{key} = {value}", text[i:j], count=1)
        assert n == 1, (section, key)
        return text[:i] + body + text[j:]
    return edit


DESIGN_CASES = {
    "thick_skin": (_set("skin", "thickness_mm", "50.0"), r"skin\.thickness_mm = 50 must be smaller than optics\.gel"),
    "skin_as_thick_as_gel": (_set("skin", "thickness_mm", "10.0"), r"skin\.thickness_mm = 10 must be smaller"),
    "deep_dome": (_set("pattern", "dome_height_mm", "50.0"), r"dome_height_mm = 50 must be at most gel\.radius_mm"),
    "dome_into_acrylic": (_set("pattern", "dome_height_mm", "9.0"), r"pins\.height_mm \+ pattern\.dome_height_mm"),
    "zero_focal": (_set("cameras.left", "fx_px", "0.0"), r"cameras\.left\.fx_px: must be in \[32, 64000\]"),
    "negative_focal": (_set("cameras.right", "fy_px", "-435.0"), r"cameras\.right\.fy_px"),
    "huge_focal": (_set("cameras.left", "fx_px", "1e308"), r"cameras\.left\.fx_px"),
    "negative_fps": (_set("cameras", "fps", "-30.0"), r"cameras\.fps: must be in \(0, 10000\]"),
    "zero_fps": (_set("cameras", "fps", "0.0"), r"cameras\.fps"),
    "toe_in_400": (_set("cameras", "toe_in_deg", "400.0"), r"cameras\.toe_in_deg: must be in \(-60, 60\)"),
    "negative_links": (_set("pattern", "links", "-12"), r"pattern\.links: must be in \[1, 64\]"),
    "million_layers": (_set("pattern", "layers", "1000000"), r"pattern\.layers: must be in \[2, 40\]"),
    "poisson_09": (_set("skin", "poisson_ratio", "0.9"), r"skin\.poisson_ratio: must be in \(0, 0\.5\)"),
    "poisson_half": (_set("gel", "poisson_ratio", "0.5"), r"gel\.poisson_ratio"),
    "negative_modulus": (_set("gel", "youngs_modulus_mpa", "-0.02"), r"gel\.youngs_modulus_mpa: must be in \(0,"),
    "negative_pin_modulus": (_set("pins", "youngs_modulus_mpa", "-1.0"), r"pins\.youngs_modulus_mpa"),
    "negative_marker_thickness": (_set("markers", "thickness_mm", "-0.3"), r"markers\.thickness_mm: must be in \(0,"),
    "marker_longer_than_pin": (_set("markers", "thickness_mm", "2.0"), r"markers\.thickness_mm = 2 must be smaller"),
    "marker_wider_than_pin": (_set("markers", "diameter_mm", "1.5"), r"markers\.diameter_mm = 1\.5 must be at most"),
    "pins_touch": (_set("pins", "diameter_mm", "2.6"), r"pins\.diameter_mm = 2\.6 must be smaller than pattern\.sep"),
    "wrong_camera_size": (_set("cameras", "width_px", "1280"), r"cameras\.width_px x height_px must be 640x480"),
    "negative_gel": (_set("optics", "gel_thickness_mm", "-10.0"), r"optics\.gel_thickness_mm: must be in \(0,"),
    "kilometre_air_gap": (_set("optics", "air_gap_mm", "1e6"), r"optics\.air_gap_mm: must be in \(0, 1000\]"),
    "folding_lens": (_set("cameras.left", "dist", "[-1.0, 0.0, 0.0, 0.0, 0.0]"),
                     r"cameras\.left\.dist: the radial distortion folds over"),
    "pattern_too_big": (_set("pattern", "separation_mm", "4.0"), r"marker pattern \(radius 24\.00 mm\) does not fit"),
}


@pytest.mark.parametrize("case", sorted(DESIGN_CASES))
def test_designs_without_physical_sense_are_refused(case, tmp_path):
    edit, message = DESIGN_CASES[case]
    p = tmp_path / f"{case}.toml"
    text = edit(_design_text())
    assert text != _design_text()
    p.write_text(text)
    t0 = time.perf_counter()
    with pytest.raises(DesignError, match=message) as info:
        load_design(p)
    assert time.perf_counter() - t0 < 1.0          # size limits come before anything is built
    assert str(p) in str(info.value) and "\n" not in str(info.value)


def test_binary_and_oversized_design_files(tmp_path):
    p = tmp_path / "bin.toml"
    p.write_bytes(b"\xff\xfe\x00garbage" * 10)
    with pytest.raises(DesignError, match=r"bin\.toml: not a text file"):
        load_design(p)
    big = tmp_path / "big.toml"
    big.write_text("# " + "x" * (2 << 20))
    with pytest.raises(DesignError, match=r"big\.toml: .* bytes"):
        load_design(big)


def test_builtin_designs_pass_every_check():
    from pipeline.design import analytic_pattern_radius_mm, list_designs

    names = list_designs()
    assert {"hexagon127", "square121", "circular217_dome"} <= set(names)
    for name in names:
        d = load_design(name)
        assert analytic_pattern_radius_mm(d.pattern) == pytest.approx(d.pattern_radius_mm(), abs=1e-9)


def test_cli_bad_design_exit_code_2(tmp_path, capsys):
    from stereotactip.cli import main

    p = tmp_path / "thick.toml"
    p.write_text(_set("skin", "thickness_mm", "50.0")(_design_text()))
    img = tmp_path / "f.png"
    import cv2

    cv2.imwrite(str(img), np.zeros((480, 1280), np.uint8))
    rc = main(["detect", str(img), "--design", str(p)])
    err = capsys.readouterr().err.strip().splitlines()
    assert rc == 2 and len(err) == 1 and "thick.toml" in err[0] and "skin.thickness_mm" in err[0]
