"""contact: the twin's contact validity over the whole range the paper's findings live in, not only its grids.

The Gaussian and sine experiments score one settled frame at the paper's 5 mm for the paper's σ² and ω. The
skin must stay out of the indenter in every frame a user may press, so this sweep presses, with the meshes
those experiments press on and the designs' friction:

* Gaussians h = 5 mm, σ² ∈ {5/3, 2.5, 5, 10, 20, 50} mm², captured settled at 1, 2, 3, 4 and 5 mm, skins 0.5,
  1.0 and 1.5 mm (the Gaussian experiment's designs and its axis contact mesh);
* sines z = 2.5 sin(ωx), ω ∈ {π/15, 2π/15, π/5, 4π/15, π/3, 2π/5} (the paper's five and π/3 between its two
  narrowest), at the paper's 5 mm (the sine experiment's plate and mesh), on hexagon127: the pins are embedded in the
  skin mesh kinematically (:mod:`twin.mesh`), so the marker pattern enters the physics only through the settle's
  stopping test, the markers' drift (:func:`twin.solve.settle`), and the sine experiment's three separations press
  the same skin (measured 2026-11-29: at five of the six ω the three give the same penetration and contact force to
  the last digit; at 2π/15 hexagon61_sep354's differ from the other two by 2e-5 mm and 0.001 N, also in fresh
  processes).

Each frame is judged by its own verdict (:mod:`twin.validity`): the outer skin's vertices, face centroids and
edge midpoints, and the indenter's 0.1 mm samples, at most 0.05 mm inside the indenter's true surface; the
press settled; no MuJoCo warning. The cell counts (``invalid_cells``, ``valid_cells``) count frames. The letters G, e, o and the terrain taps are pressed by their own
experiments (``tracking``, ``terrain``), whose records count their invalid frames. The pipeline is not run:
the calibration mode does not enter, and every press is the design as drawn.
"""

from __future__ import annotations

import math

import numpy as np

from benchmarks.experiments._common import (CELL_COUNT_METRICS, finite_max, friction_knob, make_indenter, run_press_cells,
                                            validity_columns)
from benchmarks.registry import Context, Finding, Result, register
from benchmarks.results import PAGE_IN, paper_style, save_figure

H_MM = 5.0
DEPTH_MM = 5.0
#: Frames of each Gaussian press, settled at DEPTH_MM·k/n: 1, 2, 3, 4 and 5 mm.
GAUSSIAN_FRAMES = 5
SIGMA2_MM2 = (5.0 / 3.0, 2.5, 5.0, 10.0, 20.0, 50.0)
OMEGAS = (math.pi / 15, 2 * math.pi / 15, math.pi / 5, 4 * math.pi / 15, math.pi / 3, 2 * math.pi / 5)
OMEGA_LABELS = ("π/15", "2π/15", "π/5", "4π/15", "π/3", "2π/5")
#: The bound every frame is held to (twin.validity's own): outer skin at most this far inside the indenter.
PENETRATION_BOUND_MM = 0.05


@register("contact", tags=("quick",),
          metrics={**CELL_COUNT_METRICS, "frames": "1", "presses": "1", "penetration_max_mm": "mm",
                   "penetration_p99_max_mm": "mm", "penetration_max_mm_gaussian": "mm", "penetration_max_mm_sine": "mm",
                   "contact_force_max_n": "N"},
          requires=("twin.simulate", "twin.validity", "twin.indenters"))
