"""Independent references for the renderer: where a rendered marker must land, and what it must look like.

The renderer moves every vertex to its apparent position per camera and rasterises flat triangles
(:mod:`twin.render.placement`, :mod:`twin.render.renderer`). Two references check that shortcut without using it:

* :func:`blob_centroids` — the centroids of the bright marker images of a rendered view, to be compared with
  the exact projection of the marker centres (:func:`twin.optics.project_exact`): render versus math;
* :func:`trace_albedo` — a per-pixel ray tracer of whole marker bodies (faces, walls, pin caps and walls, the
  skin underside) with exact vector Snell through the stack, sharing only the photometric constants; rendered
  through the same shading and blur (:func:`traced_window`) it is the image a per-pixel renderer would give,
  and :func:`bright_moments` compares the two windows' centroids and bright mass.

Both are used by ``tests/test_render.py`` (with tolerances derived there) and by ``bench accuracy`` (which
records the figures the README's renderer table is written from).
"""

from __future__ import annotations

import cv2
import numpy as np

from pipeline.design import SensorDesign
from twin.camera import pixels_to_normalised
from twin.optics import FlatStack, project_exact, trace_forward
from twin.render.photometry import BLUR_SIGMA_PX, MARKER_BGR, MARKER_SIDE_BGR, PIN_BGR, SKIN_BGR
from twin.render.scene import marker_rotations

__all__ = ["grey", "blob_centroids", "nearest_offsets", "trace_albedo", "bright_moments", "traced_window",
           "rendered_centre_errors", "trace_picks", "trace_comparison", "displaced_markers"]

#: Blob area range of one marker image (px): markers are ~250 px at the design's 2.54 mm separation; the
#: mount ring and the LED glare are far larger, sensor noise specks far smaller.
MARKER_AREA_PX = (20, 2000)
#: Window of the traced comparison: half-size (px) around the projected centre, blur padding (px) and
#: sub-samples per pixel axis (16 rays a pixel: the 4x MSAA of the render, and finer).
TRACE_HALF_PX, TRACE_PAD_PX, TRACE_SUBSAMPLES = 15, 5, 4


def grey(img) -> np.ndarray:
    """A BGR view as float64 grey levels."""
    return cv2.cvtColor(np.ascontiguousarray(img), cv2.COLOR_BGR2GRAY).astype(np.float64)


def blob_centroids(img, thr: float = 90.0, lo: float = 20.0) -> np.ndarray:
    """Marker centroids (N, 2) px of a rendered view: components above ``thr``; inside a padded box, weights
    clip((I − lo)/(hi − lo)), hi = the blob's 90th percentile (≈ coverage, robust to the smooth LED shading)."""
    g = grey(img)
    n, lab, stats, _ = cv2.connectedComponentsWithStats((g > thr).astype(np.uint8), connectivity=8)
    out = []
    for k in range(1, n):
        if not MARKER_AREA_PX[0] < stats[k, cv2.CC_STAT_AREA] < MARKER_AREA_PX[1]:
            continue
        x0, y0, w, h = stats[k, :4]
        x0, y0 = max(x0 - 3, 0), max(y0 - 3, 0)
        patch = g[y0:y0 + h + 6, x0:x0 + w + 6]
        lp = lab[y0:y0 + h + 6, x0:x0 + w + 6]
        hi = np.percentile(patch[lp == k], 90)
        wgt = np.clip((patch - lo) / (hi - lo), 0.0, 1.0) * ((lp == k) | (lp == 0))
        ys, xs = np.mgrid[y0:y0 + patch.shape[0], x0:x0 + patch.shape[1]]
        out.append([(wgt * xs).sum() / wgt.sum(), (wgt * ys).sum() / wgt.sum()])
    return np.array(out).reshape(-1, 2)


def nearest_offsets(found: np.ndarray, truth: np.ndarray) -> np.ndarray:
    """For each true point, the offset of the nearest found centroid (N, 2)."""
    d = np.linalg.norm(found[:, None] - truth[None], axis=2)
    return found[d.argmin(axis=0)] - truth


