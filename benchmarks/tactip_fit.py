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
   scored on every training tap), bending (within a factor 2) and pin rotation once more.
4. **camera again** — the camera refitted on all training taps with the fitted skin (the uncertainties
   printed are from this fit's Jacobian, sigma^2 (J^T J)^-1 with the soft-L1 scaled residuals).
5. **appearance** — background and marker grey, radial marker shading, marker size and pixel noise from
   the real frames' image statistics (the same detector and :func:`pipeline.vision.tactip_id.frame_stats` on twin
   renders, three fixed-point passes).

The tilt-frame search scores the projected twin pin tips against the identified real markers (RMS px over
the training frames); the pin-rotation, skin and depth-offset searches score the displacements (each frame minus
the reference tap, twin against real), which the reference camera's rest-geometry bias does not enter.
The held-out frames are never used here.

One module over ~400 lines on purpose: the stages above are one fit read top to bottom, each stage
refining what the one before fixed (the camera the physics searches project through, the skin the camera
is refitted with) and all sharing :class:`FitContext`; the command, its cache and the summary are
:mod:`benchmarks.tactip_fit_cli`.
"""

from __future__ import annotations

import json
import math

import numpy as np
from scipy.optimize import least_squares, minimize_scalar

from pipeline.design import SensorDesign, design_from_dict, to_dict
from pipeline.vision.detection import detect_markers
from pipeline.vision.tactip_id import frame_stats, identify_by_reference, identify_sequence
from twin.tactip import PIN_MODEL, TAP_MODEL, DomeSkin, TapPose, check_monocular, project_markers, render_frame
from benchmarks.tapdata import TapDataError, digest, load_tap_frames, read_frame, split_indices

__all__ = ["FitContext", "apply_params", "PIN_ROTATION_RANGE", "TILT_PIVOTS_MM", "FITTED_POSITION_PARAMETERS", "camera_vector",
           "fit_layout", "fit_camera_reference", "fit_camera_all",
           "fit_physics", "fit_appearance", "CAM_KEYS", "LAYOUT_SEPARATIONS_MM"]

CAM_KEYS = ("f_px", "cx_px", "cy_px", "k1", "k2", "k3", "x_mm", "y_mm", "air_gap_mm", "roll_deg")
#: parameters that place the markers: pin spacing, the camera, tilt frame and mirror, bending, depth offset,
#: pin rotation, tilt pivot
FITTED_POSITION_PARAMETERS = 1 + len(CAM_KEYS) + 4 + 1 + 1
#: coarse heights (mm) of the tap's tilt pivot above the dome's centre of curvature: from the centre (a tilted
#: surface first touches at depth 0) past the apex of the 20 mm dome; one parabolic step refines the best
TILT_PIVOTS_MM = (0.0, 12.0, 24.0, 36.0)
#: the depth offset's fall per mm of pivot height (mm/mm) before two heights are scored, and the half-width of
#: its search bracket around the value extrapolated from the heights scored (the offsets fitted from 0 to
#: 20 mm fell 0.020-0.027 mm per mm)
PIVOT_OFFSET_SLOPE = 0.022
PIVOT_OFFSET_BRACKET_MM = 0.2
SEARCH_FRAMES = 10      # training taps used by the 1-D physics searches (spread over depth and tilt)


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
    _SKIN_KEYS = ("bending_ratio", "depth_offset_mm", "tilt_frame_deg", "tilt_mirror", "tilt_pivot_mm")

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
    uv = project_markers(fitted, p)
    idx = identify_by_reference(real, uv)
    ref_xy = np.full_like(uv, np.nan)
    ref_xy[idx >= 0] = real[idx[idx >= 0]]
    report = {"roll_grid_median_px": best[0], "matched": int((idx >= 0).sum()),
              "rms_px": float(np.sqrt(np.mean(np.sum((uv[idx >= 0] - ref_xy[idx >= 0]) ** 2, axis=1))))}
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
    """Stage 4: the camera on all training taps with the fitted skin; uncertainty from the Jacobian."""
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


# ----- stages 2/3: physics ------------------------------------------------------------------

def _search_set(ctx: FitContext) -> list[int]:
    tr = list(ctx.train)
    if len(tr) <= SEARCH_FRAMES:
        return tr
    pick = np.linspace(0, len(tr) - 1, SEARCH_FRAMES).round().astype(int)
    return [tr[k] for k in pick]


def _curvature_sd(f, x, h, f0, n_obs):
    """1-sigma of a 1-D least-squares parameter from the objective's curvature (RMS objective)."""
    try:
        fp, fm = f(x + h), f(x - h)
    except Exception:  # noqa: BLE001 - outside the model's range: no estimate
        return float("nan")
    # SSE = n * rms^2; var(x) = 2 sigma^2 / SSE''
    sse = lambda v: n_obs * v * v  # noqa: E731
    curv = (sse(fp) - 2 * sse(f0) + sse(fm)) / (h * h)
    sigma2 = sse(f0) / max(n_obs - 1, 1)
    return float(math.sqrt(2 * sigma2 / curv)) if curv > 0 else float("nan")


