"""Scoring helpers shared by the experiments (truth is only ever read here, after the pipeline ran).

All positions are sensor frame, mm (see :mod:`pipeline.design`).
"""

from __future__ import annotations

from typing import Any

import numpy as np

__all__ = [
    "interp_heightmap",
    "true_skin_height",
    "identity_correct",
    "radial_rms",
    "rms",
    "gaussian_curvature_profile",
    "reconstruct",
    "twin_calibration",
    "calibration_note",
    "make_indenter",
    "surface_grid",
    "finite_max",
    "physically_valid",
    "press_setup",
    "CELL_COUNT_METRICS",
]

#: The cell counts a press grid records (its ``register(metrics=...)`` declares them): cells that failed the
#: twin's physics checks and cells that passed them (:func:`physically_valid`), presses that raised
#: (:func:`run_press_cells`).
CELL_COUNT_METRICS = {"invalid_cells": "1", "valid_cells": "1", "failed_cells": "1"}


def rms(x: np.ndarray) -> float:
    x = np.asarray(x, dtype=np.float64)
    x = x[np.isfinite(x)]
    return float(np.sqrt(np.mean(x**2))) if x.size else float("nan")


def finite_max(values) -> float:
    """Largest finite value; NaN when there is none (nothing measured: a pattern without markers, a grid point
    whose every press failed or left its penetration unmeasured)."""
    v = np.asarray(list(values), dtype=np.float64)
    v = v[np.isfinite(v)]
    return float(v.max()) if v.size else float("nan")


def interp_heightmap(hm, xy_mm: np.ndarray) -> np.ndarray:
    """Bilinear height of a ``HeightMap`` at points ``xy_mm`` (N, 2); NaN outside or where it has no data."""
    from scipy.interpolate import RegularGridInterpolator

    f = RegularGridInterpolator((np.asarray(hm.y_mm), np.asarray(hm.x_mm)), np.asarray(hm.z_mm),
                                bounds_error=False, fill_value=np.nan)
    xy_mm = np.asarray(xy_mm, dtype=np.float64).reshape(-1, 2)
    return f(xy_mm[:, ::-1])


def true_skin_height(truth, xy_mm: np.ndarray) -> np.ndarray:
    """z of the twin's deformed outer skin at ``xy_mm`` (N, 2): linear interpolation over the skin
    mesh vertices seen from above (the outer skin is a height field over x-y); NaN outside."""
    from scipy.interpolate import LinearNDInterpolator

    v = np.asarray(truth.skin_vertices_mm, dtype=np.float64)
    f = LinearNDInterpolator(v[:, :2], v[:, 2])
    return f(np.asarray(xy_mm, dtype=np.float64).reshape(-1, 2))


def identity_correct(ids: np.ndarray, xyz_mm: np.ndarray, truth, max_dist_mm: float) -> np.ndarray:
    """Per reported marker: True when the nearest truth marker to its 3-D position has the same id
    and lies within ``max_dist_mm`` (half the marker separation: a closer wrong marker is impossible)."""
    from scipy.spatial import cKDTree

    ids = np.asarray(ids)
    if len(ids) == 0:
        return np.zeros(0, dtype=bool)
    tree = cKDTree(np.asarray(truth.marker_xyz_mm))
    d, j = tree.query(np.asarray(xyz_mm))
    truth_ids = np.asarray(truth.marker_ids)[j]
    return (truth_ids == ids) & (d <= max_dist_mm)


