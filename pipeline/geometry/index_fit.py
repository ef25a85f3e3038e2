"""Refractive indices measured from a press: what ``calibrate-refraction`` fits.

* :func:`fit_refractive_index` — the effective index n of the paper's linear model (Eq. 8), the slope of
  true vs apparent depth displacements;
* :func:`fit_index_from_press` — from a skin-less marker-board press with known robot steps, both that
  linear index and the gel index for which the exact correction
  (:func:`pipeline.geometry.refraction.correct_exact`) reproduces the steps best.

The stack model itself (Snell at the acrylic and gel planes, the exact and linear corrections) is
:mod:`pipeline.geometry.refraction`.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from pipeline.design import SensorDesign
from pipeline.geometry.refraction import RefractionError, correct_exact
from pipeline.types import MarkerMatches, StereoCalibration

__all__ = ["fit_refractive_index", "fit_index_from_press", "PressFit", "RefractionFit"]


@dataclass(frozen=True)
class RefractionFit:
    """Effective refractive index from true vs apparent depth changes.

    ``n`` slope of true = n * apparent (least squares through the origin, the model of Eq. 8);
    ``intercept`` (mm) and ``slope_with_intercept`` of the unconstrained line true = a * apparent + c;
    ``r2`` coefficient of determination of the through-origin model (centred total sum of squares);
    ``residual_rms_mm`` RMS residual of the through-origin model; ``n_points`` samples used.
    """

    n: float
    intercept: float
    r2: float
    residual_rms_mm: float
    slope_with_intercept: float = float("nan")
    n_points: int = 0

    def summary(self) -> str:
        return (f"n = {self.n:.4f} (through origin), line: {self.slope_with_intercept:.4f} * dz' + "
                f"{self.intercept:+.4f} mm; R^2 = {self.r2:.5f}; residual RMS {self.residual_rms_mm:.4f} mm "
                f"({self.n_points} samples)")


def fit_refractive_index(true_dz_mm: np.ndarray, apparent_dz_mm: np.ndarray) -> RefractionFit:
    """Fit true_dz = n * apparent_dz (and with an intercept) by least squares.

    Parameters
    ----------
    true_dz_mm, apparent_dz_mm : (N,) float64
        Known displacements (e.g. press steps) and the triangulated apparent displacements, mm.

    Returns
    -------
    RefractionFit
    """
    t = np.asarray(true_dz_mm, dtype=np.float64).reshape(-1)
    a = np.asarray(apparent_dz_mm, dtype=np.float64).reshape(-1)
    if t.shape != a.shape:
        raise RefractionError(f"fit_refractive_index: {t.size} true vs {a.size} apparent displacements")
    ok = np.isfinite(t) & np.isfinite(a)
    t, a = t[ok], a[ok]
    if len(t) < 2 or np.ptp(a) == 0:
        raise RefractionError("fit_refractive_index: need at least 2 distinct apparent displacements")
    n = float(a @ t / (a @ a))
    slope, intercept = np.polyfit(a, t, 1)
    res = t - n * a
    ss_tot = float(np.sum((t - t.mean()) ** 2))
    r2 = 1.0 - float(res @ res) / ss_tot if ss_tot > 0 else float("nan")
    return RefractionFit(n=n, intercept=float(intercept), r2=r2, residual_rms_mm=float(np.sqrt(np.mean(res**2))),
                         slope_with_intercept=float(slope), n_points=int(len(t)))


@dataclass(frozen=True)
class PressFit:
    """Indices fitted from a skin-less board press.

    ``linear`` the effective index of the paper's linear model (slope of true vs apparent displacement,
    :func:`fit_refractive_index`; wide-angle markers make it exceed the gel's index by the error term E);
    ``n_gel_exact`` the gel index for which :func:`correct_exact` reproduces the robot's displacements
    best (least squares over every marker and step); ``exact_residual_rms_mm`` the RMS displacement
    error of the exact correction with that index.
    """

    linear: RefractionFit
    n_gel_exact: float
    exact_residual_rms_mm: float

    def summary(self) -> str:
        return (f"linear model: {self.linear.summary()}\nexact model: n_gel = {self.n_gel_exact:.4f} "
                f"(displacement residual RMS {self.exact_residual_rms_mm:.4f} mm)")


def fit_index_from_press(frames, steps_mm, design: SensorDesign, calib: StereoCalibration, *,
                         progress: bool = True, echo=print) -> PressFit:
    """Indices from a skin-less press on a marker board (what ``calibrate-refraction`` runs).

    ``frames`` are the stereo frames of one or more trials, ``len(steps_mm)`` frames per trial in step
    order (robot press depths, mm). Each frame is matched by a :class:`pipeline.runner.Reconstructor`;
    per marker seen in both, the displacement from the trial's first step is paired with the robot's.
    The apparent (straight-ray) displacements give the linear model's effective index; the exact
    correction's displacements, as a function of the gel index, give the exact model's gel index.

    Raises
    ------
    RefractionError
        ``frames`` is not a whole number of trials, or markers were reconstructed at fewer than two
        distinct steps.
    """
    from scipy.optimize import minimize_scalar  # noqa: PLC0415
    from tqdm import tqdm  # noqa: PLC0415

    from pipeline.runner import Reconstructor  # noqa: PLC0415 (the runner chains the stages: a layer above this one)

    frames = list(frames)
    steps = [float(s) for s in steps_mm]
    if not steps or not frames or len(frames) % len(steps):
        raise RefractionError(f"{len(frames)} frames is not a whole number of trials of {len(steps)} steps "
                              f"(one frame per step, repeated trials)")
    rec = Reconstructor(design, calib, refraction="exact")
    true_dz, app_dz, pairs = [], [], []   # pairs: (reference matches, matches, robot displacement)
    n_trials = len(frames) // len(steps)
    for trial in range(n_trials):
        results = []
        for k in tqdm(range(len(steps)), desc=f"trial {trial + 1}/{n_trials}", leave=False, disable=not progress):
            results.append(rec.process(frames[trial * len(steps) + k]))
        ref = results[0].apparent
        for step, res in zip(steps, results):
            cloud = res.apparent
            common, i_ref, i_cur = np.intersect1d(ref.ids, cloud.ids, return_indices=True)
            if len(common) == 0:
                echo(f"trial {trial + 1}, step {step:g} mm: no markers in common with the first step (skipped)")
                continue
            true_dz.append(np.full(len(common), step - steps[0]))
            # the press moves the board toward the cameras (-z): apparent displacement z'_0 - z'
            app_dz.append(ref.xyz_mm[i_ref, 2] - cloud.xyz_mm[i_cur, 2])
            if step != steps[0]:
                pairs.append((_subset(results[0].matches, common), _subset(res.matches, common), step - steps[0]))
    if len({float(t[0]) for t in true_dz if len(t)}) < 2 or not pairs:
        raise RefractionError("markers were reconstructed at fewer than 2 distinct steps; cannot fit a refractive index")
    linear = fit_refractive_index(np.concatenate(true_dz), np.concatenate(app_dz))

    def residuals(n: float) -> np.ndarray:
        out = []
        for m0, m, dz in pairs:
            z0 = correct_exact(m0, calib, design, n_gel=n).xyz_mm[:, 2]
            z = correct_exact(m, calib, design, n_gel=n).xyz_mm[:, 2]
            out.append((z0 - z) - dz)
        return np.concatenate(out)

    best = minimize_scalar(lambda n: float(np.mean(residuals(n) ** 2)), bounds=(1.0, 3.0), method="bounded",
                           options={"xatol": 1e-6})
    n_exact = float(best.x)
    return PressFit(linear, n_exact, float(np.sqrt(np.mean(residuals(n_exact) ** 2))))


def _subset(matches: MarkerMatches, ids: np.ndarray) -> MarkerMatches:
    """The matches of ``ids`` (all present in ``matches``), in the order of ``ids``."""
    pos = {int(i): k for k, i in enumerate(matches.ids)}
    sel = np.array([pos[int(i)] for i in ids], dtype=np.int64)
    return MarkerMatches(np.asarray(ids), matches.left_px[sel], matches.right_px[sel])