def fit_physics(ctx: FitContext, design: SensorDesign, twin: dict, bar) -> tuple[dict, dict]:
    twin = dict(twin)
    tilted = sorted(ctx.train, key=lambda i: -np.hypot(ctx.frames[i].pose.tilt_x_deg, ctx.frames[i].pose.tilt_y_deg))[:4]
    grid = []
    for mirror in (0.0, 1.0):
        for psi in np.arange(-180.0, 180.0, 30.0):
            grid.append((ctx.rms(design, tilted, {**twin, "tilt_frame_deg": psi, "tilt_mirror": mirror}), psi, mirror))
            bar.update(1)
    _, psi0, mirror = min(grid)
    twin["tilt_mirror"] = mirror
    search = _search_set(ctx)
    f_psi = lambda v: ctx.rms(design, search, {**twin, "tilt_frame_deg": v})  # noqa: E731
    r = minimize_scalar(f_psi, bounds=(psi0 - 30, psi0 + 30), method="bounded", options={"xatol": 1.0, "maxiter": 12})
    twin["tilt_frame_deg"] = float((r.x + 180) % 360 - 180)
    bar.update(1)
    # the pins and the skin are fitted on how the markers move (displacement from the reference tap), not
    # where they are: the reference camera was fitted with pins held normal to the skin, a rest-geometry
    # bias the positions would carry into both
    twin["pin_rotation"] = _fit_pin_rotation(ctx, design, search, twin)
    f_b = lambda lv: ctx.displacement_rms(design, search, {**twin, "bending_ratio": 10 ** lv})  # noqa: E731
    r = minimize_scalar(f_b, bounds=(-2.5, 1.5), method="bounded", options={"xatol": 0.05, "maxiter": 14})
    twin["bending_ratio"] = float(10 ** r.x)
    bar.update(1)
    f_d = lambda v: ctx.displacement_rms(design, search, {**twin, "depth_offset_mm": v})  # noqa: E731
    r = minimize_scalar(f_d, bounds=(-1.5, 1.5), method="bounded", options={"xatol": 0.02, "maxiter": 12})
    twin["depth_offset_mm"] = float(r.x)
    bar.update(1)
    twin["pin_rotation"] = _fit_pin_rotation(ctx, design, search, twin)
    twin["tilt_pivot_mm"], pivot_scores = _fit_tilt_pivot(ctx, design, search, twin, bar)
    # the pivot moves the bending ratio little (0.082 -> 0.107 for a pivot at the apex): re-searched within
    # a factor 2 of its value
    f_b = lambda lv: ctx.displacement_rms(design, search, {**twin, "bending_ratio": 10 ** lv})  # noqa: E731
    lv0 = math.log10(twin["bending_ratio"])
    r = minimize_scalar(f_b, bounds=(lv0 - 0.3, lv0 + 0.3), method="bounded", options={"xatol": 0.03, "maxiter": 10})
    twin["bending_ratio"] = float(10 ** r.x)
    twin["pin_rotation"] = _fit_pin_rotation(ctx, design, search, twin)
    bar.update(1)
    f_a = lambda a: ctx.displacement_rms(design, search, {**twin, "pin_rotation": a})  # noqa: E731
    f_b = lambda lv: ctx.displacement_rms(design, search, {**twin, "bending_ratio": 10 ** lv})  # noqa: E731
    f_d = lambda v: ctx.displacement_rms(design, search, {**twin, "depth_offset_mm": v})  # noqa: E731
    n_obs = sum(int(np.all(np.isfinite(ctx.real_xy[i]), axis=1).sum()) for i in search)
    f0, p0 = f_a(twin["pin_rotation"]), ctx.rms(design, search, twin)
    # the curvature is taken inside [0, 1] (a pin cannot turn against the skin nor past it): at a bound,
    # one step in from it
    h_a = 0.05
    a0 = min(max(twin["pin_rotation"], PIN_ROTATION_RANGE[0] + h_a), PIN_ROTATION_RANGE[1] - h_a)
    sd = {"log10_bending_ratio": _curvature_sd(f_b, math.log10(twin["bending_ratio"]), 0.15, f0, n_obs),
          "depth_offset_mm": _curvature_sd(f_d, twin["depth_offset_mm"], 0.1, f0, n_obs),
          "tilt_frame_deg": _curvature_sd(f_psi, twin["tilt_frame_deg"], 3.0, p0, n_obs),
          "pin_rotation": _curvature_sd(f_a, a0, h_a, f_a(a0), n_obs)}
    bar.update(1)
    return twin, {"grid": [[float(a), float(b), float(c)] for a, b, c in grid], "rms_px_search": p0,
                  "displacement_rms_px_search": f0, "sd": sd, "pin_rotation": twin["pin_rotation"],
                  "tilt_pivot_scores": pivot_scores,
                  "search_frames": [ctx.frames[i].path.name for i in search]}


