"""The TacTip twin's optional Coulomb contact on the tapped plane (twin.tactip_friction): the frictionless
tap unchanged at 0, touching nodes held by friction on a tilted tap, and the smoothed Coulomb term's
derivatives."""

from __future__ import annotations

import numpy as np
import pytest

from pipeline.design import load_design


@pytest.fixture(scope="module")
def skin():
    """The tactip331 dome's skin model (its design: ``skin.design``)."""
    from twin.tactip import DomeSkin

    return DomeSkin(load_design("tactip331"))


def test_a_frictionless_tap_is_one_solve_at_the_final_depth_as_before(skin):
    """tap_friction = 0 (the default) is the frictionless model: one projected-Newton solve at the final
    depth, the same energy and iterations as before friction existed (recorded), with or without the key;
    the press followed in depth steps with a vanishing coefficient reaches the same equilibrium."""
    from twin.tactip import TapPose

    params = skin.design.twin_params()
    assert params["tap_friction"] == 0.0
    pose = TapPose(2.0, 12.0, -8.0)
    X, info = skin.tap(pose, params)
    assert info["energy"] == pytest.approx(0.6959724972568433, rel=1e-9) and info["iterations"] == 9
    assert "steps" not in info and "slip_mm" not in info
    X2, _ = skin.tap(pose, {k: v for k, v in params.items() if k != "tap_friction"})
    np.testing.assert_array_equal(X, X2)
    Xp, infop = skin.tap(pose, {**params, "tap_friction": 1e-12})
    assert infop["converged"] and len(infop["steps"]) >= 2
    assert np.max(np.abs(Xp - X)) < 1e-3


def test_coulomb_friction_holds_touching_nodes_on_a_tilted_tap(skin, monkeypatch):
    """On a tilted plane pressed along the sensor axis a frictionless skin slides along the plane; a Coulomb
    coefficient cuts the touching nodes' slip relative to the plane, the more the larger it is, and a large
    one approaches no-slip (the slip left is the smoothing's elastic stick, a few FRICTION_EPS_MM)."""
    import twin.tactip as tt

    import twin.tactip_friction

    monkeypatch.setattr(twin.tactip_friction, "FRICTION_STEP_MM", 0.5)
    pose = tt.TapPose(2.0, 12.0, -8.0)
    params = skin.design.twin_params()
    m, c = skin.plane(pose, params)
    slips, states = {}, {}
    for mu in (1e-12, 0.3, 1.0, 10.0):
        X, info = skin.tap(pose, {**params, "tap_friction": mu})
        assert info["converged"] and info["penetration_max_mm"] < 2e-3
        touched = info["slip_mm"] > 0
        assert touched.sum() >= 10
        slips[mu], states[mu] = float(info["slip_mm"][touched].mean()), X
    assert slips[1e-12] > 0.05                                  # frictionless: the skin slides
    assert slips[1e-12] > slips[0.3] > slips[1.0] > slips[10.0]
    assert slips[10.0] < 0.05 * slips[1e-12] and slips[10.0] < 5 * tt.FRICTION_EPS_MM
    # friction changes where the skin ends up (held by the plane instead of sliding)
    assert np.max(np.abs(states[10.0] - states[1e-12])) > 0.05


def test_the_smoothed_coulomb_term_is_consistent(skin):
    """The friction potential's gradient and Hessian match finite differences below and beyond the
    smoothing slip, the force's magnitude is mu x lambda beyond it, and the Hessian is positive
    semi-definite."""
    from twin.tactip_friction import FRICTION_EPS_MM, coulomb_dissipation

    m = np.array([0.3, -0.2, 1.0])
    m /= np.linalg.norm(m)
    P = np.eye(3) - np.outer(m, m)
    rng = np.random.default_rng(3)
    for scale in (0.3 * FRICTION_EPS_MM, 5 * FRICTION_EPS_MM):
        u = rng.normal(size=(6, 3)) @ P
        u *= scale / np.linalg.norm(u, axis=1, keepdims=True)
        lam = rng.uniform(0.1, 2.0, 6)
        e, g, H = coulomb_dissipation(u, lam, 0.7, m, hessian=True)
        h = 1e-9
        for k in range(3):
            du = np.zeros_like(u)
            du[:, k] = h
            ep = coulomb_dissipation((u + du) @ P, lam, 0.7, m)[0]
            em = coulomb_dissipation((u - du) @ P, lam, 0.7, m)[0]
            gp = coulomb_dissipation((u + du) @ P, lam, 0.7, m)[1]
            # the term depends on the slip projected on the plane: derivatives along P's columns
            assert (ep - em) / (2 * h) == pytest.approx(float(np.sum(g @ P[:, k])), rel=1e-5, abs=1e-9)
            np.testing.assert_allclose((gp - g) / h, H @ P[:, k], rtol=1e-4, atol=1e-3 * np.abs(H).max())
        assert np.min(np.linalg.eigvalsh(H)) > -1e-9 * np.abs(H).max()
        if scale > FRICTION_EPS_MM:
            np.testing.assert_allclose(np.linalg.norm(g, axis=1), 0.7 * lam, rtol=1e-12)


# ----- render and identification ----------------------------------------------------------
