"""The sine experiment's scores when presses fail: an ω whose every cell raised (with μ = 1 both quick
π/5 presses pushed markers out of the gel and did not render) is reported as unmeasured, not a crash of the whole experiment."""

import math

import pytest


def _row(design, k, pen):
    return {"design": design.name, "separation_mm": design.pattern.separation_mm, "omega_index": k,
            "upper_rms_mm": 0.3, "lowest_point_rms_mm": 0.5, "valley_gap_mm": 0.04,
            "skin_penetration_mm": pen, "physics_valid": pen <= 0.05}


def test_an_omega_without_cells_scores_nan_and_the_others_their_own():
    from benchmarks.experiments.sine import _Grid, _score_against_cad
    from benchmarks.registry import Result
    from pipeline.design import load_design

    d = load_design("hexagon61_sep354")
    rows = [_row(d, 0, 0.044), _row(d, 2, 2.59), _row(d, 2, float("nan"))]   # ω index 4: every press failed to render
    out = Result(designs=[d], setups=[])
    _score_against_cad(out, rows, [r for r in rows if r["physics_valid"]], _Grid([0, 2, 4], [0.0], 1, 0.0, [d], {}))
    m = {k: v for k, (v, _) in out.metrics.items()}
    assert m["skin_penetration_max_mm"] == pytest.approx(2.59)
    assert m["skin_penetration_max_mm_w1"] == pytest.approx(0.044)
    assert m["skin_penetration_max_mm_w3"] == pytest.approx(2.59)      # an unmeasured cell does not hide the other
    assert math.isnan(m["skin_penetration_max_mm_w5"]) and math.isnan(m["valley_gap_mm_w5"])
    assert math.isnan(m["valley_gap_mm_w3"]) and m["valley_gap_mm_w1"] == pytest.approx(0.04)
