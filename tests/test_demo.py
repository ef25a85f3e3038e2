"""The README's main command: twin press → files → pipeline → scores, end to end (short press)."""

import json

import pytest

from stereotactip.cli import main

# Marker localisation bound for the demo frames: the rendered 0.3 mm-thick white marker walls shift blob
# centroids by ~0.35 px RMS in opposite directions in the two views (measured in tests/test_render.py),
# i.e. ~0.7 px of disparity at ~170 px disparity ≈ 0.4 % of the ~30 mm range ≈ 0.13 mm; 0.2 mm leaves
# room for noise while still failing on any axis flip, mismatched id or refraction error (≥ 0.5 mm).
MARKER_RMS_TOL_MM = 0.2


@pytest.mark.slow
@pytest.mark.physics
@pytest.mark.render
def test_demo_end_to_end(tmp_path, capsys):
    out = tmp_path / "demo"
    assert main(["demo", "--out", str(out), "--depth", "2", "--frames", "1", "--quiet"]) == 0
    doc = json.loads((out / "demo.json").read_text())
    (frame,) = doc["frames"]
    assert frame["markers_matched"] == frame["markers_expected"] == 127
    assert frame["marker_rms_mm"] < MARKER_RMS_TOL_MM
    assert frame["depth_mm"] == pytest.approx(2.0)
    # the demo presses on the axis contact mesh: its frame passes the twin's own physics checks
    assert frame["twin_physics_valid"] is True and doc["twin_invalid_frames"] == 0
    assert frame["twin_validity"]["penetration_max_mm"] <= 0.05
    for name in ("demo.png", "twin/calib.yaml", "twin/frame_0000.png", "twin/truth_0000.npz",
                 "pipeline/summary.json", "pipeline/heightmap_0000.npz", "pipeline/surface_0000.stl"):
        assert (out / name).is_file(), name
    assert "127/127 markers" in capsys.readouterr().out


# With a user's calibration (twin.estimated, seed 0: stack built 0.099 mm thinner gel, +0.006 mm acrylic,
# n +0.011) the marker RMS was 0.084-0.087 mm over the 5 mm press (oracle 0.064-0.067 mm). The bound: the
# oracle's 0.2 mm plus the largest camera shift a build within tolerance makes (0.2 + 0.1 mm of stack).
ESTIMATED_MARKER_RMS_TOL_MM = MARKER_RMS_TOL_MM + 0.3


@pytest.mark.slow
@pytest.mark.physics
@pytest.mark.render
def test_demo_with_an_estimated_calibration(tmp_path, capsys):
    out = tmp_path / "demo"
    assert main(["demo", "--out", str(out), "--depth", "2", "--frames", "1", "--quiet",
                 "--calibration", "estimated"]) == 0
    doc = json.loads((out / "demo.json").read_text())
    cal = doc["calibration"]
    assert cal["mode"] == "estimated" and cal["sources"] == ["calibration", "index", "thickness"]
    # the twin built (and wrote the truth of) the perturbed stack; the pipeline got the estimates
    assert cal["true_stack"]["gel_thickness_mm"] != cal["assumed_stack"]["gel_thickness_mm"]
    assert abs(cal["index"]["n"] - cal["true_stack"]["gel_n"]) < 0.005
    assert (out / "calib_estimated.yaml").is_file() and (out / "calibration_cache").is_dir()
    (frame,) = doc["frames"]
    assert frame["markers_matched"] == frame["markers_expected"] == 127
    assert frame["marker_rms_mm"] < ESTIMATED_MARKER_RMS_TOL_MM
    assert "calib_estimated.yaml and n_gel = " in capsys.readouterr().out
