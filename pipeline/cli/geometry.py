"""Geometry subcommands of the ``stereotactip`` CLI: ``calibrate``, ``calibrate-refraction``, ``reconstruct``.

``register(sub)`` adds them to the pipeline's subparsers (wired in :mod:`pipeline.cli`).
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import cv2
import numpy as np

from pipeline.errors import UserError
from pipeline.design import DEFAULT_DESIGN

__all__ = ["register", "read_image", "frames_from_paths"]

IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg", ".bmp", ".tif", ".tiff")


class CliInputError(UserError, ValueError):
    """A command-line input (file, folder, option) is unusable."""


def read_image(path: Path) -> np.ndarray:
    """An 8-bit grey or BGR image of any size (a BGRA image loses its alpha, as frames do)."""
    from pipeline.io.sources import drop_alpha

    img = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    if img is None:
        raise CliInputError(f"{path}: not a readable image")
    if img.dtype != np.uint8:
        raise CliInputError(f"{path}: expected 8-bit pixels, got {img.dtype}")
    return drop_alpha(img)


def read_frame(path: Path) -> np.ndarray:
    """A stereo frame by :func:`pipeline.io.sources.check_frame`'s rule."""
    from pipeline.io.sources import check_frame

    return check_frame(cv2.imread(str(path), cv2.IMREAD_UNCHANGED), str(path))


def _expand(paths: list[str]) -> list[Path]:
    out: list[Path] = []
    for p in map(Path, paths):
        if p.is_dir():
            files = sorted(f for f in p.iterdir() if f.suffix.lower() in IMAGE_SUFFIXES)
            if not files:
                raise CliInputError(f"{p}: folder holds no images ({', '.join(IMAGE_SUFFIXES)})")
            out.extend(files)
        elif p.is_file():
            out.append(p)
        else:
            raise CliInputError(f"{p}: no such file or folder")
    return out


def frames_from_paths(paths: list[str]):
    """StereoFrames from concatenated 1280x480 images (files or folders, sorted by name)."""
    from pipeline.types import StereoFrame

    for k, p in enumerate(_expand(paths)):
        yield StereoFrame(read_frame(p), index=k, source=str(p))


def _open_source(spec: str):
    from pipeline.io.sources import open_source

    # an unreadable frame in a recording (cut off mid-write, say) is skipped and named, not fatal
    return open_source(spec, skip_unreadable=True)


def _load_calib(path: str):
    from pipeline.types import StereoCalibration

    calib = StereoCalibration.load_yaml(path)
    calib.check_fits_frame(f"calibration file {path}")
    return calib


def _board(text: str) -> tuple[int, int]:
    try:
        a, b = (int(v) for v in text.lower().split("x"))
    except ValueError:
        raise argparse.ArgumentTypeError(f"--board {text!r}: expected COLSxROWS squares, e.g. 9x7") from None
    if a < 3 or b < 3:
        raise argparse.ArgumentTypeError(f"--board {text!r}: need at least 3x3 squares")
    return a, b


def _steps(text: str) -> np.ndarray:
    try:
        vals = np.array([float(v) for v in text.split(",") if v.strip()])
    except ValueError:
        raise argparse.ArgumentTypeError(f"--steps-mm {text!r}: expected comma-separated numbers") from None
    if len(vals) < 2:
        raise argparse.ArgumentTypeError("--steps-mm: need at least two steps")
    if not np.all(np.isfinite(vals)) or np.any(np.abs(vals) > 100.0):
        raise argparse.ArgumentTypeError(f"--steps-mm {text!r}: steps must be finite and within ±100 mm")
    return vals


def _square_mm(text: str) -> float:
    try:
        v = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"--square-mm {text!r}: expected a number") from None
    if not (np.isfinite(v) and 0.0 < v <= 1000.0):
        raise argparse.ArgumentTypeError(f"--square-mm {text!r}: must be in (0, 1000] mm")
    return v


def _calibrate(args: argparse.Namespace) -> int:
    from pipeline.geometry.calibration import calibrate_stereo
    from pipeline.design import load_design

    design = load_design(args.design)
    if args.left or args.right:
        if args.pairs:
            raise CliInputError("give either concatenated PAIRS or --left/--right lists, not both")
        lefts, rights = _expand(args.left or []), _expand(args.right or [])
        if len(lefts) != len(rights):
            raise CliInputError(f"--left has {len(lefts)} images but --right has {len(rights)}")
        pairs = [(f"{l.name}|{r.name}", read_image(l), read_image(r)) for l, r in zip(lefts, rights)]
    else:
        if not args.pairs:
            raise CliInputError("no chessboard images: give PAIRS (1280x480 frames or folders) or --left/--right")
        pairs = [(f.source, f.left, f.right) for f in frames_from_paths(args.pairs)]
    calib, report = calibrate_stereo(pairs, board_squares=args.board, square_mm=args.square_mm,
                                     sensor_from_left=design.camera_poses()["left"])
    print(report.summary())
    calib.save_yaml(args.out)
    print(f"wrote {args.out} (sensor_from_left from design {design.name!r} nominal pose)")
    return 0


