"""Labelled real tap frames of a monocular TacTip: loading, checks, the train / held-out split, the
observations (detected and identified markers) that ``fit-twin`` and ``validate`` share.

Targets CSV: the tactile data-collection format (columns ``sensor_image``, ``pose_1..6`` — ``pose_3`` the
tap depth in mm, ``pose_4``/``pose_5`` the surface tilt in degrees — plus bookkeeping columns). A frame is
matched to its row by file name, else by the integer at the end of both names (``image_7.png`` ↔
``tactip331_tap_7.png``). Split: frames ordered by that integer; every 4th (positions 3, 7, 11, …) is
held out, the rest train.
"""

from __future__ import annotations

import csv
import hashlib
import re
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from pipeline.design import SensorDesign
from pipeline.errors import UserError
from twin.tactip import TapPose

__all__ = ["TapFrame", "load_tap_frames", "split_indices", "TapDataError", "HOLDOUT_EVERY"]

REQUIRED_COLUMNS = ("sensor_image", "pose_3", "pose_4", "pose_5")
KNOWN_COLUMNS = set(REQUIRED_COLUMNS) | {"sensor_video", "obj_id", "obj_pose", "pose_id", "pose_1", "pose_2",
                                         "pose_6", "move_1", "move_2", "move_3", "move_4", "move_5", "move_6"}
HOLDOUT_EVERY = 4
MAX_DEPTH_MM = 15.0
MAX_TILT_DEG = 45.0


class TapDataError(UserError, ValueError):
    """Frames or targets that cannot be used."""


@dataclass(frozen=True)
class TapFrame:
    path: Path
    index: int          # the integer of the file name
    pose: TapPose


def _index(name: str) -> int | None:
    m = re.search(r"(\d+)\D*$", Path(name).stem)
    return int(m.group(1)) if m else None


def _frame_paths(frames: str | Path | list) -> list[Path]:
    if isinstance(frames, (list, tuple)):
        paths = [Path(p) for p in frames]
    else:
        p = Path(frames)
        if p.is_dir():
            paths = sorted(q for q in p.iterdir() if q.suffix.lower() in (".png", ".jpg", ".jpeg", ".bmp"))
        elif p.is_file():
            paths = [p]
        else:
            raise TapDataError(f"frames {str(p)!r}: no such file or folder")
    if not paths:
        raise TapDataError(f"frames {frames!s}: no images found")
    return paths


def load_tap_frames(frames, targets: str | Path, design: SensorDesign, *,
                    skip_unlabelled: bool = False, log=None) -> list[TapFrame]:
    """The labelled frames, ordered by their index; every frame must have a target row, every image the
    design's camera size (checked on read, :func:`read_frame`)."""
    tpath = Path(targets)
    if not tpath.is_file():
        raise TapDataError(f"targets {str(tpath)!r}: no such file")
    try:
        with tpath.open(newline="", encoding="utf-8") as fh:
            rows = list(csv.DictReader(fh))
    except (UnicodeDecodeError, csv.Error) as exc:
        raise TapDataError(f"targets {tpath}: not a CSV file ({exc})") from None
    if not rows:
        raise TapDataError(f"targets {tpath}: no rows")
    cols = set(rows[0])
    unknown = sorted(c for c in cols if c not in KNOWN_COLUMNS)
    if unknown:
        raise TapDataError(f"targets {tpath}: unknown column {unknown[0]!r} (known: {', '.join(sorted(KNOWN_COLUMNS))})")
    missing = [c for c in REQUIRED_COLUMNS if c not in cols]
    if missing:
        raise TapDataError(f"targets {tpath}: missing column {missing[0]!r} (pose_3 = tap depth mm, pose_4/pose_5 "
                           f"= surface tilt deg, sensor_image = frame name)")
    by_name, by_index = {}, {}
    for k, row in enumerate(rows):
        try:
            pose = TapPose(float(row["pose_3"]), float(row["pose_4"]), float(row["pose_5"]))
        except (TypeError, ValueError):
            raise TapDataError(f"targets {tpath}: row {k + 2}: pose_3/4/5 must be numbers") from None
        if not (0 <= pose.depth_mm <= MAX_DEPTH_MM and abs(pose.tilt_x_deg) <= MAX_TILT_DEG
                and abs(pose.tilt_y_deg) <= MAX_TILT_DEG) or not np.all(np.isfinite(
                [pose.depth_mm, pose.tilt_x_deg, pose.tilt_y_deg])):
            raise TapDataError(f"targets {tpath}: row {k + 2}: depth {pose.depth_mm} mm / tilt "
                               f"({pose.tilt_x_deg}, {pose.tilt_y_deg}) deg outside [0, {MAX_DEPTH_MM}] mm / "
                               f"±{MAX_TILT_DEG} deg")
        name = Path(row["sensor_image"]).name
        by_name[name] = pose
        i = _index(name)
        if i is not None:
            by_index[i] = pose
    out = []
    for p in _frame_paths(frames):
        i = _index(p.name)
        pose = by_name.get(p.name, by_index.get(i) if i is not None else None)
        if pose is None and skip_unlabelled:
            if log:
                log(f"skipping {p.name}: no row in {tpath.name}")
            continue
        if pose is None:
            raise TapDataError(f"frame {p.name}: no row in {tpath.name} (matched by file name or trailing number; "
                               f"--skip-unlabelled leaves such frames out)")
        out.append(TapFrame(p, i if i is not None else len(out), pose))
    out.sort(key=lambda f: f.index)
    if len(out) < 4:
        raise TapDataError(f"frames: {len(out)} labelled frames; fitting needs at least 4")
    return out


def split_indices(n: int) -> tuple[np.ndarray, np.ndarray]:
    """(train, held-out) positions: every HOLDOUT_EVERY-th frame (positions 3, 7, ...) is held out."""
    k = np.arange(n)
    held = (k % HOLDOUT_EVERY) == HOLDOUT_EVERY - 1
    return k[~held], k[held]


def read_frame(path: Path, design: SensorDesign) -> np.ndarray:
    """The 8-bit grey image of a frame, checked against the design's camera size."""
    img = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    if img is None:
        raise TapDataError(f"frame {path}: unreadable or not an image")
    if img.dtype != np.uint8:
        raise TapDataError(f"frame {path}: {img.dtype} pixels; expected 8-bit")
    h, w = img.shape[:2]
    cam = design.camera
    if (w, h) != (cam.width_px, cam.height_px):
        raise TapDataError(f"frame {path}: {w}x{h} px; the design {design.name!r} camera gives "
                           f"{cam.width_px}x{cam.height_px}")
    if img.ndim == 3:
        img = cv2.cvtColor(img[:, :, :3], cv2.COLOR_BGR2GRAY)
    return img


def digest(*parts) -> str:
    h = hashlib.sha256()
    for p in parts:
        if isinstance(p, Path):
            h.update(p.read_bytes())
        else:
            h.update(repr(p).encode())
    return h.hexdigest()[:16]
