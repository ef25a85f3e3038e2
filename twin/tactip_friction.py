"""Coulomb friction on the TacTip twin's tapped plane (:mod:`twin.tactip`, the ``[twin]`` key ``tap_friction``).

With ``tap_friction`` > 0 the press is followed from first touch in depth steps of at most
:data:`FRICTION_STEP_MM` (the plane moves along the sensor axis, so on a tilted plane a touching node slides
relative to it unless friction holds it), each step adding a lagged, smoothed Coulomb dissipation potential
in the style of incremental potential contact (Li et al. 2020, ACM Trans. Graph. 39(4)): a touching node's
slip ``u`` relative to the plane over the step, projected on the plane, costs ``mu * lambda * f0(|u|)``,
``lambda`` its penalty contact force at the step's start and ``f0`` the slip smoothed below
:data:`FRICTION_EPS_MM` (the force rises from 0 to ``mu * lambda`` over that slip); its gradient and its
positive semi-definite Hessian enter the same projected-Newton solve. Against 0.125 mm steps the markers
differ by at most 0.018 mm with 0.25 mm steps (0.054 mm with 0.5 mm).

Measured on the real taps (2026-11-25, with the fit's first tilt frame of -160 degrees, since found 20 degrees
off; not re-measured with the corrected one): Coulomb friction measured with the frictionless fit's camera and
skin held (bending 0.106, depth offset -0.639 mm, pin rotation 0.024, tilt pivot 17.5 mm) on the markers' displacements from the reference tap
(projected pin tips): training error 1.87 / 1.78 / 2.23 px at mu 0 / 0.1 / 0.3, held out 2.00 / 1.88 /
2.25 px. End to end (rendered, detected, identified) at mu 0.1 the held-out marker RMS is 2.05 px against
2.17 frictionless, the held-out displacement error 1.88 px against 1.98. A deeper depth offset does not
favour more friction (the fit's 10 search taps: 1.77 px frictionless; mu 0.1 1.74 at the fitted offset,
1.75 at 0.1 mm deeper; mu 0.2 1.96 at 0.15 mm deeper; mu 0.3 2.29 at 0.25 mm deeper). Friction holds
the skin back on the tilted plane, the inner rings most: per ring, real / twin RMS displacement on the 10 held-out taps
is 0.95-0.97 on rings 0-4 and 1.19-1.28 on rings 8-10 frictionless, 1.02-1.06 and 1.17-1.25 at mu 0.1,
1.25-1.34 and 1.09-1.14 at mu 0.3 (on the 8 taps tilted 15-19 degrees: 0.95-0.98 / 1.16-1.26, 1.04-1.06 /
1.15-1.24, 1.27-1.30 / 1.06-1.12): the outer rings' excess over the inner ones shrinks with friction, but
the outer rings themselves still move too little. A tap with friction costs ~10x a frictionless one
(depth steps of 0.25 mm, each a solve: ~17 s per tap against 1.6 s). ``stereotactip fit-twin`` does not
fit the coefficient (0 unless the design sets it).
"""

from __future__ import annotations

import math

import numpy as np

__all__ = ["FRICTION_STEP_MM", "FRICTION_EPS_MM", "followed_press", "coulomb_dissipation"]

FRICTION_STEP_MM = 0.25  # with friction, the press is followed in depth steps of at most this
FRICTION_EPS_MM = 1e-3   # slip below which the smoothed Coulomb force falls linearly to 0 (static friction)


def followed_press(skin, m: np.ndarray, c: float, kb: float, mu: float, max_iter: int) -> tuple[np.ndarray, dict]:
    """The press of :class:`twin.tactip.DomeSkin` ``skin`` followed with Coulomb friction: the plane
    ``m . x = c`` is reached by moving it along the sensor axis from where it first touches the rest skin,
    in equal steps of at most :data:`FRICTION_STEP_MM`, each solved by ``skin._solve`` with the step's
    dissipation (:func:`coulomb_dissipation`), whose normal forces are the skin's own
    (``skin.normal_force``) at the step's start."""
    # the plane at travel s further along the axis is m . x = c_s with c_s = c + (s_end - s) m_z;
    # travel 0 is first touch of the rest nodes
    mz = float(m[2])
    travel = (float(np.max(skin.X0 @ m)) - c) / mz if mz > 0 else 0.0
    X = skin.X0.copy()
    free = skin.free
    lam = np.zeros(skin.n_nodes)
    slip = np.zeros(skin.n_nodes)
    n_steps = max(int(math.ceil(travel / FRICTION_STEP_MM - 1e-9)), 1) if travel > 0 else 0
    e, n_total, converged, steps = 0.0, 0, True, []
    for k in range(1, n_steps + 1):
        ck = c + travel * (1.0 - k / n_steps) * mz
        dp = np.array([0.0, 0.0, -travel / n_steps])     # the plane's displacement over the step
        touching = free[lam[free] > 0.0]
        fr = (touching, lam[touching], X[touching].copy(), dp, mu) if len(touching) else None
        Xprev = X.copy()
        X, e, n_it, ok = skin._solve(X[free].ravel().copy(), m, ck, kb, max_iter, friction=fr)
        n_total += n_it
        converged &= ok
        u = X - Xprev - dp
        u -= np.outer(u @ m, m)
        new_lam = skin.normal_force(X, m, ck)
        both = (lam > 0.0) & (new_lam > 0.0)
        slip[both] += np.linalg.norm(u[both], axis=1)
        lam = new_lam
        steps.append(n_it)
    return X, {"energy": e, "iterations": n_total, "converged": bool(converged), "steps": steps,
               "slip_mm": slip}


def coulomb_dissipation(u: np.ndarray, lam: np.ndarray, mu: float, m: np.ndarray, hessian: bool = False):
    """Lagged, smoothed Coulomb dissipation of touching nodes over one step (incremental potential
    contact, Li et al. 2020): ``u`` (K, 3) each node's slip relative to the plane projected on it,
    ``lam`` its normal force at the step's start. Per node ``mu lam f0(|u|)``, ``f0(y) = y`` beyond
    :data:`FRICTION_EPS_MM` and ``-y^3 / (3 eps^2) + y^2 / eps + eps / 3`` below (C1: the force rises
    from 0 to ``mu lam`` over a slip of eps); returns the energy and the gradient (K, 3) and, with
    ``hessian``, its exact Hessian blocks (K, 3, 3) (positive semi-definite: ``2 / eps - 2 y / eps^2``
    along the slip below eps, 0 beyond, ``f1(y) / y`` across it in the plane, 0 along the normal)."""
    eps = FRICTION_EPS_MM
    y = np.linalg.norm(u, axis=1)
    w = mu * lam
    low = y < eps
    f0 = np.where(low, -y ** 3 / (3 * eps * eps) + y * y / eps + eps / 3, y)
    f1y = np.where(low, 2 / eps - y / (eps * eps), 1.0 / np.maximum(y, eps))     # f1(y) / y
    e = float(w @ f0)
    g = (w * f1y)[:, None] * u
    if not hessian:
        return e, g
    # (f1'(y) y - f1(y)) / y^3: -1 / eps^2 / y below eps (times u u^T, |u| = y), -1 / y^3 beyond
    ys = np.maximum(y, 1e-300)
    cu = np.where(low, -1.0 / (eps * eps * ys), -1.0 / ys ** 3)
    cu = np.where(y > 0, cu, 0.0)
    P = np.eye(3) - np.outer(m, m)
    H = w[:, None, None] * (f1y[:, None, None] * P[None] + cu[:, None, None] * u[:, :, None] * u[:, None, :])
    return e, g, H