def _calibrate_refraction(args: argparse.Namespace) -> int:
    from pipeline.design import load_design
    from pipeline.geometry.index_fit import fit_index_from_press
    from pipeline.geometry.refraction import RefractionError

    design = load_design(args.design)
    calib = _load_calib(args.calib)
    steps = args.steps_mm
    frames = list(frames_from_paths([args.sequence]))
    if len(frames) % len(steps):
        raise CliInputError(f"{args.sequence}: {len(frames)} frames is not a multiple of the {len(steps)} steps "
                            f"(one frame per step, repeated trials)")
    try:
        fit = fit_index_from_press(frames, steps, design, calib)
    except RefractionError as exc:
        raise CliInputError(f"{args.sequence}: {exc}") from None
    print(f"{len(frames) // len(steps)} trial(s) x {len(steps)} steps: {fit.summary()}")
    print(f"use --refraction linear --n-gel {fit.linear.n:.4f} or --refraction exact --n-gel {fit.n_gel_exact:.4f} "
          f"with reconstruct")
    return 0


def _reconstruct(args: argparse.Namespace) -> int:
    from pipeline.design import load_design
    from pipeline.batch import reconstruct
    from pipeline.priority import cpu_latency, frame_priority
    from pipeline.runner import Reconstructor

    design = load_design(args.design)
    calib = _load_calib(args.calib)
    rec = Reconstructor(design, calib, refraction=args.refraction, n_gel=args.n_gel, tracker=args.tracker,
                        view_threads=args.view_threads, view_process=args.view_process)
    try:
        with frame_priority(args.nice), cpu_latency(args.cpu_latency):
            summary = reconstruct(_open_source(args.source), rec, args.out, max_frames=args.max_frames,
                                  preview_every=args.preview_every)
    finally:
        rec.close()
    if rec.view_process_error:
        print(f"reconstruct: the view worker process stopped ({rec.view_process_error}); the right view was coded "
              "in this process from then on", file=sys.stderr)
    line = f"{summary['frames']} frame(s)"
    if summary["median_total_ms"] is not None:
        line += (f", median {summary['median_total_ms']:.1f} ms/frame (p95 {summary['p95_total_ms']:.1f}; "
                 f"views on {summary['view_threads']} thread(s))")
    if summary["skipped"]:
        line += f"; {len(summary['skipped'])} unreadable frame(s) skipped: " + \
            ", ".join(s["file"] for s in summary["skipped"][:8]) + ("..." if len(summary["skipped"]) > 8 else "")
    if summary["no_markers"]:
        line += f"; {len(summary['no_markers'])} frame(s) without any marker"
    print(f"{line}; wrote {args.out}")
    return 0


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("calibrate", help="stereo chessboard calibration -> calib.yaml")
    p.add_argument("pairs", nargs="*", metavar="PAIRS", help="concatenated 1280x480 chessboard frames or folders")
    p.add_argument("--left", nargs="+", help="left images (files or a folder), paired in name order with --right")
    p.add_argument("--right", nargs="+", help="right images (files or a folder)")
    p.add_argument("--board", type=_board, default=(9, 7), help="chessboard squares COLSxROWS (default 9x7)")
    p.add_argument("--square-mm", type=_square_mm, default=4.0, help="square side in mm (default 4)")
    p.add_argument("--design", default=DEFAULT_DESIGN, help="design whose nominal left-camera pose places the sensor frame")
    p.add_argument("--out", default="calib.yaml", help="output calibration file (OpenCV YAML)")
    p.set_defaults(func=_calibrate)

    p = sub.add_parser("calibrate-refraction", help="fit the refractive index (linear and exact models) from a skin-less press")
    p.add_argument("sequence", metavar="SEQUENCE", help="folder of frames, one per step (trials repeated in order)")
    p.add_argument("--calib", required=True, help="stereo calibration YAML")
    p.add_argument("--design", default=DEFAULT_DESIGN)
    p.add_argument("--steps-mm", type=_steps, default=_steps("0,1,2,3,4,5,6,7,8"),
                   help="press depth of each frame in mm, comma-separated (default 0,1,...,8)")
    p.set_defaults(func=_calibrate_refraction)

    p = sub.add_parser("reconstruct", help="markers + skin surface for every frame of a source")
    p.add_argument("source", metavar="SOURCE", help="camera index, video, image folder or image")
    p.add_argument("--calib", required=True, help="stereo calibration YAML")
    p.add_argument("--design", default=DEFAULT_DESIGN)
    p.add_argument("--out", required=True, help="output folder")
    p.add_argument("--refraction", choices=("exact", "linear"), default="exact")
    p.add_argument("--n-gel", type=float, default=None, help="refractive index (linear model: effective, e.g. 1.51)")
    p.add_argument("--tracker", choices=("dtrc", "nn"), default="dtrc")
    p.add_argument("--max-frames", type=int, default=None)
    p.add_argument("--preview-every", type=int, default=0, help="also write mesh + PNG every k-th frame")
    p.add_argument("--view-threads", type=int, choices=(1, 2), default=None,
                   help="2: the right view detected and identified on a worker thread beside the left (the "
                        "default on two or more CPUs; the same result); 1: both on the frame's thread")
    p.add_argument("--view-process", action="store_true",
                   help="the right view detected and identified in a worker process instead (the same result): "
                        "faster where the views have missing or spurious blobs, slower on clean ones")
    p.add_argument("--nice", type=int, default=None, metavar="N",
                   help="process frames at niceness N (e.g. -10: a larger share of a loaded machine; below the "
                        "current niceness needs root or CAP_SYS_NICE)")
    p.add_argument("--cpu-latency", type=int, default=None, metavar="US",
                   help="while frames are processed, ask Linux that every CPU wake within US microseconds (PM QoS, "
                        "/dev/cpu_dma_latency; 0: idle CPUs poll instead of halting, so the right view's thread starts "
                        "at once, at the cost of the idle cores' power; needs root)")
    p.set_defaults(func=_reconstruct)
