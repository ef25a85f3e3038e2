"""A monocular TacTip in the twin: a tap of a flat rigid surface into a hemispherical gel-filled skin, and
the single camera's frame of the pins' markers.

Physics (a reduced skin model, stated): the skin is a triangulated elastic membrane through the pin bases
(one node per pin, one free ring outside the last pin ring and the clamped rim of the hemisphere), with

* stretching: springs on the mesh edges, energy ``sum (l - l0)^2`` (mm^2);
* bending: ``bending_ratio * sum |L x - L x0|^2`` with the umbrella Laplacian ``L`` (the membrane resists
  changes of its local curvature; ``bending_ratio`` is the bending/stretching weight, dimensionless on this
  mesh, and the skin parameter ``stereotactip fit-twin`` identifies);
* gel: the fill is incompressible, a stiff penalty on the enclosed volume (dome closed by the rim plane);
* contact: the rigid surface is a plane, a stiff penalty on penetration, pressed along the sensor axis
  (:class:`TapPose`, :data:`TAP_MODEL`). It is tilted about a pivot on the sensor axis ``tilt_pivot_mm``
  (the ``[twin]`` key) above the dome's centre of curvature: at 0 a tilted surface still first touches the
  dome at depth 0 (where the dome's normal is its own); with the pivot higher, a tilted tap reaches
  ``tilt_pivot_mm * (1 - cos tilt)`` deeper along the surface's normal (at the dome radius the surface
  turns about the apex). A tapping robot tilts its tool about its tool centre point, which need not be
  the dome's centre; ``stereotactip fit-twin`` identifies the pivot's height;
* friction: none by default (the ``[twin]`` key ``tap_friction``, a Coulomb coefficient, is 0); with
  ``tap_friction`` > 0 the press is followed in depth steps with a lagged, smoothed Coulomb dissipation
  (:mod:`twin.tactip_friction`, where what it was measured to do on the real taps is stated).

The equilibrium is found by minimising the energy (projected Newton). A position-controlled tap
into a rigid plane fixes the shape up to the stiffness *ratios*: the absolute modulus does not change the
marker positions (it would scale the contact force, which the labelled frames do not record). Pins are
rigid, of the design's height, rooted on the skin's inner surface (skin thickness inside the outer surface
along the deformed normal); the pin's axis turns by a fraction ``pin_rotation`` (alpha in [0, 1], the
``[twin]`` key) of the skin normal's rotation from rest. A pin held normal to the skin (alpha = 1)
amplifies the skin's bending into marker motion by its full length; the gel around the pins holds them
back (alpha < 1), which is what ``stereotactip fit-twin`` identifies (on the real 331-pin taps pins held
normal moved the inner rings' markers 1.3-1.5x as far as the real ones).

Contact is frictionless by default. A no-slip contact (each touching node held where it touched and carried
with the plane, the press followed in 0.5 mm steps) was measured on the real taps with the frictionless
fit's camera and skin: held-out marker displacement error 5.1 px against 2.6 px frictionless (the markers
moved more, not less), and 5-10x slower per tap; it is not kept. Coulomb friction between the two
(``tap_friction``): :mod:`twin.tactip_friction`.
A surface tilted about the apex (through the apex at
depth 0, pressed along its normal: a tapping robot's tool-point convention) lowered the held-out
displacement error with the fitted camera and skin held (2.22 -> 2.01 px) but, re-fitted end to end,
raised the held-out marker RMS (2.40 -> 2.83 px: the stages before the skin fit use the nominal depth
offset, and the over-pressed reference tap mis-set the pin spacing and the reference ids). The pivot's
height is now a fitted ``[twin]`` value (``tilt_pivot_mm``) that only the skin stage moves: the stages
before it tap with the pivot at the dome's centre, as before.

On the real taps the first fit of the robot's tilt frame (``tilt_frame_deg``, fitted on positions with the
pivot at the dome's centre and the nominal skin) was 20 degrees off: the tilted taps' outer rings then seemed
to lack 11-21 % of their motion, and a membrane pre-tension (edge rest lengths shortened by a pre-strain)
tried against it raised the held-out displacement error at every pre-strain (2.19 px at 0, 2.23 at 0.01,
2.39 at 0.03). Single tilted taps' poses fitted to the real markers showed the labelled tilt turned by
18-22 degrees against the one the twin needed; ``stereotactip fit-twin`` now re-searches the tilt frame once
the skin and pivot are fitted (179.4 degrees; held-out marker RMS 2.17 -> 1.24 px).

Rendering: :mod:`twin.tactip_render` (the single camera's frame of the pin-tip markers).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from scipy import sparse
from scipy.sparse.linalg import splu
from scipy.spatial import Delaunay

from pipeline.design import SensorDesign, marker_layout
from pipeline.errors import UserError
from twin.tactip_friction import FRICTION_EPS_MM, FRICTION_STEP_MM, coulomb_dissipation, followed_press
from twin.tactip_render import camera_extrinsics, project_markers, render_frame

__all__ = ["TAP_MODEL", "PIN_MODEL", "TapPose", "DomeSkin", "pin_axes", "tap_markers", "project_markers", "render_frame",
           "camera_extrinsics", "check_monocular", "FRICTION_STEP_MM", "FRICTION_EPS_MM"]

#: what a tap means (part of the fit's cache keys: a fit cached under another meaning is recomputed)
TAP_MODEL = ("membrane: frictionless plane tilted about a pivot tilt_pivot_mm above the dome's centre, pressed "
             "along the sensor axis")
#: where a marker sits on a tapped skin (part of the fit's cache keys with TAP_MODEL)
PIN_MODEL = ("rigid pins: base on the skin's inner surface along its normal, axis turned by pin_rotation of the "
             "normal's rotation from rest, tip at the pin height along the axis")
VOLUME_WEIGHT = 1e5      # energy per (relative volume change)^2: the gel fill is incompressible
CONTACT_WEIGHT = 1e3     # energy per mm^2 of penetration into the plane
STEP_TOL_MM = 1e-5       # Newton iterations stop when no node moves more than this
DEBUG = False


class TacTipError(UserError, ValueError):
    """A design that is not a monocular dome, or a tap the model cannot solve."""


def check_monocular(design: SensorDesign) -> None:
    if not design.monocular or design.pattern.mapping != "arc":
        raise TacTipError(f"design {design.name!r}: the tap model needs a monocular design with a [camera] block "
                          f"and pattern.mapping = 'arc' (a TacTip dome), e.g. tactip331")


@dataclass(frozen=True)
class TapPose:
    """A tap of a flat surface: ``depth_mm`` along the sensor axis past first touch, surface tilted by
    ``tilt_x_deg`` about the robot's first tilt axis and ``tilt_y_deg`` about its second."""

    depth_mm: float
    tilt_x_deg: float = 0.0
    tilt_y_deg: float = 0.0


