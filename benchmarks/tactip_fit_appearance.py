"""Stage 5 of fitting a TacTip twin (:mod:`benchmarks.tactip_fit`): the twin's appearance (background and
marker grey, radial marker shading, marker size and pixel noise) from the real frames' image statistics, by
three fixed-point passes on twin renders measured with the same detector.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np

from pipeline.design import SensorDesign
from pipeline.vision.detection import detect_markers
from pipeline.vision.tactip_id import frame_stats
from twin.tactip import render_frame
from benchmarks.tactip_fit_skin import _search_set

if TYPE_CHECKING:
    from benchmarks.tactip_fit import FitContext

__all__ = ["fit_appearance"]


def fit_appearance(ctx: FitContext, design: SensorDesign, twin: dict) -> tuple[dict, dict]:
    from benchmarks.tactip_fit import apply_params     # here: benchmarks.tactip_fit imports this module

    twin = dict(twin)
    pick = _search_set(ctx)[:4]
    real = [frame_stats(ctx.greys[i], ctx.blobs[i]) for i in pick]
    target = {k: float(np.median([s[k] for s in real])) for k in ("radius_px", "contrast", "background", "noise")}
    # radial shading: real marker core brightness against the squared normalised image radius
    cam = design.camera
    vals, rho2 = [], []
    for i in pick:
        g = ctx.greys[i].astype(np.float64)
        for u, v in ctx.blobs[i].xy_px:
            vals.append(g[int(round(v)) - 1:int(round(v)) + 2, int(round(u)) - 1:int(round(u)) + 2].mean())
            rho2.append(((u - cam.cx_px) ** 2 + (v - cam.cy_px) ** 2) / (0.5 * cam.height_px) ** 2)
    A = np.column_stack([np.ones(len(rho2)), rho2])
    a0, a1 = np.linalg.lstsq(A, np.asarray(vals), rcond=None)[0]
    twin["marker_shading"] = float(a1 / a0) if a0 > 0 else 0.0
    twin["background_grey"] = target["background"]
    twin["marker_grey"] = float(np.clip(a0, 1, 255))
    twin["noise_grey"] = max(target["noise"], 0.0)
    history = []
    for _ in range(3):
        d = apply_params(design, twin=twin)
        sims = []
        for i in pick:
            p, ax = ctx.tap(i, twin)
            img = render_frame(d, p, ax, seed=i)
            sims.append(frame_stats(img, detect_markers(img)))
        got = {k: float(np.median([s[k] for s in sims if s[k] is not None])) for k in target}
        history.append(got)
        twin["marker_scale"] = float(np.clip(twin["marker_scale"] * target["radius_px"] / got["radius_px"], 0.3, 3.0))
        twin["marker_grey"] = float(np.clip(twin["marker_grey"] + (target["contrast"] - got["contrast"]), 1, 255))
        twin["background_grey"] = float(np.clip(twin["background_grey"] + (target["background"] - got["background"]), 0, 255))
        if got["noise"] > 0:
            twin["noise_grey"] = float(max(twin["noise_grey"] * target["noise"] / got["noise"], 0.0))
    return twin, {"real": target, "twin_passes": history}
