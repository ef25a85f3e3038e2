"""fit-twin and validate for the monocular TacTip: the fit's 1-D searches on stand-in contexts with known
optima, the baselines and goals of validate, and both commands on the shared real TacTip frames (which skip with
the reason where those frames are absent). The twin itself (design schema, tap physics, render, identification)
is tests/test_tactip.py."""

from __future__ import annotations

import json
import math
from pathlib import Path

import cv2
import numpy as np
import pytest

from pipeline.design import load_design

DATA = Path(__file__).resolve().parents[2] / "shared" / "data" / "real_frames"
TARGETS = DATA / "tactip331_tap_targets.csv"
ROOT = Path(__file__).resolve().parents[1]
HAVE_REAL = TARGETS.is_file()


@pytest.fixture(scope="module")
def design():
    return load_design("tactip331")


# ----- the fit's searches on stand-in contexts ----------------------------------------------

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
