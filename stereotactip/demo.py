"""``stereotactip demo``: the whole loop on the built-in sensor design, scored against truth.

1. The twin presses a Gaussian indenter (h = 5 mm, σ² = 10 mm²) into the default skin module
   (hexagon127) at the paper's 1 mm/s, capturing one stereo frame per millimetre, and writes frames
   (PNG), truth (NPZ) and its true calibration (OpenCV YAML). With ``--calibration estimated`` the
   twin's stack deviates from the drawing within manufacturing tolerances and the pipeline is given
   what a user's calibration session would hand over instead (:mod:`benchmarks.estimated`): a chessboard
   stereo calibration and a press-fitted gel index, written beside the twin's files.
2. The pipeline reads those files back (it never sees the truth), detects, matches (DTRC),
   triangulates, corrects refraction and reconstructs the skin surface of every frame.
3. The reconstruction is scored against the twin's truth (marker centres and deformed outer skin) and
   a figure is written.
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import numpy as np
from pipeline.design import DEFAULT_DESIGN

__all__ = ["run_demo", "register"]


def _truth_skin_z(truth, xy_mm: np.ndarray) -> np.ndarray:
    """Height of the twin's deformed outer skin at sensor x-y (linear interpolation on its mesh)."""
    from scipy.interpolate import LinearNDInterpolator

    v = truth.skin_vertices_mm
    return LinearNDInterpolator(v[:, :2], v[:, 2])(xy_mm)


def _score(design, res, truth) -> dict:
    """Marker and skin errors of one reconstructed frame against the twin's truth (mm)."""
    out = {"markers_matched": int(res.n_matched), "markers_expected": int(res.n_expected)}
    if res.n_matched:
        idx = np.searchsorted(truth.marker_ids, res.corrected.ids)
        err = np.linalg.norm(res.corrected.xyz_mm - truth.marker_xyz_mm[idx], axis=1)
        out.update(marker_rms_mm=float(np.sqrt(np.mean(err**2))), marker_max_mm=float(err.max()))
    if res.skin is not None:
        zt = _truth_skin_z(truth, res.skin.xyz_mm[:, :2])
        ok = np.isfinite(zt)
        dz = res.skin.xyz_mm[ok, 2] - zt[ok]
        out.update(skin_rms_mm=float(np.sqrt(np.mean(dz**2))), skin_max_mm=float(np.max(np.abs(dz))),
                   skin_points=int(ok.sum()))
    return out


def _figure(path: Path, design, frame, res, truth) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig = plt.figure(figsize=(13, 7.5), constrained_layout=True)
    gs = fig.add_gridspec(2, 3)
    ax = fig.add_subplot(gs[0, :])
    ax.imshow(frame.image[:, :, ::-1] if frame.image.ndim == 3 else frame.image, cmap="gray")
    if len(res.matches):
        ax.plot(res.matches.left_px[:, 0], res.matches.left_px[:, 1], "r+", ms=5, lw=0.8)
        ax.plot(res.matches.right_px[:, 0] + 640, res.matches.right_px[:, 1], "r+", ms=5, lw=0.8)
    ax.set_title(f"twin stereo frame (1280×480) — {res.n_matched}/{res.n_expected} markers matched (red +)")
    ax.axis("off")

    v = truth.skin_vertices_mm
    r = design.pattern_radius_mm()
    lim = (-r - 1, r + 1)
    sk = res.skin.xyz_mm if res.skin is not None else np.empty((0, 3))
    zt = _truth_skin_z(truth, sk[:, :2]) if len(sk) else np.empty(0)
    vmin, vmax = float(np.nanmin(v[:, 2])), max(float(np.nanmax(v[:, 2])), 0.1)
    for k, (title, xyz, c) in enumerate([
            ("twin truth: outer skin z (mm)", v, v[:, 2]),
            ("pipeline: reconstructed skin z (mm)", sk, sk[:, 2] if len(sk) else np.empty(0))]):
        a = fig.add_subplot(gs[1, k])
        sc = a.scatter(xyz[:, 0], xyz[:, 1], c=c, s=6 if k == 0 else 28, cmap="viridis", vmin=vmin, vmax=vmax)
        a.set_xlim(*lim), a.set_ylim(*lim), a.set_aspect("equal"), a.set_title(title)
        a.set_xlabel("x (mm)"), a.set_ylabel("y (mm)")
        fig.colorbar(sc, ax=a, shrink=0.8)
    a = fig.add_subplot(gs[1, 2])
    if len(sk):
        rad = np.hypot(sk[:, 0], sk[:, 1])
        a.plot(rad, sk[:, 2] - zt, ".", ms=4)
    a.axhline(0, color="k", lw=0.5)
    a.set_xlabel("distance from centre (mm)"), a.set_ylabel("reconstructed − true skin z (mm)")
    a.set_title("skin error versus radius")
    fig.suptitle(f"StereoTacTip demo: {design.name}, Gaussian σ²=10 mm² pressed "
                 f"{-truth.robot_pose[2]:.1f} mm")
    from pipeline.io.atomic import savefig_atomic

    try:
        savefig_atomic(fig, path, dpi=110)
    finally:
        plt.close(fig)


