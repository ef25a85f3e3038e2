"""Drawing helpers (OpenCV) for detection and DTRC results: markers, mesh, coloured rings, ids."""

from __future__ import annotations

import cv2
import numpy as np

from pipeline.vision.dtrc import RingCoding
from pipeline.types import Blobs

__all__ = ["ring_colour", "draw_blobs", "draw_mesh", "draw_coding", "annotate_view"]

_SHIFT = 4  # sub-pixel drawing: coordinates scaled by 2**_SHIFT
_S = 1 << _SHIFT


def _pt(xy) -> tuple[int, int]:
    return int(round(float(xy[0]) * _S)), int(round(float(xy[1]) * _S))


def ring_colour(ring: int) -> tuple[int, int, int]:
    """A distinct BGR colour per ring index (HSV wheel, golden-angle steps)."""
    hue = int((ring * 0.381966 * 180) % 180)
    hsv = np.uint8([[[hue, 230, 255]]])
    b, g, r = cv2.cvtColor(hsv, cv2.COLOR_HSV2BGR)[0, 0]
    return int(b), int(g), int(r)


def _bgr(image: np.ndarray) -> np.ndarray:
    if image.ndim == 2:
        return cv2.cvtColor(image, cv2.COLOR_GRAY2BGR)
    return np.ascontiguousarray(image).copy()


def draw_blobs(image: np.ndarray, blobs: Blobs, colour=(0, 0, 255)) -> np.ndarray:
    """Circles of radius sqrt(2) sigma at each blob centre; returns a BGR copy."""
    out = _bgr(image)
    for xy, s in zip(blobs.xy_px, blobs.sigma_px):
        cv2.circle(out, _pt(xy), int(round(np.sqrt(2) * s * _S)), colour, 1, cv2.LINE_AA, _SHIFT)
    return out


def draw_mesh(image: np.ndarray, xy_px: np.ndarray, edges: np.ndarray, colour=(90, 90, 90)) -> np.ndarray:
    """Mesh edges (E, 2) between points ``xy_px`` (N, 2); draws in place on a BGR image and returns it."""
    for a, b in edges:
        cv2.line(image, _pt(xy_px[a]), _pt(xy_px[b]), colour, 1, cv2.LINE_AA, _SHIFT)
    return image


def draw_coding(image: np.ndarray, blobs: Blobs, coding: RingCoding, *, ids: bool = True) -> np.ndarray:
    """Rings in colour (closed polylines in coding order), uncoded blobs as red crosses, ids as text."""
    xy = blobs.xy_px
    for r in range(len(coding.ring_sizes_found)):
        members = np.nonzero(coding.ring == r)[0]
        if len(members) == 0:
            continue
        c = xy[members].mean(axis=0)
        o = members[np.argsort(np.arctan2(xy[members, 1] - c[1], xy[members, 0] - c[0]))]
        col = ring_colour(r)
        if len(o) > 1:
            poly = np.round(xy[o] * _S).astype(np.int32).reshape(-1, 1, 2)
            cv2.polylines(image, [poly], True, col, 1, cv2.LINE_AA, _SHIFT)
        for k in o:
            cv2.circle(image, _pt(xy[k]), 2 * _S, col, -1, cv2.LINE_AA, _SHIFT)
    for k in np.nonzero(coding.ids < 0)[0]:
        cv2.drawMarker(image, (int(round(xy[k, 0])), int(round(xy[k, 1]))), (0, 0, 255), cv2.MARKER_TILTED_CROSS, 8, 1)
    if ids:
        for k in np.nonzero(coding.ids >= 0)[0]:
            cv2.putText(image, str(int(coding.ids[k])), (int(xy[k, 0]) + 3, int(xy[k, 1]) - 3),
                        cv2.FONT_HERSHEY_PLAIN, 0.6, (255, 255, 255), 1, cv2.LINE_AA)
    return image


def annotate_view(image: np.ndarray, blobs: Blobs, coding: RingCoding | None = None, *,
                  ids: bool = True) -> np.ndarray:
    """Blobs + carved Delaunay mesh + coloured rings + ids on a BGR copy of one view."""
    out = draw_blobs(image, blobs, (0, 0, 255))
    if coding is not None:
        draw_mesh(out, blobs.xy_px, coding.mesh_edges)
        draw_coding(out, blobs, coding, ids=ids)
    return out
