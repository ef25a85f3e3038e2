"""Stage 1: frame sources (live camera, video file, image folder, single image) and recording.

Every source yields :class:`pipeline.types.StereoFrame` (1280x480 concatenated left | right, uint8
grey or BGR). A frame of the wrong size, channel count or dtype, or an unreadable file, raises
:class:`pipeline.errors.SourceError` naming the source and the file or frame index.
"""

from __future__ import annotations

import csv
import os
import time
from pathlib import Path
from typing import Iterator

import cv2
import numpy as np

from pipeline.errors import SourceError
from pipeline.types import FRAME_HEIGHT_PX, FRAME_WIDTH_PX, DataError, StereoFrame

__all__ = ["FrameSource", "open_source", "record", "check_frame", "drop_alpha", "IMAGE_SUFFIXES",
           "VIDEO_SUFFIXES"]

IMAGE_SUFFIXES = (".png", ".bmp", ".tif", ".tiff", ".jpg", ".jpeg", ".pgm", ".ppm")
VIDEO_SUFFIXES = (".avi", ".mp4", ".mkv", ".mov", ".m4v", ".mjpg", ".mjpeg", ".webm")


def drop_alpha(img: np.ndarray) -> np.ndarray:
    """A 4-channel BGRA image without its alpha channel (alpha carries no light); others unchanged."""
    if img.ndim == 3 and img.shape[2] == 4:
        return np.ascontiguousarray(img[:, :, :3])
    return img


def check_frame(img: np.ndarray | None, where: str) -> np.ndarray:
    """The one rule for what a stereo frame is, shared by every command that reads frames (``record``,
    ``reconstruct``, ``detect``, ``calibrate``, ``calibrate-refraction``).

    A frame is an 8-bit image of exactly 1280x480 pixels (left view in columns 0-639, right view in
    640-1279), grey (H, W) or (H, W, 1), BGR (H, W, 3) or BGRA (H, W, 4), whose alpha is dropped.
    Anything else (another size, 16-bit or float pixels, 2 channels, an unreadable file) raises
    :class:`SourceError` naming ``where``. Returns the image grey (H, W) or BGR (H, W, 3) uint8.
    """
    if img is None:
        raise SourceError(f"{where}: unreadable (not an image, or decoding failed)")
    if img.dtype != np.uint8:
        raise SourceError(f"{where}: expected 8-bit pixels, got {img.dtype}")
    if img.ndim == 3 and img.shape[2] == 1:
        img = img[:, :, 0]
    img = drop_alpha(img)
    if img.ndim not in (2, 3) or (img.ndim == 3 and img.shape[2] != 3):
        raise SourceError(f"{where}: expected a grey, BGR or BGRA image, got shape {img.shape}")
    if img.shape[:2] != (FRAME_HEIGHT_PX, FRAME_WIDTH_PX):
        raise SourceError(f"{where}: expected a {FRAME_WIDTH_PX}x{FRAME_HEIGHT_PX} stereo frame (left|right), "
                          f"got {img.shape[1]}x{img.shape[0]}")
    return img


_check_frame = check_frame


def _frame(img: np.ndarray, t: float, index: int, name: str, where: str) -> StereoFrame:
    try:
        return StereoFrame(_check_frame(img, where), timestamp_s=float(t), index=int(index), source=name)
    except DataError as exc:  # pragma: no cover - _check_frame catches these first
        raise SourceError(f"{where}: {exc}") from None


class FrameSource:
    """Iterable of :class:`StereoFrame` with ``close()`` and context-manager support.

    Build with :func:`open_source`. ``name`` is used in error messages; ``kind`` is one of
    ``camera``, ``video``, ``folder``, ``image``.
    """

    def __init__(self, name: str, kind: str, *, loop: bool = False) -> None:
        self.name = name
        self.kind = kind
        self.loop = loop
        self._closed = False

    def _frames(self) -> Iterator[StereoFrame]:  # pragma: no cover - abstract
        raise NotImplementedError

    def __iter__(self) -> Iterator[StereoFrame]:
        if self._closed:
            raise SourceError(f"{self.name}: source is closed")
        return self._frames()

    def close(self) -> None:
        self._closed = True

    def __enter__(self) -> "FrameSource":
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def __repr__(self) -> str:
        return f"<FrameSource {self.kind} {self.name!r}>"


