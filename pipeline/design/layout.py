"""Marker patterns: the x-y layout of every marker, in the canonical (id) order."""

from __future__ import annotations

import functools
import math

import numpy as np

from pipeline.design.schema import DesignError, Pattern


def _canonical_ring_order(xy: np.ndarray) -> np.ndarray:
    """Indices ordering one ring CCW from the marker nearest polar angle 0 about its centroid."""
    c = xy.mean(axis=0)
    ang = np.arctan2(xy[:, 1] - c[1], xy[:, 0] - c[0])
    start = int(np.argmin(np.abs(ang)))
    ang_from_start = np.mod(ang - ang[start], 2 * np.pi)
    return np.argsort(ang_from_start, kind="stable")


def marker_layout(pattern: Pattern) -> tuple[np.ndarray, np.ndarray]:
    """Marker x-y positions (N, 2) mm and layer indices (N,) in canonical order.

    hexagon: hexagonal lattice, layer k holds 6k markers (127 for 7 layers);
    circular: layer k holds 6k markers on a circle of radius k·separation (217 for 9 layers);
    square: square lattice, layer k is the square ring of 8k markers (121 for 6 layers).
    Computed once per pattern (the runner asks for it on every frame: 1.5 ms a call); callers get copies.
    """
    xy, layers = _marker_layout(pattern)
    return xy.copy(), layers.copy()


@functools.lru_cache(maxsize=64)
def _marker_layout(pattern: Pattern) -> tuple[np.ndarray, np.ndarray]:
    s = pattern.separation_mm
    m = pattern.layers
    rings: list[np.ndarray] = []
    for k in range(m):
        if k == 0:
            rings.append(np.zeros((1, 2)))
            continue
        if pattern.kind == "hexagon":
            corners = [np.array([math.cos(math.radians(60 * i)), math.sin(math.radians(60 * i))]) * k * s
                       for i in range(6)]
            pts = []
            for i in range(6):
                a, b = corners[i], corners[(i + 1) % 6]
                for j in range(k):
                    pts.append(a + (b - a) * j / k)
            ring = np.array(pts)
        elif pattern.kind == "circular":
            n = 6 * k
            t = 2 * np.pi * np.arange(n) / n
            ring = np.column_stack([np.cos(t), np.sin(t)]) * k * s
        elif pattern.kind == "square":
            pts = [(i, j) for i in range(-k, k + 1) for j in range(-k, k + 1) if max(abs(i), abs(j)) == k]
            ring = np.array(pts, dtype=np.float64) * s
        else:  # validated earlier
            raise DesignError(f"unknown pattern kind {pattern.kind!r}")
        rings.append(ring[_canonical_ring_order(ring)])
    xy = np.concatenate(rings[::-1])
    layers = np.concatenate([np.full(len(r), k) for k, r in reversed(list(enumerate(rings)))])
    xy[np.abs(xy) < 1e-12] = 0.0
    return xy, layers.astype(np.int64)


def analytic_pattern_radius_mm(pattern: Pattern) -> float:
    """Distance of the outermost marker from the centre, computed without building the layout:
    hexagon and circular rings have their outermost markers at (layers - 1)·separation, the square
    ring's corners at √2 times that."""
    r = (pattern.layers - 1) * pattern.separation_mm
    return r * math.sqrt(2.0) if pattern.kind == "square" else r