def displaced_markers(design: SensorDesign, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """The design's rest markers moved up to 0.4 mm sideways and 0.8 mm in depth, pins tilted up to ~14°:
    marker centres (N, 3) mm and unit pin axes (N, 3), as a deformed skin places them."""
    P = design.rest_markers_mm()
    n = len(P)
    P = P + np.column_stack([rng.uniform(-0.4, 0.4, (n, 2)), rng.uniform(-0.8, 0.8, n)])
    A = np.column_stack([rng.uniform(-0.18, 0.18, (n, 2)), -np.ones(n)])
    return P, A / np.linalg.norm(A, axis=1, keepdims=True)


def _inside(uv: np.ndarray, width: int, height: int, margin: float = 12) -> np.ndarray:
    return (uv[:, 0] > margin) & (uv[:, 0] < width - 1 - margin) & (uv[:, 1] > margin) & (uv[:, 1] < height - 1 - margin)


def rendered_centre_errors(frame, design: SensorDesign, P: np.ndarray) -> dict[str, dict]:
    """Compare, per view of a rendered stereo ``frame``, the blob centroids with the exact projection of the
    bright dots' centres ``P`` (mm; markers, or a board's printed dots) that lie inside the view:
    {side: {"errors_px": per dot inside, the distance to the nearest centroid; "found": centroids;
    "expected": dots inside}}."""
    w, h = design.cameras.width_px, design.cameras.height_px
    out = {}
    for side, img in (("left", frame.left), ("right", frame.right)):
        truth = project_exact(P, design, side)
        ok = _inside(truth, w, h)
        found = blob_centroids(img)
        err = np.linalg.norm(nearest_offsets(found, truth[ok]), axis=1) if len(found) else np.full(ok.sum(), np.inf)
        out[side] = {"errors_px": err, "found": len(found), "expected": int(ok.sum())}
    return out


def trace_albedo(design: SensorDesign, side: str, uv: np.ndarray, P: np.ndarray, A: np.ndarray) -> np.ndarray:
    """BGR albedo seen along each pixel ray (N, 3): exact vector Snell through the stack, then the first
    hit among marker faces, marker walls, pin caps and pin walls of markers P (axes A), else the skin."""
    d = design
    pose = d.camera_poses()[side]
    cam = getattr(d.cameras, side)
    n = pixels_to_normalised(uv, cam.K, cam.D)
    d_air = np.column_stack([n, np.ones(len(n))]) @ pose[:3, :3].T
    stack = FlatStack.from_design(d)
    o, dg = trace_forward(pose[:3, 3], d_air, stack, d.gel_acrylic_z_mm + 1e-9)
    r, t = d.markers.diameter_mm / 2.0, d.markers.thickness_mm
    rp, Hp = d.pins.diameter_mm / 2.0, d.pins.height_mm
    best = np.full(len(o), np.inf)
    colour = np.tile(np.array(SKIN_BGR), (len(o), 1))
    # skin underside (flat, z = −T)
    s_skin = (-d.skin.thickness_mm - o[:, 2]) / dg[:, 2]
    best = np.minimum(best, s_skin)
    rot = marker_rotations(A)
    for m in range(len(P)):
        lo = (o - P[m]) @ rot[m]                     # R^T (o − P): local frame, rest axis (0, 0, −1)
        ld = dg @ rot[m]

        def consider(s, mask, bgr):
            take = mask & (s > 0) & (s < best)
            best[take] = s[take]
            colour[take] = bgr

        def plane(z0, rmax, bgr):
            with np.errstate(divide="ignore", invalid="ignore"):
                s = (z0 - lo[:, 2]) / ld[:, 2]
            x = lo[:, :2] + s[:, None] * ld[:, :2]
            consider(s, np.isfinite(s) & (np.sum(x * x, axis=1) <= rmax**2), bgr)

        def wall(rad, z0, z1, bgr):
            a = np.sum(ld[:, :2] ** 2, axis=1)
            b = 2 * np.sum(lo[:, :2] * ld[:, :2], axis=1)
            c = np.sum(lo[:, :2] ** 2, axis=1) - rad**2
            disc = b * b - 4 * a * c
            ok = disc >= 0
            sq = np.sqrt(np.where(ok, disc, 0.0))
            for s in ((-b - sq) / (2 * a), (-b + sq) / (2 * a)):
                z = lo[:, 2] + s * ld[:, 2]
                consider(s, ok & (z >= z0) & (z <= z1), bgr)

        plane(0.0, r, MARKER_BGR)
        wall(r, 0.0, t, MARKER_SIDE_BGR)
        plane(t / 2.0, rp, PIN_BGR)
        wall(rp, t / 2.0, Hp, PIN_BGR)
    return colour


def bright_moments(g: np.ndarray, x0: int, y0: int) -> tuple[np.ndarray, float]:
    """Centroid (x, y) px and bright mass of a grey window whose top-left pixel is (x0, y0), above the median
    of its border (the local background)."""
    bg = np.median(np.concatenate([g[0], g[-1], g[:, 0], g[:, -1]]))
    w = np.clip(g - bg, 0.0, None)
    ys, xs = np.mgrid[y0:y0 + g.shape[0], x0:x0 + g.shape[1]]
    return np.array([(w * xs).sum() / w.sum(), (w * ys).sum() / w.sum()]), float(w.sum())


def traced_window(renderer, design: SensorDesign, side: str, x0: int, y0: int, size: int, P: np.ndarray,
                  A: np.ndarray, near: np.ndarray) -> np.ndarray:
    """The ray-traced reference of a ``size``-px square window at (x0, y0) of view ``side``: markers ``near``
    traced with :data:`TRACE_SUBSAMPLES`² rays a pixel, shaded by the renderer's LED map and blurred like it,
    as 8-bit BGR."""
    ss = TRACE_SUBSAMPLES
    sub = (np.arange(ss) + 0.5) / ss - 0.5
    U, V = np.meshgrid(np.arange(x0, x0 + size), np.arange(y0, y0 + size))
    su = (U[..., None, None] + sub[None, None, None, :]).repeat(ss, axis=2)
    sv = (V[..., None, None] + sub[None, None, :, None]).repeat(ss, axis=3)
    uv = np.column_stack([su.ravel(), sv.ravel()])
    alb = trace_albedo(design, side, uv, P[near], A[near]).reshape(size, size, ss * ss, 3).mean(axis=2)
    shade = renderer.shading_map(side)
    syn = (255.0 * alb * shade[y0:y0 + size, x0:x0 + size, None]).astype(np.float32)
    syn = cv2.GaussianBlur(syn, (0, 0), BLUR_SIGMA_PX)
    return np.clip(syn + 0.5, 0, 255).astype(np.uint8)


def trace_picks(design: SensorDesign) -> list[int]:
    """The markers whose windows :func:`trace_comparison` checks: the centre marker, one half-way out, the
    first marker and one on the outer ring (the most oblique view)."""
    layers = design.marker_layers()
    outer = design.pattern.layers - 1
    return [int(np.argmax(layers == 0)), int(np.argmax(layers == outer // 2)), 0,
            min(int(np.argmax(layers == outer)) + 9, len(layers) - 1)]


def trace_comparison(renderer, design: SensorDesign, P: np.ndarray, A: np.ndarray,
                     picks: list[int]) -> list[dict]:
    """Render markers ``P`` (axes ``A``) once and compare, for each marker in ``picks`` and each view where its
    window lies inside the image, the rendered window with the ray-traced one: rows of {side, marker,
    centroid_offset_px, mass_ratio} (rendered over traced)."""
    frame = renderer.render_markers(P, A)
    w, h = design.cameras.width_px, design.cameras.height_px
    half, pad = TRACE_HALF_PX, TRACE_PAD_PX
    size = 2 * (half + pad) + 1
    rows = []
    for side, img in (("left", frame.left), ("right", frame.right)):
        truth = project_exact(P, design, side)
        for m in picks:
            cu, cv = np.round(truth[m]).astype(int)
            x0, y0 = cu - half - pad, cv - half - pad
            if x0 < 0 or y0 < 0 or x0 + size > w or y0 + size > h:
                continue
            near = np.argsort(np.linalg.norm(P[:, :2] - P[m, :2], axis=1))[:7]
            ref = traced_window(renderer, design, side, x0, y0, size, P, A, near)
            sl = np.s_[pad:-pad, pad:-pad]
            c_ref, m_ref = bright_moments(grey(ref)[sl], x0 + pad, y0 + pad)
            c_got, m_got = bright_moments(grey(img[y0:y0 + size, x0:x0 + size])[sl], x0 + pad, y0 + pad)
            rows.append({"side": side, "marker": int(m), "centroid_offset_px": float(np.linalg.norm(c_got - c_ref)),
                         "mass_ratio": float(m_got / m_ref)})
    return rows
