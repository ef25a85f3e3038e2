"""Where the skin's vertex contacts cannot hold a rigid indenter out, and the spheres that do.

The skin's outer surface is a triangle mesh with vertices ``fine_mm`` apart. Each free outer vertex
carries a contact sphere against the indenter's height field, which keeps the *vertices* out. Between
vertices the skin is a flat triangle, and a convex part of the indenter with curvature ``κ`` (a tip, a
crest) pokes through a triangle of edge ``L`` by up to its chord sag ``κ L² / 8``: 0.28 mm on a σ² = 10
Gaussian cap under a 2.1 mm cell diagonal, 2 mm on the σ² = 5/3 tip. Steep flanks add a second path:
a vertex sphere pushed sideways slips through the height field's vertical prism walls.

So the indenter also carries small spheres on its own surface, wherever the vertex contacts are not
enough, and these collide with the skin's outer *triangles* (a 2-D flex over the outer faces, with no
stiffness of its own): a face is then held out by the sphere under it, wherever on the face that is.

Placement (indenter's own frame, contact face up, height ``h(x, y)``):

* **convex regions** — where the larger principal curvature of the cap, ``κ = −λ_min(∇²h)``, exceeds
  ``κ_c = 8 · SAG_TOL_MM / L²`` (``L``: the skin cell's diagonal): the chord sag there would exceed
  ``SAG_TOL_MM``. The sphere spacing follows the curvature, ``s = sqrt(8 · SAG_TOL_MM / κ)`` clipped to
  ``[SPACING_MIN_MM, SPACING_MAX_MM]``, so a flat face lying on neighbouring spheres is within
  ``SAG_TOL_MM`` of the surface between them; spacings are snapped to a few nested grids.
* **steep flanks** — slope above ``STEEP_SLOPE`` (45°), at ``STEEP_SPACING_MM``.

Each sphere touches the surface from inside: centre ``p − r n`` (``n`` the outward unit normal at
``p``), radius ``r = SPHERE_RADIUS_MM``. The radius is larger than the skin's worst chord sag under
the σ² = 10 cap, so when a press starts with faces already through the surface (the direct solve's
warm start places vertices, not faces, on the indenter) the faces still lie on the outer side of the
sphere centres and are pushed out, not pulled through (r = 0.15 mm: a σ² = 10 direct solve ended with a
face 0.44 mm inside; r = 0.4 mm: 0.015 mm). Where the tip is sharper than the sphere (σ² = 5/3: tip
radius 0.33 mm), the envelope of the spheres stands proud of the true surface by ``d²/2 (1/R − 1/r)``
at distance ``d`` from the sphere's contact point: ≤ 0.003 mm at half the 0.2 mm spacing.
A sphere standing proud by more than ``PROUD_TOL_MM`` elsewhere (a part much sharper than it: a crest
of a short sine, a terrain peak from the 0.2 mm relief raster) is replaced by the largest of
``SHARP_RADII_MM`` that does not: lowering the 0.4 mm sphere instead left a 2π/5 sine's crests 0.14 mm above
the spheres (smaller spheres: 0.07 mm) and a terrain tap's peak 0.16 mm, a skin face 0.2 mm inside it.
"""

from __future__ import annotations

import math

import numpy as np

from twin.indenters import Indenter

__all__ = ["SAG_TOL_MM", "SPHERE_RADIUS_MM", "EDGE_RADIUS_MM", "surface_spheres"]

SAG_TOL_MM = 0.02          # a skin face may sag this far into a convex part before spheres are added there
SPHERE_RADIUS_MM = 0.4     # see the module notes (tunnelling from a warm start vs standing proud of a sharp tip)
SPACING_MIN_MM = 0.2       # = the collision height field's cell
SPACING_MAX_MM = 1.0       # never sparser than this where spheres are needed
STEEP_SLOPE = 1.0          # flanks steeper than 45 deg
STEEP_SPACING_MM = 0.4
MAX_SPHERES = 40000        # contact budget (see surface_spheres)
_LEVELS_MM = (0.2, 0.3, 0.4, 0.6, 0.8, 1.0)   # nested sphere grids (each a multiple of the 0.1 mm base grid)
_BASE_MM = 0.1
PROUD_TOL_MM = 0.01        # a sphere standing proud of the true surface by more than this is lowered until it does
                           # not (a sphere on a cliff of a letter, normal nearly horizontal, stood 0.375 mm above the
                           # letter's flat top and held the skin off it); the Gaussians' curved tips stay within 0.003
CLIFF_SLOPE = 5.0          # walls steeper than 79 deg (a letter's extruded sides, a coastline step of the terrain
                           # relief: 1.5 mm over one 0.2 mm raster cell, slope 7.5, which at 10 got none and was cut
                           # 0.18 mm deep by a face; the steepest Gaussian and sine flanks are below 3.2) get edge
                           # spheres along their top
