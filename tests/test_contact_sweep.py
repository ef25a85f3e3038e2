"""The contact validity sweep's bookkeeping (benchmarks/experiments/contact.py): every captured frame counted, an
invalid frame named and failing the finding, the bound applied to the largest penetration. The presses themselves
run in the CI gate's quick variant (`bench contact --quick`), whose frames are gated there."""

import math

import pytest

from benchmarks.experiments import contact
from benchmarks.registry import Result


def _row(family, value, depth, pen, valid=True, reasons=()):
    return {"design": "hexagon127", "skin_mm": 1.0, "separation_mm": 2.54, "family": family,
            "sigma2_mm2": value if family == "gaussian" else None,
            "omega_rad_per_mm": contact.OMEGAS[value] if family == "sine" else None,
            "condition": contact._label(family, value), "depth_mm": depth, "skin_penetration_mm": pen,
            "skin_penetration_p99_mm": pen / 2, "contact_force_n": 1.0 + depth, "physics_valid": valid,
            "physics_reasons": list(reasons)}


def test_every_frame_is_counted_and_the_worst_one_decides():
    rows = [_row("gaussian", 2.5, d, 0.004 * d) for d in (1.0, 2.0, 3.0, 4.0, 5.0)] + [_row("sine", 4, 5.0, 0.017)]
    out = Result()
    contact._summarise(out, rows)
    m = {k: v[0] for k, v in out.metrics.items()}
    assert (m["frames"], m["invalid_cells"], m["valid_cells"], m["presses"]) == (6, 0, 6, 2)
    assert m["penetration_max_mm"] == pytest.approx(0.02) and m["penetration_max_mm_sine"] == pytest.approx(0.017)
    assert m["penetration_max_mm_gaussian"] == pytest.approx(0.02) and m["contact_force_max_n"] == pytest.approx(6.0)
    assert out.findings[0].agrees is True and not out.notes


def test_an_invalid_frame_is_named_and_fails_the_finding():
    rows = [_row("gaussian", 20.0, 1.0, 0.01), _row("gaussian", 20.0, 2.0, 0.08, False, ["skin 0.080 mm inside"])]
    out = Result()
    contact._summarise(out, rows)
    assert out.metrics["invalid_cells"][0] == 1 and out.findings[0].agrees is False
    assert "hexagon127 σ²=20 at 2 mm (skin 0.080 mm inside)" in out.notes[0]


def test_a_frame_within_its_checks_but_beyond_the_bound_fails_the_finding():
    out = Result()
    contact._summarise(out, [_row("sine", 5, 5.0, contact.PENETRATION_BOUND_MM * 1.5)])
    assert out.findings[0].agrees is False


def test_the_sweep_covers_the_whole_range_and_refuses_an_unknown_family():
    assert contact.SIGMA2_MM2 == (5 / 3, 2.5, 5.0, 10.0, 20.0, 50.0)
    assert [round(w * 15 / math.pi, 9) for w in contact.OMEGAS] == [1, 2, 3, 4, 5, 6]
    with pytest.raises(ValueError, match="unknown contact family"):
        contact.press_condition(None, "sphere", 1.0)
