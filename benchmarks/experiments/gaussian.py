"""gaussian: skin thickness vs object sharpness (paper Sec. V-A, Fig. 10).

z = h·exp(−(x² + y²) / 2σ²), h = 5 mm, σ² ∈ {50, 50/3, 10, 5, 5/3} mm², skins 0.5 / 1.0 / 1.5 mm,
pressed 5 mm at 1 mm/s, 3 repetitions rotated by 120°. Each press's final frame goes through the
unchanged pipeline; the reconstructed skin (``pipeline.geometry.surface.height_map``) is compared with the
indenter CAD over its footprint (where it dips below the rest skin plane) and with the twin's true
skin everywhere, as a function of distance from the Gaussian's tip, with the analytic profile
curvature beside it. The paper's finding — error follows curvature and grows with skin thickness —
is tested, not assumed.
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np

from benchmarks.experiments._common import (CELL_COUNT_METRICS, finite_max, friction_knob, gaussian_curvature_profile,
                                            make_indenter, physically_valid, press_setup, radial_rms, rms,
                                            run_press_cells, surface_grid, calibration_note, reconstruct,
                                            validity_columns)
from benchmarks.registry import Context, Finding, Result, register
from benchmarks.results import PAGE_IN, paper_style, save_figure

H_MM = 5.0
DEPTH_MM = 5.0
SIGMA2_MM2 = (50.0, 50.0 / 3.0, 10.0, 5.0, 5.0 / 3.0)
SKIN_DESIGNS = {0.5: "hexagon127_skin050", 1.0: "hexagon127", 1.5: "hexagon127_skin150"}
YAWS_DEG = (0.0, 120.0, 240.0)
CENTRE_RADIUS_MM = 1.0      # "at the tip": inside one marker half-separation of the peak
RADIAL_EDGES_MM = np.arange(0.0, 14.01, 1.0)
FOOTPRINT_TOL_MM = 0.05     # "below the rest skin plane": 50 um, far above interpolation noise of the truth map
# The presses use the twin's axis contact mesh (twin.physics.AXIS_CONTACT_MESH: 0.5 mm cells about the axis,
# face contact): on the default 1.5 mm vertex-contact mesh no cell of the grid is physically valid.
# Physics validity of a cell is the twin frame's own verdict (twin.validity, recorded in its truth): the
# outer skin - vertices, face centroids, edge midpoints and the indenter's 0.1 mm samples - at most
# 0.05 mm inside the indenter, the press settled, no MuJoCo warning. Invalid cells are kept out of every
# score against CAD and of the findings; the reconstruction vs the twin's own skin (the pipeline's
# accuracy on the frames it was given) is reported over all cells and over the valid ones.


def _s2tag(sigma2_mm2: float) -> str:
    return f"{sigma2_mm2:.3g}".replace(".", "p")      # 10 -> "10", 5/3 -> "1p67"


def _tag(thickness_mm: float) -> str:
    return f"{int(round(thickness_mm * 100)):03d}"


@register(
    "gaussian",
    tags=("quick", "paper"),
    metrics={
        "matched_fraction_min": "1",
        "rms_vs_cad_mm": "mm",
        "rms_vs_true_skin_mm": "mm",
        "centre_error_mm_sharpest": "mm",
        "error_curvature_correlation": "1",
        **{f"rms_vs_cad_mm_skin{_tag(t)}": "mm" for t in SKIN_DESIGNS},
        **{f"centre_error_mm_skin{_tag(t)}": "mm" for t in SKIN_DESIGNS},
        **{f"conformity_gap_centre_mm_skin{_tag(t)}": "mm" for t in SKIN_DESIGNS},
        **CELL_COUNT_METRICS,
        "rms_vs_true_skin_mm_valid": "mm",
        "skin_penetration_max_mm": "mm",
        **{f"skin_penetration_max_mm_s{_s2tag(s)}": "mm" for s in SIGMA2_MM2},
    },
    requires=("pipeline.runner", "pipeline.geometry.surface", "twin.simulate", "twin.render", "twin.indenters"),
)
def run(ctx: Context) -> Result:
    """Gaussian indenters × skin thickness: reconstruction error vs distance from the tip, with curvature."""
    grid = _grid(ctx)
    out = Result(designs=grid.designs, setups=[st.provenance for st in grid.setups.values()])
    cells = _press_grid(ctx, out, grid)
    rows = [c[0] for c in cells]
    _tabulate(out, cells)
    _score_against_cad(out, cells, grid)
    _physics_health(out, rows, grid.sigma2s)
    _findings(out, rows, grid)
    out.notes.append("Error vs CAD over the footprint (indenter below the rest skin plane z = 0); error vs true "
                     "skin over the whole pattern; reconstruction via pipeline.geometry.surface.height_map on a 0.5 mm grid.")
    out.notes.append(calibration_note(grid.setups.values()) + " Refraction: the Reconstructor's default (exact) model.")
    out.figures.append(_plot(ctx, cells, grid))
    return out


class _Grid(NamedTuple):
    """The cells of this run: skins (one design each) × σ² × yaws."""

    sigma2s: list
    yaws: list
    designs: list
    setups: dict      # design name -> its SensorSetup (estimated calibration: once per design)


def _grid(ctx: Context) -> _Grid:
    """The grid of cells from the experiment's knobs (quick: σ² 10 and 5/3, the thinnest and thickest skin, yaw 0)."""
    sigma2s = [float(s) for s in ctx.param("sigma2", SIGMA2_MM2, quick=(10.0, 5.0 / 3.0))]
    skins = [float(t) for t in ctx.param("skins", tuple(SKIN_DESIGNS), quick=(0.5, 1.5))]
    yaws = [float(y) for y in ctx.param("yaws", YAWS_DEG, quick=(0.0,))]
    designs = ctx.designs([SKIN_DESIGNS[t] for t in skins])
    setups = {d.name: ctx.sensor_setup(d) for d in designs}
    return _Grid(sigma2s, yaws, designs, setups)