EDGE_RADIUS_MM = 0.25      # edge spheres: radius r, each placed as low as it can while every surface point within
EDGE_COVER_MM = 0.1        # this of its centre (horizontally) lies inside it, so the sharp top edge of a cliff is
                           # inside the union of spheres and a skin face lying on them cannot cut it; they stand at
                           # most r - sqrt(r^2 - cover^2) = 0.021 mm proud of the flat top beside the edge, and only
                           # centres under the surface are kept (none hangs in front of the wall). A sphere
                           # tangent to both top and wall (r = 0.4 as elsewhere) rounds the edge off and a face
                           # crossing it sags 0.2-0.3 mm into the letter (vertically); r = 0.1 is tunnelled by faces
                           # lagging 0.05-0.08 mm in contact (G at 1 mm: 0.49 mm inside)
EDGE_SPACING_MM = 0.1      # <= cover * sqrt 2: the cover discs of the grid overlap
SHARP_RADII_MM = (0.3, 0.25, 0.2)   # smaller spheres tried, largest first, where a SPHERE_RADIUS_MM one stands proud
_FINE_MM = 0.025           # sampling of the true surface around a sphere (the letters' raster is 0.05 mm)


def _derivatives(ind: Indenter, spacing_mm: float):
    x, y, z = ind.grid(spacing_mm)
    hy, hx = np.gradient(z, spacing_mm, spacing_mm)
    hyy, hyx = np.gradient(hy, spacing_mm, spacing_mm)
    hxy, hxx = np.gradient(hx, spacing_mm, spacing_mm)
    hxy = 0.5 * (hxy + hyx)
    tr, det = hxx + hyy, hxx * hyy - hxy * hxy
    lam_min = 0.5 * tr - np.sqrt(np.maximum(0.25 * tr * tr - det, 0.0))
    return x, y, z, hx, hy, -lam_min


def _snap(need: np.ndarray) -> np.ndarray:
    """Points to keep: each point's required spacing snapped down to a level of nested grids, the point
    kept when it lies on that level's grid; spacings beyond the coarsest level use multiples of it."""
    iy, ix = np.indices(need.shape)
    keep = np.zeros(need.shape, bool)
    levels = list(_LEVELS_MM)
    top = float(np.nanmax(np.where(np.isfinite(need), need, 0.0))) if np.isfinite(need).any() else 0.0
    while levels[-1] * 1.5 <= top:
        levels.append(levels[-1] * 1.5)
    for k, s in enumerate(levels):
        step = max(1, int(round(s / _BASE_MM)))
        upper = levels[k + 1] if k + 1 < len(levels) else np.inf
        band = (need >= (s if k else 0.0)) & (need < upper) & np.isfinite(need)
        keep |= band & (ix % step == 0) & (iy % step == 0)
    return keep


def surface_spheres(ind: Indenter, *, skin_cell_mm: float, radius_mm: float = SPHERE_RADIUS_MM,
                    sag_tol_mm: float = SAG_TOL_MM, max_spheres: int | None = None, with_radii: bool = False):
    """Sphere centres ``(K, 3)`` (indenter's own frame, mm) for an indenter pressed into a skin whose
    outer cells are ``skin_cell_mm`` square (see the module notes); empty where vertex contacts suffice
    (a flat plate, a wide gentle bump). ``with_radii``: ``(centres, radii (K,))``, the spheres along the top
    of cliffs being smaller (``EDGE_RADIUS_MM``) than the others (``radius_mm``)."""
    max_spheres = MAX_SPHERES if max_spheres is None else int(max_spheres)
    L = math.sqrt(2.0) * float(skin_cell_mm)
    kappa_c = 8.0 * sag_tol_mm / (L * L)
    x, y, z, hx, hy, kappa = _derivatives(ind, _BASE_MM)
    ok = np.isfinite(z) & np.isfinite(kappa)
    need = np.full(z.shape, np.inf)                      # required spacing (inf: no sphere needed)
    convex = ok & (kappa > kappa_c)
    need[convex] = np.clip(np.sqrt(8.0 * sag_tol_mm / kappa[convex]), SPACING_MIN_MM, SPACING_MAX_MM)
    steep = ok & (np.hypot(hx, hy) > STEEP_SLOPE)
    need[steep] = np.minimum(need[steep], STEEP_SPACING_MM)
    keep = _snap(need)
    # contact budget: every sphere under a face in contact is one more constraint. With the faces next to
    # the clamped rim left out of face contact (twin.mesh) and the smaller spheres on sharp crests, every
    # sine of the paper presses 5 mm with all its spheres and no MuJoCo warning (measured, hexagon61_sep354:
    # pi/5 12,726 spheres 0.057 mm inside, with 3,000 1.49 mm; 4 pi/15 17,334, 0.052 mm, with 15,386
    # 0.087 mm; 2 pi/5 31,445, 0.021 mm). Beyond the budget all spacings are coarsened together; what is
    # then lost shows in the frame's own penetration check (twin.validity), never silently.
    while keep.sum() > max_spheres and np.isfinite(need).any():
        need = np.where(np.isfinite(need), need * 1.25, need)
        keep = _snap(need)
    X, Y = np.meshgrid(x, y)
    n = np.stack([-hx, -hy, np.ones_like(z)], axis=-1)
    n /= np.linalg.norm(n, axis=-1, keepdims=True)
    p = np.stack([X, Y, z], axis=-1)
    P, N = p[keep], n[keep]
    centres = P - radius_mm * N
    radii = np.full(len(centres), float(radius_mm))
    if len(centres):
        proud = _proud_mm(ind, centres, radius_mm)
        # a part sharper than the sphere (a terrain peak, a crest of a short sine): a smaller sphere at the
        # same point, the largest that does not stand proud (else the smallest, lowered below); cliffs
        # have their own edge spheres
        sharp = (proud > PROUD_TOL_MM) & (np.hypot(hx, hy)[keep] <= CLIFF_SLOPE)
        for r_s in [r for r in SHARP_RADII_MM if r < radius_mm]:
            idx = np.nonzero(sharp)[0]
            if not len(idx):
                break
            c_s = P[idx] - r_s * N[idx]
            pr = _proud_mm(ind, c_s, r_s)
            take = (pr <= PROUD_TOL_MM) | ((r_s == min(SHARP_RADII_MM)) & (pr < proud[idx]))
            centres[idx[take]], radii[idx[take]], proud[idx[take]] = c_s[take], r_s, pr[take]
            sharp[idx[pr <= PROUD_TOL_MM]] = False
        lower = proud > PROUD_TOL_MM
        centres[lower, 2] -= proud[lower]
    # cliffs, and crests sharper than the smallest sphere (a one-cell ridge of the terrain raster): where even
    # the smallest sphere stands proud and is lowered, a face lying on the spheres would be cut by the crest
    # (English Channel tap: 0.11 mm), so their tops get edge spheres
    crest = ok & (kappa > 1.0 / min(SHARP_RADII_MM))
    cliff = ok & ((np.hypot(hx, hy) > CLIFF_SLOPE) | crest)
    if cliff.any():
        edge = _edge_spheres(ind, X, Y, cliff)
        centres = np.vstack([centres, edge])
        radii = np.concatenate([radii, np.full(len(edge), EDGE_RADIUS_MM)])
    return (centres, radii) if with_radii else centres


