"""Friction: Coulomb's law at the skin's outer vertices, as stick constraints with a return map.

With friction (``SkinSim(friction=μ)``) every free outer vertex has two inactive joint equalities to the
driven indenter, one tying the vertex's world x to the indenter's and one its y (:mod:`twin.model` adds
them; MuJoCo's own friction cone is not used, ``condim = 1``), and :func:`update` applies Coulomb's law
with them after every physics step.

A vertex that comes into contact sticks: its x and y are tied to the indenter at the point where it
touched (an anchor in the indenter's frame, so a yawing indenter carries it round), so it moves with the
indenter without creeping (MuJoCo's own friction is a velocity-level soft constraint: under a held
tangential load it creeps back). Its z stays free and the contact keeps carrying the normal load: the
indenter is a height field, so a vertex held at one (x, y) of it and kept on its surface by the contact
is stuck to one point of the surface. Coulomb's law is checked on the whole force the indenter exerts on
the vertex (contact + tie, split along the indenter's true surface normal there into N and T): where T
exceeds μN the anchor slides on the indenter towards where the skin pulls, by the excess over the
vertex's tangential stiffness (a return map, as in penalty-based finite-element friction), so a sliding
vertex carries μN and no more. The tie is released where N pulls (the skin separates).

Measured before this form: a point constraint per vertex that carried the normal load too, with the
vertex's contact switched off while it stuck. Stuck vertices then sank 0.13 mm into the indenter on the
constraint's softness, and at the edge of a deep contact they were released and stuck again every few
steps (σ² = 10 Gaussian at 5 mm: ~80 of each per 50 steps, markers drifting 0.07-0.2 mm per 50 steps),
so deep presses never settled.
"""

from __future__ import annotations

import math
from typing import Callable

import numpy as np

from pipeline.design import MAX_FRICTION
from twin import units
from twin.mesh import PhysicsError

__all__ = ["update", "anchor_offsets", "to_indenter_frame", "resolve_friction", "check_friction"]

STICK_FORCE_STEPS = 50      # steps of the running mean of a stuck vertex's constraint force
STICK_SIGNIFICANCE = 2.0     # ... and slides only by the excess beyond this many standard errors of that mean
                             # (3: a press on the axis contact mesh settles in 97 steps instead of 128, but the
                             # μ = 0.3 slide holds Q/P 0.36 and keeps relaxing while held: the limit overshoots μ)
STICK_RELAX = 0.1           # a sliding anchor moves this fraction of the excess force over the vertex stiffness
                             # (0.3: the axis-mesh σ² = 10 press settles in 219 steps instead of 128) ...
STICK_MAX_SLIDE_MM = 0.005   # ... and at most this far a step (the neighbours move too: a full step overshoots)
NORMAL_STEP_MM = 0.05        # central-difference step of the indenter's surface normal


def check_friction(mu) -> float:
    """``mu`` as a float, refused (:class:`~twin.mesh.PhysicsError`) unless a Coulomb coefficient in
    [0, ``MAX_FRICTION``], the range a design's ``[twin] friction`` is held to."""
    mu = float(mu)
    if not math.isfinite(mu) or not 0.0 <= mu <= MAX_FRICTION:
        raise PhysicsError(f"friction {mu!r}: must be a coefficient in [0, {MAX_FRICTION:g}]")
    return mu


def resolve_friction(design, friction: float | None, indenter=None) -> float:
    """The Coulomb coefficient a press uses: ``friction`` if given, else the indenter's own (its material,
    :attr:`twin.indenters.Indenter.friction`), else the design's ``[twin] friction``."""
    if friction is None and indenter is not None:
        friction = getattr(indenter, "friction", None)
    return check_friction(design.twin_params()["friction"] if friction is None else friction)


