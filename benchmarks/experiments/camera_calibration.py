"""camera-calibration: chessboard stereo calibration on the twin's cameras vs their true parameters.

Paper (Sec. III-B-1): 20 pairs of a 9×7 board of 4 mm squares, skin removed, reprojection error
0.12 px. Here the twin renders skin-less chessboard pairs, :func:`pipeline.geometry.calibration.calibrate_stereo`
calibrates them unchanged, and the result is scored against ``twin.render.true_calibration``.
"""

from __future__ import annotations

import numpy as np

from benchmarks.registry import Context, Finding, PaperValue, Result, register
from benchmarks.results import PAGE_IN, paper_style, save_figure

PAPER_RMS_PX = 0.12


@register(
    "camera-calibration",
    tags=("quick", "paper"),
    metrics={
        "rms_px": "px",
        "rms_left_px": "px",
        "rms_right_px": "px",
        "pairs_used": "1",
        "baseline_error_mm": "mm",
        "focal_error_max_px": "px",
        "principal_point_error_max_px": "px",
        "rotation_error_deg": "deg",
        "reprojection_vs_truth_rms_px": "px",
    },
    requires=("pipeline.geometry.calibration", "twin.render"),
    paper={"rms_px": PaperValue(PAPER_RMS_PX, "px", "Sec. III-B-1: 20 chessboard pairs, MATLAB calibrator")},
)
def run(ctx: Context) -> Result:
    """Chessboard stereo calibration of the twin's cameras: RMS, baseline and focal errors vs truth."""
    import cv2

    from pipeline.geometry.calibration import calibrate_stereo
    from twin.render import render_chessboard_pairs, true_calibration

    design = ctx.design()
    n_pairs = int(ctx.param("n_pairs", 20, quick=12))
    rng = ctx.rng("camera-calibration/boards")
    pairs = render_chessboard_pairs(design, n_pairs, rng, progress=ctx.progress)
    calib, report = calibrate_stereo(pairs, board_squares=(9, 7), square_mm=4.0)
    truth = true_calibration(design)

    out = Result(designs=[design])
    out.metric("rms_px", report.rms_px, "px")
    out.metric("rms_left_px", report.rms_left_px, "px")
    out.metric("rms_right_px", report.rms_right_px, "px")
    out.metric("pairs_used", len(report.used), "1")
    out.metric("baseline_error_mm", calib.baseline_mm - truth.baseline_mm, "mm")
    focal = {f"{side}_{ax}": float(est[i, i] - tru[i, i])
             for side, est, tru in (("left", calib.K1, truth.K1), ("right", calib.K2, truth.K2))
             for i, ax in ((0, "fx"), (1, "fy"))}
    pp = {f"{side}_{ax}": float(est[i, 2] - tru[i, 2])
          for side, est, tru in (("left", calib.K1, truth.K1), ("right", calib.K2, truth.K2))
          for i, ax in ((0, "cx"), (1, "cy"))}
    out.metric("focal_error_max_px", max(abs(v) for v in focal.values()), "px")
    out.metric("principal_point_error_max_px", max(abs(v) for v in pp.values()), "px")
    dR = calib.R @ truth.R.T
    angle = np.degrees(np.arccos(np.clip((np.trace(dR) - 1) / 2, -1, 1)))
    out.metric("rotation_error_deg", angle, "deg")

    # Pixel error of the estimated model on points it never saw: project a grid of 3-D points in front
    # of the left camera (camera frame, 60-200 mm range is irrelevant here; use the working depth of the
    # stack: the markers sit ~|camera_z| mm away) with both models and compare.
    depth = abs(design.camera_z_mm) - design.marker_depth_mm
    g = np.linspace(-0.5, 0.5, 9) * depth
    X, Y = np.meshgrid(g, g)
    pts = np.column_stack([X.ravel(), Y.ravel(), np.full(X.size, depth)])
    zero = np.zeros(3)
    est_px, _ = cv2.projectPoints(pts.reshape(-1, 1, 3), zero, zero, calib.K1, calib.D1)
    tru_px, _ = cv2.projectPoints(pts.reshape(-1, 1, 3), zero, zero, truth.K1, truth.D1)
    diff = (est_px - tru_px).reshape(-1, 2)
    inside = np.all((tru_px.reshape(-1, 2) >= 0) & (tru_px.reshape(-1, 2) < np.array(truth.image_size)), axis=1)
    out.metric("reprojection_vs_truth_rms_px", float(np.sqrt(np.mean(np.sum(diff[inside] ** 2, axis=1)))), "px")

    out.tables["per_pair_rms_px"] = [{"pair": k, "rms_px": v} for k, v in report.per_pair_rms_px.items()]
    out.tables["intrinsics"] = [{"parameter": k, "error_px": v} for k, v in {**focal, **pp}.items()]
    out.tables["skipped"] = [{"pair": k, "reason": v} for k, v in report.skipped.items()]
    out.notes.append(f"{len(report.used)} of {n_pairs} rendered pairs showed the whole board in both views; "
                     f"calibration by cv2.calibrateCamera per camera then cv2.stereoCalibrate (fixed intrinsics).")
    out.notes.append("Truth: twin.render.true_calibration(design) — the cameras the twin actually rendered with.")
    out.findings.append(Finding(
        f"chessboard calibration reaches a reprojection RMS of about {PAPER_RMS_PX} px",
        f"twin: stereo {report.rms_px:.3f} px over {len(report.used)} pairs; per camera "
        f"{report.rms_left_px:.3f} / {report.rms_right_px:.3f} px; baseline error "
        f"{calib.baseline_mm - truth.baseline_mm:+.3f} mm",
        bool(report.rms_px <= 2 * PAPER_RMS_PX)))

    with paper_style() as plt:
        fig, axes = plt.subplots(1, 2, figsize=(PAGE_IN * 0.7, 2.2))
        names = list(report.per_pair_rms_px)
        axes[0].bar(range(len(names)), [report.per_pair_rms_px[n] for n in names], color="0.4")
        axes[0].axhline(report.rms_px, color="C3", lw=0.8, label=f"stereo RMS {report.rms_px:.3f} px")
        axes[0].axhline(PAPER_RMS_PX, color="C0", lw=0.8, ls="--", label=f"paper {PAPER_RMS_PX} px")
        axes[0].set_xlabel("pair")
        axes[0].set_ylabel("reprojection RMS (px)")
        axes[0].legend()
        keys = list(focal) + list(pp)
        axes[1].barh(range(len(keys)), [({**focal, **pp})[k] for k in keys], color="0.4")
        axes[1].set_yticks(range(len(keys)), keys)
        axes[1].axvline(0, color="k", lw=0.5)
        axes[1].set_xlabel("estimate − truth (px)")
        axes[1].set_title(f"baseline error {calib.baseline_mm - truth.baseline_mm:+.3f} mm")
        out.figures.append(save_figure(fig, ctx.figure_path("camera_calibration")))
    return out
