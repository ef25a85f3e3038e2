"""patterns: rest frames of the domed circular 217, flat hexagon 127 and flat square 121 modules.

Paper (Sec. IV-A, Fig. 8): DTRC meshes and matches every marker of each pattern and all 3-D marker
positions are obtained. Here each module's rest frame is rendered by the twin's renderer (markers at
the design's rest positions: truth by construction, no physics needed at rest), run through the
unchanged :class:`pipeline.runner.Reconstructor`, and scored: matched fraction, correct-identity
fraction and 3-D localisation error of the refraction-corrected marker cloud.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from benchmarks.experiments._common import calibration_note, finite_max, identity_correct, reconstruct
from benchmarks.registry import Context, Finding, PaperValue, Result, register
from benchmarks.results import PAGE_IN, paper_style, save_figure

DESIGNS = ("circular217_dome", "hexagon127", "square121")
KINDS = ("circular", "hexagon", "square")


@dataclass(frozen=True)
class RestTruth:
    """Truth of an undeformed module, by construction: markers at the design's rest positions on
    pins along −z, and the (flat or domed) outer skin as a triangulated height field."""

    marker_ids: np.ndarray
    marker_xyz_mm: np.ndarray
    marker_axis: np.ndarray
    skin_vertices_mm: np.ndarray
    skin_faces: np.ndarray

    @classmethod
    def of(cls, design) -> "RestTruth":
        from scipy.spatial import Delaunay

        P = design.rest_markers_mm()
        r = np.linspace(0, design.gel.radius_mm, 16)
        pts = [np.zeros((1, 2))] + [np.column_stack([rr * np.cos(t), rr * np.sin(t)])
                                    for rr in r[1:] for t in [np.linspace(0, 2 * np.pi, 48, endpoint=False)]]
        xy = np.concatenate(pts)
        v = np.column_stack([xy, design.dome_z_mm(xy)])
        return cls(np.arange(len(P)), P, np.tile([0.0, 0.0, -1.0], (len(P), 1)), v, Delaunay(xy).simplices)


@register(
    "patterns",
    tags=("quick", "paper", "cheap"),
    metrics={
        "matched_fraction_min": "1",
        "identity_correct_fraction_min": "1",
        "localisation_rms_mm_max": "mm",
        "localisation_max_mm": "mm",
        **{f"matched_fraction_{k}": "1" for k in KINDS},
        **{f"localisation_rms_mm_{k}": "mm" for k in KINDS},
    },
    requires=("pipeline.runner", "pipeline.vision.dtrc", "twin.render"),
    paper={"matched_fraction_min": PaperValue(1.0, "1", "Sec. IV-A: the 3-D positions of all markers are obtained")},
)
def run(ctx: Context) -> Result:
    """Rest frames of circular / hexagon / square modules: matched fraction and 3-D localisation error."""
    import gc

    from twin.render import StereoRenderer

    out = Result()
    rows, panels = [], []
    setups = []
    for design in ctx.bar(ctx.designs(DESIGNS), desc="patterns"):
        setup = ctx.sensor_setup(design)   # the twin renders setup.twin_design; the pipeline gets setup.design
        setups.append(setup)
        out.setups.append(setup.provenance)
        truth = RestTruth.of(setup.twin_design)
        renderer = StereoRenderer(setup.twin_design, rng=ctx.rng(f"patterns/{design.name}"))
        frame = renderer.render_markers(truth.marker_xyz_mm, truth.marker_axis)
        del renderer
        gc.collect()  # one headless GL context at a time
        # truth is not passed: the pipeline sees pixels only
        fr = reconstruct(setup.design, setup.calib, [frame], **setup.reconstructor_kw())[0]
        ids = np.asarray(fr.corrected.ids)
        n = design.marker_count
        tmap = {int(i): k for k, i in enumerate(np.asarray(truth.marker_ids))}
        true_xyz = np.asarray(truth.marker_xyz_mm)[[tmap[int(i)] for i in ids]] if len(ids) else np.empty((0, 3))
        err = np.linalg.norm(np.asarray(fr.corrected.xyz_mm) - true_xyz, axis=1)
        ok = identity_correct(ids, fr.corrected.xyz_mm, truth, design.pattern.separation_mm / 2)
        row = {"design": design.name, "kind": design.pattern.kind, "markers": n,
               "matched": int(len(fr.matches.ids)), "matched_fraction": len(fr.matches.ids) / n,
               "identity_correct_fraction": float(ok.sum()) / n,
               "localisation_rms_mm": float(np.sqrt(np.mean(err**2))) if len(err) else float("nan"),
               "localisation_max_mm": float(err.max()) if len(err) else float("nan"),
               "localisation_rms_z_mm": float(np.sqrt(np.mean((fr.corrected.xyz_mm[:, 2] - true_xyz[:, 2]) ** 2)))
               if len(err) else float("nan")}
        rows.append(row)
        panels.append((design, truth, fr, err))
        out.designs.append(design)
        out.metric(f"matched_fraction_{design.pattern.kind}", row["matched_fraction"], "1")
        out.metric(f"localisation_rms_mm_{design.pattern.kind}", row["localisation_rms_mm"], "mm")

    out.tables["per_pattern"] = rows
    out.metric("matched_fraction_min", min(r["matched_fraction"] for r in rows), "1")
    out.metric("identity_correct_fraction_min", min(r["identity_correct_fraction"] for r in rows), "1")
    out.metric("localisation_rms_mm_max", finite_max(r["localisation_rms_mm"] for r in rows), "mm")
    out.metric("localisation_max_mm", finite_max(r["localisation_max_mm"] for r in rows), "mm")
    out.notes.append(calibration_note(setups))
    out.findings.append(Finding(
        "every marker of every pattern is matched and localised",
        "; ".join(f"{r['design']}: {r['matched']}/{r['markers']} matched, "
                  f"{r['identity_correct_fraction']:.3f} correct ids, RMS {r['localisation_rms_mm']:.3f} mm" for r in rows),
        all(r["matched_fraction"] == 1.0 and r["identity_correct_fraction"] == 1.0 for r in rows)))

    with paper_style() as plt:
        fig = plt.figure(figsize=(PAGE_IN, 3.0))
        for k, (design, truth, fr, err) in enumerate(panels):
            ax = fig.add_subplot(1, len(panels), k + 1, projection="3d")
            v, f = np.asarray(truth.skin_vertices_mm), np.asarray(truth.skin_faces)
            ax.plot_trisurf(v[:, 0], v[:, 1], f, v[:, 2], color="0.85", alpha=0.3, linewidth=0)
            tx = np.asarray(truth.marker_xyz_mm)
            ax.scatter(tx[:, 0], tx[:, 1], tx[:, 2], c="0.6", s=1, depthshade=False)
            xyz = np.asarray(fr.corrected.xyz_mm)
            sc = ax.scatter(xyz[:, 0], xyz[:, 1], xyz[:, 2], c=err, cmap="viridis", s=4, depthshade=False)
            ax.set_title(f"{design.name}: {len(fr.matches.ids)}/{design.marker_count} matched")
            ax.set_xlabel("x (mm)", labelpad=-8)
            ax.set_ylabel("y (mm)", labelpad=-8)
            ax.set_zlabel("z (mm)", labelpad=-6)
            ax.tick_params(pad=-3)
            ax.set_box_aspect((1, 1, 0.4))
            ax.view_init(elev=30, azim=-60)
            if len(err):
                fig.colorbar(sc, ax=ax, orientation="horizontal", shrink=0.6, pad=0.02, label="3-D error (mm)")
        out.figures.append(save_figure(fig, ctx.figure_path("patterns")))
    return out
