"""``stereotactip validate``: the twin against labelled real frames of a monocular TacTip.

For each real frame the twin taps the labelled pose and renders it; the real and the twin frame go
through the same detector (:func:`pipeline.vision.detection.detect_markers`) and the same identification
(:func:`pipeline.vision.tactip_id.identify_sequence`, each from its own reference: the shallowest training
tap, real or twin; the real reference takes its ids from the twin's projected pin tips, the twin's from its
truth). Per frame: marker count, apparent radius, contrast, background, spacing and noise of both; per
marker the position error twin − real (px) and the displacement error (twin − twin reference) − (real −
real reference). Baselines on the same held-out frames: (a) static — each marker where the training frames
put it on average; (b) ridge regression from the pose to every marker position, on [1, d, tx, ty, d·tx,
d·ty, tx·ty, d², tx², ty²] (features standardised, intercept free, λ = 1e-3 × the number of training frames), fitted per marker on the training frames.
Writes an overlay PNG per frame, ``summary.json``, ``report.md``, ``report.html`` and ``errors.png``.
"""

from __future__ import annotations

import html
import time
from pathlib import Path
from typing import NamedTuple

import cv2
import numpy as np

from pipeline.io.atomic import atomic_write_json, atomic_write_text, imwrite_atomic, savefig_atomic
from pipeline.design import load_design
from pipeline.vision.detection import detect_markers
from pipeline.vision.tactip_id import frame_stats, identify_by_reference
from benchmarks.executor import make_engine, run_cells
from benchmarks.results import git_commit
from benchmarks.tactip_fit import FITTED_POSITION_GROUPS, FITTED_POSITION_PARAMETERS, FitContext, identify_chain
from twin.tactip import project_markers, render_frame
from benchmarks.tapdata import TapDataError

__all__ = ["validate", "register", "cmd_validate", "ridge_features", "GOAL_STATIC", "GOAL_RIDGE", "GOAL_IMAGE",
           "GOAL_IMAGE_KEYS", "STAT_KEYS"]

RIDGE_LAMBDA = 1e-3
STAT_KEYS = ("count", "radius_px", "contrast", "spacing_px", "background", "noise")
#: the goals: the twin's held-out marker RMS at most GOAL_STATIC × the static baseline's and GOAL_RIDGE × the
#: ridge's; the image statistics GOAL_IMAGE_KEYS within GOAL_IMAGE (relative) of the real frames'
GOAL_STATIC, GOAL_RIDGE, GOAL_IMAGE = 0.5, 1.5, 0.10
GOAL_IMAGE_KEYS = ("count", "radius_px", "contrast", "spacing_px")


def ridge_features(poses) -> np.ndarray:
    P = np.array([[p.depth_mm, p.tilt_x_deg / 10.0, p.tilt_y_deg / 10.0] for p in poses])
    d, tx, ty = P.T
    return np.column_stack([np.ones(len(P)), d, tx, ty, d * tx, d * ty, tx * ty, d * d, tx * tx, ty * ty])


def baselines(real_xy: list[np.ndarray], poses, train, held) -> dict[str, list[np.ndarray]]:
    """Held-out predictions (M, 2) per held-out frame of the static and ridge baselines."""
    Y = np.stack([real_xy[i] for i in train])            # (T, M, 2)
    with np.errstate(all="ignore"):
        import warnings

        with warnings.catch_warnings():
            warnings.simplefilter("ignore", RuntimeWarning)   # markers never identified stay NaN
            static = np.nanmean(Y, axis=0)
    F = ridge_features([poses[i] for i in train])[:, 1:]
    Fh = ridge_features([poses[i] for i in held])[:, 1:]
    mu, sd = F.mean(axis=0), F.std(axis=0) + 1e-12
    F, Fh = (F - mu) / sd, (Fh - mu) / sd          # standardised; the intercept is not penalised
    M = Y.shape[1]
    ridge = np.full((len(held), M, 2), np.nan)
    for m in range(M):
        ok = np.all(np.isfinite(Y[:, m]), axis=1)
        if ok.sum() < F.shape[1] + 2:
            continue
        A, y = F[ok], Y[ok, m]
        am, ym = A.mean(axis=0), y.mean(axis=0)
        coef = np.linalg.solve((A - am).T @ (A - am) + RIDGE_LAMBDA * ok.sum() * np.eye(A.shape[1]), (A - am).T @ (y - ym))
        ridge[:, m] = ym + (Fh - am) @ coef
    return {"static": [static] * len(held), "ridge": list(ridge)}


