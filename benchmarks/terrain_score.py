"""Scoring the terrain scan: whether each region's feature is resolved, and the figures that show it.

A mountain region is resolved when its peak height and width at half height match the DEM's; a sea or
channel when the land-sea contrast of the reconstruction reaches a fraction of what the tap plane lets
the skin reach (:data:`FEATURE_CRITERIA`, printed into ``terrain.json``).
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np

from benchmarks.terrain_regions import region
from pipeline.types import HeightMap

__all__ = ["FEATURE_CRITERIA", "PEAK_TOL_MM", "score_region", "region_panel", "world_panel"]

# Measurable criteria for "feature resolved" (one table, printed into terrain.json).
PEAK_TOL_MM = 0.3          # mountains: |recon peak - true peak| (about the paper's Gaussian-peak errors)
WIDTH_RATIO_RANGE = (0.8, 1.25)   # mountains: recon / true mean width at half height
CONTRAST_FRACTION = 0.5    # seas/channels: recon land-sea contrast >= 50 % of the reachable contrast
MIN_CONTRAST_MM = 0.1      # ... and at least 0.1 mm (below that a sea is "barely visible")
FEATURE_CRITERIA = {
    "mountains": f"peak height within {PEAK_TOL_MM} mm of the DEM's AND mean width at half height "
                 f"(per map row, cells above half the row's maximum) within {WIDTH_RATIO_RANGE} of the DEM's",
    "sea": f"land-sea contrast (90th percentile of land cells - median of sea cells) of the reconstruction "
           f">= {CONTRAST_FRACTION:.0%} of the reachable truth's (DEM clipped at the tap plane) AND >= {MIN_CONTRAST_MM} mm",
    "channel": "as 'sea' (the channel's water cells against the land on its shores)",
}


# ----- scoring ------------------------------------------------------------------------------

def _half_height_width(z: np.ndarray, min_peak_mm: float = 0.5) -> float:
    """Mean over rows (rows whose max exceeds ``min_peak_mm``) of the cell count above half the row max."""
    widths = []
    for row in z:
        if not np.any(np.isfinite(row)):
            continue
        m = np.nanmax(row)
        if m > min_peak_mm:
            widths.append(np.sum(row > m / 2))
    return float(np.mean(widths)) if widths else float("nan")


def _contrast(z: np.ndarray, land: np.ndarray, sea: np.ndarray) -> float:
    zl, zs = z[land & np.isfinite(z)], z[sea & np.isfinite(z)]
    if len(zl) == 0 or len(zs) == 0:
        return float("nan")
    return float(np.percentile(zl, 90) - np.median(zs))


def score_region(key: str, recon: HeightMap, truth: HeightMap, land: np.ndarray, tap_z_mm: float) -> dict[str, Any]:
    """Metrics of one region on the common grid (global frame, mm).

    recon, truth : HeightMaps on the same grid; land : (H, W) bool truth land mask on that grid.
    Errors are over cells where the reconstruction exists (the scanned area inside the box).
    """
    r = region(key)
    zr, zt = recon.z_mm, truth.z_mm
    reach = np.maximum(zt, tap_z_mm)
    ok = np.isfinite(zr)
    err, err_reach = zr[ok] - zt[ok], zr[ok] - reach[ok]
    out: dict[str, Any] = {
        "name": r.name, "kind": r.kind, "box_deg": [r.lat_min, r.lat_max, r.lon_min, r.lon_max],
        "box_mm": [round(v, 3) for v in r.box_mm()],
        "covered_fraction": float(ok.mean()),
        "rms_err_mm": float(np.sqrt(np.mean(err**2))) if err.size else float("nan"),
        "max_abs_err_mm": float(np.max(np.abs(err))) if err.size else float("nan"),
        "rms_err_reachable_mm": float(np.sqrt(np.mean(err_reach**2))) if err.size else float("nan"),
        "max_abs_err_reachable_mm": float(np.max(np.abs(err_reach))) if err.size else float("nan"),
        "true_max_mm": float(np.nanmax(zt)), "recon_max_mm": float(np.nanmax(zr)) if ok.any() else float("nan"),
    }
    if r.kind == "mountains":
        peak_err = out["recon_max_mm"] - out["true_max_mm"]
        zt_cov = np.where(ok, zt, np.nan)
        w_true, w_rec = _half_height_width(zt_cov), _half_height_width(zr)
        ratio = w_rec / w_true if w_true > 0 else float("nan")
        out.update(peak_err_mm=float(peak_err), half_height_width_ratio=float(ratio),
                   resolved=bool(abs(peak_err) <= PEAK_TOL_MM and WIDTH_RATIO_RANGE[0] <= ratio <= WIDTH_RATIO_RANGE[1]))
    else:
        sea = ~land
        c_true = _contrast(np.where(ok, reach, np.nan), land, sea)
        c_rec = _contrast(zr, land, sea)
        floor_err = float(np.median((zr - zt)[sea & ok])) if np.any(sea & ok) else float("nan")
        out.update(contrast_reachable_mm=c_true, contrast_recon_mm=c_rec, sea_floor_err_mm=floor_err,
                   resolved=bool(np.isfinite(c_rec) and c_rec >= CONTRAST_FRACTION * c_true and c_rec >= MIN_CONTRAST_MM))
    return out


# ----- outputs ------------------------------------------------------------------------------

def region_panel(path: Path, title: str, truth: HeightMap, recon: HeightMap, centres: np.ndarray | None = None) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    ext = [truth.x_mm[0], truth.x_mm[-1], truth.y_mm[0], truth.y_mm[-1]]
    vmin, vmax = float(np.nanmin(truth.z_mm)), max(float(np.nanmax(truth.z_mm)), 0.1)
    err = recon.z_mm - truth.z_mm
    emax = max(float(np.nanmax(np.abs(err))) if np.any(np.isfinite(err)) else 0.1, 0.1)
    fig, axes = plt.subplots(1, 3, figsize=(14, 4.4), constrained_layout=True)
    for ax, z, t, cmap, lim in ((axes[0], truth.z_mm, "DEM truth (global z, mm)", "terrain", (vmin, vmax)),
                                (axes[1], recon.z_mm, "reconstruction (mm)", "terrain", (vmin, vmax)),
                                (axes[2], err, "reconstruction - truth (mm)", "RdBu_r", (-emax, emax))):
        im = ax.imshow(z, origin="lower", extent=ext, cmap=cmap, vmin=lim[0], vmax=lim[1], aspect="equal")
        ax.set_title(t)
        ax.set_xlabel("x (mm)")
        fig.colorbar(im, ax=ax, shrink=0.8)
        if centres is not None and ax is axes[1]:
            ax.plot(centres[:, 0], centres[:, 1], "k.-", lw=0.6, ms=3)
    axes[0].set_ylabel("y (mm)")
    fig.suptitle(title)
    from pipeline.io.atomic import savefig_atomic

    try:
        savefig_atomic(fig, path, dpi=110)
    finally:
        plt.close(fig)


def world_panel(path: Path, tmap, results: dict[str, dict]) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.patches import Rectangle

    hm = tmap.height_map(frame="global")
    s = 4
    fig, axes = plt.subplots(2, 1, figsize=(12, 12.5), constrained_layout=True)
    vmin, vmax = -2.0, float(np.max(hm.z_mm))
    ext = [0, 320, 0, 160]
    axes[0].imshow(hm.z_mm[::s, ::s], origin="lower", extent=ext, cmap="terrain", vmin=vmin, vmax=vmax)
    axes[0].set_title("DEM truth, global frame (z = 0 mm at sea level); scanned regions boxed")
    canvas = np.full(hm.z_mm[::s, ::s].shape, np.nan)
    xs, ys = hm.x_mm[::s], hm.y_mm[::s]
    for key, res in results.items():
        rec: HeightMap = res["recon"]
        from scipy.interpolate import RegularGridInterpolator

        jx = np.flatnonzero((xs >= rec.x_mm[0]) & (xs <= rec.x_mm[-1]))
        iy = np.flatnonzero((ys >= rec.y_mm[0]) & (ys <= rec.y_mm[-1]))
        if len(jx) and len(iy):
            f = RegularGridInterpolator((rec.y_mm, rec.x_mm), rec.z_mm, bounds_error=False)
            Y, X = np.meshgrid(ys[iy], xs[jx], indexing="ij")
            v = f(np.column_stack([Y.ravel(), X.ravel()])).reshape(Y.shape)
            sub = canvas[np.ix_(iy, jx)]
            canvas[np.ix_(iy, jx)] = np.where(np.isfinite(v), v, sub)
    axes[1].imshow(np.where(np.isfinite(canvas), np.nan, hm.z_mm[::s, ::s]), origin="lower", extent=ext,
                   cmap="Greys", alpha=0.35, vmin=vmin, vmax=vmax)
    im = axes[1].imshow(canvas, origin="lower", extent=ext, cmap="terrain", vmin=vmin, vmax=vmax)
    axes[1].set_title("tactile reconstruction of the scanned regions")
    for ax in axes:
        for key, res in results.items():
            x0, x1, y0, y1 = res["metrics"]["box_mm"]
            ax.add_patch(Rectangle((x0, y0), x1 - x0, y1 - y0, fill=False, ec="r", lw=1))
            ax.text(x0, y1 + 1, key, color="r", fontsize=7)
        ax.set_xlabel("x (mm)")
        ax.set_ylabel("y (mm)")
    fig.colorbar(im, ax=axes, shrink=0.5, label="z (mm)")
    from pipeline.io.atomic import savefig_atomic

    try:
        savefig_atomic(fig, path, dpi=100)
    finally:
        plt.close(fig)
