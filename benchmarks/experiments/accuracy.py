"""accuracy: the pipeline's and the renderer's stages against analytic truth (no physics).

Each part measures one stage where the answer is known exactly:

* **sub-pixel centres** — grids of anti-aliased discs at known sub-pixel centres
  (:func:`pipeline.io.synthetic.disc_grid_image`, r = 3 / 5 / 8 px) through the detector;
* **end to end** — analytic stereo frames of three patterns (markers projected through the exact refraction
  stack and drawn as discs, :mod:`pipeline.io.synthetic`) at rest and under a 2.5 mm Gaussian press with
  lateral motion, through the whole :class:`pipeline.runner.Reconstructor`: 3-D error of every matched marker;
* **refraction models** — the paper's linear depth correction against the exact stack on pure depth moves of
  the default design's (or a sweep cell's) rest pattern (1 / 4 / 8 mm): its relative error per ring, and the exact correction's residual;
* **renderer** — on the same design, the twin's rendered marker centroids against the exact projection of the marker centres
  (thin markers, rest and displaced), and per-vertex refraction against a per-pixel ray tracer
  (:mod:`twin.render.reference`);
* **real frames** (only with ``--param real_frames=DIR``) — the monocular dome parameters on real TacTip frames:
  pins found per frame, the closest two centres, detections inside saturated LED glare, and the time detection
  takes a view (one thread, after a warm-up frame: a real frame's crowded and elongated pins reach screens the
  analytic frames of ``bench latency`` do not).

The README's Pipeline and renderer tables are written from this record (``report DIR --block
pipeline-accuracy`` / ``renderer-accuracy``); ``tests/test_detection.py``, ``test_runner.py``,
``test_refraction.py`` and ``test_render.py`` assert the same quantities against derived tolerances.
"""

from __future__ import annotations

import time

from pathlib import Path

import numpy as np

from benchmarks.registry import Context, Result, register
from benchmarks.results import COLUMN_IN, paper_style, save_figure

DISC_RADII_PX = (3.0, 5.0, 8.0)
E2E_DESIGNS = ("hexagon127", "square121", "circular217_dome")
#: The analytic press of the end-to-end frames: depth (mm), Gaussian σ (mm), outward lateral fraction.
E2E_DEPTHS_MM, E2E_SIGMA_MM, E2E_LATERAL = (0.0, 2.5), 4.0, 0.3
REFRACTION_DEPTHS_MM = (1.0, 4.0, 8.0)
#: Markers whose discs lie wholly inside both images (others may legitimately be lost at the image edge).
VISIBLE_MARGIN_PX = 4.0
#: Saturated LED glare on the real frames: connected regions of grey ≥ 250 of at least 20 px, grown by 3 px.
GLARE_GREY, GLARE_MIN_AREA_PX, GLARE_GROW_PX = 250, 20, 3


# ----- tolerances: what each figure must stay within, derived from the stage's own error budget -----
# (``tests/test_detection.py``, ``test_runner.py``, ``test_refraction.py`` and ``test_render.py`` assert them;
# the README's tables read the benchmark's figures against them.)

#: Centre RMS on noise-free anti-aliased discs. cv2.circle(LINE_AA, shift=8) places the centre to
#: 1/256 px and approximates edge coverage to a few % of a pixel; the centroid averages ~2*pi*r edge
#: pixels, leaving ~0.02-0.03 px (measured 0.018 / 0.022 / 0.027 px for r = 3 / 5 / 8).
CENTRE_RMS_TOL_PX = 0.05
#: Worst single centre on the same images (measured <= 0.062 px).
CENTRE_MAX_TOL_PX = 0.1
#: End-to-end 3-D error on analytic frames. Detected centres on the synthetic discs are within ~0.07 px of the
#: projection (measured: median 0.03, p95 0.06 px). Depth sensitivity at the ~25 mm apparent range is
#: z^2 / (b f) ~ 0.11 mm per px of disparity, scaled by ~1.4 through the gel: 0.1 px of disparity error ->
#: ~0.016 mm; 0.05 mm leaves 3x.
E2E_TOL_MM = 0.05
#: The exact refraction model: forward projection (bisection to 2^-64) and back-projection (undistortion to
#: 1e-12) are both at double precision; 1e-6 mm is ~1e-7 of the 30 mm optical path and still catches any
#: geometric slip.
EXACT_TOL_MM = 1e-6
#: Render-versus-math, thin markers (0.02 mm, so only the face is seen). The centroid of the image of a
#: disc differs from the image of its centre by the perspective term f·r²·sinα·cosα/Z² ≤ 442·0.25·0.45/620²
#: px ≈ 0.13 px (r = 0.5 mm, apparent distance Z ≈ 25 mm, face tilted α ≤ 35° to the line of sight), plus
#: the shading gradient across the blob (g·r²/4 ≤ 0.002/px · 81 px² / 4 ≈ 0.04 px) and the 0.02 mm wall
#: (≤ 0.01 mm · 18 px/mm ≈ 0.2 px·tanθ_gel ≈ 0.08 px): ≤ 0.25 px. A half-pixel offset or a flip fails it.
RENDER_CENTROID_TOL_PX = 0.3
#: Ray-traced reference vs per-vertex render: same photometric chain, so the residual is MSAA (4 samples
#: per pixel on ~60 edge pixels: ~0.02 px), the area-matched 16-gon vs circle (area 0, outline +1.3/−0.7 %,
#: centroid 0 by symmetry), the bilinear lens remap with 1/32-px fixed-point maps from a 0.8x pinhole
#: render (~0.03 px) and the per-vertex linear interpolation (second order over 1 mm: < 0.01 px).
#: Measured: typically 0.01-0.06 px, worst 0.08 px (mass ≤ 1.2 %); bound 0.15 px.
TRACE_CENTROID_TOL_PX = 0.15
#: Relative "bright mass" difference of the same windows (0.64 % polygon + remap smoothing).
TRACE_AREA_TOL = 0.03


