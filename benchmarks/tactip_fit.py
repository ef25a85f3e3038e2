"""Fitting a TacTip twin: identify what a public TacTip design does not fix from labelled real taps.

Stages (run in order and cached by ``stereotactip fit-twin``, :mod:`benchmarks.tactip_fit_cli`):

1. **camera** — the shallowest training tap is simulated with the nominal skin; its pin tips are projected
   through a camera on the sensor axis; the camera's roll about its axis is found by a 1° grid over the
   pattern's 60° symmetry (median nearest-marker distance), then focal length, principal point, radial
   distortion (k1, k2, k3), lateral offset and axial position by robust least squares (soft-L1) on mutual
   nearest-neighbour matches, re-matched 6 times. The matches give the reference frame's marker ids; every
   frame is identified from that reference (:func:`pipeline.vision.tactip_id.identify_sequence`).
2. **tilt frame** — the robot's tilt axes relative to the pattern (angle about the sensor axis and the
   handedness of the second tilt): 12 angles x 2 handedness on the 4 most tilted training taps, refined
   by a bounded 1-D search.
3. **skin and pins** — the pins' rotation fraction (how much of the skin normal's rotation the pin axes
   follow, ``twin.pin_rotation`` in [0, 1], with the design's pin height), the membrane's
   bending/stretching ratio (log-scale bounded search) and the depth offset of the labels (first touch vs
   the labelled zero), each by a bounded 1-D search on the training taps (pin rotation, bending, offset,
   pin rotation again), scored on the markers' displacement from the reference tap; then the height of the
   tap's tilt pivot (``twin.tilt_pivot_mm``, a coarse grid from the dome's centre to beyond its apex refined
   by one parabolic step, the depth offset re-searched for each in a bracket around its extrapolated value,
   scored on every training tap), bending (within a factor 2) and pin rotation once more; then the tilt
   frame again (within 30 degrees of its first fit, on the displacements of the 10 most tilted training
   taps, where the first fit's pivot at the dome's centre and nominal skin had turned it 20 degrees on the
   real taps), the depth offset after it and the pin rotation.
4. **camera again** — the reference's ids taken again from the fitted twin's projected pin tips (stage 1's,
   taken with the nominal skin and tilt, gave 8 outer-ring markers a neighbour's id on the real taps), the
   camera refitted on all training taps with the fitted skin, and the ids taken once more with the fitted
   camera (the camera refitted if they changed). The uncertainties printed are from this fit's Jacobian,
   sigma^2 (J^T J)^-1 with the soft-L1 scaled residuals.
5. **appearance** — background and marker grey, radial marker shading, marker size and pixel noise from
   the real frames' image statistics (the same detector and :func:`pipeline.vision.tactip_id.frame_stats` on twin
   renders, three fixed-point passes).

The tilt-frame search scores the projected twin pin tips against the identified real markers (RMS px over
the training frames); the pin-rotation, skin and depth-offset searches score the displacements (each frame minus
the reference tap, twin against real), which the reference camera's rest-geometry bias does not enter.
The held-out frames are never used here.

Stages 2 and 3 are :mod:`benchmarks.tactip_fit_skin`, stage 5 :mod:`benchmarks.tactip_fit_appearance`;
this module holds what every stage shares (:class:`FitContext`, :func:`apply_params`) and the camera
stages (0, 1 and 4), and re-exports the others' functions. The command, its cache and the summary are
:mod:`benchmarks.tactip_fit_cli`.
"""

from __future__ import annotations

import json

import numpy as np
from scipy.optimize import least_squares

from pipeline.design import SensorDesign, design_from_dict, to_dict
from pipeline.vision.detection import detect_markers
from pipeline.vision.tactip_id import identify_by_reference, identify_sequence
from twin.tactip import PIN_MODEL, TAP_MODEL, DomeSkin, TapPose, check_monocular, project_markers
from benchmarks.tapdata import TapDataError, digest, load_tap_frames, read_frame, split_indices
from benchmarks.tactip_fit_appearance import fit_appearance
from benchmarks.tactip_fit_skin import (PIN_ROTATION_RANGE, PIVOT_OFFSET_BRACKET_MM, PIVOT_OFFSET_SLOPE,  # noqa: F401
                                        SEARCH_FRAMES, TILT_PIVOTS_MM, _fit_tilt_pivot, fit_physics)