def _rms(err: np.ndarray) -> float | None:
    e = err[np.all(np.isfinite(err), axis=1)]
    return float(np.sqrt(np.mean(np.sum(e * e, axis=1)))) if len(e) else None


def _overlay(real: np.ndarray, twin: np.ndarray, rxy: np.ndarray, txy: np.ndarray, title: str) -> np.ndarray:
    a = cv2.cvtColor(real, cv2.COLOR_GRAY2BGR)
    b = cv2.cvtColor(twin, cv2.COLOR_GRAY2BGR)
    for img in (a, b):
        for (u, v), (p, q) in zip(rxy, txy):
            if np.isfinite(u) and np.isfinite(p):
                cv2.line(img, (int(round(u)), int(round(v))), (int(round(p)), int(round(q))), (0, 255, 255), 1)
            if np.isfinite(u):
                cv2.circle(img, (int(round(u)), int(round(v))), 3, (0, 200, 0), 1)
            if np.isfinite(p):
                cv2.drawMarker(img, (int(round(p)), int(round(q))), (0, 0, 255), cv2.MARKER_CROSS, 6, 1)
    out = np.hstack([a, b])
    cv2.putText(out, title, (8, 22), cv2.FONT_HERSHEY_SIMPLEX, 0.55, (255, 255, 255), 2)
    cv2.putText(out, title, (8, 22), cv2.FONT_HERSHEY_SIMPLEX, 0.55, (0, 0, 0), 1)
    cv2.putText(out, "real (green o) | twin (red +), yellow: twin - real", (8, 470), cv2.FONT_HERSHEY_SIMPLEX,
                0.45, (255, 255, 255), 1)
    return out


_SKINS: dict = {}


def twin_frame_cell(design, pose, params: dict, seed: int) -> tuple:
    """One frame of the twin (a cell): tap ``pose``, render, detect. Returns pin tips, pin axes, image,
    detected blobs and the pin tips' exact projections."""
    from twin.tactip import DomeSkin

    skin = _SKINS.get(design.name)
    if skin is None or skin.design != design:
        skin = _SKINS[design.name] = DomeSkin(design)
    X, info = skin.tap(pose, params)
    if not info["converged"]:
        raise TapDataError(f"the tap did not converge (iterations {info['iterations']}, "
                           f"penetration {info['penetration_max_mm']:.3f} mm)")
    p, ax = skin.markers(X)
    img = render_frame(design, p, ax, seed=seed)
    return p, ax, img, detect_markers(img), project_markers(design, p)


def validate(frames, targets, design_name, out: Path, *, progress: bool = True, log=print,
             skip_unlabelled: bool = False, engine=None) -> dict:
    """Tap and render the twin at every labelled pose, compare it marker by marker and image by image with
    the real frames and with the static and ridge baselines; write the overlays, ``summary.json``, the
    reports and ``errors.png``. Returns the summary."""
    t0 = time.time()
    design = load_design(design_name)
    ctx = FitContext(frames, targets, design, progress=progress, skip_unlabelled=skip_unlabelled, log=log)
    tw = design.twin_params()
    out.mkdir(parents=True, exist_ok=True)
    uv_ref, ref_real = _real_reference(ctx, design, tw)
    twin = _twin_frames(ctx, design, tw, engine, progress)
    ref_twin, twin_xy = _twin_identification(ctx, twin, uv_ref)
    poses = [f.pose for f in ctx.frames]
    base = baselines(ctx.real_xy, poses, ctx.train, ctx.held)
    cmp = _compare_frames(ctx, twin, twin_xy, ref_twin, ref_real, base, out)
    held, held_common = _held_out_rms(cmp)
    stats = _image_stats(cmp.per_frame)
    n_params = {"twin": FITTED_POSITION_PARAMETERS, "static": 2 * design.marker_count,
                "ridge": 2 * design.marker_count * ridge_features(poses[:1]).shape[1]}
    summary = {"design": design.name, "commit": git_commit(), "frames": len(ctx.frames), "train": len(ctx.train), "held_out": len(ctx.held),
               "held_out_frames": [ctx.frames[i].path.name for i in ctx.held],
               "reference": ctx.frames[ctx.ref].path.name,
               "held_out_rms_px": held, "held_out_rms_px_common_markers": held_common,
               "fitted_position_parameters": n_params, "fitted_position_parameter_groups": FITTED_POSITION_GROUPS,
               "image_stats_median": stats,
               "goals": _goals(held_common, stats),
               "per_frame": cmp.per_frame, "seconds": time.time() - t0}
    atomic_write_json(out / "summary.json", summary, indent=1)
    _plot(out, cmp.held_err, cmp.per_frame)
    _report(out, summary)
    _log_summary(log, summary, out)
    return summary


