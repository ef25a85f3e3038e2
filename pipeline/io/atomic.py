"""Atomic file writes: every output of the project goes through here.

A result file either holds its complete new content or its previous state (or does not exist): it is
written to a temporary file in the SAME folder (a rename across file systems is not atomic), flushed
and fsynced, then moved over the final name with ``os.replace``. A process killed half-way leaves at
most a hidden ``.<name>.<random>.tmp`` file, which no reader of the project takes for a result
(frame folders skip names starting with ``.``; ``.tmp`` is no image, JSON, CSV or NPZ suffix).

Writers that want a file name rather than a file object (OpenCV, matplotlib, trimesh) are given
file objects or encoded bytes instead, so that nothing ever opens a final output path for writing.
"""

from __future__ import annotations

import contextlib
import io
import json
import os
import secrets
from pathlib import Path
from typing import IO, Any, Iterator

__all__ = ["atomic_open", "atomic_write_bytes", "atomic_write_text", "atomic_write_json", "TEMP_SUFFIX",
           "is_temp_name"]

TEMP_SUFFIX = ".tmp"


def is_temp_name(name: str) -> bool:
    """True for the name of a temporary file left by an interrupted atomic write."""
    return name.startswith(".") and name.endswith(TEMP_SUFFIX)


def _fsync_dir(folder: Path) -> None:
    try:
        fd = os.open(folder, os.O_RDONLY)
    except OSError:  # pragma: no cover - e.g. a platform without directory fds
        return
    try:
        os.fsync(fd)
    except OSError:  # pragma: no cover
        pass
    finally:
        os.close(fd)


@contextlib.contextmanager
def atomic_open(path: str | os.PathLike, mode: str = "w", *, encoding: str | None = "utf-8",
                newline: str | None = None, fsync: bool = True) -> Iterator[IO[Any]]:
    """Open a temporary file beside ``path``; on a clean exit it replaces ``path`` atomically.

    Parameters
    ----------
    path : the final file name; its folder must exist (it is created if missing).
    mode : ``"w"`` (text) or ``"wb"`` (binary).
    fsync : flush the data (and the folder entry) to disk before and after the rename.

    If the block raises (including KeyboardInterrupt), the temporary file is removed and ``path`` is
    left untouched.
    """
    if mode not in ("w", "wb"):
        raise ValueError(f"atomic_open: mode must be 'w' or 'wb', got {mode!r}")
    path = Path(path)
    folder = path.parent
    folder.mkdir(parents=True, exist_ok=True)
    tmp = folder / f".{path.name}.{os.getpid()}-{secrets.token_hex(4)}{TEMP_SUFFIX}"
    kwargs: dict[str, Any] = {} if mode == "wb" else {"encoding": encoding, "newline": newline}
    fh = open(tmp, "x" + mode[1:], **kwargs)  # exclusive: never clobbers another writer's temp file
    try:
        yield fh
        fh.flush()
        if fsync:
            os.fsync(fh.fileno())
        fh.close()
        os.replace(tmp, path)
        if fsync:
            _fsync_dir(folder)
    except BaseException:
        fh.close()
        with contextlib.suppress(OSError):
            os.unlink(tmp)
        raise


def atomic_write_bytes(path: str | os.PathLike, data: bytes, *, fsync: bool = True) -> Path:
    """Write ``data`` to ``path`` atomically; returns the path."""
    with atomic_open(path, "wb", fsync=fsync) as fh:
        fh.write(data)
    return Path(path)


def atomic_write_text(path: str | os.PathLike, text: str, *, encoding: str = "utf-8", fsync: bool = True) -> Path:
    """Write ``text`` to ``path`` atomically; returns the path."""
    with atomic_open(path, "w", encoding=encoding, fsync=fsync) as fh:
        fh.write(text)
    return Path(path)


def atomic_write_json(path: str | os.PathLike, obj: Any, *, indent: int | None = 2, fsync: bool = True,
                      **dumps_kw: Any) -> Path:
    """``json.dumps(obj)`` + newline written atomically (the text is built first, so a value that
    cannot be serialised leaves the old file in place)."""
    return atomic_write_text(path, json.dumps(obj, indent=indent, **dumps_kw) + "\n", fsync=fsync)


def savefig_atomic(fig, path: str | os.PathLike, **kw: Any) -> Path:
    """``fig.savefig`` into memory (format from the suffix), then an atomic write."""
    path = Path(path)
    buf = io.BytesIO()
    fig.savefig(buf, format=kw.pop("format", path.suffix.lstrip(".") or "png"), **kw)
    return atomic_write_bytes(path, buf.getvalue())


def imwrite_atomic(path: str | os.PathLike, image, params: list[int] | None = None) -> Path:
    """``cv2.imencode`` (format from the suffix) then an atomic write; raises OSError if encoding fails."""
    import cv2

    path = Path(path)
    ok, buf = cv2.imencode(path.suffix or ".png", image, params or [])
    if not ok:
        raise OSError(f"{path}: cannot encode the image as {path.suffix or '.png'}")
    return atomic_write_bytes(path, buf.tobytes())


__all__ += ["savefig_atomic", "imwrite_atomic"]
