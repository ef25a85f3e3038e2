"""The identification benchmark's press-sequence condition (benchmarks/experiments/identification_twin.py) and
the runner's identification on given blobs (``Reconstructor.identify``), against analytic truth. The twin's
own presses run in the benchmark's CI gate (`bench identification --quick`), not here."""

from types import SimpleNamespace

import numpy as np
import pytest

from benchmarks.experiments import identification_twin as twin_cond
from pipeline.design import load_design
from pipeline.io.synthetic import gaussian_press_markers, nominal_calibration, synth_stereo_frame
from pipeline.runner import Reconstructor
from pipeline.vision.detection import DetectionParams, detect_markers


def _analytic_sequence(design, sigma_mm=3.0):
    return [gaussian_press_markers(design, d, sigma_mm=sigma_mm, lateral=0.2) for d in (1.0, 2.0, 3.0, 4.0, 5.0)]


@pytest.mark.parametrize("name", ["hexagon127", "circular217_dome"])
def test_a_press_sequence_read_with_defects_gives_no_wrong_pair(name):
    """Five frames from rest to 5 mm, 3 % missing + 3 % spurious blobs per view and frame: no wrong pair in
    any frame, and at least 95 % of the markers present in both views identified in each (measured
    0.995-1.0 with seed 3); without defects every marker of every frame."""
    design = load_design(name)
    calib = nominal_calibration(design)
    seq = _analytic_sequence(design)
    recs = twin_cond.read_sequence(design, calib, seq, np.random.default_rng(3))
    assert [r["wrong"] for r in recs] == [0] * 5
    assert min(r["correct"] / r["present"] for r in recs) >= 0.95, recs
    clean = twin_cond.read_sequence(design, calib, seq, np.random.default_rng(3), rate=0.0)
    assert all(r["correct"] == r["present"] == design.marker_count for r in clean), clean


def test_trials_cycle_the_sequences_and_the_table_counts_them():
    design = load_design("hexagon61_sep354")
    calib = nominal_calibration(design)
    seqs = [{"xyz": _analytic_sequence(design)[:2], "press": "a"}, {"xyz": _analytic_sequence(design, 5.0)[:3],
                                                                      "press": "b"}]
    recs = twin_cond.read_trials(design, calib, seqs, np.random.default_rng(0), 12)
    assert len(recs) == 12
    assert [r["press"] for r in recs] == ["a", "a", "b", "b", "b"] * 2 + ["a", "a"]
    rows = twin_cond.table_rows(design, recs)
    assert [(r["press"], r["depth_mm"], r["frames"]) for r in rows] == [("a", 1.0, 3), ("a", 2.0, 3), ("b", 1.0, 2),
                                                                         ("b", 2.0, 2), ("b", 3.0, 2)]
    assert sum(r["wrong_ids"] for r in rows) == sum(r["wrong"] for r in recs) == 0


def test_a_press_sequence_ends_at_its_first_physically_invalid_frame(monkeypatch):
    """A frame whose skin broke the twin's checks, and every frame after it, is left out of the sequence."""
    import twin.simulate

    design = load_design("hexagon127")
    flags = [True, True, False, True, True]
    fake = [SimpleNamespace(physics_valid=v, marker_xyz_mm=np.full((3, 3), float(k))) for k, v in enumerate(flags)]
    monkeypatch.setattr(twin.simulate, "press_truth", lambda *a, **k: fake)
    r = twin_cond.press_sequence(design, "gaussian", 10.0)
    assert r["frames"] == 5 and r["invalid_from"] == 3
    assert [x[0, 0] for x in r["xyz"]] == [0.0, 1.0]
    with pytest.raises(ValueError, match="unknown indenter"):
        twin_cond.press_sequence(design, "cone", 1.0)


def test_identify_on_detected_blobs_gives_what_process_gives_on_the_frames():
    """``Reconstructor.identify`` is the identification of ``process``: on the same frames (detected blobs),
    the same ids in the same views, frame after frame."""
    design = load_design("hexagon127")
    calib = nominal_calibration(design)
    frames = [synth_stereo_frame(design, calib, xyz) for xyz in _analytic_sequence(design)[:3]]
    params = DetectionParams()          # given, so the runner does not narrow its scales after a frame
    a, b = (Reconstructor(design, calib, detection_params=params, view_threads=1) for _ in range(2))
    for f in frames:
        got = a.process(f).matches
        m = b.identify(detect_markers(f.left, params=params), detect_markers(f.right, params=params))
        np.testing.assert_array_equal(m.ids, got.ids)
        np.testing.assert_allclose(m.left_px, got.left_px)
        assert len(m.ids) == design.marker_count


def test_the_presses_run_through_the_executor_and_a_pattern_without_a_valid_frame_leaves_the_condition_out(
        monkeypatch, tmp_path):
    """``press_all`` runs every (design, press) cell on the context's engine and keeps the sequences with a valid
    frame, with a note for each cut; when one pattern has none the condition is left out with a note (its
    trials would have nothing to read), and a press that raised is named."""
    from benchmarks.executor import InlineEngine
    from benchmarks.registry import Context, Result

    designs = [load_design("hexagon61_sep354"), load_design("hexagon127")]
    xyz = [np.zeros((3, 3))]

    def fake(design, kind, value):
        if kind == "sine" and design.name == "hexagon127":
            raise RuntimeError("solver failed")
        if kind == "sine":
            return {"xyz": [], "frames": 5, "invalid_from": 1}
        return {"xyz": xyz * 2, "frames": 5, "invalid_from": 3}

    monkeypatch.setattr(twin_cond, "press_sequence", fake)
    ctx = Context(out_dir=tmp_path, progress=False, engine=InlineEngine(),
                  params={"twin_presses": [["gaussian", 10.0], ["sine", 1.0]]})
    out = Result(designs=designs)
    seqs = twin_cond.press_all(ctx, out, designs)
    assert {k: [s["press"] for s in v] for k, v in seqs.items()} == {"hexagon61_sep354": ["gaussian σ²=10"],
                                                                      "hexagon127": ["gaussian σ²=10"]}
    assert out.metrics["twin_sequence_frames_invalid"][0] == 3 + 3 + 5
    assert any("solver failed" in n for n in out.notes) and any("from frame 3" in n for n in out.notes)
    ctx = Context(out_dir=tmp_path, progress=False, engine=InlineEngine(), params={"twin_presses": [["sine", 1.0]]})
    out = Result(designs=designs)
    assert twin_cond.press_all(ctx, out, designs) == {}
    assert any(n.startswith("twin_sequence left out: no physically valid pressed frame for hexagon61_sep354")
               for n in out.notes)
