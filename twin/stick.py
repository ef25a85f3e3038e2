"""Friction: Coulomb's law at the skin's outer vertices, as stick constraints with a return map.

With friction (``SkinSim(friction=μ)``) every free outer vertex has an inactive point constraint to the
driven indenter (:mod:`twin.model` adds them; MuJoCo's own friction cone is not used, ``condim = 1``), and
:func:`update` applies Coulomb's law with them after every physics step.

A vertex that comes into contact sticks: a point constraint to the indenter is switched on at the
point where it touched, so it moves with the indenter without creeping (MuJoCo's own friction is a
velocity-level soft constraint: under a held tangential load it creeps back). Where the tangential
force T on a stuck vertex exceeds μN (N its normal force), the anchor slides on the indenter's
surface towards where the skin pulls, by the excess over the vertex's tangential stiffness (a
return map, as in penalty-based finite-element friction), so a sliding vertex carries μN and no
more. The constraint is switched off where N pulls (the skin separates). Normals are the
indenter's true surface normals at the vertex.
"""

from __future__ import annotations

import math
from typing import Callable

import numpy as np

from twin import units
from twin.model import _FLIP

__all__ = ["update", "stuck_contact"]

STICK_FORCE_STEPS = 50      # steps of the running mean of a stuck vertex's constraint force
STICK_SIGNIFICANCE = 2.0     # ... and slides only by the excess beyond this many standard errors of that mean
STICK_RELAX = 0.1           # a sliding anchor moves this fraction of the excess force over the vertex stiffness ...
STICK_MAX_SLIDE_MM = 0.005   # ... and at most this far a step (the neighbours move too: a full step overshoots)
NORMAL_STEP_MM = 0.05        # central-difference step of the indenter's surface normal


def update(model, data, *, friction: float, eq: np.ndarray, qadr: np.ndarray, stick_free: np.ndarray,
           rest_free_m: np.ndarray, stick_k: np.ndarray, stick_geom: np.ndarray, ind_qadr: np.ndarray,
           mean_F: np.ndarray, var: np.ndarray, surface_z: Callable[[np.ndarray], np.ndarray]) -> None:
    """Coulomb's law at each outer vertex, with the constraint forces of the step just taken (module notes).

    ``eq``: the stick constraints (one per vertex that can stick), ``stick_free`` those vertices' places among
    the free vertices (``qadr`` their slide DOFs, ``rest_free_m`` their rest world positions), ``stick_k``
    their tangential stiffness, ``stick_geom`` their contact spheres; ``ind_qadr`` the driven indenter's
    x, y, z, yaw DOFs; ``mean_F`` (K, 3) and ``var`` (K,) the running mean of each vertex's constraint force
    and its variance, updated in place; ``surface_z(xy)`` the indenter surface's sensor z above sensor
    points."""
    d, mu = data, friction
    idx = qadr[stick_free]                       # (K, 3) the vertices' slide DOFs (world axes)
    F = d.qfrc_constraint[idx]
    stuck = d.eq_active[eq] != 0
    a = np.nonzero(stuck | np.any(F != 0.0, axis=1))[0]
    if not len(a):
        return
    # a step's constraint forces carry the inflated vertex masses' transients: the Coulomb check uses
    # their running mean over ~STICK_FORCE_STEPS steps
    w = 1.0 / STICK_FORCE_STEPS
    dev2 = np.sum((F[a] - mean_F[a]) ** 2, axis=1)
    mean_F[a] = np.where(stuck[a, None], (1 - w) * mean_F[a] + w * F[a], F[a])
    var[a] = np.where(stuck[a], (1 - w) * var[a] + w * dev2, 0.0)
    X = rest_free_m[stick_free[a]] + d.qpos[idx[a]]            # world m
    xs = units.m_to_mm(X[:, :2]) * _FLIP[:2]                               # sensor x-y mm
    h = NORMAL_STEP_MM
    gx = (surface_z(xs + [h, 0]) - surface_z(xs - [h, 0])) / (2 * h)
    gy = (surface_z(xs + [0, h]) - surface_z(xs - [0, h])) / (2 * h)
    n = np.stack([gx, -gy, np.ones_like(gx)], axis=1)       # into the skin, world frame
    n = np.where(np.isfinite(n), n, [0.0, 0.0, 1.0])
    n /= np.linalg.norm(n, axis=1, keepdims=True)
    Fa = mean_F[a]
    N = np.einsum("ij,ij->i", Fa, n)
    Tv = Fa - N[:, None] * n
    T = np.linalg.norm(Tv, axis=1)
    st = stuck[a]
    p_ind, yaw = d.qpos[ind_qadr[:3]], float(d.qpos[ind_qadr[3]])
    c, s_ = math.cos(yaw), math.sin(yaw)

    def to_local(w):
        return np.stack([c * w[:, 0] + s_ * w[:, 1], -s_ * w[:, 0] + c * w[:, 1], w[:, 2]], axis=1)

    release = st & (N <= 0.0)
    d.eq_active[eq[a[release]]] = 0
    stuck_contact(model, stick_geom, a[release], True)
    # slide only where the excess is beyond the mean's own noise (its standard error, from the running
    # variance): otherwise the noise walks the anchors at the contact's edge and the press never settles
    noise = STICK_SIGNIFICANCE * np.sqrt(var[a] * w / (2 - w)) * (1 + mu)
    slide = st & (N > 0.0) & (T - mu * N > noise)
    if np.any(slide):
        # the anchor moves against the constraint's tangential force, i.e. where the skin pulls
        step_m = STICK_RELAX * (T[slide] - mu * N[slide] - noise[slide]) / stick_k[a[slide]]
        step_m = np.minimum(step_m, units.mm_to_m(STICK_MAX_SLIDE_MM))
        shift = -Tv[slide] / T[slide, None] * step_m[:, None]
        e = eq[a[slide]]
        model.eq_data[e, 3:6] += to_local(shift)
    stick = ~st & (N > 0.0)
    if np.any(stick):
        e = eq[a[stick]]
        # the anchor is where the vertex touches the surface: a vertex that lags inside is held on it
        P = X[stick].copy()
        zi = -units.mm_to_m(surface_z(xs[stick]))                # world z of the surface
        P[:, 2] = np.where(np.isfinite(zi), np.maximum(P[:, 2], zi), P[:, 2])   # the indenter lies below (world)
        model.eq_data[e, 0:3] = 0.0
        model.eq_data[e, 3:6] = to_local(P - p_ind)
        d.eq_active[e] = 1
        stuck_contact(model, stick_geom, a[stick], False)


def stuck_contact(model, stick_geom: np.ndarray, k: np.ndarray, on: bool) -> None:
    """A stuck vertex's contact sphere is switched off: its constraint carries the normal load too (a
    contact and a point constraint on one vertex fight over it, and the press never settles)."""
    g = stick_geom[k]
    model.geom_contype[g] = 2 if on else 0
    model.geom_conaffinity[g] = 1 if on else 0