class _FileSource(FrameSource):
    """A sorted list of image files; timestamps are the file order (index) unless given.

    With ``skip_unreadable`` a file that is not a valid frame (truncated, unreadable, wrong size) is
    skipped instead of ending the iteration: it is appended to ``skipped`` as
    ``{"index": k, "file": name, "error": message}`` and its index is not reused.
    """

    def __init__(self, name: str, kind: str, files: list[Path], timestamps: dict[str, float] | None = None,
                 *, loop: bool = False, skip_unreadable: bool = False) -> None:
        super().__init__(name, kind, loop=loop)
        self.files = files
        self.timestamps = timestamps or {}
        self.skip_unreadable = skip_unreadable
        self.skipped: list[dict] = []

    def __len__(self) -> int:
        return len(self.files)

    def _frames(self) -> Iterator[StereoFrame]:
        index = 0
        while True:
            for f in self.files:
                if self._closed:
                    return
                img = cv2.imread(str(f), cv2.IMREAD_UNCHANGED)
                where = f"{self.name}: file {f.name} (frame {index})"
                t = self.timestamps.get(f.name, float(index))
                try:
                    if img is None and not f.is_file():
                        raise SourceError(f"{where}: does not exist")
                    frame = _frame(img, t, index, self.name, where)
                except SourceError as exc:
                    if not self.skip_unreadable:
                        raise
                    self.skipped.append({"index": index, "file": f.name, "error": str(exc)})
                    index += 1
                    continue
                yield frame
                index += 1
            if not self.loop or not self.files:
                return


class _CaptureSource(FrameSource):
    """cv2.VideoCapture on a camera index or a video file."""

    def __init__(self, name: str, kind: str, cap: "cv2.VideoCapture", *, loop: bool = False) -> None:
        super().__init__(name, kind, loop=loop)
        self.cap = cap
        self._t0: float | None = None

    def _frames(self) -> Iterator[StereoFrame]:
        index = 0
        while not self._closed:
            ok, img = self.cap.read()
            if not ok:
                if self.kind == "video" and self.loop and index > 0:
                    self.cap.set(cv2.CAP_PROP_POS_FRAMES, 0)
                    continue
                if self.kind == "camera":
                    raise SourceError(f"{self.name}: camera stopped delivering frames at frame {index}")
                return
            if self.kind == "camera":
                now = time.monotonic()
                if self._t0 is None:
                    self._t0 = now
                t = now - self._t0
            else:
                t = self.cap.get(cv2.CAP_PROP_POS_MSEC) / 1000.0
            yield _frame(img, t, index, self.name, f"{self.name}: frame {index}")
            index += 1

    def close(self) -> None:
        super().close()
        self.cap.release()


def _read_timestamps(folder: Path) -> dict[str, float]:
    p = folder / "timestamps.csv"
    if not p.is_file():
        return {}
    out: dict[str, float] = {}
    try:
        with open(p, newline="", encoding="utf-8") as fh:
            for row in csv.DictReader(fh):
                t = float(row["timestamp_s"])
                if not np.isfinite(t):
                    raise ValueError(f"timestamp_s {row['timestamp_s']!r} of {row['file']} is not finite")
                out[row["file"]] = t
    except (KeyError, TypeError, ValueError, csv.Error) as exc:   # UnicodeDecodeError is a ValueError
        raise SourceError(f"{p}: malformed timestamps.csv ({type(exc).__name__}: {str(exc)[:120]})") from None
    return out


