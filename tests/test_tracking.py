"""The tracking experiment's letter motions in the twin: every captured frame physically valid."""

import numpy as np
import pytest


@pytest.mark.physics
def test_letter_e_slid_along_the_paper_path_stays_valid():
    """'e' pressed 3 mm and slid twice by 1 mm with friction (mu = 1), the experiment's own indenter, mesh and
    path: every frame settles within the penetration bound. With 3 mm letters the backing plate sank to the
    skin's rest level and, after the 2 mm slide, cut the skin bulging beside the letter 0.197 mm deep."""
    from benchmarks.experiments import tracking
    from pipeline.design import load_design
    from twin import robot
    from twin.validity import PENETRATION_MAX_MM

    sim = tracking._letter_sim(load_design("hexagon127"), "e")
    out = robot.execute(sim, tracking._paper_motion("e"))
    assert len(out) == 1 + len(tracking.PAPER_POSES["e"])
    assert sim.face_contact and sim.face_contact_fallback is None
    for _, stats, truth in out:
        v = truth.validity
        assert stats.converged and v["valid"], v["reasons"]
        assert v["penetration_max_mm"] <= PENETRATION_MAX_MM


@pytest.mark.physics
def test_the_rapid_o_keeps_every_marker_through_dtrc_and_not_through_nearest_neighbours(monkeypatch):
    """'o' touched, then moved 2 mm + 2 mm diagonally at the robot's rapid speed with friction: the stuck skin
    moves up to 2.4 mm between the two frames (separation 2.54 mm). In the left view that move bends the rings
    under the letter beyond ring coding and the frame-to-frame map (seven markers beside the letter left open);
    the right view reads all 127, and its ids carried across through the stereo geometry identify the seven
    (``pipeline.cross_view``). DTRC identifies every marker in every frame, none wrong; nearest-neighbour
    tracking confuses markers in that frame."""
    from benchmarks.experiments import tracking
    from benchmarks.experiments._common import identity_correct, reconstruct
    from pipeline.design import load_design
    from twin.render import true_calibration

    design = load_design("hexagon127")
    seq = tracking._simulate(design, "o", np.random.default_rng(0))
    frames, truths = [f for f, _ in seq], [t for _, t in seq]
    assert tracking._max_step_mm(truths) > 2.0
    calib = true_calibration(design)
    for tracker, every in (("dtrc", True), ("nn", False)):
        results = reconstruct(design, calib, frames, tracker=tracker)
        ok = [identity_correct(r.corrected.ids, r.corrected.xyz_mm, t, design.pattern.separation_mm / 2)
              for r, t in zip(results, truths)]
        assert all(len(k) == design.marker_count and k.all() for k in ok) == every, [int(k.sum()) for k in ok]
    import pipeline.runner as runner

    monkeypatch.setattr(runner, "across_views", lambda blobs, codings, d, locate, previous=None: codings)
    last = reconstruct(design, calib, frames, tracker="dtrc")[-1]       # each view on its own
    ok = identity_correct(last.corrected.ids, last.corrected.xyz_mm, truths[-1], design.pattern.separation_mm / 2)
    assert ok.all() and len(ok) < design.marker_count
