"""Fuzzing the readers a user can hand a file to: calibration YAML, design TOML, frames.

For any input the reader either returns a valid result or raises its one-line UserError naming the
file: never another exception (a library's traceback), never a hang. Derandomized, so the examples
are the same on every run and in CI.
"""

import re
import tempfile
import time
from pathlib import Path

import cv2
import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from pipeline.design import DesignError, SensorDesign, design_path, load_design, to_toml
from pipeline.errors import SourceError, UserError
from pipeline.types import CalibrationError, StereoCalibration

FUZZ = settings(derandomize=True, database=None, deadline=None, max_examples=100,
                suppress_health_check=[HealthCheck.too_slow])
#: No single reader call may take longer than this (a hang, or work done before validation).
MAX_CALL_S = 2.0

_DIR = Path(tempfile.mkdtemp(prefix="fuzz_"))


def _timed(fn, *args):
    t0 = time.perf_counter()
    try:
        return fn(*args)
    finally:
        assert time.perf_counter() - t0 < MAX_CALL_S, f"{fn.__name__} took {time.perf_counter() - t0:.1f} s"


def _assert_one_line(exc: UserError, path: Path) -> None:
    text = str(exc)
    assert str(path) in text and "\n" not in text and "Traceback" not in text


# values a file can hold where a number is expected
yaml_scalars = st.one_of(
    st.floats(allow_nan=True, allow_infinity=True).map(lambda v: ".nan" if v != v else
                                                       (".inf" if v == float("inf") else
                                                        ("-.inf" if v == float("-inf") else repr(v)))),
    st.integers(min_value=-10**30, max_value=10**30).map(str),
    st.sampled_from(["", "abc", "[]", "{}", "~", "null", "true", "0x10", "1e999", "!!opencv-matrix", "'5'",
                     "- 1", ":", "\"\"", "[ 1, 2 ]"]),
)


@pytest.fixture(scope="module")
def calib_text():
    from pipeline.io.synthetic import nominal_calibration

    p = _DIR / "good.yaml"
    nominal_calibration(load_design("hexagon127")).save_yaml(p)
    return p.read_text()


def _check_calibration(path: Path) -> None:
    try:
        c = _timed(StereoCalibration.load_yaml, path)
    except CalibrationError as exc:
        _assert_one_line(exc, path)
        return
    for k in ("K1", "K2", "D1", "D2", "R", "T", "sensor_from_left"):
        assert np.all(np.isfinite(getattr(c, k)))
    assert c.K1[0, 0] > 0 and c.K2[1, 1] > 0 and 0.1 <= c.baseline_mm <= 1000
    assert abs(np.linalg.det(c.R) - 1) < 1e-5


@FUZZ
@given(data=st.data())
def test_calibration_with_any_value_replaced(calib_text, data):
    """Replace one scalar, one matrix entry, a header field or the dt of a key with anything."""
    spots = [m.span(1) for m in re.finditer(r"(?m)^\w+: ([^!\n][^\n]*)$", calib_text)]     # scalars
    spots += [m.span(1) for m in re.finditer(r"(?m)^   (?:rows|cols|dt): (\S+)$", calib_text)]
    spots += [m.span() for m in re.finditer(r"-?\d+\.?\d*(?:e[-+]?\d+)?", calib_text)]     # numbers
    a, b = data.draw(st.sampled_from(spots))
    text = calib_text[:a] + data.draw(yaml_scalars) + calib_text[b:]
    p = _DIR / "replaced.yaml"
    p.write_text(text)
    _check_calibration(p)


@FUZZ
@given(cut=st.integers(min_value=0, max_value=4000), junk=st.binary(max_size=64))
def test_calibration_truncated_or_with_junk(calib_text, cut, junk):
    p = _DIR / "cut.yaml"
    p.write_bytes(calib_text.encode()[:cut] + junk)
    _check_calibration(p)


@FUZZ
@given(raw=st.binary(max_size=512))
def test_calibration_from_arbitrary_bytes(raw):
    p = _DIR / "bytes.yaml"
    p.write_bytes(raw)
    _check_calibration(p)


# ----- designs -------------------------------------------------------------------------------

toml_values = st.one_of(
    st.floats(allow_nan=True, allow_infinity=True).map(lambda v: "nan" if v != v else
                                                       ("inf" if v == float("inf") else
                                                        ("-inf" if v == float("-inf") else repr(v)))),
    st.integers(min_value=-10**12, max_value=10**12).map(str),
    st.sampled_from(['"text"', "true", "[]", "[1, 2]", "{}", "1979-05-27", '""', "0x7fffffff", "1e308",
                     "[1.0, 2.0, 3.0, 4.0, 5.0]", "[1e308, 0, 0, 0, 0]", "'", "= 3"]),
)