#: the pin rotation fraction is searched over its physical range: 0, pins that keep their rest direction
#: while the skin turns under them; 1, pins held normal to the skin
PIN_ROTATION_RANGE = (0.0, 1.0)


def _fit_pin_rotation(ctx: FitContext, design: SensorDesign, search, twin: dict) -> float:
    """The pins' rotation fraction by a bounded 1-D search on the markers' displacements, with the design's
    pin height; the taps are shared by every candidate, so the search costs projections only. The bounded
    search never evaluates the bounds themselves: they are scored too and kept when better."""
    f = lambda a: ctx.displacement_rms(design, search, {**twin, "pin_rotation": a})  # noqa: E731
    r = minimize_scalar(f, bounds=PIN_ROTATION_RANGE, method="bounded", options={"xatol": 0.005, "maxiter": 25})
    best = min([(float(r.fun), float(r.x))] + [(f(a), a) for a in PIN_ROTATION_RANGE])
    return float(best[1])


def _fit_tilt_pivot(ctx: FitContext, design: SensorDesign, search, twin: dict, bar) -> tuple[float, list]:
    """The height of the tap's tilt pivot above the dome's centre, from its centre to 16 mm past the apex of
    the 20 mm dome (a tapping robot's tool centre point may lie beyond the apex, in the tapped object): a
    coarse grid (:data:`TILT_PIVOTS_MM`), then one step to the vertex of the parabola through the best grid height and
    its neighbours. For each height the depth offset is re-searched on the search taps (a higher pivot
    presses tilted taps deeper, which the offset partly absorbs) in a bracket around its value extrapolated
    from the heights already scored (the offset falls almost linearly with the height), then the height is
    scored on the displacements of every training tap (the search taps alone under-weight the most tilted
    taps, where the pivot matters). Returns the best height and the [height, offset, RMS px] rows in the
    order scored."""
    rows: list[list[float]] = []
    train = [i for i in ctx.train if i != ctx.ref]

    def score(h: float) -> list[float]:
        t = {**twin, "tilt_pivot_mm": float(h)}
        if rows:
            known = sorted((r[0], r[1]) for r in rows)
            if len(known) == 1:
                pred = known[0][1] - PIVOT_OFFSET_SLOPE * (h - known[0][0])
            else:
                (h0, o0), (h1, o1) = min(((a, b) for a, b in zip(known, known[1:])),
                                         key=lambda ab: abs(0.5 * (ab[0][0] + ab[1][0]) - h))
                pred = o0 + (o1 - o0) * (h - h0) / (h1 - h0)
            lo, hi = pred - PIVOT_OFFSET_BRACKET_MM, pred + PIVOT_OFFSET_BRACKET_MM
            f_d = lambda v: ctx.displacement_rms(design, search, {**t, "depth_offset_mm": v})  # noqa: E731
            r = minimize_scalar(f_d, bounds=(lo, hi), method="bounded", options={"xatol": 0.02, "maxiter": 12})
            t["depth_offset_mm"] = float(r.x)
        row = [float(h), float(t["depth_offset_mm"]), ctx.displacement_rms(design, train, t)]
        rows.append(row)
        bar.update(1)
        return row

    # the height 0 keeps the offset the skin stage has just fitted (the same taps, the same search)
    grid = [score(h) for h in TILT_PIVOTS_MM]
    k = min(range(len(grid)), key=lambda j: grid[j][2])
    if 0 < k < len(grid) - 1:
        (h0, _, e0), (h1, _, e1), (h2, _, e2) = grid[k - 1], grid[k], grid[k + 1]
        den = (h1 - h0) * (e1 - e2) - (h1 - h2) * (e1 - e0)
        if den != 0:
            hv = h1 - 0.5 * ((h1 - h0) ** 2 * (e1 - e2) - (h1 - h2) ** 2 * (e1 - e0)) / den
            if h0 < hv < h2 and abs(hv - h1) > 0.5:
                score(hv)
    h, off, _ = min(rows, key=lambda row: row[2])
    twin["depth_offset_mm"] = off
    return h, rows


