"""physics: the design's convergence press against a locking-free reference family (full runs only).

The convergence study of :mod:`benchmarks.experiments.physics` refines the production mesh element by element:
its meshes lock (linear tetrahedra as ν → 0.5, one tetrahedron through the stiff skin in bending), so they
converge towards a stiffer answer than the material's (at a 2 mm sphere press 2.7 → 2.1 N from 2 to 1 mm cells,
1.8 N at 0.75 mm with two skin layers). The reference family removes both locks at once: cells of 1.5, 1.0 and
0.75 mm out to :data:`REFERENCE_HALF_MM` (beyond the pattern's outermost marker, where the production meshes grow
coarser), the gel refined through its thickness, two tetrahedra through the skin and the bulk stiffness on
averaged nodal volumes (``MeshSpec(volumetric="nodal")``, :mod:`twin.volumetric`). Its finest member is the
reference the production mesh's markers are measured against; its own differences say how well the reference
itself is converged.

The meshes the twin presses the experiments on (``simulate --mesh default|axis|sine``, ``twin.mesh.NAMED_MESHES``; ``face`` has the default's cells; :data:`OFFERED_MESHES`) are
measured against the same finest member (:func:`offered_meshes`): the error a user inherits from the mesh they pick.
"""

from __future__ import annotations

from typing import Callable

import numpy as np

REFERENCE_HALF_MM = 16.0   # the family's cells reach this far from the axis: beyond hexagon127's outermost marker
REFERENCE_FAMILY = ((1.5, 2, (0.75, 1.5, 2.5, 4.0, 6.0)), (1.0, 2, (0.75, 1.5, 2.5, 4.0, 6.0)),
                    (0.75, 2, (0.5, 1.0, 1.75, 2.5, 4.0, 6.0)))    # (cells mm, skin layers, gel levels mm)
OFFERED_MESHES = ("axis", "sine")   # besides the default (the convergence study's production row), pressed in turn



def reference_family(design, family, depth_mm: float, press: Callable, bar) -> list[dict]:
    """The design pressed to ``depth_mm`` on each member of ``family`` (coarsest first) with ``press`` (the
    physics experiment's ``_press_series``); each row holds its markers and its difference from the finest."""
    from twin.physics import MeshSpec

    rows = []
    for cells, layers, levels in family:
        spec = MeshSpec(fine_mm=float(cells), fine_half_mm=REFERENCE_HALF_MM, skin_layers=int(layers),
                        gel_levels_mm=tuple(float(v) for v in levels), volumetric="nodal")
        res, secs, sim = press(design, [depth_mm], spec)
        _, force, truth, _, _ = res[0]
        rows.append({"cells_mm": float(cells), "skin_layers": int(layers), "gel_levels_mm": [float(v) for v in levels],
                     "dofs": int(sim.model.nv), "force_n": float(force), "seconds": float(secs),
                     "penetration_max_mm": truth.validity["penetration_max_mm"], "markers": truth.marker_xyz_mm})
        bar.update()
    for r in rows:
        r["marker_diff_vs_finest_mm"] = marker_diff_mm(r["markers"], rows[-1]["markers"])
    return rows


def offered_meshes(design, names, depth_mm: float, press: Callable, bar, prod: dict, finest: dict) -> list[dict]:
    """The default mesh (``prod``, already pressed) and each named mesh pressed as the family was, each row with
    its markers' largest and RMS distance from the family's finest (``finest``)."""
    from twin.physics import NAMED_MESHES

    rows = [{"mesh": "default", "dofs": prod["dofs"], "force_n": prod["force_n"], "markers": prod["markers"],
             "seconds": prod["seconds"], "penetration_max_mm": prod["penetration_max_mm"]}]
    for name in names:
        res, secs, sim = press(design, [depth_mm], NAMED_MESHES[name])
        _, force, truth, _, _ = res[0]
        rows.append({"mesh": name, "dofs": int(sim.model.nv), "force_n": float(force), "markers": truth.marker_xyz_mm,
                     "seconds": float(secs), "penetration_max_mm": truth.validity["penetration_max_mm"]})
        bar.update()
    for r in rows:
        d = _marker_distances_mm(r.pop("markers"), finest["markers"])
        r["marker_diff_vs_reference_mm"] = float(d.max())
        r["marker_rms_vs_reference_mm"] = float(np.sqrt(np.mean(d * d)))
    return rows


def _marker_distances_mm(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Distance (mm) between each marker's positions in two presses."""
    return np.linalg.norm(np.asarray(a) - np.asarray(b), axis=1)


def marker_diff_mm(a: np.ndarray, b: np.ndarray) -> float:
    """Largest distance (mm) between the same markers in two presses."""
    return float(np.max(_marker_distances_mm(a, b)))


def report(out, conv: list[dict], prod: dict, ref: list[dict], offered: list[dict] = ()) -> None:
    """Metrics and tables: the production mesh, the element-wise finest and the offered meshes against the
    family's finest."""
    finest = ref[-1]
    out.metric("convergence_marker_vs_reference_mm", marker_diff_mm(prod["markers"], finest["markers"]), "mm")
    out.metric("convergence_finest_vs_reference_mm", marker_diff_mm(conv[-1]["markers"], finest["markers"]), "mm")
    out.metric("reference_marker_diff_mm", ref[-2]["marker_diff_vs_finest_mm"] if len(ref) > 1 else float("nan"), "mm")
    out.metric("reference_force_n", finest["force_n"], "N")
    for c in conv:
        c["marker_diff_vs_reference_mm"] = marker_diff_mm(c["markers"], finest["markers"])
    out.tables["reference_family"] = [{k: v for k, v in r.items() if k != "markers"} for r in ref]
    for r in offered:
        if r["mesh"] != "default":
            out.metric(f"{r['mesh']}_mesh_marker_vs_reference_mm", r["marker_diff_vs_reference_mm"], "mm")
    if offered:
        out.tables["reference_meshes"] = list(offered)
