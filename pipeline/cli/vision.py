"""``stereotactip detect`` and ``stereotactip record`` (wired in by ``pipeline.cli`` via ``register``)."""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import cv2
import numpy as np

from pipeline.errors import SourceError, UserError
from pipeline.design import DEFAULT_DESIGN

__all__ = ["register", "detect_image", "identify_recording"]


def detect_image(path: Path, design, *, out_dir: Path | None = None) -> dict:
    """Detection + ring coding on both views of one 1280x480 stereo frame file.

    Writes ``<stem>_detect.png`` into ``out_dir`` (default: next to the image) and returns a JSON-able
    report: per view the marker count, ring sizes found vs expected, uncoded/unmatched counts.
    """
    from pipeline.vision.annotate import annotate_view
    from pipeline.vision.detection import detect_markers
    from pipeline.vision.dtrc import code_rings

    from pipeline.io.sources import check_frame

    # the same rule as every other reader of frames (pipeline.io.sources.check_frame): a frame that
    # reconstruct would refuse is refused here too, rather than detected as one wide "view"
    img = check_frame(cv2.imread(str(path), cv2.IMREAD_UNCHANGED), str(path))
    h, w = img.shape[:2]
    views = {"left": img[:, : w // 2], "right": img[:, w // 2:]}
    report = {"image": str(path), "width_px": w, "height_px": h, "design": design.name, "views": {}}
    panels = []
    for name, view in views.items():
        blobs = detect_markers(view)
        coding = code_rings(blobs, design)
        report["views"][name] = {
            "markers_found": len(blobs),
            "ring_sizes_found": list(coding.ring_sizes_found),
            "ring_sizes_expected": list(coding.ring_sizes_expected),
            "rings_match_design": coding.ring_sizes_found == coding.ring_sizes_expected,
            "coded": coding.coded,
            "unmatched_ids": coding.unmatched_ids.tolist(),
            "messages": list(coding.messages),
        }
        panels.append(annotate_view(view, blobs, coding))
    out_dir = Path(out_dir) if out_dir is not None else path.parent
    out_dir.mkdir(parents=True, exist_ok=True)
    out_png = out_dir / f"{path.stem}_detect.png"
    from pipeline.io.atomic import imwrite_atomic

    try:
        imwrite_atomic(out_png, np.concatenate(panels, axis=1))
    except OSError as exc:
        raise SourceError(f"{out_png}: cannot write ({exc})") from None
    report["annotated_png"] = str(out_png)
    return report


def _natural_key(path: Path):
    import re

    return [int(t) if t.isdigit() else t for t in re.split(r"(\d+)", path.name)]


def identify_recording(paths: list[Path], design, *, reference: int = 0) -> dict:
    """Markers and their ids in every frame of a monocular dome (TacTip-type) recording.

    Each frame is detected with :data:`pipeline.vision.detection.MONOCULAR_DOME`; the ids are the reference
    frame's marker indices (its detections sorted by v then u) and are carried to the other frames by
    :func:`pipeline.vision.tactip_id.identify_sequence` in frame order (consecutive frames move markers
    little). Returns a JSON-able report: per frame every detected marker's centre, id (``None`` when
    not identified) and the reason it was not.

    Raises
    ------
    SourceError
        A frame is unreadable, or not of the design camera's size.
    UserError
        ``reference`` is not a frame index.
    """
    from pipeline.vision.detection import MONOCULAR_DOME, detect_markers
    from pipeline.vision.tactip_id import REASONS, identify_sequence

    if not (0 <= reference < len(paths)):
        raise UserError(f"--reference {reference}: the recording has frames 0..{len(paths) - 1}")
    cam = design.camera
    blobs = []
    for path in paths:
        img = cv2.imread(str(path), cv2.IMREAD_GRAYSCALE)
        if img is None:
            raise SourceError(f"{path}: unreadable or not an image")
        if (img.shape[1], img.shape[0]) != (cam.width_px, cam.height_px):
            raise SourceError(f"{path}: {img.shape[1]}x{img.shape[0]} px; the design {design.name!r} camera gives "
                              f"{cam.width_px}x{cam.height_px}")
        blobs.append(detect_markers(img, params=MONOCULAR_DOME))
    seq = identify_sequence(blobs, None, reference, blobs[reference].xy_px)
    frames = []
    for path, b, ids, reasons in zip(paths, blobs, seq.ids, seq.reasons):
        frames.append({
            "image": str(path), "markers_found": len(b), "identified": int((ids >= 0).sum()),
            "markers": [{"u": round(float(u), 3), "v": round(float(v), 3), "id": int(k) if k >= 0 else None,
                         "reason": r} for (u, v), k, r in zip(b.xy_px, ids, reasons)],
        })
    return {"design": design.name, "marker_count": design.marker_count, "reference": str(paths[reference]),
            "ids": "the reference frame's marker indices (detections sorted by v then u)",
            "reasons": REASONS, "frames": frames}


def _detect_monocular(args: argparse.Namespace, design) -> int:
    paths: list[Path] = []
    for p in args.images:
        path = Path(p)
        if path.is_dir():
            paths.extend(sorted((q for q in path.iterdir() if q.suffix.lower() in (".png", ".jpg", ".jpeg", ".bmp")),
                                key=_natural_key))
        elif path.is_file():
            paths.append(path)
        else:
            raise SourceError(f"{path}: no such image file or folder")
    if not paths:
        raise SourceError("no image files given")
    report = identify_recording(paths, design, reference=args.reference)
    if args.json:
        json.dump(report, sys.stdout, indent=1)
        print()
        return 0
    print(f"{len(paths)} frame(s), design {design.name} ({design.marker_count} markers), reference "
          f"{report['reference']}:")
    for fr in report["frames"]:
        why: dict = {}
        for m in fr["markers"]:
            if m["reason"]:
                why[m["reason"]] = why.get(m["reason"], 0) + 1
        print(f"  {fr['image']}: {fr['markers_found']} markers, {fr['identified']} identified"
              + ("".join(f", {n} {k}" for k, n in sorted(why.items()))))
    return 0


def _detect(args: argparse.Namespace) -> int:
    from pipeline.design import load_design

    design = load_design(args.design)
    if design.monocular:
        return _detect_monocular(args, design)
    if args.reference != 0:
        raise UserError("--reference applies to a monocular design's recording only")
    reports = []
    for p in args.images:
        path = Path(p)
        if not path.is_file():
            raise SourceError(f"{path}: no such image file")
        reports.append(detect_image(path, design, out_dir=args.out))
    if args.json:
        json.dump(reports if len(reports) > 1 else reports[0], sys.stdout, indent=2)
        print()
        return 0
    for r in reports:
        print(f"{r['image']} ({r['width_px']}x{r['height_px']}), design {r['design']}:")
        for name, v in r["views"].items():
            ok = "matches design" if v["rings_match_design"] else "DIFFERS from design"
            print(f"  {name:5s}: {v['markers_found']} markers, {v['coded']} coded, "
                  f"{len(v['unmatched_ids'])} design ids unmatched")
            print(f"         rings found    {v['ring_sizes_found']}")
            print(f"         rings expected {v['ring_sizes_expected']}  ({ok})")
            for m in v["messages"]:
                print(f"         note: {m}")
        print(f"  annotated: {r['annotated_png']}")
    return 0


def _record(args: argparse.Namespace) -> int:
    from pipeline.io.sources import open_source, record

    if args.max_frames is not None and args.max_frames < 0:
        raise UserError(f"--max-frames must be >= 0, got {args.max_frames}")
    with open_source(args.source) as src:
        n = record(src, args.out, max_frames=args.max_frames, progress=not args.quiet, overwrite=args.overwrite,
                   resume=args.resume)
    total = sum(1 for _ in Path(args.out).glob("frame_*.png"))
    print(f"recorded {n} frame(s) from {args.source} into {args.out}"
          + (f" (resumed; the recording now holds {total})" if args.resume else ""))
    return 0


def register(sub: argparse._SubParsersAction) -> None:
    """Add the ``detect`` and ``record`` subcommands."""
    p = sub.add_parser("detect", help="detect markers and DTRC rings in images; write annotated PNGs; with a "
                       "monocular (TacTip) design: identify the markers of a recording, frame by frame")
    p.add_argument("images", nargs="+", metavar="IMAGE",
                   help="1280x480 stereo frame (left|right; grey, BGR or BGRA); with a monocular design: the frames "
                        "of one recording, in order (files, or folders taken in natural name order)")
    p.add_argument("--design", default=DEFAULT_DESIGN, help=f"design name or TOML path (default {DEFAULT_DESIGN})")
    p.add_argument("--json", action="store_true", help="print a JSON report (monocular: per frame every marker's "
                   "centre, id or the reason it has none)")
    p.add_argument("--reference", type=int, default=0, help="monocular design: index of the frame whose markers "
                   "define the ids (default 0, the first)")
    p.add_argument("--out", type=Path, default=None, help="folder for <stem>_detect.png (default: beside the image)")
    p.set_defaults(func=_detect)

    p = sub.add_parser("record", help="record frames losslessly (PNG + timestamps.csv)")
    p.add_argument("source", metavar="SOURCE", help="camera index, video file, image folder or image")
    p.add_argument("--out", required=True, type=Path, help="output folder")
    p.add_argument("--max-frames", type=int, default=None,
                   help="stop when the recording holds N frames (with --resume: old and new together)")
    p.add_argument("--overwrite", action="store_true", help="replace an existing recording in --out")
    p.add_argument("--resume", action="store_true",
                   help="append to the recording in --out after its last complete frame")
    p.add_argument("--quiet", action="store_true", help="no progress bar")
    p.set_defaults(func=_record)