__all__ = ["FitContext", "apply_params", "PIN_ROTATION_RANGE", "TILT_PIVOTS_MM", "FITTED_POSITION_PARAMETERS",
           "FITTED_POSITION_GROUPS", "camera_vector",
           "fit_layout", "fit_camera_reference", "fit_camera_all",
           "fit_physics", "fit_appearance", "CAM_KEYS", "LAYOUT_SEPARATIONS_MM"]

CAM_KEYS = ("f_px", "cx_px", "cy_px", "k1", "k2", "k3", "x_mm", "y_mm", "air_gap_mm", "roll_deg")
#: parameters that place the markers, by group: pin spacing, the camera, the tap and skin (tilt frame and mirror,
#: bending, depth offset), pin rotation, tilt pivot
FITTED_POSITION_GROUPS = {"pin spacing": 1, "camera": len(CAM_KEYS), "tap/skin": 4, "pin rotation": 1,
                          "tilt pivot": 1}
FITTED_POSITION_PARAMETERS = sum(FITTED_POSITION_GROUPS.values())


def apply_params(design: SensorDesign, cam: dict | None = None, twin: dict | None = None,
                 name: str | None = None) -> SensorDesign:
    """A copy of a monocular design with camera values (``CAM_KEYS``), the dome geometry (``separation_mm``,
    ``pin_height_mm``) and ``[twin]`` values replaced."""
    raw = to_dict(design)
    if cam:
        c = raw["camera"]
        for k, v in cam.items():
            if k == "f_px":
                c["fx_px"] = c["fy_px"] = float(v)
            elif k in ("k1", "k2", "k3"):
                c["dist"][{"k1": 0, "k2": 1, "k3": 4}[k]] = float(v)
            elif k == "air_gap_mm":
                raw["optics"]["air_gap_mm"] = float(v)
            elif k in ("separation_mm", "pin_height_mm"):
                continue
            else:
                c[k] = float(v)
    if cam and "separation_mm" in cam:
        raw["pattern"]["separation_mm"] = float(cam["separation_mm"])
    if cam and "pin_height_mm" in cam:
        raw["pins"]["height_mm"] = float(cam["pin_height_mm"])
    if twin:
        raw["twin"] = {**raw.get("twin", {}), **{k: float(v) for k, v in twin.items()}}
    if name:
        raw["name"] = name
    return design_from_dict(raw, source=design.source_file or "<fit>")


def camera_vector(design: SensorDesign) -> np.ndarray:
    c = design.camera
    return np.array([c.fx_px, c.cx_px, c.cy_px, c.dist[0], c.dist[1], c.dist[4], c.x_mm, c.y_mm,
                     design.optics.air_gap_mm, c.roll_deg])