# ----- stage 5: appearance -----------------------------------------------------------------

def fit_appearance(ctx: FitContext, design: SensorDesign, twin: dict) -> tuple[dict, dict]:
    twin = dict(twin)
    pick = _search_set(ctx)[:4]
    real = [frame_stats(ctx.greys[i], ctx.blobs[i]) for i in pick]
    target = {k: float(np.median([s[k] for s in real])) for k in ("radius_px", "contrast", "background", "noise")}
    # radial shading: real marker core brightness against the squared normalised image radius
    cam = design.camera
    vals, rho2 = [], []
    for i in pick:
        g = ctx.greys[i].astype(np.float64)
        for u, v in ctx.blobs[i].xy_px:
            vals.append(g[int(round(v)) - 1:int(round(v)) + 2, int(round(u)) - 1:int(round(u)) + 2].mean())
            rho2.append(((u - cam.cx_px) ** 2 + (v - cam.cy_px) ** 2) / (0.5 * cam.height_px) ** 2)
    A = np.column_stack([np.ones(len(rho2)), rho2])
    a0, a1 = np.linalg.lstsq(A, np.asarray(vals), rcond=None)[0]
    twin["marker_shading"] = float(a1 / a0) if a0 > 0 else 0.0
    twin["background_grey"] = target["background"]
    twin["marker_grey"] = float(np.clip(a0, 1, 255))
    twin["noise_grey"] = max(target["noise"], 0.0)
    history = []
    for _ in range(3):
        d = apply_params(design, twin=twin)
        sims = []
        for i in pick:
            p, ax = ctx.tap(i, twin)
            img = render_frame(d, p, ax, seed=i)
            sims.append(frame_stats(img, detect_markers(img)))
        got = {k: float(np.median([s[k] for s in sims if s[k] is not None])) for k in target}
        history.append(got)
        twin["marker_scale"] = float(np.clip(twin["marker_scale"] * target["radius_px"] / got["radius_px"], 0.3, 3.0))
        twin["marker_grey"] = float(np.clip(twin["marker_grey"] + (target["contrast"] - got["contrast"]), 1, 255))
        twin["background_grey"] = float(np.clip(twin["background_grey"] + (target["background"] - got["background"]), 0, 255))
        if got["noise"] > 0:
            twin["noise_grey"] = float(max(twin["noise_grey"] * target["noise"] / got["noise"], 0.0))
    return twin, {"real": target, "twin_passes": history}