def run(ctx: Context) -> Result:
    """Twin contact validity: every frame of Gaussians σ² 5/3-50 at 1-5 mm on three skins and sines π/15-2π/5."""
    from benchmarks.experiments.gaussian import SKIN_DESIGNS
    from benchmarks.experiments.sine import SEP_DESIGNS

    sigma2s = [float(s) for s in ctx.param("sigma2", SIGMA2_MM2, quick=(2.5, 20.0))]
    skins = [float(t) for t in ctx.param("skins", tuple(SKIN_DESIGNS), quick=(1.0,))]
    omega_idx = [int(k) for k in ctx.param("omega_index", range(len(OMEGAS)), quick=(4,))]
    seps = [float(s) for s in ctx.param("separations", (2.54,))]
    gauss_designs = ctx.designs([SKIN_DESIGNS[t] for t in skins])
    sine_designs = ctx.designs([SEP_DESIGNS[s] for s in seps])
    out = Result(designs=list({d.name: d for d in [*gauss_designs, *sine_designs]}.values()))
    mu = friction_knob(ctx, out)
    jobs = [(d, "gaussian", s2, mu) for d in gauss_designs for s2 in sigma2s] + \
           [(d, "sine", k, mu) for d in sine_designs for k in omega_idx]
    cells = run_press_cells(ctx, out, press_condition, jobs, desc="contact", params=lambda j: (
        {"design": j[0].name, "family": j[1], "value": j[2]}, f"{j[0].name} {_label(j[1], j[2])}"))
    rows = [r for cell in cells for r in cell]
    out.tables["frames"] = rows
    _summarise(out, rows)
    out.figures.append(_plot(ctx, rows, sigma2s, omega_idx))
    out.notes.append("Each frame's own verdict (twin.validity): the outer skin's vertices, face centroids, edge "
                     f"midpoints and the indenter's 0.1 mm samples at most {PENETRATION_BOUND_MM:g} mm inside the "
                     "indenter's true surface, the press settled, no MuJoCo warning. Gaussians on the Gaussian "
                     "experiment's axis contact mesh (twin.physics.AXIS_CONTACT_MESH), captured settled at 1-5 mm; "
                     "sines on the sine experiment's plate and mesh at 5 mm, yaw 0. The letters and terrain taps are "
                     "counted by the tracking and terrain experiments. The pipeline is not run (no calibration enters).")
    return out


def _label(family: str, value) -> str:
    return f"σ²={value:.3g}" if family == "gaussian" else f"ω={OMEGA_LABELS[int(value)]}"


def press_condition(design, family: str, value, friction: float | None = None) -> list[dict]:
    """Press one condition and return one row per captured frame (its depth and the frame's verdict):
    ``family`` "gaussian" (``value`` σ², mm²; frames at 1-5 mm on the axis contact mesh) or "sine" (``value``
    the index into :data:`OMEGAS`; the sine experiment's plate and mesh, 5 mm)."""
    from twin.simulate import press_truth

    if family == "gaussian":
        from twin.physics import AXIS_CONTACT_MESH

        truths = press_truth(design, make_indenter("gaussian", h_mm=H_MM, sigma2_mm2=float(value)), DEPTH_MM,
                             n_frames=GAUSSIAN_FRAMES, mesh=AXIS_CONTACT_MESH, friction=friction)
    elif family == "sine":
        from benchmarks.experiments.sine import sine_mesh, sine_plate

        truths = press_truth(design, sine_plate(OMEGAS[int(value)]), DEPTH_MM, n_frames=1, mesh=sine_mesh(),
                             friction=friction)
    else:
        raise ValueError(f"unknown contact family {family!r} (gaussian, sine)")
    n = len(truths)
    return [{"design": design.name, "skin_mm": design.skin.thickness_mm, "separation_mm": design.pattern.separation_mm,
             "family": family, "sigma2_mm2": float(value) if family == "gaussian" else None,
             "omega_rad_per_mm": OMEGAS[int(value)] if family == "sine" else None,
             "condition": _label(family, value), "depth_mm": DEPTH_MM * (k + 1) / n, **validity_columns(tr)}
            for k, tr in enumerate(truths)]