def _check_design(path: Path) -> None:
    try:
        d = _timed(load_design, path)
    except DesignError as exc:
        _assert_one_line(exc, path)
        return
    assert isinstance(d, SensorDesign)
    _timed(d.rest_markers_mm)          # a design that loads is buildable, quickly


@FUZZ
@given(data=st.data())
def test_design_with_any_value_replaced(data):
    # the written-out design (every key in one file) or the file as shipped (its extends line and pattern)
    text = data.draw(st.sampled_from([to_toml(load_design("hexagon127")), design_path("hexagon127").read_text()]))
    spots = [m.span(1) for m in re.finditer(r"(?m)^\w+ = (.*)$", text) if '"""' not in m.group(1)]
    a, b = data.draw(st.sampled_from(spots))
    p = _DIR / "replaced.toml"
    p.write_text(text[:a] + data.draw(toml_values) + text[b:])
    _check_design(p)


@FUZZ
@given(data=st.data())
def test_design_with_two_values_scaled(data):
    """Physically plausible-looking edits: two numbers scaled by factors from 1e-3 to 1e3."""
    text = to_toml(load_design("hexagon127"))
    spots = [m.span(1) for m in re.finditer(r"(?m)^\w+ = (-?\d+\.?\d*)$", text)]
    for _ in range(2):
        a, b = data.draw(st.sampled_from(spots))
        v = float(text[a:b]) * data.draw(st.sampled_from([1e-3, 0.1, 0.5, 2.0, 10.0, 1e3, -1.0]))
        text = text[:a] + (repr(v) if "." in text[a:b] else str(int(v))) + text[b:]
        spots = [m.span(1) for m in re.finditer(r"(?m)^\w+ = (-?\d+\.?\d*(?:e-?\d+)?)$", text)]
    p = _DIR / "scaled.toml"
    p.write_text(text)
    _check_design(p)


@FUZZ
@given(raw=st.binary(max_size=512))
def test_design_from_arbitrary_bytes(raw):
    p = _DIR / "bytes.toml"
    p.write_bytes(raw)
    _check_design(p)


# ----- frames --------------------------------------------------------------------------------

@st.composite
def images(draw):
    h = draw(st.sampled_from([1, 3, 479, 480, 481]))
    w = draw(st.sampled_from([1, 640, 1279, 1280, 1281]))
    ch = draw(st.sampled_from([None, 1, 3, 4]))
    dtype = draw(st.sampled_from([np.uint8, np.uint16]))
    shape = (h, w) if ch is None else (h, w, ch)
    value = draw(st.integers(0, 255))
    return np.full(shape, value, dtype=dtype)


@settings(FUZZ, max_examples=25)
@given(img=images(), suffix=st.sampled_from([".png", ".tiff"]))
def test_frame_readers_agree_on_any_image(img, suffix):
    """open_source (reconstruct, record) and check_frame (detect) accept exactly the same images."""
    from pipeline.io.sources import check_frame, open_source

    p = _DIR / f"frame{suffix}"
    assert cv2.imwrite(str(p), img)
    verdicts = []
    for read in (lambda: next(iter(open_source(p))).image,
                 lambda: check_frame(cv2.imread(str(p), cv2.IMREAD_UNCHANGED), str(p))):
        try:
            out = _timed(read)
        except SourceError as exc:
            _assert_one_line(exc, p)
            verdicts.append(None)
        else:
            assert out.shape[:2] == (480, 1280) and out.dtype == np.uint8
            verdicts.append(out)
    a, b = verdicts
    assert (a is None) == (b is None)
    if a is not None:
        np.testing.assert_array_equal(a, b)
    ok_shape = img.shape[:2] == (480, 1280) and img.dtype == np.uint8
    assert (a is not None) == ok_shape


@settings(FUZZ, max_examples=40)
@given(raw=st.binary(max_size=256), keep=st.integers(0, 2000))
def test_truncated_or_garbage_frame_files(raw, keep):
    from pipeline.io.sources import open_source

    good = cv2.imencode(".png", np.zeros((480, 1280), np.uint8))[1].tobytes()
    p = _DIR / "broken.png"
    p.write_bytes(good[:keep] + raw)
    try:
        frames = _timed(lambda: list(open_source(p)))
    except SourceError as exc:
        _assert_one_line(exc, p)
    else:
        assert len(frames) == 1 and frames[0].image.shape == (480, 1280)