def open_source(spec: int | str | os.PathLike, *, loop: bool = False, skip_unreadable: bool = False) -> FrameSource:
    """Open a frame source.

    Parameters
    ----------
    spec : int, str or path
        A camera index (``0`` or ``"0"``; opened with cv2.VideoCapture requesting 1280x480), a video
        file, a folder of images (sorted by name; if any are named ``frame_*`` only those are read;
        ``timestamps.csv`` from :func:`record` is honoured) or a single image file.
    loop : bool
        Restart a video or folder at its end (for demos); ignored for cameras and single images.
    skip_unreadable : bool
        For a folder: skip a file that is not a valid frame and list it in the source's ``skipped``
        instead of raising (a recording cut off mid-frame still reconstructs).

    Raises
    ------
    SourceError
        The spec names nothing readable.
    """
    if isinstance(spec, (int, np.integer)) or (isinstance(spec, str) and spec.strip().isdigit()):
        idx = int(spec)
        cap = cv2.VideoCapture(idx)
        if not cap.isOpened():
            cap.release()
            raise SourceError(f"camera {idx}: cannot be opened (no such device or it is busy)")
        cap.set(cv2.CAP_PROP_FRAME_WIDTH, FRAME_WIDTH_PX)
        cap.set(cv2.CAP_PROP_FRAME_HEIGHT, FRAME_HEIGHT_PX)
        return _CaptureSource(f"camera {idx}", "camera", cap)
    path = Path(spec)
    if path.is_dir():
        files = sorted(p for p in path.iterdir()
                       if p.suffix.lower() in IMAGE_SUFFIXES and not p.name.startswith(".") and p.is_file())
        # A recording (ours or the twin's) names its frames frame_*; then other images in the folder
        # (previews, annotated copies) are not frames.
        frames_only = [p for p in files if p.name.startswith("frame_")]
        files = frames_only or files
        if not files:
            raise SourceError(f"{path}: folder holds no images ({', '.join(IMAGE_SUFFIXES)})")
        return _FileSource(str(path), "folder", files, _read_timestamps(path), loop=loop,
                           skip_unreadable=skip_unreadable)
    if not path.exists():
        raise SourceError(f"{path}: no such file, folder or camera index")
    if path.suffix.lower() in IMAGE_SUFFIXES:
        return _FileSource(str(path), "image", [path])
    cap = cv2.VideoCapture(str(path))
    if not cap.isOpened():
        cap.release()
        raise SourceError(f"{path}: not a readable video or image")
    return _CaptureSource(str(path), "video", cap, loop=loop)


def _complete_frames(out: Path) -> tuple[list[list[str]], list[Path]]:
    """The recording already in ``out``: its rows ``[index, timestamp_s, file]`` up to the last complete
    frame, and the frame files after it (incomplete, unlisted or unreadable).

    A row counts when it is well formed, its index continues the sequence and its PNG decodes to a valid
    frame; the first row that fails ends the kept prefix (a recording killed mid-frame, or a torn last
    line of ``timestamps.csv``)."""
    rows: list[list[str]] = []
    p = out / "timestamps.csv"
    if p.is_file():
        with open(p, newline="", encoding="utf-8", errors="replace") as fh:
            for k, row in enumerate(csv.reader(fh)):
                if k == 0:
                    if row != ["index", "timestamp_s", "file"]:
                        raise SourceError(f"{p}: not a recording's timestamps.csv (header {row!r})")
                    continue
                try:
                    ok = len(row) == 3 and int(row[0]) == len(rows) and row[2] == f"frame_{len(rows):06d}.png"
                    ok = ok and np.isfinite(float(row[1]))
                except ValueError:
                    ok = False
                if not ok:
                    break
                f = out / row[2]
                try:
                    check_frame(cv2.imread(str(f), cv2.IMREAD_UNCHANGED) if f.is_file() else None, str(f))
                except SourceError:
                    break
                rows.append(row)
    kept = {r[2] for r in rows}
    stale = [f for f in sorted(out.glob("frame_*.png")) if f.name not in kept]
    return rows, stale