def radial_rms(r_mm: np.ndarray, err_mm: np.ndarray, edges_mm: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """RMS of ``err_mm`` in radial bins ``edges_mm``; returns (bin centres, rms) with NaN for empty bins."""
    centres = 0.5 * (edges_mm[1:] + edges_mm[:-1])
    out = np.full(len(centres), np.nan)
    k = np.digitize(r_mm, edges_mm) - 1
    for i in range(len(centres)):
        sel = (k == i) & np.isfinite(err_mm)
        if np.any(sel):
            out[i] = np.sqrt(np.mean(err_mm[sel] ** 2))
    return centres, out


def gaussian_curvature_profile(r_mm: np.ndarray, h_mm: float, sigma2_mm2: float) -> np.ndarray:
    """Curvature (1/mm) of the profile z = h·exp(−r²/2σ²) at radius r: |z''| / (1 + z'²)^{3/2}."""
    e = np.exp(-(r_mm**2) / (2 * sigma2_mm2))
    dz = -h_mm * r_mm / sigma2_mm2 * e
    d2z = h_mm * e * (r_mm**2 / sigma2_mm2 - 1.0) / sigma2_mm2
    return np.abs(d2z) / (1 + dz**2) ** 1.5


def twin_calibration(design):
    """The twin's true stereo calibration (the experiments other than camera-calibration use it, so
    their numbers measure reconstruction, not chessboard calibration error)."""
    from twin.render import true_calibration

    return true_calibration(design)


def calibration_note(setups) -> str:
    """One note saying what the pipeline was given (oracle or estimated, with the drawn deviations)."""
    setups = list(setups)
    if not setups or all(s.mode == "oracle" for s in setups):
        return ("Calibration: oracle — the pipeline is given the twin's exact cameras, refractive index and stack "
                "(a best case; --calibration estimated gives a user's chessboard calibration, press-fitted index "
                "and a stack within manufacturing tolerances).")
    parts = []
    for s in setups:
        p = s.provenance
        d = p["drawn"]
        cal = p["calibration"]
        idx = p["index"]
        parts.append(f"{s.design.name}: sources {'+'.join(p['sources'])}; built stack gel "
                     f"{d['gel_thickness_mm']:+.3f} mm, acrylic {d['acrylic_thickness_mm']:+.3f} mm, gel n "
                     f"{d['gel_n']:+.4f} vs the drawing; calibration {cal['route']}"
                     + (f" (RMS {cal['rms_px']:.3f} px, baseline error {cal['baseline_error_mm']:+.3f} mm)"
                        if "rms_px" in cal else "")
                     + f"; index {idx['route']}" + (f" n = {idx['n']:.4f} (true {p['true_stack']['gel_n']:.4f})"
                                                    if "n" in idx else ""))
    return "Calibration: estimated — " + "; ".join(parts) + "."


def reconstruct(design, calib, frames, **kw: Any):
    """Run frames in order through one :class:`pipeline.runner.Reconstructor`; list of FrameResult."""
    from pipeline.runner import Reconstructor

    rec = Reconstructor(design, calib, **kw)
    return [rec.process(f) for f in frames]


def make_indenter(name: str, **params: Any):
    """An indenter from the twin's registry (``twin.indenters``) by name and parameters."""
    from twin import indenters

    return indenters.make_indenter(name, **params)


def surface_grid(surface, truth, radius_mm: float, step_mm: float = 0.5) -> dict[str, np.ndarray]:
    """Reconstructed skin, true skin and indenter heights on one grid inside ``radius_mm``.

    The reconstruction is resampled with the pipeline's own :func:`pipeline.geometry.surface.height_map`
    (what a user gets); truth is interpolated from the twin's skin mesh and indenter height map.
    Returns flat arrays ``x, y, r`` (mm) and ``z_rec, z_skin, z_ind`` (mm, NaN where undefined).
    ``surface`` may be None (the pipeline identified too few markers for a surface): ``z_rec`` is
    then all NaN, so the frame counts as not reconstructed rather than aborting the experiment.
    """
    from pipeline.geometry.surface import height_map

    ax = np.arange(-radius_mm, radius_mm + 1e-9, step_mm)
    gx, gy = np.meshgrid(ax, ax)
    xy = np.column_stack([gx.ravel(), gy.ravel()])
    if surface is None:
        z_rec = np.full(len(xy), np.nan)
    else:
        z_rec = np.asarray(height_map(surface, ax, ax, mask_radius_mm=radius_mm).z_mm).ravel()
    return {"x": xy[:, 0], "y": xy[:, 1], "r": np.hypot(xy[:, 0], xy[:, 1]),
            "z_rec": z_rec, "z_skin": true_skin_height(truth, xy),
            "z_ind": interp_heightmap(truth.indenter, xy)}


def validity_columns(truth) -> dict:
    """The twin frame's own physics verdict (twin.validity, recorded in its truth) as cell columns; a figure the
    verdict could not measure (None: e.g. the penetration of a skin mesh that broke) is NaN, as a missing one."""
    v = truth.validity or {}

    def num(key):
        x = v.get(key)
        return float("nan") if x is None else float(x)
    return {"skin_penetration_mm": num("penetration_max_mm"),
            "skin_penetration_p99_mm": num("penetration_p99_mm"),
            "contact_force_n": num("contact_force_n"),
            "physics_valid": bool(v.get("valid", False)),
            "physics_reasons": list(v.get("reasons", ["no physics validity recorded"]))}


def physically_valid(out, rows: list[dict], label, kept_out_of: str) -> list[dict]:
    """The cells of ``rows`` that passed the twin's physics checks (:func:`validity_columns`); records the
    ``invalid_cells`` and ``valid_cells`` metrics and, when any failed, a note naming each failed cell
    (``label(row)``, with the checks' reasons) and what it is kept out of (every ``kept_out_of``)."""
    valid = [r for r in rows if r["physics_valid"]]
    invalid = [r for r in rows if not r["physics_valid"]]
    out.metric("invalid_cells", len(invalid), "1")
    out.metric("valid_cells", len(valid), "1")
    if invalid:
        out.notes.append(f"{len(invalid)} of {len(rows)} cells failed the twin's physics checks and are kept out of every "
                         f"{kept_out_of}: " + "; ".join(f"{label(r)} ({'; '.join(r['physics_reasons'])})"
                                                       for r in invalid) + ".")
    return valid


def press_setup(design, setup, seed: int, stream: str) -> tuple:
    """What a press cell starts from: (its noise, the stream ``stream`` under ``seed``
    (:func:`benchmarks.registry.stream_rng`); its sensor setup, ``setup`` or, None, the oracle setup of
    ``design`` (the twin's exact sensor); the radius (mm) its surface is scored within, the pattern's less
    half a separation of the design the pipeline is given)."""
    from benchmarks.estimated import sensor_setup
    from benchmarks.registry import stream_rng

    rng = stream_rng(seed, stream)
    setup = setup if setup is not None else sensor_setup(design)
    given = setup.design
    return rng, setup, given.pattern_radius_mm() - given.pattern.separation_mm / 2


def friction_knob(ctx, out, default: float | None = None, why: str = "") -> float | None:
    """The ``friction`` knob of a press grid (``--param friction=MU``): the Coulomb coefficient every press uses;
    unset, ``default`` (None: each design's own ``[twin] friction``, with ``why`` the grid departs from it); the
    report's notes say which."""
    mu = ctx.param("friction", None)
    if mu is None and default is None:
        out.notes.append("Contact friction: each design's [twin] friction (the built-in designs: μ = 1).")
        return None
    if mu is None:
        out.notes.append(f"Contact friction: μ = {default:g} in every press, not the designs' own: {why}")
        return float(default)
    from twin.stick import check_friction

    mu = check_friction(mu)
    out.notes.append(f"Contact friction: μ = {mu:g} in every press (--param friction).")
    return mu


def run_press_cells(ctx, out, fn, jobs: list, *, desc: str, params) -> list:
    """Run a grid experiment's presses through the executor; returns the results of the cells that ran.

    A press that raises is left out: ``failed_cells`` (metric and table) and a note name it, with the job's
    parameters from ``params(job) -> (columns dict, label)``. If every press raised, the experiment fails.
    """
    outcomes = ctx.run_cells(fn, jobs, desc=desc)
    failed = []
    for job, o in zip(jobs, outcomes):
        if not o.ok:
            cols, label = params(job)
            failed.append({**cols, "label": label, "error": o.error.splitlines()[0]})
    out.metric("failed_cells", len(failed), "1")
    if failed:
        out.tables["failed_cells"] = [{k: v for k, v in f.items() if k != "label"} for f in failed]
        out.notes.append(f"{len(failed)} of {len(jobs)} presses raised and are left out of every score and figure: "
                         + "; ".join(f"{f['label']} ({f['error']})" for f in failed) + ".")
    cells = [o.result for o in outcomes if o.ok]
    if not cells:
        raise RuntimeError("every press failed: " + "; ".join(f["error"] for f in failed))
    return cells