class DomeSkin:
    """The membrane mesh of a design's dome (built once per design; :meth:`tap` per pose)."""

    def __init__(self, design: SensorDesign):
        check_monocular(design)
        self.design = design
        xy, _ = marker_layout(design.pattern)
        self.n_markers = len(xy)
        R = design.dome_radius_mm()
        self.R = R
        s = design.pattern.separation_mm
        r_last = float(np.max(np.hypot(xy[:, 0], xy[:, 1])))
        arc_rim = R * math.pi / 2 if design.pattern.dome_height_mm >= design.gel.radius_mm else \
            R * math.asin(design.gel.radius_mm / R)
        rings = []
        r = r_last + s
        n_ring = max(6, int(round(2 * math.pi * r_last / s)))
        while r < arc_rim - 0.5 * s:
            rings.append(r)
            r += s
        layout = [xy]
        for r in rings:
            t = 2 * np.pi * (np.arange(n_ring) + 0.5) / n_ring
            layout.append(np.column_stack([np.cos(t), np.sin(t)]) * r)
        t = 2 * np.pi * np.arange(n_ring) / n_ring
        layout.append(np.column_stack([np.cos(t), np.sin(t)]) * arc_rim)
        layout = np.concatenate(layout)
        self.n_nodes = len(layout)
        self.fixed = np.zeros(self.n_nodes, bool)
        self.fixed[-n_ring:] = True
        X0, _ = design.arc_surface(layout)
        self.X0 = X0
        tri = Delaunay(layout).simplices
        # orient triangles so their normals point out of the dome
        a, b, c = X0[tri[:, 0]], X0[tri[:, 1]], X0[tri[:, 2]]
        nrm = np.cross(b - a, c - a)
        centre = np.array([0.0, 0.0, -R])
        flip = np.einsum("ij,ij->i", nrm, (a + b + c) / 3 - centre) < 0
        tri[flip] = tri[flip][:, [0, 2, 1]]
        self.tri = tri
        edges = np.sort(np.concatenate([tri[:, [0, 1]], tri[:, [1, 2]], tri[:, [2, 0]]]), axis=1)
        self.edges = np.unique(edges, axis=0)
        self.l0 = np.linalg.norm(X0[self.edges[:, 0]] - X0[self.edges[:, 1]], axis=1)
        n = self.n_nodes
        i, j = self.edges[:, 0], self.edges[:, 1]
        A = sparse.coo_matrix((np.ones(2 * len(i)), (np.r_[i, j], np.r_[j, i])), shape=(n, n)).tocsr()
        deg = np.asarray(A.sum(axis=1)).ravel()
        self.L = (sparse.diags(1.0 / deg) @ A - sparse.eye(n)).tocsr()
        self.LX0 = self.L @ X0
        self.centre = np.array([0.0, 0.0, -R + R])  # rim plane centre (z of the rim)
        self.centre[2] = X0[self.fixed][:, 2].mean()
        self.V0 = self.volume(X0)
        self.free = np.nonzero(~self.fixed)[0]
        ne, nt = len(i), len(tri)
        #: scatter matrices: edge forces and triangle-corner terms onto nodes (sparse: np.add.at is slow)
        self.E = sparse.coo_matrix((np.r_[np.ones(ne), -np.ones(ne)], (np.r_[i, j], np.r_[np.arange(ne), np.arange(ne)])),
                                   shape=(n, ne)).tocsr()
        self.Tk = [sparse.coo_matrix((np.ones(nt), (tri[:, k], np.arange(nt))), shape=(n, nt)).tocsr()
                   for k in range(3)]
        self.LtL = (self.L.T @ self.L).tocsr()
        self.LtLX0 = self.L.T @ self.LX0
        #: the pins' rest directions (outward skin normals at rest): the pin rotation is measured from them
        self.N0 = self.normals(X0)[: self.n_markers]

    # ----- geometry ---------------------------------------------------------------------
    def volume(self, X: np.ndarray) -> float:
        a, b, c = (X[self.tri[:, k]] - self.centre for k in range(3))
        return float(np.einsum("ij,ij->i", a, np.cross(b, c)).sum() / 6.0)

    def normals(self, X: np.ndarray) -> np.ndarray:
        a, b, c = X[self.tri[:, 0]], X[self.tri[:, 1]], X[self.tri[:, 2]]
        fn = np.cross(b - a, c - a)
        vn = np.zeros_like(X)
        for k in range(3):
            np.add.at(vn, self.tri[:, k], fn)
        return vn / np.linalg.norm(vn, axis=1, keepdims=True)

    def markers(self, X: np.ndarray, pin_rotation: float | None = None) -> tuple[np.ndarray, np.ndarray]:
        """Marker (pin tip) centres and pin axes (pointing into the dome) of a skin state, (N, 3) each.

        The pin's base is on the skin's inner surface (skin thickness inside the outer surface, along the
        deformed normal); its axis turns by ``pin_rotation`` (alpha, the design's ``twin.pin_rotation``
        unless given) of the skin normal's rotation from rest, about the same axis: alpha = 1 is a pin
        held normal to the skin, alpha = 0 a pin that keeps its rest direction while its base moves. The
        tip is the pin's height along that axis from the base."""
        a = self.design.twin_params()["pin_rotation"] if pin_rotation is None else float(pin_rotation)
        n = self.normals(X)[: self.n_markers]
        x = X[: self.n_markers]
        if a == 1.0:
            return x - self.design.marker_depth_mm * n, -n
        axis = pin_axes(self.N0, n, a)
        return x - self.design.skin.thickness_mm * n - self.design.pins.height_mm * axis, -axis

    # ----- the tap ----------------------------------------------------------------------
    def plane(self, pose: TapPose, params: dict[str, float]) -> tuple[np.ndarray, float]:
        """Unit normal ``m`` (from the skin into the object) and offset ``c``: the object is ``m . x > c``."""
        psi = math.radians(params["tilt_frame_deg"])
        ax = math.radians(pose.tilt_x_deg)
        ay = math.radians(pose.tilt_y_deg) * (-1.0 if params["tilt_mirror"] >= 0.5 else 1.0)
        Rx = np.array([[1, 0, 0], [0, math.cos(ax), -math.sin(ax)], [0, math.sin(ax), math.cos(ax)]])
        Ry = np.array([[math.cos(ay), 0, math.sin(ay)], [0, 1, 0], [-math.sin(ay), 0, math.cos(ay)]])
        Rz = np.array([[math.cos(psi), -math.sin(psi), 0], [math.sin(psi), math.cos(psi), 0], [0, 0, 1]])
        m = Rz @ Rx @ Ry @ np.array([0.0, 0.0, 1.0])
        depth = pose.depth_mm + params["depth_offset_mm"]
        # tilted about a point on the sensor axis ``tilt_pivot_mm`` above the dome's centre of curvature: at
        # 0 the surface rolls over the dome (it still first touches at depth 0), at the dome radius it turns
        # about the apex and a tilted surface is pressed R (1 - cos tilt) further in
        h = float(params["tilt_pivot_mm"])
        c = float(m @ np.array([0.0, 0.0, -self.R]) + self.R - depth * m[2] - h * (1.0 - m[2]))
        return m, c

    def tap(self, pose: TapPose, params: dict[str, float], *, x_init: np.ndarray | None = None,
            max_iter: int = 3000) -> tuple[np.ndarray, dict]:
        """Equilibrium skin nodes (n_nodes, 3) of a tap and a small report (energy, iterations, max
        penetration mm, relative volume change).

        Frictionless (``tap_friction`` 0, the default) the equilibrium is one solve at the final depth
        (from ``x_init`` when given). With a Coulomb coefficient ``tap_friction`` > 0 the press is followed
        from first touch in depth steps of at most :data:`FRICTION_STEP_MM` (``x_init`` is not used: the
        state depends on the path): each step adds a lagged, smoothed Coulomb dissipation potential
        (:func:`twin.tactip_friction.coulomb_dissipation`); the report then also carries the steps and each
        node's tangential slip over the press relative to the plane (``slip_mm``, summed over the steps it was
        touching at both ends)."""
        m, c = self.plane(pose, params)
        kb = float(params["bending_ratio"])
        mu = float(params.get("tap_friction", 0.0))
        if mu <= 0.0:
            q0 = (x_init if x_init is not None else self.X0)[self.free].ravel().copy()
            X, e, n_it, converged = self._solve(q0, m, c, kb, max_iter)
            info = {"energy": e, "iterations": n_it, "converged": converged}
        else:
            X, info = followed_press(self, m, c, kb, mu, max_iter)
        pen = float(np.max(X @ m - c))
        info.update({"penetration_max_mm": max(pen, 0.0), "volume_change": (self.volume(X) - self.V0) / self.V0})
        return X, info

    @staticmethod
    def normal_force(X: np.ndarray, m: np.ndarray, c: float) -> np.ndarray:
        """Each node's normal force from the plane ``m . x = c``: the derivative of the contact penalty
        ``CONTACT_WEIGHT * penetration^2`` (energy units per mm, >= 0)."""
        return 2 * CONTACT_WEIGHT * np.maximum(X @ m - c, 0.0)

    def _solve(self, q: np.ndarray, m: np.ndarray, c: float, kb: float, max_iter: int,
               friction: tuple | None = None) -> tuple[np.ndarray, float, int, bool]:
        """Projected Newton from the free nodes ``q`` against the plane ``m . x = c``; ``friction`` (nodes,
        their normal forces, their positions at the step's start, the plane's displacement over the step,
        the coefficient) adds the step's Coulomb dissipation (:func:`coulomb_dissipation`)."""
        X = self.X0.copy()
        free = self.free
        i, j = self.edges[:, 0], self.edges[:, 1]
        L, LX0, V0 = self.L, self.LX0, self.V0
        if friction is not None:
            f_nodes, f_lam, f_x0, f_dp, f_mu = friction
            P = np.eye(3) - np.outer(m, m)

        def energy(q):
            X[free] = q.reshape(-1, 3)
            d = X[i] - X[j]
            ln = np.linalg.norm(d, axis=1)
            st = ln - self.l0
            e = float(st @ st)
            f = (2 * st / ln)[:, None] * d
            g = self.E @ f
            r = L @ X - LX0
            e += kb * float(np.sum(r * r))
            g += 2 * kb * (self.LtL @ X - self.LtLX0)
            a, b, cc = (X[self.tri[:, k]] - self.centre for k in range(3))
            bc = np.cross(b, cc)
            V = float(np.einsum("ij,ij->i", a, bc).sum() / 6.0)
            dv = (V - V0) / V0
            e += VOLUME_WEIGHT * dv * dv
            kv = 2 * VOLUME_WEIGHT * dv / V0 / 6.0
            g += kv * (self.Tk[0] @ bc + self.Tk[1] @ np.cross(cc, a) + self.Tk[2] @ np.cross(a, b))
            pen = np.maximum(X @ m - c, 0.0)
            e += CONTACT_WEIGHT * float(pen @ pen)
            g += self.normal_force(X, m, c)[:, None] * m
            if friction is not None:
                ef, gf = coulomb_dissipation((X[f_nodes] - f_x0 - f_dp) @ P, f_lam, f_mu, m)
                e += ef
                g[f_nodes] += gf
            return e, g[free].ravel()

        nf = len(free)
        pos = -np.ones(self.n_nodes, np.int64)
        pos[free] = np.arange(nf)
        Hb = sparse.kron(2 * kb * self.LtL[free][:, free], sparse.eye(3)).tocsr()
        ei, ej = pos[i], pos[j]
        e_ok = [(ei >= 0) & (ej >= 0), ei >= 0, ej >= 0]
        e, g = energy(q)
        n_it, converged = 0, False
        for n_it in range(1, max_iter + 1):
            # projected Newton step: Hessian of springs (clamped PSD), bending, active contact, friction,
            # volume (Gauss-Newton rank one, by Sherman-Morrison)
            d = X[i] - X[j]
            ln = np.linalg.norm(d, axis=1)
            dh = d / ln[:, None]
            B = 2 * ((self.l0 / ln)[:, None, None] * dh[:, :, None] * dh[:, None, :]
                     + np.maximum(1 - self.l0 / ln, 0.0)[:, None, None] * np.eye(3)[None])
            rows, cols, vals = [], [], []
            for (a_, b_, sgn, ok) in ((ei, ei, 1.0, e_ok[1]), (ej, ej, 1.0, e_ok[2]),
                                      (ei, ej, -1.0, e_ok[0]), (ej, ei, -1.0, e_ok[0])):
                r3 = (3 * a_[ok])[:, None, None] + np.arange(3)[None, :, None]
                c3 = (3 * b_[ok])[:, None, None] + np.arange(3)[None, None, :]
                rows.append(np.broadcast_to(r3, (ok.sum(), 3, 3)).ravel())
                cols.append(np.broadcast_to(c3, (ok.sum(), 3, 3)).ravel())
                vals.append((sgn * B[ok]).ravel())
            active = free[(X[free] @ m - c) > 0.0]
            if len(active):
                r3 = (3 * pos[active])[:, None, None] + np.arange(3)[None, :, None]
                c3 = (3 * pos[active])[:, None, None] + np.arange(3)[None, None, :]
                mm = 2 * CONTACT_WEIGHT * np.outer(m, m)
                rows.append(np.broadcast_to(r3, (len(active), 3, 3)).ravel())
                cols.append(np.broadcast_to(c3, (len(active), 3, 3)).ravel())
                vals.append(np.broadcast_to(mm, (len(active), 3, 3)).ravel())
            if friction is not None:
                _, _, Hf = coulomb_dissipation((X[f_nodes] - f_x0 - f_dp) @ P, f_lam, f_mu, m, hessian=True)
                r3 = (3 * pos[f_nodes])[:, None, None] + np.arange(3)[None, :, None]
                c3 = (3 * pos[f_nodes])[:, None, None] + np.arange(3)[None, None, :]
                rows.append(np.broadcast_to(r3, Hf.shape).ravel())
                cols.append(np.broadcast_to(c3, Hf.shape).ravel())
                vals.append(Hf.ravel())
            H = sparse.coo_matrix((np.concatenate(vals), (np.concatenate(rows), np.concatenate(cols))),
                                  shape=(3 * nf, 3 * nf)).tocsc() + Hb + 1e-8 * sparse.eye(3 * nf)
            a, b, cc = (X[self.tri[:, k]] - self.centre for k in range(3))
            u = (self.Tk[0] @ np.cross(b, cc) + self.Tk[1] @ np.cross(cc, a) + self.Tk[2] @ np.cross(a, b)) / 6.0
            u = u[free].ravel() / V0
            alpha = 2 * VOLUME_WEIGHT
            lu = splu(H.tocsc())
            Hg, Hu = lu.solve(-g), lu.solve(u)
            step = Hg - Hu * (alpha * (u @ Hg) / (1 + alpha * (u @ Hu)))
            if g @ step >= 0:
                step = -g
            t = 1.0
            while True:
                e_new, g_new = energy(q + t * step)
                if e_new <= e + 1e-4 * t * (g @ step) or t < 1e-6:
                    break
                t *= 0.5
            q = q + t * step
            de = e - e_new
            e, g = e_new, g_new
            if DEBUG:
                print(n_it, e, de, t, np.max(np.abs(t * step)), np.max(np.abs(g)), len(active))
            if np.max(np.abs(t * step)) < STEP_TOL_MM or np.max(np.abs(g)) < 1e-7:
                converged = True
                break
        X[free] = q.reshape(-1, 3)
        return X.copy(), float(e), int(n_it), bool(converged)