def _real_reference(ctx: FitContext, design, tw: dict) -> tuple[np.ndarray, np.ndarray]:
    """Ids of the real reference frame: its markers nearest the twin's projected pin tips. Sets them as the
    context's reference (which identifies every real frame) and returns (projected tips, real reference)."""
    ref_real = ctx.reference_from_twin(design, tw)
    ctx.set_reference(ref_real)
    return project_markers(design, ctx.tap(ctx.ref, tw)[0]), ref_real


class _TwinFrames(NamedTuple):
    """The twin's frame at every labelled pose (frame order)."""

    images: list
    blobs: list
    truth_uv: list      # the pin tips' exact projections (px)


def _twin_frames(ctx: FitContext, design, tw: dict, engine, progress: bool) -> _TwinFrames:
    """Tap, render and detect the twin at every pose; each frame is an independent cell of the project's one
    executor (local processes by default, a Dask cluster with --cluster). A tap that fails stops the run."""
    n = len(ctx.frames)
    params = {**design.twin_params(), **tw}
    jobs = [(design, ctx.frames[i].pose, params, 1000 + i) for i in range(n)]
    outcomes = run_cells(twin_frame_cell, jobs, engine=engine, desc="validate", progress=progress)
    failed = [(ctx.frames[o.index].path.name, o.error.strip().splitlines()[-1]) for o in outcomes if not o.ok]
    if failed:
        raise TapDataError("the twin could not tap " + "; ".join(f"{name} ({err})" for name, err in failed))
    twin_imgs, twin_blobs, truth_uv = [None] * n, [None] * n, [None] * n
    for o in outcomes:
        p, ax, twin_imgs[o.index], twin_blobs[o.index], truth_uv[o.index] = o.result
        ctx.remember_tap(o.index, tw, (p, ax))
    return _TwinFrames(twin_imgs, twin_blobs, truth_uv)


def _twin_identification(ctx: FitContext, twin: _TwinFrames, uv_ref: np.ndarray) -> tuple[np.ndarray, list]:
    """The twin's reference ids from its truth, then the same chained identification as the real frames (pose
    order, nearest identified pose). Returns (twin reference positions, positions per frame)."""
    idx = identify_by_reference(twin.blobs[ctx.ref].xy_px, twin.truth_uv[ctx.ref])
    ref_twin = np.full_like(uv_ref, np.nan)
    ref_twin[idx >= 0] = twin.blobs[ctx.ref].xy_px[idx[idx >= 0]]
    return ref_twin, identify_chain(twin.blobs, [f.pose for f in ctx.frames], ctx.ref, ref_twin)


class _Comparison(NamedTuple):
    per_frame: list         # one row per frame (the summary's per_frame)
    held_err: dict          # method -> per held-out frame (M, 2) position errors (px)
    disp_err_held: list     # per held-out frame, the twin's displacement error (M, 2) (px)