def _disc_offsets(radius_mm: float, step_mm: float = _FINE_MM) -> np.ndarray:
    k = np.arange(-math.floor(radius_mm / step_mm), math.floor(radius_mm / step_mm) + 1) * step_mm
    dx, dy = np.meshgrid(k, k)
    inside = np.hypot(dx, dy) <= radius_mm + 1e-12
    return np.column_stack([dx[inside], dy[inside]])


def _surface_in_discs(ind: Indenter, xy: np.ndarray, off: np.ndarray, chunk: int = 500) -> np.ndarray:
    """True surface height (K, M) at ``xy[k] + off[m]``; NaN off the part."""
    out = np.empty((len(xy), len(off)))
    for i in range(0, len(xy), chunk):
        q = xy[i:i + chunk, None, :] + off[None, :, :]
        out[i:i + chunk] = ind.height(q[..., 0], q[..., 1])
    return out


def _proud_mm(ind: Indenter, centres: np.ndarray, radius_mm: float) -> np.ndarray:
    """How far each sphere reaches above the true surface (mm, >= 0), sampled at ``_FINE_MM``."""
    off = _disc_offsets(radius_mm)
    cap = np.sqrt(np.maximum(radius_mm ** 2 - np.sum(off ** 2, axis=1), 0.0))
    h = _surface_in_discs(ind, centres[:, :2], off)
    above = centres[:, 2:3] + cap[None, :] - h
    above = np.where(np.isfinite(above), above, -np.inf)
    return np.maximum(above.max(axis=1), 0.0)


def _edge_spheres(ind: Indenter, X: np.ndarray, Y: np.ndarray, cliff: np.ndarray,
                  radius_mm: float = EDGE_RADIUS_MM) -> np.ndarray:
    """Spheres along the top edges of cliffs (see ``EDGE_RADIUS_MM``): centres on an ``EDGE_SPACING_MM`` grid
    over the cliff cells and their neighbours, each as low as it can be while the true surface within
    ``EDGE_COVER_MM`` of it (horizontally) lies inside it; only centres below the surface at their own x-y."""
    from scipy.ndimage import binary_dilation

    step = max(1, int(round(EDGE_SPACING_MM / _BASE_MM)))
    band = binary_dilation(cliff, iterations=max(1, step))
    iy, ix = np.indices(band.shape)
    band &= (ix % step == 0) & (iy % step == 0)
    xy = np.column_stack([X[band], Y[band]])
    off = _disc_offsets(EDGE_COVER_MM)
    cap = np.sqrt(np.maximum(radius_mm ** 2 - np.sum(off ** 2, axis=1), 0.0))
    h = _surface_in_discs(ind, xy, off)
    zc = np.where(np.isfinite(h), h - cap[None, :], -np.inf).max(axis=1)
    ok = np.isfinite(zc) & (ind.height(xy[:, 0], xy[:, 1]) >= zc)
    return np.column_stack([xy[ok], zc[ok]])