def update(model, data, *, friction: float, eq: np.ndarray, qadr: np.ndarray, stick_free: np.ndarray,
           rest_free_m: np.ndarray, stick_k: np.ndarray, ind_qadr: np.ndarray, anchor: np.ndarray,
           mean_F: np.ndarray, var: np.ndarray, surface_z: Callable[[np.ndarray], np.ndarray]) -> None:
    """Coulomb's law at each outer vertex, with the constraint forces of the step just taken (module notes).

    ``eq`` (K, 2): the x and y ties of each vertex that can stick, ``stick_free`` those vertices' places among
    the free vertices (``qadr`` their slide DOFs, ``rest_free_m`` their rest world positions), ``stick_k``
    their tangential stiffness; ``ind_qadr`` the driven indenter's x, y, z, yaw DOFs; ``anchor`` (K, 3) each
    stuck vertex's anchor in the indenter's frame (m), ``mean_F`` (K, 3) and ``var`` (K,) the running mean of
    each vertex's constraint force and its variance, all updated in place; ``surface_z(xy)`` the indenter
    surface's sensor z above sensor points."""
    d, mu = data, friction
    idx = qadr[stick_free]                       # (K, 3) the vertices' slide DOFs (world axes)
    F = d.qfrc_constraint[idx]
    stuck = d.eq_active[eq[:, 0]] != 0
    a = np.nonzero(stuck | np.any(F != 0.0, axis=1))[0]
    p_ind, yaw = d.qpos[ind_qadr[:3]], float(d.qpos[ind_qadr[3]])
    c, s_ = math.cos(yaw), math.sin(yaw)
    if len(a):
        # a step's constraint forces carry the inflated vertex masses' transients: the Coulomb check uses
        # their running mean over ~STICK_FORCE_STEPS steps
        w = 1.0 / STICK_FORCE_STEPS
        dev2 = np.sum((F[a] - mean_F[a]) ** 2, axis=1)
        mean_F[a] = np.where(stuck[a, None], (1 - w) * mean_F[a] + w * F[a], F[a])
        var[a] = np.where(stuck[a], (1 - w) * var[a] + w * dev2, 0.0)
        X = rest_free_m[stick_free[a]] + d.qpos[idx[a]]            # world m
        # the indenter's surface normal at the vertex, into the skin, world frame (world y and z are the
        # sensor's mirrored: twin.model._FLIP)
        xs = units.m_to_mm(X[:, :2]) * [1.0, -1.0]
        h = NORMAL_STEP_MM
        gx = (surface_z(xs + [h, 0]) - surface_z(xs - [h, 0])) / (2 * h)
        gy = (surface_z(xs + [0, h]) - surface_z(xs - [0, h])) / (2 * h)
        n = np.stack([gx, -gy, np.ones_like(gx)], axis=1)
        n = np.where(np.isfinite(n), n, [0.0, 0.0, 1.0])
        n /= np.linalg.norm(n, axis=1, keepdims=True)
        Fa = mean_F[a]
        N = np.einsum("ij,ij->i", Fa, n)
        Tv = Fa - N[:, None] * n
        T = np.linalg.norm(Tv, axis=1)
        st = stuck[a]
        release = st & (N <= 0.0)
        d.eq_active[eq[a[release]].ravel()] = 0
        # slide only where the excess is beyond the mean's own noise (its standard error, from the running
        # variance): otherwise the noise walks the anchors at the contact's edge and the press never settles
        noise = STICK_SIGNIFICANCE * np.sqrt(var[a] * w / (2 - w)) * (1 + mu)
        slide = st & (N > 0.0) & (T - mu * N > noise)
        if np.any(slide):
            # the anchor moves against the tie's tangential force, i.e. where the skin pulls
            step_m = STICK_RELAX * (T[slide] - mu * N[slide] - noise[slide]) / stick_k[a[slide]]
            step_m = np.minimum(step_m, units.mm_to_m(STICK_MAX_SLIDE_MM))
            shift = -Tv[slide] / T[slide, None] * step_m[:, None]
            anchor[a[slide]] += _rotate(shift, c, -s_)
        stick = ~st & (N > 0.0)
        if np.any(stick):
            anchor[a[stick]] = _rotate(X[stick] - p_ind, c, -s_)     # where it touched, indenter frame
            d.eq_active[eq[a[stick]].ravel()] = 1
    on = np.nonzero(d.eq_active[eq[:, 0]] != 0)[0]
    if len(on):
        model.eq_data[eq[on], 0] = anchor_offsets(anchor[on], rest_free_m[stick_free[on]], c, s_)


def anchor_offsets(anchor: np.ndarray, rest_m: np.ndarray, c: float, s: float) -> np.ndarray:
    """The ties' constants (K, 2): a vertex at rest position ``rest_m`` (world m) held at ``anchor`` (indenter
    frame, m) of an indenter yawed by (cos, sin) = (c, s) has q_vertex = constant + q_indenter along x and y."""
    return _rotate(anchor, c, s)[:, :2] - rest_m[:, :2]


def to_indenter_frame(X: np.ndarray, p_ind: np.ndarray, yaw: float) -> np.ndarray:
    """World points (K, 3) m relative to the indenter at ``p_ind`` yawed by ``yaw`` (rad), in its frame (m):
    the frame of the anchors."""
    return _rotate(X - p_ind, math.cos(yaw), -math.sin(yaw))


def _rotate(v: np.ndarray, c: float, s: float) -> np.ndarray:
    """Rotate world/indenter-frame vectors (K, 3) about z by the angle whose cosine and sine are (c, s)."""
    return np.stack([c * v[:, 0] - s * v[:, 1], s * v[:, 0] + c * v[:, 1], v[:, 2]], axis=1)
