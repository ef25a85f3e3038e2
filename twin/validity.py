"""Physical validity of a twin frame: does the outer skin stay out of the rigid indenter?

MuJoCo reports contact distances only where it detects a contact (at the skin's contact points), so
a skin face can pass through a sharp tip or a narrow ridge between those points without any contact
saying so. This module measures penetration from the geometry alone, independently of the solver:

* **skin side** — every outer-skin vertex, every triangle centroid and every edge midpoint: its
  height above the indenter's true surface at the same x-y (``z_skin - z_indenter``, positive =
  inside the indenter);
* **indenter side** — every point of the indenter's surface sampled at ``INDENTER_SAMPLE_MM``: the
  skin's height there, linearly interpolated on the deformed skin triangles. This sees a tip that
  pokes through the interior of a skin triangle, which no skin-side sample would.

Penetration is measured vertically (the press direction). The indenter's own height function is the
truth (:meth:`twin.indenters.Indenter.height`), not the collision height field MuJoCo sees.

:func:`frame_validity` adds the solver's own health: settle convergence and MuJoCo's warning
counters. A frame is valid only when every check passes; :data:`PENETRATION_MAX_MM` is the bound.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass, field
from typing import Callable

import numpy as np

__all__ = ["PENETRATION_MAX_MM", "INDENTER_SAMPLE_MM", "Penetration", "FrameValidity", "skin_penetration",
           "frame_validity", "rim_overlap_mm"]

PENETRATION_MAX_MM = 0.05   # the outer skin may sit at most 50 um inside the rigid indenter anywhere (max)
INDENTER_SAMPLE_MM = 0.1    # indenter-side sampling: half the collision height field's cell, so a feature the
                            # collider resolves is sampled at least twice across
TOUCH_TOL_MM = 0.05         # a skin sample within this of the indenter surface counts as touching


@dataclass(frozen=True)
class Penetration:
    """Skin–indenter penetration statistics of one frame (mm; positive = skin inside the indenter)."""

    max_mm: float            # deepest penetration over all samples (>= 0)
    p99_mm: float            # 99th percentile over the samples inside the indenter footprint (>= 0)
    vertex_max_mm: float     # ... at vertices only (what a vertex-contact model sees)
    gap_touching_max_mm: float   # largest |gap| over the skin samples within TOUCH_TOL_MM (NaN: no contact)
    gap_touching_rms_mm: float
    n_touching: int
    n_samples: int


def _skin_samples(v: np.ndarray, f: np.ndarray) -> tuple[np.ndarray, int]:
    """Vertices, triangle centroids and unique edge midpoints of a triangle mesh; (points, n_vertices)."""
    cent = v[f].mean(axis=1)
    e = np.sort(np.vstack([f[:, [0, 1]], f[:, [1, 2]], f[:, [2, 0]]]), axis=1)
    e = np.unique(e, axis=0)
    mid = 0.5 * (v[e[:, 0]] + v[e[:, 1]])
    return np.vstack([v, cent, mid]), len(v)


def skin_penetration(skin_vertices_mm: np.ndarray, skin_faces: np.ndarray,
                     indenter_z: Callable[[np.ndarray], np.ndarray], *,
                     footprint: tuple[np.ndarray, np.ndarray] | None = None,
                     sample_mm: float = INDENTER_SAMPLE_MM, free: np.ndarray | None = None) -> Penetration:
    """Penetration of the deformed outer skin into the indenter (see the module notes).

    ``indenter_z(xy)`` gives the indenter's surface height (sensor z, mm) above sensor points (N, 2),
    NaN off the part. ``footprint = (x_mm, y_mm)`` axes of the indenter-side grid (default: the skin's
    x-y extent at ``sample_mm``); only points where both the indenter and the skin exist are used.
    ``free`` (V,) bool marks the deformable vertices: faces touching a clamped vertex (the rigid mount at
    the rim) are left out, since an indenter reaching there meets the mount, which the skin cannot
    model (:func:`rim_overlap_mm` measures that separately).
    """
    from matplotlib.tri import LinearTriInterpolator, Triangulation

    v = np.asarray(skin_vertices_mm, float)
    f = np.asarray(skin_faces, np.int64)
    if not np.all(np.isfinite(v)):
        return Penetration(float("inf"), float("inf"), float("inf"), float("nan"), float("nan"), 0, 0)
    if free is not None:
        f = f[np.all(np.asarray(free, bool)[f], axis=1)]
        used = np.unique(f)
        remap = -np.ones(len(v), np.int64)
        remap[used] = np.arange(len(used))
        v, f = v[used], remap[f]
    pts, nv = _skin_samples(v, f)
    zi = indenter_z(pts[:, :2])
    pen_skin = pts[:, 2] - zi                    # > 0: inside
    ok = np.isfinite(pen_skin)
    if footprint is None:
        lo, hi = v[:, :2].min(axis=0), v[:, :2].max(axis=0)
        gx = np.arange(lo[0], hi[0] + 1e-9, sample_mm)
        gy = np.arange(lo[1], hi[1] + 1e-9, sample_mm)
    else:
        gx, gy = footprint
    X, Y = np.meshgrid(gx, gy)
    gxy = np.column_stack([X.ravel(), Y.ravel()])
    zg = indenter_z(gxy)
    # only where the indenter comes within 1 mm of the highest skin point can it reach the skin
    has = np.isfinite(zg) & (zg < v[:, 2].max() + 1.0)
    pen_ind = np.zeros(0)
    if has.any():
        try:
            tri = Triangulation(v[:, 0], v[:, 1], f)
            zs = np.asarray(LinearTriInterpolator(tri, v[:, 2])(gxy[has, 0], gxy[has, 1]).filled(np.nan))
        except (RuntimeError, ValueError):
            # faces overlap in x-y: the skin folded over itself (a collapsed press) - not a valid frame
            return Penetration(float("inf"), float("inf"), float(max(0.0, np.nanmax(pen_skin[:nv], initial=0.0))),
                               float("nan"), float("nan"), 0, 0)
        pen_ind = zs - zg[has]
        pen_ind = pen_ind[np.isfinite(pen_ind)]
    allpen = np.concatenate([pen_skin[ok], pen_ind])
    if len(allpen) == 0:
        return Penetration(0.0, 0.0, 0.0, float("nan"), float("nan"), 0, 0)
    vert = pen_skin[:nv][ok[:nv]]
    touch = np.abs(pen_skin[ok]) <= TOUCH_TOL_MM
    gaps = -pen_skin[ok][touch]
    # p99 over the samples that face the indenter closely (within 1 mm): far-away skin would dilute it
    close = allpen[allpen > -1.0]
    return Penetration(
        max_mm=float(max(0.0, allpen.max())),
        p99_mm=float(max(0.0, np.percentile(close, 99))) if len(close) else 0.0,
        vertex_max_mm=float(max(0.0, vert.max())) if len(vert) else 0.0,
        gap_touching_max_mm=float(np.abs(gaps).max()) if len(gaps) else float("nan"),
        gap_touching_rms_mm=float(np.sqrt(np.mean(gaps ** 2))) if len(gaps) else float("nan"),
        n_touching=int(touch.sum()), n_samples=int(len(allpen)))


def rim_overlap_mm(skin_vertices_mm: np.ndarray, clamped: np.ndarray,
                   indenter_z: Callable[[np.ndarray], np.ndarray]) -> float:
    """How far the indenter reaches below the clamped rim of the skin (mm, >= 0): a wide indenter pressed
    deep meets the sensor's rigid mount there. Recorded beside the validity; it describes the experiment's
    geometry (the robot would stall on the mount), not an error of the skin model."""
    v = np.asarray(skin_vertices_mm, float)[np.asarray(clamped, bool)]
    if len(v) == 0:
        return 0.0
    pen = v[:, 2] - indenter_z(v[:, :2])
    pen = pen[np.isfinite(pen)]
    return float(max(0.0, pen.max())) if len(pen) else 0.0


@dataclass(frozen=True)
class FrameValidity:
    """Everything that decides whether a simulated frame may be scored.

    ``valid`` is False when the skin penetrates the indenter beyond ``PENETRATION_MAX_MM``, a pin's tip
    lies beyond the gel (``pin_overrun_mm`` > 0: into the acrylic window, which a real pin cannot reach),
    the settle did not converge, or MuJoCo raised any warning; ``reasons`` names each failed check.
    A frame filmed in motion (``in_motion``, :func:`twin.robot.press_motion` ``film_every_mm``) is the
    state the camera sees while the indenter moves on: the skin lags the indenter by up to the robot's
    lag limit and nothing has settled, so it is never valid; it is an input to identification across
    frames, never scored against the indenter.
    """

    penetration_max_mm: float
    penetration_p99_mm: float
    penetration_vertex_max_mm: float
    gap_touching_max_mm: float
    gap_touching_rms_mm: float
    contact_force_n: float
    settled: bool
    mujoco_warnings: dict = field(default_factory=dict)
    rim_overlap_mm: float = 0.0
    pin_overrun_mm: float = 0.0
    valid: bool = True
    reasons: tuple = ()
    in_motion: bool = False   # filmed while the indenter moved: not at equilibrium, so never valid (a tracking input)

    def to_dict(self) -> dict:
        """Plain JSON types; an undefined statistic (NaN, e.g. no gap when nothing touches) becomes None."""
        d = asdict(self)
        d["reasons"] = list(self.reasons)
        return {k: (None if isinstance(x, float) and not np.isfinite(x) else x) for k, x in d.items()}

    @classmethod
    def from_dict(cls, d: dict) -> "FrameValidity":
        d = {k: (float("nan") if x is None else x) for k, x in d.items()}
        d["reasons"] = tuple(d.get("reasons", ()))
        d["mujoco_warnings"] = dict(d.get("mujoco_warnings", {}))
        return cls(**d)


def frame_validity(pen: Penetration, *, contact_force_n: float, settled: bool, mujoco_warnings: dict,
                   rim_overlap: float = 0.0, penetration_max_mm: float = PENETRATION_MAX_MM,
                   pin_overrun: float = 0.0, in_motion: bool = False) -> FrameValidity:
    """Combine the geometric checks with the solver's health into one verdict (``in_motion``: a frame filmed
    while the indenter moves, see :class:`FrameValidity`)."""
    reasons = ["filmed in motion, not at equilibrium: an input to tracking, never scored"] if in_motion else []
    if not np.isfinite(pen.max_mm):
        reasons.append("skin mesh degenerate (non-finite vertices or faces folded over each other)")
    elif pen.max_mm > penetration_max_mm:
        reasons.append(f"skin {pen.max_mm:.3f} mm inside the indenter (bound {penetration_max_mm:g} mm)")
    if pin_overrun > 0:
        reasons.append(f"a pin's tip {pin_overrun:.3f} mm beyond the gel, into the acrylic window")
    if not settled and not in_motion:
        reasons.append("press did not settle to equilibrium")
    if mujoco_warnings:
        reasons.append("MuJoCo warnings: " + ", ".join(f"{k} x{v}" for k, v in sorted(mujoco_warnings.items())))
    return FrameValidity(pen.max_mm, pen.p99_mm, pen.vertex_max_mm, pen.gap_touching_max_mm, pen.gap_touching_rms_mm,
                         float(contact_force_n), bool(settled), dict(mujoco_warnings), float(rim_overlap),
                         float(pin_overrun), not reasons, tuple(reasons), bool(in_motion))
