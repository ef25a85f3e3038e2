"""benchmarks.estimated: what a user's calibration session hands the pipeline, and its wiring into ``bench``."""

from __future__ import annotations

import json

import numpy as np
import pytest

from pipeline.design import load_design
from benchmarks import estimated as est
from twin.render import true_calibration


def test_drawn_stack_is_within_tolerances_reproducible_and_seeded():
    d = load_design("hexagon127")
    draws = [est.draw_stack(d, seed) for seed in range(50)]
    assert est.draw_stack(d, 3) == draws[3]                          # same design and seed: same build
    assert len({round(x["gel_thickness_mm"], 12) for x in draws}) == 50  # every seed a different build
    for key, tol in (("gel_thickness_mm", est.GEL_TOL_MM), ("acrylic_thickness_mm", est.ACRYLIC_TOL_MM),
                     ("gel_n", est.INDEX_TOL)):
        v = np.array([x[key] for x in draws])
        assert np.all(np.abs(v) <= tol)
        assert np.max(np.abs(v)) > 0.5 * tol                           # the draws do use the tolerance
    assert est.draw_stack(load_design("square121"), 3) != draws[3]    # streams differ per design


def test_oracle_setup_is_the_twins_exact_sensor():
    d = load_design("hexagon127")
    s = est.sensor_setup(d)
    assert s.mode == "oracle" and s.twin_design is d and s.design is d and s.n_gel is None
    t = true_calibration(d)
    assert np.array_equal(s.calib.K1, t.K1) and np.array_equal(s.calib.sensor_from_left, t.sensor_from_left)
    assert s.reconstructor_kw() == {}


def test_thickness_only_builds_a_different_stack_but_tells_the_pipeline_the_drawing():
    d = load_design("hexagon127")
    s = est.sensor_setup(d, mode="estimated", seed=5, sources="thickness")
    drawn = est.draw_stack(d, 5)
    assert s.design is d                                   # the pipeline gets the nominal drawing
    assert s.twin_design.optics.gel_thickness_mm == pytest.approx(d.optics.gel_thickness_mm
                                                                  + drawn["gel_thickness_mm"], abs=1e-12)
    assert s.twin_design.optics.acrylic_thickness_mm == pytest.approx(d.optics.acrylic_thickness_mm
                                                                      + drawn["acrylic_thickness_mm"], abs=1e-12)
    assert s.twin_design.optics.gel_n == d.optics.gel_n   # index not a source: unchanged, not fitted
    assert s.n_gel is None
    # the cameras sit below the built stack: they move with its thickness error
    dz = s.twin_design.camera_z_mm - d.camera_z_mm
    assert dz == pytest.approx(-(drawn["gel_thickness_mm"] + drawn["acrylic_thickness_mm"]), abs=1e-12)
    assert np.array_equal(s.calib.sensor_from_left, true_calibration(d).sensor_from_left)  # nominal pose
    assert s.provenance["drawn"]["gel_n"] == 0.0 and s.provenance["sources"] == ["thickness"]
    json.dumps(s.provenance)                               # recorded as JSON


def test_bad_mode_and_sources_are_user_errors():
    d = load_design("hexagon127")
    with pytest.raises(est.SetupError, match="calibration mode"):
        est.sensor_setup(d, mode="guess")
    with pytest.raises(est.SetupError, match="error sources"):
        est.parse_sources("calibration,focus")
    with pytest.raises(est.SetupError, match="error sources"):
        est.parse_sources("")
    assert est.parse_sources("thickness, calibration") == ("calibration", "thickness")


def test_estimated_setup_recovers_the_sensor_and_is_cached(tmp_path):
    """The full route (20 chessboard pairs, a 5-step board press) on the twin: the chessboard calibration is
    close to the truth, the exact-model index fit recovers the built gel index, and a second call reads the
    cache instead of rendering again."""
    d = load_design("hexagon127")
    s = est.sensor_setup(d, mode="estimated", seed=0, cache_dir=tmp_path)
    t = true_calibration(d)
    cal, idx = s.provenance["calibration"], s.provenance["index"]
    assert cal["cached"] is False and idx["cached"] is False
    assert cal["pairs_used"] >= 15 and cal["rms_px"] < 0.3
    assert abs(s.calib.baseline_mm - t.baseline_mm) < 0.1               # mm, of a 20 mm-class baseline
    true_n = s.twin_design.optics.gel_n
    assert true_n != d.optics.gel_n
    assert abs(s.n_gel - true_n) < 0.005, (s.n_gel, true_n)             # drawn deviations are up to 0.02
    assert idx["n_linear_effective"] > true_n + 0.03                   # the linear model's index is not it
    again = est.sensor_setup(d, mode="estimated", seed=0, cache_dir=tmp_path)
    assert again.provenance["calibration"]["cached"] is True and again.provenance["index"]["cached"] is True
    assert np.array_equal(again.calib.K1, s.calib.K1) and again.n_gel == s.n_gel
    assert sorted(p.suffix for p in tmp_path.iterdir()) == [".json", ".json", ".yaml"]


def test_bench_records_the_calibration_mode_and_rejects_sources_without_estimated(tmp_path):
    from benchmarks import registry as reg
    from benchmarks.registry import Result, register
    from stereotactip.cli import main

    seen = {}

    def probe(ctx):
        """Probe: which setup the context hands an experiment."""
        s = ctx.sensor_setup(ctx.design())
        seen[ctx.calibration] = s
        return Result(designs=[s.design], setups=[s.provenance])

    saved = dict(reg._REGISTRY)
    try:
        register("probe", tags=("quick",), metrics={"x": "1"})(probe)
        out = tmp_path / "o"
        assert main(["bench", "probe", "--out", str(out), "--no-progress"]) == 0
        rec = json.loads((out / "probe.json").read_text())
        assert rec["calibration"]["mode"] == "oracle" and rec["calibration"]["setups"][0]["mode"] == "oracle"
        assert main(["bench", "probe", "--out", str(out), "--no-progress", "--calibration", "estimated",
                     "--error-sources", "thickness"]) == 0
        rec = json.loads((out / "probe.json").read_text())
        assert rec["calibration"]["mode"] == "estimated" and rec["calibration"]["error_sources"] == ["thickness"]
        assert rec["calibration"]["setups"][0]["drawn"]["gel_thickness_mm"] == \
            pytest.approx(est.draw_stack(load_design("hexagon127"), 0)["gel_thickness_mm"])
        assert seen["estimated"].twin_design.optics.gel_thickness_mm != seen["oracle"].twin_design.optics.gel_thickness_mm
        assert main(["bench", "probe", "--out", str(out), "--error-sources", "thickness"]) == 2
        assert main(["bench", "probe", "--out", str(out), "--calibration", "estimated",
                     "--error-sources", "focus"]) == 2
    finally:
        reg._REGISTRY.clear()
        reg._REGISTRY.update(saved)
