"""The tracking experiment's letter motions in the twin: every captured frame physically valid."""

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
