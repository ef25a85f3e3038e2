"""A reconstruction run: a :class:`~pipeline.runner.Reconstructor` over a frame source, the results in a folder.

:func:`reconstruct` is what ``stereotactip reconstruct`` runs: per frame the corrected markers (CSV, PLY),
the skin points with normals (PLY) and the height map (NPZ), meshes and a preview now and then, and a
``summary.json`` that is written however the run ends. The per-frame chain itself is
:mod:`pipeline.runner`; the file formats are :mod:`pipeline.io.files`.
"""

from __future__ import annotations

from pathlib import Path
from typing import Iterable

import numpy as np

from pipeline.geometry.surface import height_map
from pipeline.runner import FrameResult, Reconstructor, RunnerError
from pipeline.types import HeightMap, StereoFrame

__all__ = ["reconstruct"]


def _finite_or_none(x: float) -> float | None:
    return x if np.isfinite(x) else None


def reconstruct(frames: Iterable[StereoFrame], reconstructor: Reconstructor, out_dir: str | Path, *,
                max_frames: int | None = None, preview_every: int = 0, progress: bool = True,
                echo=print, on_result=None) -> dict:
    """Run a reconstructor over frames and write results to ``out_dir``.

    Per frame: ``markers_XXXX.csv`` and ``markers_XXXX.ply`` (corrected markers), ``skin_XXXX.ply``
    (skin points + normals), ``heightmap_XXXX.npz``; for the last frame (and every ``preview_every``-th
    if > 0) ``surface_XXXX.stl`` / ``surface_XXXX.ply`` meshes and ``preview_XXXX.png``; finally
    ``summary.json``. Every file is written atomically. Returns the summary dict. ``on_result(frame,
    result)``, if given, is called for every processed frame (e.g. to score it or keep it in memory).

    ``summary.json`` is written whatever happens: with ``"stopped": null`` after the last frame, or
    with the reason if the source fails or the run is interrupted (then the exception is re-raised).
    Frames a source skipped as unreadable (``FrameSource.skipped``, see ``open_source(...,
    skip_unreadable=True)``) are printed as they occur and listed under ``"skipped"``; frames in which
    no marker was reconstructed are listed under ``"no_markers"``.
    """
    from tqdm import tqdm

    from pipeline.io.atomic import atomic_write_json
    from pipeline.io.files import heightmap_mesh, write_heightmap_npz, write_markers_csv, write_ply, write_preview_png
    from pipeline.io.files import write_stl

    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    design = reconstructor.design
    per_frame = []
    last = None
    skipped_source = getattr(frames, "skipped", None)
    n_skipped_seen = 0
    bar = tqdm(total=max_frames, unit="frame", disable=not progress, leave=False)

    def mesh_outputs(res: FrameResult, hm: HeightMap | None) -> None:
        tag = f"{res.index:04d}"
        if hm is not None:
            V, F = heightmap_mesh(hm)
            if len(F):
                write_stl(out / f"surface_{tag}.stl", V, F)
                write_ply(out / f"surface_{tag}.ply", V, faces=F, binary=True)
        write_preview_png(out / f"preview_{tag}.png", hm, res.corrected,
                          title=f"{design.name} frame {res.index}: {res.n_matched}/{res.n_expected} markers")

    def report_skips() -> None:
        nonlocal n_skipped_seen
        if skipped_source is None:
            return
        for item in skipped_source[n_skipped_seen:]:
            echo(f"frame {item['index']}: SKIPPED, {item['error']}")
        n_skipped_seen = len(skipped_source)

    def write_summary(stopped: str | None) -> dict:
        totals = np.array([f["timings_ms"]["total"] for f in per_frame])
        summary = {"design": design.name, "refraction": reconstructor.refraction,
                   "tracker": reconstructor.tracker_name, "n_gel": reconstructor.n_gel, "frames": len(per_frame),
                   "units": {"xyz": "mm", "time": "ms"},
                   "median_total_ms": float(np.median(totals)) if len(totals) else None,
                   "p95_total_ms": float(np.percentile(totals, 95)) if len(totals) else None,
                   "view_threads": getattr(reconstructor, "view_threads", 1),
                   "skipped": list(skipped_source or []),
                   "no_markers": [f["index"] for f in per_frame if f["matched"] == 0],
                   "stopped": stopped, "per_frame": per_frame}
        atomic_write_json(out / "summary.json", summary, indent=1, allow_nan=False)
        return summary

    try:
        for k, frame in enumerate(frames):
            report_skips()
            if max_frames is not None and k >= max_frames:
                break
            res = reconstructor.process(frame)
            if on_result is not None:
                on_result(frame, res)
            tag = f"{res.index:04d}"
            write_markers_csv(out / f"markers_{tag}.csv", res.corrected)
            write_ply(out / f"markers_{tag}.ply", res.corrected.xyz_mm)
            hm = res.height_map
            if res.skin is not None:
                write_ply(out / f"skin_{tag}.ply", res.skin.xyz_mm, normals=res.skin.normals)
                if hm is None:
                    hm = height_map(res.skin, mask_radius_mm=design.gel.radius_mm)
                write_heightmap_npz(out / f"heightmap_{tag}.npz", hm)
            if preview_every > 0 and k % preview_every == 0:
                mesh_outputs(res, hm)
            echo(res.summary(design))
            per_frame.append({"index": res.index, "timestamp_s": res.timestamp_s, "matched": res.n_matched,
                              "expected": res.n_expected, "max_abs_dz_mm": _finite_or_none(res.max_abs_dz_mm(design)),
                              "unmatched_ids": res.unmatched_ids.tolist(),
                              "unmatched_reasons": {str(k): v for k, v in res.unmatched_reasons.items()},
                              "timings_ms": res.timings_ms,
                              "notes": list(res.notes)})
            last = (res, hm)
            bar.update(1)
        report_skips()
    except BaseException as exc:
        bar.close()
        reason = "interrupted" if isinstance(exc, KeyboardInterrupt) else f"{type(exc).__name__}: {exc}"
        write_summary(reason.splitlines()[0] if reason else type(exc).__name__)
        raise
    bar.close()
    if last is None:
        write_summary("the source delivered no readable frame")
        n_skip = len(skipped_source or [])
        raise RunnerError("reconstruct: the source delivered no frames" if not n_skip else
                          f"reconstruct: none of the source's frames is readable ({n_skip} skipped; "
                          f"see {out / 'summary.json'})")
    mesh_outputs(*last)
    return write_summary(None)