def _summarise(out: Result, rows: list[dict]) -> None:
    """Counts, the largest penetration overall and per family, and the verdict against the bound."""
    invalid = [r for r in rows if not r["physics_valid"]]
    out.metric("frames", len(rows), "1")
    out.metric("invalid_cells", len(invalid), "1")       # a cell here is a captured frame
    out.metric("valid_cells", len(rows) - len(invalid), "1")
    out.metric("presses", len({(r["design"], r["condition"]) for r in rows}), "1")
    out.metric("penetration_max_mm", finite_max(r["skin_penetration_mm"] for r in rows), "mm")
    out.metric("penetration_p99_max_mm", finite_max(r["skin_penetration_p99_mm"] for r in rows), "mm")
    for fam in ("gaussian", "sine"):
        out.metric(f"penetration_max_mm_{fam}", finite_max(r["skin_penetration_mm"] for r in rows
                                                           if r["family"] == fam), "mm")
    out.metric("contact_force_max_n", finite_max(r["contact_force_n"] for r in rows), "N")
    if invalid:
        out.notes.append(f"{len(invalid)} of {len(rows)} frames failed the twin's physics checks: " + "; ".join(
            f"{r['design']} {r['condition']} at {r['depth_mm']:g} mm ({'; '.join(r['physics_reasons'])})"
            for r in invalid) + ".")
    worst = out.metrics["penetration_max_mm"][0]
    out.findings.append(Finding(
        f"no frame's outer skin more than {PENETRATION_BOUND_MM:g} mm inside the indenter, every frame valid",
        f"{len(rows) - len(invalid)} of {len(rows)} frames valid; at most {worst:.4f} mm inside",
        None if not rows else bool(not invalid and worst <= PENETRATION_BOUND_MM)))


def _plot(ctx: Context, rows: list[dict], sigma2s: list, omega_idx: list):
    """Largest penetration per frame against the bound: Gaussians by depth (a line per σ² and skin), sines by ω
    (a line per marker separation)."""
    with paper_style() as plt:
        fig, (ga, sa) = plt.subplots(1, 2, figsize=(PAGE_IN, 2.8), sharey=True)
        styles = {}
        for r in rows:
            styles.setdefault(r["skin_mm"], ("-", ":", "--", "-.")[len(styles) % 4])
        for j, s2 in enumerate(sigma2s):
            for skin, ls in styles.items():
                mine = sorted((r["depth_mm"], r["skin_penetration_mm"]) for r in rows
                              if r["family"] == "gaussian" and r["sigma2_mm2"] == s2 and r["skin_mm"] == skin)
                if mine:
                    ga.plot(*zip(*mine), ls, marker="o", ms=2, color=f"C{j}",
                            label=f"σ² = {s2:.3g}" if skin == next(iter(styles)) else None)
        ga.set_xlabel("depth (mm)")
        names = {"-": "solid", ":": "dotted", "--": "dashed", "-.": "dash-dot"}
        ga.set_title("Gaussians (skin " + ", ".join(f"{s:g} mm {names[ls]}" for s, ls in styles.items()) + ")")
        for j, sep in enumerate(sorted({r["separation_mm"] for r in rows if r["family"] == "sine"})):
            mine = sorted((r["omega_rad_per_mm"], r["skin_penetration_mm"]) for r in rows
                          if r["family"] == "sine" and r["separation_mm"] == sep)
            sa.plot(*zip(*mine), "-o", ms=2, color=f"C{j}", label=f"separation {sep:g} mm")
        sa.set_xticks([OMEGAS[k] for k in omega_idx], [OMEGA_LABELS[k] for k in omega_idx])
        sa.set_xlabel("ω (rad/mm)")
        sa.set_title("sines at 5 mm")
        ga.set_ylabel("outer skin inside the indenter, max (mm)")
        for ax in (ga, sa):
            ax.axhline(PENETRATION_BOUND_MM, color="k", lw=0.7, ls="--", label="bound")
            top = finite_max(r["skin_penetration_mm"] for r in rows)
            ax.set_ylim(0.0, max(1.5 * PENETRATION_BOUND_MM, 1.1 * top if np.isfinite(top) else 0.0))
            ax.grid(True)
            ax.legend(loc="upper left", ncols=2)
        return save_figure(fig, ctx.out_dir / "contact.png")