class FitContext:
    """Frames, their detections and identification, and the twin's cached taps."""

    def __init__(self, frames, targets, design: SensorDesign, *, progress: bool = True,
                 skip_unlabelled: bool = False, log=print):
        check_monocular(design)
        self.design = design
        self.frames = load_tap_frames(frames, targets, design, skip_unlabelled=skip_unlabelled, log=log)
        self.train, self.held = split_indices(len(self.frames))
        self.progress = progress
        self.greys = [read_frame(f.path, design) for f in self.frames]
        self.blobs = [detect_markers(g) for g in self.greys]
        for f, b in zip(self.frames, self.blobs):
            if len(b) < 0.5 * design.marker_count:
                raise TapDataError(f"frame {f.path.name}: {len(b)} markers detected, the design has "
                                   f"{design.marker_count}: not a frame of this sensor?")
        depths = np.array([self.frames[i].pose.depth_mm for i in self.train])
        self.ref = int(self.train[int(np.argmin(depths))])
        self.skin = DomeSkin(design)
        self._taps: dict = {}
        self._skins: dict = {}
        self.ref_xy: np.ndarray | None = None
        self.real_xy: list[np.ndarray] = []

    def with_design(self, design: SensorDesign) -> "FitContext":
        """This context (frames, detections, split) for another design (its own skin and tap cache)."""
        import copy

        c = copy.copy(self)
        c.design = design
        c.skin = DomeSkin(design)
        c._taps = {}
        c._skins = {}
        return c

    def key(self) -> str:
        return digest(*[f.path for f in self.frames], [f.pose for f in self.frames],
                      json.dumps(to_dict(self.design), sort_keys=True, default=str), TAP_MODEL, PIN_MODEL)

    # ----- twin taps ----------------------------------------------------------------------
    _SKIN_KEYS = ("bending_ratio", "depth_offset_mm", "tilt_frame_deg", "tilt_mirror", "tilt_pivot_mm", "tap_friction")

    def _tap_key(self, i: int, params: dict, keys=_SKIN_KEYS + ("pin_rotation",)) -> tuple:
        return (i, tuple(sorted((a, round(b, 9)) for a, b in params.items() if a in keys)))

    def remember_tap(self, i: int, twin: dict, markers: tuple[np.ndarray, np.ndarray]) -> None:
        """Keep a tap computed elsewhere (a cell of the executor) as :meth:`tap` would have."""
        self._taps[self._tap_key(i, {**self.design.twin_params(), **twin})] = markers

    def skin_state(self, i: int, twin: dict) -> np.ndarray:
        """The tapped skin's nodes of frame ``i`` (the pins do not enter the solve: one state serves every
        pin rotation)."""
        params = {**self.design.twin_params(), **twin}
        k = self._tap_key(i, params, self._SKIN_KEYS)
        if k not in self._skins:
            X, info = self.skin.tap(self.frames[i].pose, params)
            if not info["converged"]:
                raise TapDataError(f"frame {self.frames[i].path.name}: the tap did not converge "
                                   f"(iterations {info['iterations']}, penetration {info['penetration_max_mm']:.3f} mm)")
            self._skins[k] = X
        return self._skins[k]

    def tap(self, i: int, twin: dict) -> tuple[np.ndarray, np.ndarray]:
        """Pin tips and pin axes of frame ``i``'s tap with the twin parameters ``twin`` (over the design's)."""
        params = {**self.design.twin_params(), **twin}
        k = self._tap_key(i, params)
        if k not in self._taps:
            self._taps[k] = self.skin.markers(self.skin_state(i, twin), params["pin_rotation"])
        return self._taps[k]

    # ----- identification -----------------------------------------------------------------
    def set_reference(self, ref_xy: np.ndarray) -> None:
        """Identify every frame (:func:`pipeline.vision.tactip_id.identify_sequence`): frames in order of pose
        distance from the reference, each against the already identified frame nearest in pose, so a
        chain of small steps carries the ids to the deepest, most tilted taps; an id only where the
        match is unambiguous."""
        self.ref_xy = ref_xy
        self.real_xy = identify_chain(self.blobs, [f.pose for f in self.frames], self.ref, ref_xy)

    def reference_from_twin(self, design: SensorDesign, twin: dict) -> np.ndarray:
        """The real reference tap's markers (M, 2, NaN where unmatched) identified by the twin's projected pin
        tips of the same tap (``design``'s camera, ``twin``'s skin and tap): each id goes to the real blob that
        is mutually nearest within half a spacing (:func:`pipeline.vision.tactip_id.identify_by_reference`)."""
        uv = project_markers(design, self.tap(self.ref, twin)[0])
        real = self.blobs[self.ref].xy_px
        idx = identify_by_reference(real, uv)
        ref_xy = np.full_like(uv, np.nan)
        ref_xy[idx >= 0] = real[idx[idx >= 0]]
        return ref_xy

    def residuals(self, design: SensorDesign, idx, twin: dict) -> np.ndarray:
        out = []
        for i in idx:
            p, _ = self.tap(i, twin)
            uv = project_markers(design, p)
            r = uv - self.real_xy[i]
            out.append(r[np.all(np.isfinite(r), axis=1)].ravel())
        return np.concatenate(out)

    def displacement_rms(self, design: SensorDesign, idx, twin: dict) -> float:
        """RMS px of the twin's marker displacements from the reference tap against the real ones: the rest
        geometry and the camera's bias cancel to first order, what is left is how the markers move. A new
        ``pin_rotation`` in ``twin`` reuses the taps (the skin solve does not depend on it)."""
        def uv(i):
            p, _ = self.tap(i, twin)
            return project_markers(design, p)

        u0, r0 = uv(self.ref), self.real_xy[self.ref]
        out = []
        for i in idx:
            e = (uv(i) - u0) - (self.real_xy[i] - r0)
            out.append(e[np.all(np.isfinite(e), axis=1)])
        e = np.concatenate(out)
        return float(np.sqrt(np.mean(np.sum(e * e, axis=1)))) if len(e) else float("inf")

    def rms(self, design: SensorDesign, idx, twin: dict) -> float:
        r = self.residuals(design, idx, twin)
        return float(np.sqrt(np.mean(r * r) * 2)) if len(r) else float("inf")