def record(source: FrameSource | int | str | os.PathLike, out_dir: str | os.PathLike, *,
           max_frames: int | None = None, progress: bool = True, overwrite: bool = False,
           resume: bool = False) -> int:
    """Save frames losslessly as ``frame_000000.png`` ... plus ``timestamps.csv``.

    Each frame is written atomically (:mod:`pipeline.io.atomic`: encoded, written to a temporary file,
    renamed), then its row ``index,timestamp_s,file`` is appended to ``timestamps.csv`` and flushed, so
    an interrupted recording (Ctrl-C, a kill, a source error) keeps every frame it listed, complete;
    the exception is re-raised after the files are closed.

    Parameters
    ----------
    source : FrameSource or spec
        An open source, or anything :func:`open_source` accepts (then opened and closed here).
    out_dir : path
        Created if needed. Refused if it already holds a recording (frames or timestamps.csv) unless
        ``overwrite`` (the old frames and timestamps are deleted first) or ``resume``.
    max_frames : int, optional
        Stop when the recording holds this many frames (with ``resume``: old and new together).
    progress : bool
        Show a tqdm progress bar.
    resume : bool
        Append after the last complete frame of the recording in ``out_dir`` (see
        :func:`_complete_frames`); frame files after it are removed. New timestamps continue from the
        last kept one, one median frame interval later (the pause between the sessions is unknown).

    Returns
    -------
    int
        Number of frames written by this call.
    """
    from pipeline.io.atomic import atomic_write_text, imwrite_atomic

    if max_frames is not None and max_frames < 0:
        raise SourceError(f"record: max_frames must be >= 0, got {max_frames}")
    if overwrite and resume:
        raise SourceError("record: choose either overwrite or resume, not both")
    out = Path(out_dir)
    if out.exists() and not out.is_dir():
        raise SourceError(f"{out}: exists and is not a folder")
    old = sorted(out.glob("frame_*.png")) + ([out / "timestamps.csv"] if (out / "timestamps.csv").exists() else [])
    if old and not (overwrite or resume):
        raise SourceError(f"{out}: already holds a recording ({len(old)} files); use --resume to append to it "
                          f"or --overwrite to replace it")
    out.mkdir(parents=True, exist_ok=True)
    rows: list[list[str]] = []
    if resume and old:
        rows, stale = _complete_frames(out)
    else:
        stale = old
    for p in stale:
        p.unlink()
    # rewrite the kept rows (drops a torn last line), atomically, then append to it
    atomic_write_text(out / "timestamps.csv", "".join(f"{r[0]},{r[1]},{r[2]}\r\n" for r in
                                                        [["index", "timestamp_s", "file"]] + rows))
    n0 = len(rows)
    t_offset = 0.0
    if n0:
        ts = [float(r[1]) for r in rows]
        step = float(np.median(np.diff(ts))) if len(ts) > 1 else 0.0
        t_offset = ts[-1] + max(step, 0.0)
    own = not isinstance(source, FrameSource)
    src = open_source(source) if own else source
    from tqdm import tqdm

    n = n0
    t_first = None
    bar = tqdm(total=max_frames, initial=n0, desc=f"record {src.name}", unit="frame", disable=not progress)
    try:
        # an append-only log, flushed per row: a torn last row is dropped by the next --resume
        with open(out / "timestamps.csv", "a", newline="", encoding="utf-8") as fh:  # append-only
            w = csv.writer(fh)
            if max_frames is not None and n >= max_frames:
                return 0
            for frame in src:
                name = f"frame_{n:06d}.png"
                try:
                    imwrite_atomic(out / name, np.ascontiguousarray(frame.image))
                except OSError as exc:
                    raise SourceError(f"{out / name}: cannot write ({exc})") from None
                if t_first is None:
                    t_first = float(frame.timestamp_s)
                t = float(frame.timestamp_s) if n0 == 0 else t_offset + float(frame.timestamp_s) - t_first
                w.writerow([n, repr(t), name])
                fh.flush()
                n += 1
                bar.update(1)
                if max_frames is not None and n >= max_frames:
                    break
    finally:
        bar.close()
        if own:
            src.close()
    return n - n0