def _press_grid(ctx: Context, out: Result, grid: _Grid) -> list:
    """Press, reconstruct and score every cell (:func:`press_cell`) through the executor."""
    mu = friction_knob(ctx, out)
    jobs = [(design, s2, yaw, ctx.seed, f"gaussian/{design.name}/{s2:.4f}/{yaw:g}", grid.setups[design.name], mu)
            for design in grid.designs for s2 in grid.sigma2s for yaw in grid.yaws]
    return run_press_cells(ctx, out, press_cell, jobs, desc="gaussian", params=lambda j: (
        {"design": j[0].name, "sigma2_mm2": j[1], "yaw_deg": j[2]}, f"{j[0].name} σ²={j[1]:.3g} yaw {j[2]:g}"))


def _tabulate(out: Result, cells: list) -> None:
    """The cells table, the lowest matched fraction and every cell's radial error profile."""
    rows = [c[0] for c in cells]
    out.tables["cells"] = rows
    out.metric("matched_fraction_min", float(min(r["matched_fraction"] for r in rows)), "1")
    out.tables["radial_profiles"] = [
        {"design": c["design"], "sigma2_mm2": c["sigma2_mm2"], "yaw_deg": c["yaw_deg"], "r_mm": float(rc), "rms_mm": float(p)}
        for c, cs, pr, _, _ in cells for rc, p in zip(cs, pr)]


def _errors(which: str, cells: list) -> np.ndarray:
    """Every grid point's error of the given cells, concatenated (``which``: "cad" or "skin"); [nan] if none."""
    return np.concatenate([_e(g, which) for *_, g, _ in cells]) if cells else np.full(1, float("nan"))


def _score_against_cad(out: Result, cells: list, grid: _Grid) -> None:
    """Errors against CAD on the physically valid cells (overall, per skin, at the sharpest tip); the pipeline
    against the twin's own skin on all cells and on the valid ones."""
    nan = float("nan")
    sharpest = min(grid.sigma2s)
    valid_cells = [c for c in cells if c[0]["physics_valid"]]
    out.metric("rms_vs_cad_mm", rms(_errors("cad", valid_cells)), "mm")
    out.metric("rms_vs_true_skin_mm", rms(_errors("skin", [c for c in cells])), "mm")
    out.metric("rms_vs_true_skin_mm_valid", rms(_errors("skin", valid_cells)), "mm")
    out.metric("error_curvature_correlation", float(np.nanmean([c["error_curvature_correlation"] for c, *_ in valid_cells]))
               if valid_cells else nan, "1")
    centre_by_skin = {}
    for design in grid.designs:
        t = _tag(design.skin.thickness_mm)
        mine = [c for c in valid_cells if c[0]["design"] == design.name]
        out.metric(f"rms_vs_cad_mm_skin{t}", rms(_errors("cad", mine)), "mm")
        sharp = [c[0] for c in mine if c[0]["sigma2_mm2"] == sharpest]
        centre = float(np.nanmean([c["centre_error_mm"] for c in sharp])) if sharp else nan
        centre_by_skin[design.skin.thickness_mm] = centre
        out.metric(f"centre_error_mm_skin{t}", centre, "mm")
        out.metric(f"conformity_gap_centre_mm_skin{t}", float(np.nanmean([c["conformity_gap_centre_mm"] for c in sharp]))
                   if sharp else nan, "mm")
    out.metric("centre_error_mm_sharpest", finite_max(centre_by_skin.values()), "mm")