def _pose_vec(p: TapPose) -> np.ndarray:
    return np.array([p.depth_mm, p.tilt_x_deg / 5.0, p.tilt_y_deg / 5.0])


def identify_chain(blobs, poses, ref: int, ref_xy: np.ndarray) -> list[np.ndarray]:
    """Identified positions (M, 2, NaN where unidentified) of every frame, see FitContext.set_reference:
    :func:`pipeline.vision.tactip_id.identify_sequence` over the poses (depth mm, tilts deg / 5)."""
    P = np.array([_pose_vec(p) for p in poses])
    return identify_sequence(blobs, P, ref, ref_xy).xy


# ----- stage 1/4: camera ------------------------------------------------------------------

def _cam_residuals(vec, ctx: FitContext, pts3d, obs, base: SensorDesign):
    d = apply_params(base, dict(zip(CAM_KEYS, vec)))
    r = []
    for p, o in zip(pts3d, obs):
        uv = project_markers(d, p)
        r.append((uv - o).ravel())
    return np.concatenate(r)


def _bounds(vec):
    lo = np.array([60, 200, 120, -1.0, -1.0, -1.0, -5, -5, 0.5, -180.0])
    hi = np.array([1500, 440, 360, 1.0, 1.0, 1.0, 5, 5, 30.0, 180.0])
    return lo, hi


def fit_camera_reference(ctx: FitContext, twin: dict) -> tuple[SensorDesign, np.ndarray, dict]:
    """Stage 1: camera from the reference tap; returns the design, the reference ids' real positions
    (M, 2, NaN where unmatched) and a report."""
    design = ctx.design
    p, _ = ctx.tap(ctx.ref, twin)
    real = ctx.blobs[ctx.ref].xy_px
    from scipy.spatial import cKDTree
    tree = cKDTree(real)
    centre = real.mean(axis=0)
    best = None
    # the focal length sets the pattern's image size: scale it to the real pattern's extent first
    for roll in np.arange(0.0, 60.0, 1.0):
        d = apply_params(design, {"cx_px": centre[0], "cy_px": centre[1], "roll_deg": roll})
        uv = project_markers(d, p)
        f0 = d.camera.fx_px * np.median(np.hypot(*(real - centre).T)) / np.median(np.hypot(*(uv - centre).T))
        d = apply_params(d, {"f_px": f0})
        uv = project_markers(d, p)
        score = float(np.median(tree.query(uv)[0]))
        if best is None or score < best[0]:
            best = (score, d)
    d = best[1]
    vec = camera_vector(d)
    lo, hi = _bounds(vec)
    vec = np.clip(vec, lo + 1e-9, hi - 1e-9)
    k3 = CAM_KEYS.index("k3")
    for it in range(6):
        uv = project_markers(apply_params(design, dict(zip(CAM_KEYS, vec))), p)
        idx = identify_by_reference(real, uv)
        ok = idx >= 0
        obs = np.full_like(uv, np.nan)
        obs[ok] = real[idx[ok]]
        # k3 stays 0 until the matches have settled (freed early it trades off against k1, k2 and
        # lets the inner-ring matches pull the outer rings off their pins)
        free = np.ones(len(vec), bool)
        free[k3] = it >= 3
        full = vec.copy()

        def fun(x, full=full, free=free, ok=ok, obs=obs):
            full[free] = x
            return _cam_residuals(full, ctx, [p[ok]], [obs[ok]], design)

        res = least_squares(fun, vec[free], bounds=(lo[free], hi[free]), loss="soft_l1", f_scale=1.0,
                            x_scale="jac")
        vec = vec.copy()
        vec[free] = res.x
    fitted = apply_params(design, dict(zip(CAM_KEYS, vec)))
    ref_xy = ctx.reference_from_twin(fitted, twin)
    ok = np.isfinite(ref_xy[:, 0])
    report = {"roll_grid_median_px": best[0], "matched": int(ok.sum()),
              "rms_px": float(np.sqrt(np.mean(np.sum((project_markers(fitted, p)[ok] - ref_xy[ok]) ** 2, axis=1))))}
    return fitted, ref_xy, report