def run_demo(out_dir: str | Path, *, design_name: str = DEFAULT_DESIGN, sigma2_mm2: float = 10.0,
             depth_mm: float = 5.0, n_frames: int = 5, seed: int = 0, progress: bool = True,
             calibration: str = "oracle") -> dict:
    """Simulate a press, reconstruct it with the pipeline from the files alone, score it; returns the summary."""
    import cv2

    from pipeline.design import load_design
    from pipeline.batch import reconstruct
    from pipeline.runner import Reconstructor
    from pipeline.types import StereoCalibration, StereoFrame
    from twin.indenters import make_indenter
    from twin.physics import AXIS_CONTACT_MESH
    from twin.simulate import press, write_run
    from benchmarks.estimated import sensor_setup
    from twin.truth import Truth

    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    design = load_design(design_name)
    if calibration != "oracle":
        print(f"[0/3] {calibration} calibration: chessboard pairs and a skin-less press of a sensor built within "
              f"tolerances (cached in {out / 'calibration_cache'}) ...", flush=True)
    setup = sensor_setup(design, mode=calibration, seed=seed, cache_dir=out / "calibration_cache", progress=progress)
    indenter = make_indenter("gaussian", sigma2=sigma2_mm2)
    t0 = time.perf_counter()
    print(f"[1/3] twin: pressing a Gaussian (σ²={sigma2_mm2:g} mm²) {depth_mm:g} mm into {design.name} "
          f"({design.marker_count} markers), {n_frames} frames ...", flush=True)
    # the Gaussian sits on the sensor axis: the axis contact mesh keeps the skin's faces out of its cap
    run = press(setup.twin_design, indenter, depth_mm, n_frames=n_frames, rng=np.random.default_rng(seed), progress=progress,
                mesh=AXIS_CONTACT_MESH)
    twin_dir = write_run(out / "twin", setup.twin_design, indenter, run, extra_meta={"seed": seed, "depth_mm": depth_mm})
    t_twin = time.perf_counter() - t0

    calib_path = twin_dir / "calib.yaml"
    if setup.mode != "oracle":
        calib_path = out / "calib_estimated.yaml"
        setup.calib.save_yaml(calib_path)
    print(f"[2/3] pipeline: reconstructing the frames in {twin_dir} with {calib_path}"
          + (f" and n_gel = {setup.n_gel:.4f}" if setup.n_gel is not None else "") + " ...", flush=True)
    calib = StereoCalibration.load_yaml(calib_path)
    files = sorted(twin_dir.glob("frame_*.png"))
    frames = [StereoFrame(cv2.imread(str(p)), index=i, timestamp_s=float(i), source=str(p)) for i, p in enumerate(files)]
    rec = Reconstructor(design, calib, refraction="exact", with_height_map=True, **setup.reconstructor_kw())
    results = []
    t1 = time.perf_counter()
    reconstruct(frames, rec, out / "pipeline", progress=progress, echo=lambda s: None,
                on_result=lambda frame, res: results.append(res))
    t_pipe = time.perf_counter() - t1

    print("[3/3] scoring against the twin's truth ...", flush=True)
    truths = [Truth.load_npz(p) for p in sorted(twin_dir.glob("truth_*.npz"))]
    scores = []
    for frame, res, truth in zip(frames, results, truths):
        s = _score(design, res, truth)
        s["depth_mm"] = float(-truth.robot_pose[2])
        s["pipeline_ms"] = float(res.timings_ms["total"])
        s["twin_physics_valid"] = truth.physics_valid
        s["twin_validity"] = truth.validity
        scores.append(s)
        v = truth.validity or {}
        phys = "not checked" if not v else ("ok" if v["valid"] else "INVALID: " + "; ".join(v["reasons"]))
        print(f"  depth {s['depth_mm']:.1f} mm: {s['markers_matched']}/{s['markers_expected']} markers, "
              f"marker RMS {s.get('marker_rms_mm', float('nan')):.3f} mm, skin RMS "
              f"{s.get('skin_rms_mm', float('nan')):.3f} mm (max {s.get('skin_max_mm', float('nan')):.3f}), "
              f"{s['pipeline_ms']:.1f} ms; twin physics {phys}")
    n_bad = sum(1 for s in scores if s["twin_physics_valid"] is False)
    if n_bad:
        print(f"  {n_bad} of {len(scores)} twin frames failed the twin's physics checks: their scores measure the "
              "pipeline against the twin's own markers and skin, not the twin against the indenter")
    _figure(out / "demo.png", design, frames[-1], results[-1], truths[-1])
    doc = {"design": design.name, "indenter": {"name": "gaussian", "sigma2_mm2": sigma2_mm2, "h_mm": 5.0},
           "depth_mm": depth_mm, "seed": seed, "calibration": setup.provenance, "frames": scores, "twin_invalid_frames": n_bad, "twin_s": t_twin, "pipeline_s": t_pipe,
           "units": {"*_mm": "mm", "*_ms": "ms", "*_s": "s"}, "pipeline_summary": str(out / "pipeline" / "summary.json")}
    from pipeline.io.atomic import atomic_write_json

    atomic_write_json(out / "demo.json", doc)
    print(f"done in {time.perf_counter() - t0:.1f} s: figure {out / 'demo.png'}, scores {out / 'demo.json'}, "
          f"twin files in {twin_dir}, pipeline outputs in {out / 'pipeline'}")
    return doc


def _cmd(args: argparse.Namespace) -> int:
    run_demo(args.out, design_name=args.design, sigma2_mm2=args.sigma2, depth_mm=args.depth,
             n_frames=args.frames, seed=args.seed, progress=not args.quiet, calibration=args.calibration)
    return 0


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("demo", help="twin press → pipeline reconstruction → score against truth (default design)")
    p.add_argument("--out", default="demo_out", help="output folder (default: demo_out)")
    p.add_argument("--design", default=DEFAULT_DESIGN, help="built-in design name or TOML path")
    p.add_argument("--sigma2", type=float, default=10.0, help="Gaussian width σ² in mm² (default 10)")
    p.add_argument("--depth", type=float, default=5.0, help="press depth in mm (default 5)")
    p.add_argument("--frames", type=int, default=5, help="frames captured during the press (default 5)")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--calibration", choices=("oracle", "estimated"), default="oracle",
                   help="what the pipeline is given: the twin's exact calibration, index and stack (oracle, default) "
                        "or a chessboard calibration and press-fitted index of a stack built within tolerances")
    p.add_argument("--quiet", action="store_true", help="no progress bars")
    p.set_defaults(func=_cmd)