def _physics_health(out: Result, rows: list[dict], sigma2s: list[float]) -> None:
    """Valid and invalid cells, the skin's deepest penetration of the indenter (overall and per σ²), and a note
    naming the invalid cells."""
    physically_valid(out, rows, lambda c: f"{c['design']} σ²={c['sigma2_mm2']:.3g} yaw {c['yaw_deg']:g}",
                     "score against CAD and of the findings")
    out.metric("skin_penetration_max_mm", finite_max(c["skin_penetration_mm"] for c in rows), "mm")
    for s2 in sigma2s:
        out.metric(f"skin_penetration_max_mm_s{_s2tag(s2)}",
                   finite_max(c["skin_penetration_mm"] for c in rows if c["sigma2_mm2"] == s2), "mm")


def _findings(out: Result, rows: list[dict], grid: _Grid) -> None:
    """The paper's findings, decided by this run: thicker skin errs more at a sharp tip; error follows curvature."""
    sigma2s, designs = grid.sigma2s, grid.designs
    # the finding is decided at the sharpest sigma^2 whose cells are physically valid for every skin
    valid_s2 = [s2 for s2 in sorted(sigma2s) if all(c["physics_valid"] for c in rows if c["sigma2_mm2"] == s2)]
    if len(designs) >= 2 and valid_s2:
        s2f = valid_s2[0]
        by_skin = {d.skin.thickness_mm: float(np.nanmean([c["centre_error_mm"] for c in rows
                                                         if c["design"] == d.name and c["sigma2_mm2"] == s2f]))
                   for d in designs}
        ts = sorted(by_skin)
        vals = [by_skin[t] for t in ts]
        skipped = f" (sharper σ² {', '.join(f'{v:.3g}' for v in sorted(sigma2s) if v < s2f)} excluded: skin penetrates the indenter)" \
            if s2f != min(sigma2s) else ""
        out.findings.append(Finding(
            "thicker skin gives a larger error where the curvature is high (sharpest Gaussian, at its tip)",
            f"σ² = {s2f:.3g} mm²{skipped}, tip error by skin: " + ", ".join(f"{t:g} mm → {v:.3f} mm" for t, v in zip(ts, vals)),
            bool(all(b > a for a, b in zip(vals, vals[1:])))))
    elif len(designs) >= 2:
        out.findings.append(Finding("thicker skin gives a larger error where the curvature is high",
                                    "no σ² with a physically valid twin press for every skin (penetration)", None))
    else:
        out.findings.append(Finding("thicker skin gives a larger error where the curvature is high",
                                    "only one skin thickness in this grid (quick variant)", None))
    corr = out.metrics["error_curvature_correlation"][0]
    out.findings.append(Finding("the radial error profile follows the Gaussian's curvature",
                                f"mean Pearson r between radial RMS error and curvature: {corr:.2f}",
                                None if not np.isfinite(corr) else bool(corr > 0.5)))


def _plot(ctx: Context, cells: list, grid: _Grid):
    """Per σ²: the y = 0 profile (CAD, twin skin, reconstruction) of the first skin; radial RMS error vs CAD
    by skin with the Gaussian's curvature."""
    sigma2s, designs = grid.sigma2s, grid.designs
    with paper_style() as plt:
        fig, axes = plt.subplots(2, len(sigma2s), figsize=(PAGE_IN, 3.6), squeeze=False)
        for j, s2 in enumerate(sigma2s):
            top, bot = axes[0][j], axes[1][j]
            twin_ax = bot.twinx()
            for k, design in enumerate(designs):
                mine = [c for c in cells if c[0]["design"] == design.name and c[0]["sigma2_mm2"] == s2]
                if not mine:
                    continue
                stack = np.vstack([c[2] for c in mine])
                seen = np.isfinite(stack).any(axis=0)      # radial bins outside the footprint stay NaN
                prof = np.full(stack.shape[1], np.nan)
                prof[seen] = np.nanmean(stack[:, seen], axis=0)
                bot.plot(mine[0][1], prof, "-o", ms=2, color=f"C{k + 1}", label=f"skin {design.skin.thickness_mm:g} mm")
                if k == 0:
                    cell, _, _, g, _ = mine[0]
                    line = np.abs(g["y"]) < 0.26
                    order = np.argsort(g["x"][line])
                    for key, style, lab in (("z_ind", "k-", "CAD"), ("z_skin", "C0--", "twin skin"),
                                            ("z_rec", "C3-", "reconstructed")):
                        top.plot(g["x"][line][order], g[key][line][order], style, lw=0.8, label=lab)
            rr = np.linspace(0, RADIAL_EDGES_MM[-1], 200)
            twin_ax.plot(rr, gaussian_curvature_profile(rr, H_MM, s2), "b--", lw=0.7)
            twin_ax.set_ylabel("curvature (1/mm)", color="b") if j == len(sigma2s) - 1 else None
            top.set_title(f"σ² = {s2:.3g} mm²")
            top.set_xlabel("x (mm), y = 0")
            bot.set_xlabel("distance from centre (mm)")
            if j == 0:
                top.set_ylabel("z (mm)")
                bot.set_ylabel("RMS error vs CAD (mm)")
                top.legend(fontsize=5)
                bot.legend(fontsize=5)
        return save_figure(fig, ctx.figure_path("gaussian"))