def _compare_frames(ctx: FitContext, twin: _TwinFrames, twin_xy: list, ref_twin, ref_real, base: dict,
                    out: Path) -> _Comparison:
    """Per frame: image statistics, position and displacement errors of the twin (and on held-out frames of the
    baselines and the projected truth); write its overlay."""
    real_xy = ctx.real_xy
    held_set = set(int(i) for i in ctx.held)
    per_frame = []
    held_err = {"twin": [], "twin_truth": [], "static": [], "ridge": []}
    disp_err_held = []
    for i, f in enumerate(ctx.frames):
        err = twin_xy[i] - real_xy[i]
        derr = (twin_xy[i] - ref_twin) - (real_xy[i] - ref_real)
        row = _frame_row(ctx, twin, i, twin_xy[i], err, derr, real_xy[i] - ref_real, i in held_set)
        if i in held_set:
            k = list(ctx.held).index(i)
            row["static_rms_px"] = _rms(base["static"][k] - real_xy[i])
            row["ridge_rms_px"] = _rms(base["ridge"][k] - real_xy[i])
            row["twin_truth_rms_px"] = _rms(twin.truth_uv[i] - real_xy[i])
            held_err["twin"].append(err)
            held_err["twin_truth"].append(twin.truth_uv[i] - real_xy[i])
            held_err["static"].append(base["static"][k] - real_xy[i])
            held_err["ridge"].append(base["ridge"][k] - real_xy[i])
            disp_err_held.append(derr)
        per_frame.append(row)
        ov = _overlay(ctx.greys[i], twin.images[i], real_xy[i], twin_xy[i],
                      f"{f.path.name} [{row['split']}] d={f.pose.depth_mm:.2f} mm tilt=({f.pose.tilt_x_deg:.1f}, "
                      f"{f.pose.tilt_y_deg:.1f}) deg  RMS {row['position_rms_px'] or float('nan'):.2f} px")
        imwrite_atomic(out / f"overlay_{f.path.stem}.png", ov)
    return _Comparison(per_frame, held_err, disp_err_held)


def _frame_row(ctx: FitContext, twin: _TwinFrames, i: int, twin_xy: np.ndarray, err: np.ndarray, derr: np.ndarray,
               real_disp: np.ndarray, held: bool) -> dict:
    """One frame's pose, image statistics (real and twin), identified markers and errors. Arrays (M, 2), px:
    ``twin_xy`` the twin's identified markers, ``err`` twin − real, ``derr`` the displacement error (each from its
    reference), ``real_disp`` the real markers' displacement from the real reference."""
    f, real_xy = ctx.frames[i], ctx.real_xy[i]
    ok = np.all(np.isfinite(err), axis=1)
    e = np.linalg.norm(err[ok], axis=1)
    return {"frame": f.path.name, "split": "held_out" if held else "train",
            "depth_mm": f.pose.depth_mm, "tilt_x_deg": f.pose.tilt_x_deg, "tilt_y_deg": f.pose.tilt_y_deg,
            "real": frame_stats(ctx.greys[i], ctx.blobs[i]), "twin": frame_stats(twin.images[i], twin.blobs[i]),
            "identified_real": int(np.isfinite(real_xy[:, 0]).sum()),
            "identified_twin": int(np.isfinite(twin_xy[:, 0]).sum()), "compared": int(ok.sum()),
            "position_rms_px": _rms(err), "position_median_px": float(np.median(e)) if len(e) else None,
            "position_p95_px": float(np.percentile(e, 95)) if len(e) else None,
            "displacement_rms_px": _rms(derr),
            "real_displacement_rms_px": _rms(real_disp)}


def _held_out_rms(cmp: _Comparison) -> tuple[dict, dict]:
    """RMS over all held-out marker observations per method, and over the markers every method identified."""
    held_err = cmp.held_err
    held = {k: _rms(np.concatenate(v)) for k, v in held_err.items()}
    common = [np.all(np.isfinite(a), axis=1) & np.all(np.isfinite(b), axis=1) & np.all(np.isfinite(c), axis=1)
              for a, b, c in zip(held_err["twin"], held_err["static"], held_err["ridge"])]
    held_common = {k: _rms(np.concatenate([e[m] for e, m in zip(v, common)])) for k, v in held_err.items()}
    held["displacement_twin"] = _rms(np.concatenate(cmp.disp_err_held))
    return held, held_common