def glare_mask(grey: np.ndarray) -> np.ndarray:
    """Saturated connected regions (LED glare, a bright rim) of a grey frame, grown by :data:`GLARE_GROW_PX`."""
    import cv2

    n, lab, st, _ = cv2.connectedComponentsWithStats((grey >= GLARE_GREY).astype(np.uint8))
    big = np.isin(lab, np.nonzero(st[:, cv2.CC_STAT_AREA] >= GLARE_MIN_AREA_PX)[0][1:])
    k = 2 * GLARE_GROW_PX + 1
    return cv2.dilate(big.astype(np.uint8), np.ones((k, k), np.uint8)).astype(bool)


def subpixel_rows(ctx: Context) -> list[dict]:
    from scipy.spatial import cKDTree

    from pipeline.io.synthetic import disc_grid_image
    from pipeline.vision.detection import detect_markers

    rows = []
    for r in DISC_RADII_PX:
        img, truth = disc_grid_image(r, ctx.rng(f"discs-{r:g}"))
        blobs = detect_markers(img)
        d, _ = cKDTree(blobs.xy_px).query(truth)
        rows.append({"radius_px": r, "discs": len(truth), "found": len(blobs),
                     "rms_px": float(np.sqrt(np.mean(d ** 2))), "max_px": float(d.max())})
    return rows


def visible_markers(design, calib, xyz: np.ndarray, margin_px: float = VISIBLE_MARGIN_PX) -> np.ndarray:
    """Markers whose projected centres lie at least ``margin_px`` inside both images."""
    from pipeline.geometry.refraction import project_through_stack

    w, h = calib.image_size
    ok = np.ones(len(xyz), bool)
    for px in project_through_stack(xyz, calib, design):
        ok &= (px[:, 0] > margin_px) & (px[:, 0] < w - 1 - margin_px) & (px[:, 1] > margin_px) & (px[:, 1] < h - 1 - margin_px)
    return ok


def end_to_end_rows(ctx: Context) -> list[dict]:
    from pipeline.design import load_design
    from pipeline.io.synthetic import gaussian_press_markers, nominal_calibration, synth_stereo_frame
    from pipeline.runner import Reconstructor

    rows = []
    for name in E2E_DESIGNS:
        design = load_design(name)
        calib = nominal_calibration(design)
        rec = Reconstructor(design, calib)
        rng = ctx.rng(f"e2e-{name}")
        for depth in E2E_DEPTHS_MM:
            truth = gaussian_press_markers(design, depth, sigma_mm=E2E_SIGMA_MM, lateral=E2E_LATERAL)
            res = rec.process(synth_stereo_frame(design, calib, truth, rng=rng))
            ids = res.corrected.ids
            err = np.linalg.norm(res.corrected.xyz_mm - truth[ids], axis=1)
            visible = visible_markers(design, calib, truth)
            rows.append({"design": name, "depth_mm": depth, "markers": len(truth), "visible": int(visible.sum()),
                         "matched": len(ids), "visible_unmatched": int(len(np.setdiff1d(np.flatnonzero(visible), ids))),
                         "median_mm": float(np.median(err)), "max_mm": float(err.max())})
    return rows