def _e(g: dict, which: str) -> np.ndarray:
    if which == "cad":
        foot = np.isfinite(g["z_ind"]) & (g["z_ind"] < -FOOTPRINT_TOL_MM)
        return np.where(foot, g["z_rec"] - g["z_ind"], np.nan)
    return g["z_rec"] - g["z_skin"]


def press_cell(design, s2: float, yaw: float, seed: int, stream: str, setup=None,
               friction: float | None = None) -> tuple:
    """One cell of the grid: press the σ² Gaussian rotated by ``yaw`` into ``design``, reconstruct the
    frame with the unchanged pipeline and score it. Returns (cell row, radial bin centres, radial RMS
    profile vs CAD, the surface grid, distance from the tip), everything the summary and figure need.
    The frame's noise comes from the stream ``stream`` under ``seed`` (:func:`benchmarks.registry.stream_rng`).
    ``setup`` (:class:`benchmarks.estimated.SensorSetup`): the twin presses ``setup.twin_design`` and the pipeline is
    given ``setup.design``, ``setup.calib`` and its index; None: the oracle setup of ``design``. ``friction``: the
    Coulomb coefficient of the press, None for the design's own."""
    from twin.physics import AXIS_CONTACT_MESH
    from twin.simulate import press

    rng, setup, radius = press_setup(design, setup, seed, stream)
    built, design, calib = setup.twin_design, setup.design, setup.calib
    ind = make_indenter("gaussian", h_mm=H_MM, sigma2_mm2=s2)
    frame, truth = press(built, ind, DEPTH_MM, n_frames=1, yaw_deg=yaw, rng=rng, mesh=AXIS_CONTACT_MESH,
                         friction=friction)[-1]
    fr = reconstruct(design, calib, [frame], **setup.reconstructor_kw())[0]
    g = surface_grid(fr.skin, truth, radius)
    tip = np.nanargmin(np.where(np.isfinite(g["z_ind"]), g["z_ind"], np.inf))
    r = np.hypot(g["x"] - g["x"][tip], g["y"] - g["y"][tip])
    foot = np.isfinite(g["z_ind"]) & (g["z_ind"] < -FOOTPRINT_TOL_MM) & np.isfinite(g["z_rec"])
    e_cad = np.where(foot, g["z_rec"] - g["z_ind"], np.nan)
    e_skin = g["z_rec"] - g["z_skin"]
    gap = np.where(foot, g["z_ind"] - g["z_skin"], np.nan)
    centres, prof = radial_rms(r, e_cad, RADIAL_EDGES_MM)
    curv = gaussian_curvature_profile(centres, H_MM, s2)
    ok = np.isfinite(prof)
    corr = float(np.corrcoef(prof[ok], curv[ok])[0, 1]) if ok.sum() >= 3 else float("nan")
    near = r < CENTRE_RADIUS_MM
    cell = {"design": design.name, "matched_fraction": fr.n_matched / design.marker_count,
            "skin_mm": design.skin.thickness_mm, "sigma2_mm2": s2, "yaw_deg": yaw,
            "rms_vs_cad_mm": rms(e_cad), "rms_vs_true_skin_mm": rms(e_skin),
            "centre_error_mm": rms(e_cad[near]), "conformity_gap_centre_mm": float(np.nanmean(gap[near]))
            if np.any(np.isfinite(gap[near])) else float("nan"),
            "error_curvature_correlation": corr, "footprint_points": int(foot.sum()),
            **validity_columns(truth)}
    return cell, centres, prof, g, r