def _image_stats(per_frame: list[dict]) -> dict:
    """Median over frames of each image statistic, real and twin, and their relative difference."""
    def med(who, key):
        vals = [r[who][key] for r in per_frame if r[who][key] is not None]
        return float(np.median(vals)) if vals else None

    stats = {k: {"real": med("real", k), "twin": med("twin", k)} for k in STAT_KEYS}
    for k, v in stats.items():
        v["relative_difference"] = (abs(v["twin"] - v["real"]) / abs(v["real"])
                                    if v["real"] not in (None, 0) and v["twin"] is not None else None)
    return stats


def _goals(held_common: dict, stats: dict) -> dict:
    """The twin within half the static baseline and 1.5× the ridge; image statistics within 10 % (a statistic
    the twin and the real frames agree on exactly is met; one without a value is not)."""
    twin = held_common["twin"]
    return {
        "twin_le_half_static": twin is not None and twin <= GOAL_STATIC * held_common["static"],
        "twin_within_1p5_ridge": twin is not None and twin <= GOAL_RIDGE * held_common["ridge"],
        "image_stats_within_10pct": all(stats[k]["relative_difference"] is not None
                                        and stats[k]["relative_difference"] <= GOAL_IMAGE for k in GOAL_IMAGE_KEYS),
    }


def _log_summary(log, summary: dict, out: Path) -> None:
    """The held-out errors, image statistics and goals on the console."""
    held, held_common, stats = summary["held_out_rms_px"], summary["held_out_rms_px_common_markers"], \
        summary["image_stats_median"]
    log(f"validate: {summary['frames']} frames ({summary['held_out']} held out), reference {summary['reference']}")
    log("held-out marker RMS (px, markers identified by all methods): " + ", ".join(
        f"{k} {v:.2f}" for k, v in held_common.items() if v is not None))
    log(f"held-out displacement RMS error of the twin: {held['displacement_twin']:.2f} px")
    for k in STAT_KEYS:
        s = stats[k]
        log(f"  {k:11s} real {s['real']:.3g}  twin {s['twin']:.3g}  ({100 * (s['relative_difference'] or 0):.1f} %)")
    log("goals: " + ", ".join(f"{k} {'MET' if v else 'not met'}" for k, v in summary["goals"].items()))
    log(f"wrote {out / 'report.md'}, {out / 'report.html'}, {out / 'summary.json'} and {summary['frames']} overlays")


def _plot(out: Path, held_err, per_frame) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(1, 2, figsize=(11, 4))
    for k, c in (("twin", "C3"), ("static", "C0"), ("ridge", "C2")):
        e = np.concatenate(held_err[k])
        e = np.linalg.norm(e[np.all(np.isfinite(e), axis=1)], axis=1)
        ax[0].hist(e, bins=np.linspace(0, 20, 41), histtype="step", color=c, label=f"{k} (median {np.median(e):.2f})")
    ax[0].set_xlabel("held-out marker position error (px)")
    ax[0].set_ylabel("markers")
    ax[0].legend()
    for k, c in (("radius_px", "C0"), ("contrast", "C1"), ("spacing_px", "C2")):
        r = [p["real"][k] for p in per_frame]
        t = [p["twin"][k] for p in per_frame]
        ax[1].scatter(r, t, s=10, color=c, label=k)
    lim = ax[1].get_xlim()
    ax[1].set_xscale("log")
    ax[1].set_yscale("log")
    ax[1].plot([1, 300], [1, 300], "k:", lw=0.8)
    ax[1].set_xlabel("real frame (median over markers)")
    ax[1].set_ylabel("twin frame")
    ax[1].legend()
    del lim
    fig.tight_layout()
    savefig_atomic(fig, out / "errors.png", dpi=110)
    plt.close(fig)