def refraction_rows(design) -> list[dict]:
    from pipeline.geometry.refraction import correct_exact, correct_linear, project_through_stack
    from pipeline.geometry.triangulation import triangulate
    from pipeline.io.synthetic import nominal_calibration
    from pipeline.types import MarkerMatches

    calib = nominal_calibration(design)
    rest = design.rest_markers_mm()
    layers = design.marker_layers()
    ids = np.arange(len(rest))

    def apparent(points):
        return triangulate(MarkerMatches(ids, *project_through_stack(points, calib, design)), calib)

    reference = apparent(rest)
    rows = []
    for dz in REFRACTION_DEPTHS_MM:
        moved = rest - [0.0, 0.0, dz]
        lin = correct_linear(apparent(moved), reference, design.optics.gel_n, design)
        ex = correct_exact(MarkerMatches(ids, *project_through_stack(moved, calib, design)), calib, design)
        rel = np.abs(lin.xyz_mm[:, 2] - moved[:, 2]) / dz
        per_ring = [float(rel[layers == k].max()) for k in range(design.pattern.layers)]
        rows.append({"depth_mm": dz, "linear_rel_error_per_ring": per_ring, "linear_rel_error_centre": per_ring[0],
                     "linear_rel_error_outer": per_ring[-1], "exact_error_max_mm": float(np.max(np.abs(ex.xyz_mm - moved)))})
    return rows


def renderer_rows(ctx: Context, design) -> tuple[list[dict], list[dict]]:
    from twin import render as R
    from twin.render.reference import displaced_markers, rendered_centre_errors, trace_comparison, trace_picks

    thin = design.with_overrides({"markers.thickness_mm": 0.02})
    renderer = R.StereoRenderer(thin, rng=ctx.rng("render"), noise=False)
    rest = thin.rest_markers_mm()
    sets = {"rest": (rest, np.tile([0.0, 0.0, -1.0], (len(rest), 1))),
            "displaced": displaced_markers(thin, ctx.rng("render-displaced"))}
    centres = []
    for name, (P, A) in sets.items():
        for side, r in rendered_centre_errors(renderer.render_markers(P, A), thin, P).items():
            e = r["errors_px"]
            centres.append({"markers": name, "side": side, "found": r["found"], "expected": r["expected"],
                            "rms_px": float(np.sqrt(np.mean(e ** 2))), "max_px": float(e.max())})
    full = R.StereoRenderer(design, rng=ctx.rng("render"), noise=False)
    P, A = displaced_markers(design, ctx.rng("render-traced"))
    return centres, trace_comparison(full, design, P, A, trace_picks(design))


def real_frame_rows(folder: Path) -> list[dict]:
    import cv2
    from scipy.spatial import cKDTree

    from pipeline.errors import UserError
    from pipeline.threads import one_thread
    from pipeline.vision.detection import MONOCULAR_DOME, detect_markers

    paths = sorted(Path(folder).glob("*.png"))
    if not paths:
        raise UserError(f"--param real_frames={folder}: no PNG frames there")
    rows = []
    for k, path in enumerate(paths):
        img = cv2.imread(str(path))
        if img is None:
            raise UserError(f"{path}: not a readable image")
        with one_thread():           # as the runner detects: one thread for OpenCV and BLAS
            if k == 0:
                detect_markers(img, params=MONOCULAR_DOME)      # warm-up: buffers, first calls
            t0 = time.perf_counter()
            blobs = detect_markers(img, params=MONOCULAR_DOME)
            ms = (time.perf_counter() - t0) * 1e3
        d = cKDTree(blobs.xy_px).query(blobs.xy_px, k=2)[0][:, 1]
        ij = np.rint(blobs.xy_px).astype(int)
        glare = glare_mask(cv2.cvtColor(img, cv2.COLOR_BGR2GRAY))
        rows.append({"frame": path.name, "found": len(blobs), "closest_over_median": float(d.min() / np.median(d)),
                     "in_glare": int(glare[ij[:, 1], ij[:, 0]].sum()), "detect_ms": ms})
    return rows