def pin_axes(n0: np.ndarray, n: np.ndarray, alpha: float) -> np.ndarray:
    """Unit pin directions (N, 3): each rest normal ``n0`` turned towards the deformed normal ``n`` by the
    fraction ``alpha`` of the angle between them, about their common perpendicular (spherical
    interpolation; alpha = 0 gives ``n0``, alpha = 1 gives ``n``)."""
    c = np.clip(np.einsum("ij,ij->i", n0, n), -1.0, 1.0)
    theta = np.arccos(c)
    s = np.sin(theta)
    small = s < 1e-9
    s_safe = np.where(small, 1.0, s)
    w0 = np.where(small, 1.0 - alpha, np.sin((1.0 - alpha) * theta) / s_safe)
    w1 = np.where(small, alpha, np.sin(alpha * theta) / s_safe)
    v = w0[:, None] * n0 + w1[:, None] * n
    return v / np.linalg.norm(v, axis=1, keepdims=True)


def tap_markers(skin: DomeSkin, pose: TapPose, params: dict[str, float] | None = None):
    """Marker centres, pin axes (sensor frame, mm) and the solve report of one tap."""
    params = params or skin.design.twin_params()
    X, info = skin.tap(pose, params)
    p, axis = skin.markers(X)
    return p, axis, info


# ----- camera -------------------------------------------------------------------------------
