"""Data types validate shape, dtype and finiteness; the calibration file round-trips."""

import numpy as np
import pytest

from pipeline.types import (Blobs, CalibrationError, DataError, HeightMap, MarkerCloud, MarkerMatches,
                            StereoCalibration, StereoFrame)


def test_stereo_frame_checks_size_and_dtype():
    StereoFrame(np.zeros((480, 1280, 3), np.uint8))
    with pytest.raises(DataError, match="1280x480"):
        StereoFrame(np.zeros((480, 640, 3), np.uint8), source="cam0")
    with pytest.raises(DataError, match="uint8"):
        StereoFrame(np.zeros((480, 1280, 3), np.float32))
    with pytest.raises(DataError, match="grey"):
        StereoFrame(np.zeros((480, 1280, 4), np.uint8))


def test_empty_results_keep_shape():
    b = Blobs.empty()
    assert b.xy_px.shape == (0, 2) and len(b) == 0
    m = MarkerMatches([], [], [])
    assert m.left_px.shape == (0, 2)
    c = MarkerCloud([], [])
    assert c.xyz_mm.shape == (0, 3)


def test_non_finite_and_mismatched_arrays_are_refused():
    with pytest.raises(DataError, match="NaN"):
        MarkerCloud([0], [[0.0, np.nan, 1.0]])
    with pytest.raises(DataError, match="length"):
        MarkerMatches([0, 1], [[0, 0]], [[0, 0]])
    with pytest.raises(DataError, match="duplicate"):
        MarkerMatches([1, 1], [[0, 0], [1, 1]], [[0, 0], [1, 1]])
    with pytest.raises(DataError, match="increasing"):
        HeightMap([1.0, 0.0], [0.0], [[0.0, 0.0]])


def _calib():
    K = np.array([[440.0, 0, 320], [0, 440, 240], [0, 0, 1]])
    return StereoCalibration(K1=K, D1=np.zeros(5), K2=K, D2=np.zeros(5), R=np.eye(3),
                             T=np.array([-12.5, 0, 0]), rms_px=0.12)


def test_calibration_yaml_roundtrip(tmp_path):
    c = _calib()
    c.save_yaml(tmp_path / "c.yaml")
    d = StereoCalibration.load_yaml(tmp_path / "c.yaml")
    for k in ("K1", "D1", "K2", "D2", "R", "T", "sensor_from_left"):
        np.testing.assert_allclose(getattr(d, k), getattr(c, k))
    assert d.baseline_mm == pytest.approx(12.5) and d.rms_px == pytest.approx(0.12)


def test_calibration_with_nan_or_missing_key_is_a_clear_error(tmp_path):
    c = _calib()
    p = tmp_path / "c.yaml"
    c.save_yaml(p)
    text = p.read_text()
    assert "data: [ 440.," in text  # K1's first entry, as OpenCV writes it
    bad = tmp_path / "nan.yaml"
    bad.write_text(text.replace("data: [ 440.,", "data: [ .nan,", 1))
    with pytest.raises(CalibrationError, match="nan.yaml"):
        StereoCalibration.load_yaml(bad)
    missing = tmp_path / "missing.yaml"
    missing.write_text(text.replace("R: !!opencv-matrix", "Rx: !!opencv-matrix"))
    with pytest.raises(CalibrationError, match="missing key 'R'"):
        StereoCalibration.load_yaml(missing)