@register(
    "accuracy",
    tags=("quick", "cheap"),
    metrics={
        "centre_rms_px_max": "px",
        "centre_max_px": "px",
        "e2e_median_mm": "mm",
        "e2e_max_mm": "mm",
        "e2e_visible_unmatched": "1",
        "linear_rel_error_centre_max": "1",
        "linear_rel_error_outer_max": "1",
        "exact_refraction_error_max_mm": "mm",
        "render_centre_max_px": "px",
        "render_trace_offset_max_px": "px",
        "render_trace_mass_error_max": "1",
        "real_frames": "1",
        "real_found_min": "1",
        "real_found_max": "1",
        "real_in_glare": "1",
        "real_detect_ms_median": "ms",
        "real_detect_ms_p95": "ms",
    },
    requires=("pipeline.runner", "pipeline.vision.detection", "pipeline.geometry.refraction", "twin.render"),
)
def run(ctx: Context) -> Result:
    """Pipeline and renderer stages against analytic truth: sub-pixel centres, end to end, refraction, renderer."""
    from pipeline.design import load_design

    design = ctx.design()
    out = Result(designs=[design] + [load_design(n) for n in E2E_DESIGNS if n != design.name])
    steps = ["sub-pixel centres", "end to end", "refraction models", "renderer"]
    folder = ctx.param("real_frames", None)
    if folder is not None:
        steps.append("real frames")
    bar = ctx.bar(total=len(steps), desc="accuracy")
    tables = {}
    tables["subpixel"] = subpixel_rows(ctx)
    bar.update()
    tables["end_to_end"] = end_to_end_rows(ctx)
    bar.update()
    tables["refraction"] = refraction_rows(design)
    bar.update()
    tables["render_centres"], tables["render_trace"] = renderer_rows(ctx, design)
    bar.update()
    if folder is not None:
        tables["real_frames"] = real_frame_rows(Path(folder))
        bar.update()
    bar.close()
    out.tables.update(tables)

    sub, e2e, ref = tables["subpixel"], tables["end_to_end"], tables["refraction"]
    out.metric("centre_rms_px_max", max(r["rms_px"] for r in sub), "px")
    out.metric("centre_max_px", max(r["max_px"] for r in sub), "px")
    out.metric("e2e_median_mm", float(np.median([r["median_mm"] for r in e2e])), "mm")
    out.metric("e2e_max_mm", max(r["max_mm"] for r in e2e), "mm")
    out.metric("e2e_visible_unmatched", sum(r["visible_unmatched"] for r in e2e), "1")
    out.metric("linear_rel_error_centre_max", max(r["linear_rel_error_centre"] for r in ref), "1")
    out.metric("linear_rel_error_outer_max", max(r["linear_rel_error_outer"] for r in ref), "1")
    out.metric("exact_refraction_error_max_mm", max(r["exact_error_max_mm"] for r in ref), "mm")
    out.metric("render_centre_max_px", max(r["max_px"] for r in tables["render_centres"]), "px")
    out.metric("render_trace_offset_max_px", max(r["centroid_offset_px"] for r in tables["render_trace"]), "px")
    out.metric("render_trace_mass_error_max", max(abs(r["mass_ratio"] - 1) for r in tables["render_trace"]), "1")
    if folder is not None:
        real = tables["real_frames"]
        out.metric("real_frames", len(real), "1")
        out.metric("real_found_min", min(r["found"] for r in real), "1")
        out.metric("real_found_max", max(r["found"] for r in real), "1")
        out.metric("real_in_glare", sum(r["in_glare"] for r in real), "1")
        out.metric("real_detect_ms_median", float(np.median([r["detect_ms"] for r in real])), "ms")
        out.metric("real_detect_ms_p95", float(np.percentile([r["detect_ms"] for r in real], 95)), "ms")
        out.notes.append(f"Real frames: {len(real)} PNG frames of {folder} with the monocular dome parameters "
                         "(pipeline.vision.detection.MONOCULAR_DOME).")
    else:
        out.notes.append("Real frames: not measured (give a folder of real TacTip frames with "
                         "--param real_frames=DIR).")
    out.notes.append(f"End to end: analytic frames (pipeline.io.synthetic, 2 grey levels of noise) at "
                     f"{' and '.join(f'{d:g}' for d in E2E_DEPTHS_MM)} mm, Gaussian σ = {E2E_SIGMA_MM:g} mm with "
                     f"lateral fraction {E2E_LATERAL:g}, the nominal calibration and the exact refraction stack.")

    with paper_style() as plt:
        fig, ax = plt.subplots(figsize=(COLUMN_IN, 2.2))
        for k, row in enumerate(ref):
            ax.plot(range(len(row["linear_rel_error_per_ring"])), 100 * np.asarray(row["linear_rel_error_per_ring"]),
                    "o-", ms=3, color=f"C{k}", label=f"{row['depth_mm']:g} mm deeper")
        ax.set_xlabel("marker ring (0 = on the axis)")
        ax.set_ylabel("linear model depth error (% of the move)")
        ax.legend(fontsize=6)
        out.figures.append(save_figure(fig, ctx.figure_path("refraction_linear_error")))
    return out