LAYOUT_SEPARATIONS_MM = tuple(np.round(np.arange(1.8, 2.85, 0.1), 2))


def fit_layout(ctx: FitContext, twin: dict, bar=None) -> tuple[float, list]:
    """Stage 0: the pins' arc spacing on the dome (the published 331-pin CAD was not available): for each
    candidate the stage-1 camera fit, scored by the mean distance of every real reference marker to the
    nearest projected pin tip, capped at 8 px (unmatched markers cost the cap)."""
    from scipy.spatial import cKDTree

    real = ctx.blobs[ctx.ref].xy_px
    scores = []
    for sep in LAYOUT_SEPARATIONS_MM:
        try:
            c = ctx.with_design(apply_params(ctx.design, {"separation_mm": sep}))
        except Exception:  # noqa: BLE001 - a spacing the design cannot take (pins would touch): skipped
            continue
        d, _, _ = fit_camera_reference(c, twin)
        p, _ = c.tap(c.ref, twin)
        dist = cKDTree(project_markers(d, p)).query(real)[0]
        scores.append((float(np.mean(np.minimum(dist, 8.0))), float(sep)))
        if bar is not None:
            bar.update(1)
    return min(scores)[1], scores


def fit_camera_all(ctx: FitContext, design: SensorDesign, twin: dict) -> tuple[SensorDesign, dict]:
    """Stage 4: the camera on all training taps with the fitted skin; uncertainty from the Jacobian.

    The reference's ids (which identify every real frame) are first taken again from the twin's projected pin
    tips with the fitted skin and tap: stage 1 took them with the nominal ones, whose reference tap lies
    elsewhere on the outer rings (on the 40 real taps 8 of its 306 ids, all on the outermost ring, were a
    neighbour's, and the fitted twin matches 328). After the fit they are taken once more with the fitted
    camera, and the camera fitted again if they changed. Sets the context's reference; the report carries
    the ids' counts."""
    n_first = int(np.isfinite(ctx.ref_xy[:, 0]).sum()) if ctx.ref_xy is not None else 0
    ctx.set_reference(ctx.reference_from_twin(design, twin))
    fitted, rep = _fit_camera_all_once(ctx, design, twin)
    again = ctx.reference_from_twin(fitted, twin)
    refits = 0
    if not np.array_equal(again, ctx.ref_xy, equal_nan=True):
        ctx.set_reference(again)
        fitted, rep = _fit_camera_all_once(ctx, fitted, twin)
        refits = 1
    rep["reference_ids"] = {"first": n_first, "fitted": int(np.isfinite(ctx.ref_xy[:, 0]).sum()), "refits": refits}
    return fitted, rep


def _fit_camera_all_once(ctx: FitContext, design: SensorDesign, twin: dict) -> tuple[SensorDesign, dict]:
    pts, obs = [], []
    for i in ctx.train:
        p, _ = ctx.tap(i, twin)
        ok = np.all(np.isfinite(ctx.real_xy[i]), axis=1)
        pts.append(p[ok])
        obs.append(ctx.real_xy[i][ok])
    vec = camera_vector(design)
    lo, hi = _bounds(vec)
    res = least_squares(_cam_residuals, np.clip(vec, lo + 1e-9, hi - 1e-9), args=(ctx, pts, obs, design),
                        bounds=(lo, hi), loss="soft_l1", f_scale=1.0, x_scale="jac")
    J = res.jac
    dof = max(len(res.fun) - len(res.x), 1)
    s2 = 2 * float(res.cost) / dof
    try:
        cov = np.linalg.inv(J.T @ J) * s2
        sd = np.sqrt(np.clip(np.diag(cov), 0, None))
    except np.linalg.LinAlgError:
        sd = np.full(len(res.x), np.nan)
    fitted = apply_params(design, dict(zip(CAM_KEYS, res.x)))
    r = res.fun.reshape(-1, 2)
    return fitted, {"values": dict(zip(CAM_KEYS, map(float, res.x))), "sd": dict(zip(CAM_KEYS, map(float, sd))),
                    "rms_px": float(np.sqrt(np.mean(np.sum(r * r, axis=1)))), "n_obs": int(len(r)),
                    "converged": bool(res.success), "message": str(res.message)}