def _report(out: Path, s: dict) -> None:
    h, hc = s["held_out_rms_px"], s["held_out_rms_px_common_markers"]
    lines = [f"# Twin vs real frames: {s['design']}", "",
             f"{s['frames']} frames, {s['train']} train / {s['held_out']} held out "
             f"({', '.join(s['held_out_frames'])}); reference {s['reference']}.", "",
             "## Held-out marker position RMS (px)", "",
             "| method | fitted position parameters | RMS, markers all methods identify | RMS, all its markers |",
             "| --- | --- | --- | --- |"]
    for k in ("twin", "static", "ridge"):
        lines.append(f"| {k} | {s['fitted_position_parameters'][k]} | {hc[k]:.2f} | {h[k]:.2f} |")
    lines += ["", f"Twin pin tips projected directly (no render/detect): {h['twin_truth']:.2f} px. "
              f"Twin displacement error (vs each reference): {h['displacement_twin']:.2f} px.", "",
              "Goals: " + ", ".join(f"{k}: **{'met' if v else 'not met'}**" for k, v in s["goals"].items()), "",
              "## Image statistics (median over frames)", "", "| statistic | real | twin | difference |",
              "| --- | --- | --- | --- |"]
    for k, v in s["image_stats_median"].items():
        rd = v["relative_difference"]
        lines.append(f"| {k} | {v['real']:.3g} | {v['twin']:.3g} | {'' if rd is None else f'{100 * rd:.1f} %'} |")
    lines += ["", "![errors](errors.png)", "", "## Per frame", "",
              "| frame | split | depth mm | tilt deg | markers real/twin | RMS px | disp. RMS px | real disp. px |",
              "| --- | --- | --- | --- | --- | --- | --- | --- |"]
    f2 = lambda v: "" if v is None else f"{v:.2f}"  # noqa: E731
    for r in s["per_frame"]:
        lines.append(f"| {r['frame']} | {r['split']} | {r['depth_mm']:.2f} | ({r['tilt_x_deg']:.1f}, {r['tilt_y_deg']:.1f}) | "
                     f"{r['real']['count']}/{r['twin']['count']} | {f2(r['position_rms_px'])} | "
                     f"{f2(r['displacement_rms_px'])} | {f2(r['real_displacement_rms_px'])} |")
    lines += ["", "Overlays: `overlay_<frame>.png` (real | twin; green o real markers, red + twin markers, yellow "
              "line twin − real)."]
    atomic_write_text(out / "report.md", "\n".join(lines) + "\n")
    body = "\n".join(f"<pre>{html.escape(line)}</pre>" if line.startswith("|") else
                     f"<p>{html.escape(line)}</p>" for line in lines if line and not line.startswith("!["))
    imgs = "\n".join(f'<figure><img src="overlay_{Path(r["frame"]).stem}.png" width="960"><figcaption>'
                     f'{html.escape(r["frame"])} ({r["split"]})</figcaption></figure>' for r in s["per_frame"])
    atomic_write_text(out / "report.html", f"<!doctype html><html><head><meta charset='utf-8'><title>validate "
                                     f"{html.escape(s['design'])}</title></head><body>{body}<img src='errors.png'>"
                                     f"{imgs}</body></html>\n")


def register(sub) -> None:
    p = sub.add_parser("validate", help="compare the twin of a monocular TacTip with labelled real frames")
    p.add_argument("frames", help="folder (or image) of real frames")
    p.add_argument("--targets", required=True, help="targets CSV (pose_3 depth mm, pose_4/pose_5 tilt deg)")
    p.add_argument("--design", required=True, help="design (a fitted TOML from fit-twin, or a built-in name)")
    p.add_argument("--out", required=True, help="output folder")
    p.add_argument("--skip-unlabelled", action="store_true")
    p.add_argument("--no-progress", action="store_true")
    p.add_argument("--workers", type=int, default=None, help="local worker processes (default: all cores)")
    p.add_argument("--cluster", default=None, metavar="ADDRESS",
                   help="run the twin's frames on an existing Dask cluster (the 'cluster' extra)")
    p.set_defaults(func=cmd_validate)


def cmd_validate(args) -> int:
    engine = make_engine(args.cluster, args.workers)
    try:
        validate(args.frames, args.targets, args.design, Path(args.out), progress=not args.no_progress,
                 skip_unlabelled=args.skip_unlabelled, engine=engine)
    finally:
        engine.close()
    return 0
