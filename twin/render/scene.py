"""Scene building: the meshes of one view in the sensor frame (mm), before any refraction.

Marker discs on dark pins, the dark skin underside, the mount ring with its four LEDs (skin module), or a
chessboard / printed marker board (skin-less). Every builder returns plain ``(vertices, faces)`` arrays;
:mod:`twin.render.placement` moves the vertices to where each camera sees them and
:class:`twin.render.renderer.StereoRenderer` uploads them.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from pipeline.design import SensorDesign
from twin.gl import RenderError
from twin.render.photometry import (BOARD_BLACK_BGR, BOARD_WHITE_BGR, LED_BGR, MARKER_BGR, MOUNT_BGR, SKIN_BGR,
                                    led_positions)

MOUNT_OUTER_RADIUS_MM = 45.0
DISC_SECTIONS = 16                       # polygon sides of a marker disc (centroid exact by symmetry)
# The polygon's radius is scaled so that its AREA equals the disc's (an inscribed 16-gon would lose 2.5 %
# of the bright area); its outline then stays within +1.3 % / −0.7 % of the circle (≤ 0.12 px at r ≈ 9 px).
DISC_AREA_RADIUS_FACTOR = math.sqrt(2.0 * math.pi / (DISC_SECTIONS * math.sin(2.0 * math.pi / DISC_SECTIONS)))
PIN_SECTIONS = 8                         # dark pins on the dark skin: only their silhouette next to the disc
# Closed, outward-wound shells: their far half is hidden behind their near half (or the disc face), so
# GL back-face culling skips it (half the rasterised wall and pin triangles).
CULLED_MESHES = frozenset({"marker_wall", "pins"})

Mesh = tuple[np.ndarray, np.ndarray]


@dataclass(frozen=True)
class ChessboardSpec:
    """A printed chessboard: ``squares`` (columns, rows) of ``square_mm``, white margin ``margin_mm``.

    Board frame: origin at the board centre, x along the columns, y along the rows, printed face in the
    plane z = 0 facing −z (toward the cameras when the board's rotation is the identity). Square
    (column c, row r) is black when c + r is even (all four corner squares black for odd × odd).
    """

    squares: tuple[int, int] = (9, 7)
    square_mm: float = 4.0
    margin_mm: float = 4.0

    def __post_init__(self) -> None:
        if min(self.squares) < 2 or self.square_mm <= 0 or self.margin_mm < 0:
            raise RenderError(f"ChessboardSpec: need >= 2x2 squares of positive size and margin >= 0, got "
                              f"{self.squares}, {self.square_mm} mm, {self.margin_mm} mm")


def chessboard_corners_mm(spec: ChessboardSpec = ChessboardSpec()) -> np.ndarray:
    """Inner corners of the chessboard in its board frame, ((cols-1)*(rows-1), 3) mm, row-major from −x, −y."""
    cols, rows = spec.squares
    s = spec.square_mm
    x = (np.arange(1, cols) - cols / 2.0) * s
    y = (np.arange(1, rows) - rows / 2.0) * s
    X, Y = np.meshgrid(x, y)
    return np.column_stack([X.ravel(), Y.ravel(), np.zeros(X.size)])


def marker_rotations(axis: np.ndarray) -> np.ndarray:
    """Rotations (N, 3, 3) taking the rest pin direction (0, 0, −1) to each unit ``axis`` (minimal angle)."""
    a = np.asarray(axis, dtype=np.float64).reshape(-1, 3)
    norm = np.linalg.norm(a, axis=1, keepdims=True)
    if np.any(norm < 1e-9):
        raise RenderError("marker_axis: contains zero vectors")
    a = a / norm
    a0 = np.array([0.0, 0.0, -1.0])
    v = np.cross(a0, a)                        # (N, 3)
    c = a @ a0                                 # (N,)
    if np.any(c <= -1.0 + 1e-9):
        raise RenderError("marker_axis: a pin points straight out of the skin (+z); not physical")
    vx = np.zeros((len(a), 3, 3))
    vx[:, 0, 1], vx[:, 0, 2] = -v[:, 2], v[:, 1]
    vx[:, 1, 0], vx[:, 1, 2] = v[:, 2], -v[:, 0]
    vx[:, 2, 0], vx[:, 2, 1] = -v[:, 1], v[:, 0]
    return np.eye(3)[None] + vx + (vx @ vx) / (1.0 + c)[:, None, None]


# ----- mesh templates (local coordinates, mm) ---------------------------------------------------

def _cylinder(radius: float, z0: float, z1: float, sections: int, *, cap0: bool = True,
              cap1: bool = True) -> Mesh:
    """Cylinder along z from z0 to z1 with optional end caps: vertices (2S+2, 3), faces (2S..4S, 3)."""
    ang = np.arange(sections) * (2 * np.pi / sections)
    ring = np.column_stack([radius * np.cos(ang), radius * np.sin(ang)])
    v = np.vstack([np.column_stack([ring, np.full(sections, z0)]), np.column_stack([ring, np.full(sections, z1)]),
                   [[0.0, 0.0, z0], [0.0, 0.0, z1]]])
    i = np.arange(sections)
    j = (i + 1) % sections
    c0, c1 = 2 * sections, 2 * sections + 1
    parts = [np.column_stack([i, j, sections + j]), np.column_stack([i, sections + j, sections + i])]
    if cap0:
        parts.append(np.column_stack([np.full(sections, c0), j, i]))
    if cap1:
        parts.append(np.column_stack([np.full(sections, c1), sections + i, sections + j]))
    return v, np.vstack(parts)


def _disc(radius: float, sections: int) -> Mesh:
    """Flat disc in z = 0: vertices (S+1, 3) (centre last), fan faces (S, 3)."""
    ang = np.arange(sections) * (2 * np.pi / sections)
    v = np.vstack([np.column_stack([radius * np.cos(ang), radius * np.sin(ang), np.zeros(sections)]), [[0, 0, 0]]])
    i = np.arange(sections)
    return v, np.column_stack([np.full(sections, sections), i, (i + 1) % sections])


def _polar_faces(shape: tuple[int, int]) -> np.ndarray:
    """Two triangles per cell of a (rings, angles) vertex grid that wraps around in angle."""
    idx = np.arange(shape[0] * shape[1]).reshape(shape)
    a, b = idx[:-1], idx[1:]
    a1, b1 = np.roll(a, -1, axis=1), np.roll(b, -1, axis=1)
    return np.vstack([np.column_stack([a.ravel(), b.ravel(), b1.ravel()]),
                      np.column_stack([a.ravel(), b1.ravel(), a1.ravel()])])


def _annulus(r0: float, r1: float, n_radial: int, n_angular: int) -> Mesh:
    """Polar grid between radii r0 (may be 0) and r1 in z = 0."""
    r = np.linspace(r0, r1, n_radial + 1)
    ang = np.arange(n_angular) * (2 * np.pi / n_angular)
    R, A = np.meshgrid(r, ang, indexing="ij")
    v = np.column_stack([(R * np.cos(A)).ravel(), (R * np.sin(A)).ravel(), np.zeros(R.size)])
    return v, _polar_faces(R.shape)


def _grid_quad(x0: float, x1: float, y0: float, y1: float, n: int) -> Mesh:
    """Rectangle in z = 0 split into n x n quads (for per-vertex refraction of large faces)."""
    xs, ys = np.linspace(x0, x1, n + 1), np.linspace(y0, y1, n + 1)
    X, Y = np.meshgrid(xs, ys, indexing="ij")
    v = np.column_stack([X.ravel(), Y.ravel(), np.zeros(X.size)])
    idx = np.arange(X.size).reshape(X.shape)
    a, b, c, d = idx[:-1, :-1], idx[1:, :-1], idx[1:, 1:], idx[:-1, 1:]
    faces = np.vstack([np.column_stack([a.ravel(), b.ravel(), c.ravel()]),
                       np.column_stack([a.ravel(), c.ravel(), d.ravel()])])
    return v, faces


def _tube(radius: float, z0: float, z1: float, n_z: int, n_angular: int) -> Mesh:
    """Open cylinder wall of ``radius`` from z0 to z1, split into n_z rings (per-vertex refraction)."""
    z = np.linspace(z0, z1, n_z + 1)
    ang = np.arange(n_angular) * (2 * np.pi / n_angular)
    Z, A = np.meshgrid(z, ang, indexing="ij")
    v = np.column_stack([(radius * np.cos(A)).ravel(), (radius * np.sin(A)).ravel(), Z.ravel()])
    return v, _polar_faces(Z.shape)


def _merge(parts: list[Mesh]) -> Mesh:
    verts, faces, off = [], [], 0
    for v, f in parts:
        verts.append(v)
        faces.append(f + off)
        off += len(v)
    return np.vstack(verts), np.vstack(faces)


def _tile(v: np.ndarray, f: np.ndarray, n: int) -> np.ndarray:
    """Faces of n copies of a template with V vertices each."""
    return (f[None, :, :] + (np.arange(n) * len(v))[:, None, None]).reshape(-1, 3)


# ----- the skin module ------------------------------------------------------------------------

def module_meshes(design: SensorDesign) -> dict[str, tuple[np.ndarray, np.ndarray, tuple]]:
    """The parts of the skin module that do not move: ``{name: (vertices, faces, bgr)}``.

    ``mount`` (ring on the acrylic + its inner wall around the gel), ``leds`` (in air, under the
    acrylic) and ``skin_flat`` (the undeformed skin underside, drawn when no skin mesh is given).
    """
    d = design
    # the mount is one colour: its tessellation only has to follow the refracted edges (96 segments:
    # chord sag 0.01 mm at the gel rim) and keep the apparent surface's depth, not shade anything
    ring_v, ring_f = _annulus(d.gel.radius_mm, MOUNT_OUTER_RADIUS_MM, 3, 96)
    ring_v[:, 2] = d.gel_acrylic_z_mm - 1e-3         # rests on the acrylic, seen through it
    wall_v, wall_f = _tube(d.gel.radius_mm, d.gel_acrylic_z_mm, -d.skin.thickness_mm, 4, 96)
    mount_v, mount_f = _merge([(ring_v, ring_f), (wall_v, wall_f)])   # + its inner wall around the gel
    led_parts = []
    for L in led_positions(d):
        v, f = _disc(1.5, 16)
        led_parts.append((v + L, f))
    led_v, led_f = _merge(led_parts)
    skin_v, skin_f = _annulus(0.0, d.gel.radius_mm, 20, 96)
    skin_v[:, 2] = -d.skin.thickness_mm
    return {"mount": (mount_v, mount_f, MOUNT_BGR), "leds": (led_v, led_f, LED_BGR),
            "skin_flat": (skin_v, skin_f, SKIN_BGR)}


def marker_template(design: SensorDesign, n: int) -> dict[str, Mesh]:
    """Local vertices and tiled faces of n markers: face disc, its wall, the pin."""
    d = design
    t = d.markers.thickness_mm
    r = d.markers.diameter_mm / 2.0 * DISC_AREA_RADIUS_FACTOR
    wall_v, wall_f = _tube(r, 0.0, t, 1, DISC_SECTIONS)
    parts = {"marker_face": _disc(r, DISC_SECTIONS),                     # the face, z = 0
             "marker_wall": (wall_v, wall_f[:, ::-1]),                   # outward-wound, like the pin
             # the pin is wider than the disc: its cap inside the disc's thickness hides part of the wall
             "pins": _cylinder(d.pins.diameter_mm / 2.0, t / 2.0, d.pins.height_mm, PIN_SECTIONS, cap1=False)}
    return {name: (v, _tile(v, f, n).astype(np.uint32)) for name, (v, f) in parts.items()}


def place_markers(template: dict[str, Mesh], P: np.ndarray, R: np.ndarray) -> dict[str, Mesh]:
    """The template's markers at face centres ``P`` (N, 3) turned by ``R`` (N, 3, 3): sensor-frame meshes."""
    parts = {}
    for name, (v, f) in template.items():
        world = (P[:, None, :] + np.einsum("nij,vj->nvi", R, v)).reshape(-1, 3)
        parts[name] = (world, f)
    return parts


def skin_underside(vertices_mm, faces, thickness_mm: float) -> Mesh:
    """Underside of the skin: outer vertices moved by the thickness against their area-weighted normals."""
    v = np.asarray(vertices_mm, dtype=np.float64)
    f = np.asarray(faces)
    if v.ndim != 2 or v.shape[1] != 3 or not np.all(np.isfinite(v)):
        raise RenderError(f"skin_vertices_mm: expected a finite (V, 3) array, got shape {v.shape}")
    if f.ndim != 2 or f.shape[1] != 3 or f.dtype.kind not in "iu" or (f.size and (f.min() < 0 or f.max() >= len(v))):
        raise RenderError(f"skin_faces: expected (F, 3) integer indices into the {len(v)} skin vertices")
    fn = np.cross(v[f[:, 1]] - v[f[:, 0]], v[f[:, 2]] - v[f[:, 0]])
    vn = np.zeros_like(v)
    for k in range(3):
        np.add.at(vn, f[:, k], fn)
    if np.sum(vn[:, 2]) < 0:
        vn = -vn
    norm = np.linalg.norm(vn, axis=1, keepdims=True)
    vn = np.where(norm > 0, vn / np.maximum(norm, 1e-300), np.array([0.0, 0.0, 1.0]))
    return v - thickness_mm * vn, f.astype(np.uint32)


# ----- skin-less boards ---------------------------------------------------------------------

def _chessboard_meshes(spec: ChessboardSpec, subdiv: int) -> tuple[Mesh, Mesh]:
    """(black, white) meshes of the board in its frame (z = 0 face, -z facing).

    The board is one grid of cells (margin strips included) whose break lines are shared by every
    cell, so neighbouring quads have identical edge vertices: no T-junctions, hence no cracks or
    doubly-covered samples whose colour would depend on the (unordered) draw order.
    """
    cols, rows = spec.squares
    s, m = spec.square_mm, spec.margin_mm
    xb = (np.arange(cols + 1) - cols / 2.0) * s
    yb = (np.arange(rows + 1) - rows / 2.0) * s
    if m > 0:
        xb = np.concatenate([[xb[0] - m], xb, [xb[-1] + m]])
        yb = np.concatenate([[yb[0] - m], yb, [yb[-1] + m]])
    off = 1 if m > 0 else 0
    black, white = [], []
    for i in range(len(xb) - 1):
        for j in range(len(yb) - 1):
            c, r = i - off, j - off
            q = _grid_quad(xb[i], xb[i + 1], yb[j], yb[j + 1], subdiv)
            is_square = 0 <= c < cols and 0 <= r < rows
            (black if is_square and (c + r) % 2 == 0 else white).append(q)
    return _merge(black), _merge(white)


def board_meshes(kind: str, board_design, design: SensorDesign, *,
                 through_stack: bool) -> dict[str, tuple[np.ndarray, np.ndarray, tuple]]:
    """``{name: (vertices, faces, bgr)}`` of a board in its own frame (see ``StereoRenderer.render_board``)."""
    if kind == "chessboard":
        spec = board_design if board_design is not None else ChessboardSpec()
        if not isinstance(spec, ChessboardSpec):
            raise RenderError(f"board_design: a chessboard needs a ChessboardSpec, got {type(spec).__name__}")
        (bv, bf), (wv, wf) = _chessboard_meshes(spec, subdiv=4 if through_stack else 1)
        return {"chess_black": (bv, bf, BOARD_BLACK_BGR), "chess_white": (wv, wf, BOARD_WHITE_BGR)}
    if kind == "marker_board":
        bd = board_design if board_design is not None else design
        if not isinstance(bd, SensorDesign):
            raise RenderError(f"board_design: a marker board needs a SensorDesign, got {type(bd).__name__}")
        xy = bd.rest_markers_mm()[:, :2]
        dv, df = _disc(bd.markers.diameter_mm / 2.0, DISC_SECTIONS)
        dots_v = (np.column_stack([xy, np.zeros(len(xy))])[:, None, :] + dv[None]).reshape(-1, 3)
        back_v, back_f = _annulus(0.0, bd.gel.radius_mm, 24, 128)
        back_v[:, 2] = 0.02                              # just behind the printed face
        return {"mboard_dots": (dots_v, _tile(dv, df, len(xy)), MARKER_BGR),
                "mboard_back": (back_v, back_f, BOARD_BLACK_BGR)}
    raise RenderError(f"kind: expected 'chessboard' or 'marker_board', got {kind!r}")
