"""The README's ``physics-checks`` block: the twin's contact mechanics against published solutions, written from
one ``bench physics`` record (:mod:`benchmarks.experiments.physics`).

Every row is read from the record's tables (``force_depth``: one row per case and depth; ``cases``: each case's
ν and mesh; ``convergence``: one row per mesh resolution), whatever cases, depths and resolutions the run pressed;
the targets are the experiment's own tolerances and each verdict is computed here from the rows:

* uniform gel against the bonded-layer Hertz solution, one row per mesh, at the gel's ν (other ν beside it):
  met when the FE / theory ratio is within ``FORCE_TOL`` at every depth;
* a symmetric press, one row per mesh the design was pressed on: met when the centre marker's sideways motion
  and the mirrored markers' disagreement stay within ``SYMMETRY_TOL_MM`` at every depth;
* mesh convergence: met when the production mesh is within ``CONVERGENCE_TOL_MM`` of the finest on marker
  positions and the marker differences shrink as the mesh is refined.
"""

from __future__ import annotations

from typing import Any, Iterable, Mapping

import numpy as np

from benchmarks.readme_render import Records, _provenance
from benchmarks.results import ResultsError

__all__ = ["physics_checks_markdown"]

#: MeshSpec fields that do not say which mesh a case was pressed on (the case table's own columns)
_CASE_KEYS = ("case", "nu", "uniform")


def _verdict(met: bool) -> str:
    return "met" if met else "**not met**"


def _span(values: Iterable[float], digits: int = 2) -> str:
    """``lo–hi`` of the values (one value if they agree to the digits shown)."""
    v = list(values)
    lo, hi = f"{min(v):.{digits}f}", f"{max(v):.{digits}f}"
    return lo if lo == hi else f"{lo}–{hi}"


def _mm(value: float) -> str:
    return f"{value:.2g}" if abs(value) < 0.01 else f"{value:.3g}"


def _depths(rows: list[dict]) -> str:
    d = [r["depth_mm"] for r in rows]
    return f"{min(d):g}–{max(d):g} mm" if min(d) != max(d) else f"{d[0]:g} mm"


def _levels(levels: Iterable[float]) -> str:
    return ", ".join(f"{g:g}" for g in levels)


def mesh_words(spec: Mapping[str, Any]) -> str:
    """A case's mesh (its MeshSpec fields in the record) in the README's words."""
    words = [f"{spec['fine_mm']:g} mm mesh"]
    if spec.get("core_mm"):
        words.append(f"{spec['core_mm']:g} mm cells within {spec['core_half_mm']:g} mm of the axis")
    words.append("mirrored split" if spec.get("mirrored_split") else "one split direction")
    if spec.get("face_contact"):
        words.append("face contact")
    if spec.get("volumetric", "element") != "element":
        words.append(f"{spec['volumetric']} volumetric stiffness")
    words.append(f"gel levels {_levels(spec['gel_levels_mm'])} mm")
    return ", ".join(words)


def _mesh_key(spec: Mapping[str, Any]) -> tuple:
    return tuple(sorted((k, str(v)) for k, v in spec.items() if k not in _CASE_KEYS))


def _uniform_rows(rows: list[dict], cases: list[dict], nu_gel: float, h_mm: float, tol: float) -> list[tuple]:
    """One row per mesh the uniform gel was pressed on at the gel's ν; the other ν on that mesh beside it."""
    out = []
    uniform = [c for c in cases if c["uniform"]]
    for k, c in enumerate(c for c in uniform if np.isclose(c["nu"], nu_gel)):
        mine = [r for r in rows if r["case"] == c["case"]]
        if not mine:
            continue
        ratios = [r["ratio"] for r in mine]
        measured = [f"FE / theory {_span(ratios)} (median {np.median(ratios):.2f}) at ν = {c['nu']:g}"]
        for o in uniform:
            if o is not c and _mesh_key(o) == _mesh_key(c) and not np.isclose(o["nu"], nu_gel):
                other = [r["ratio"] for r in rows if r["case"] == o["case"]]
                if other:
                    measured.append(f"{_span(other)} at ν = {o['nu']:g}")
        if all("press_s" in r for r in mine):
            measured.append(f"{np.median([r['press_s'] for r in mine]):.2g} s a press")
        chi = [r["chi"] for r in mine]
        what = (f"uniform gel (skin and pins given the gel's material) on the {mesh_words(c)}: force vs Hertz with "
                f"the bonded-layer correction of Dimitriadis et al. 2002 (h = {h_mm:g} mm, χ = {_span(chi)})" if not k
                else f"the same on the {mesh_words(c)}")
        met = all(abs(x - 1) <= tol for x in ratios)
        out.append((what, f"within {tol:.0%} at every depth".replace("%", " %"), "; ".join(measured), _verdict(met)))
    return out


def _contact_row(rows: list[dict], cases: list[dict], nu_gel: float) -> tuple | None:
    """Contact radius over √(Rδ) of the uniform gel at the gel's ν, per mesh."""
    parts = []
    for c in cases:
        if not (c["uniform"] and np.isclose(c["nu"], nu_gel)):
            continue
        cr = [r["contact_radius_mm"] / r["hertz_radius_mm"] for r in rows
              if r["case"] == c["case"] and r["contact_radius_mm"] > 0]
        if cr:
            parts.append(f"{mesh_words(c)}: median {np.median(cr):.2f} ({_span(cr)})")
    if not parts:
        return None
    return ("contact radius (outermost skin vertex on the sphere) vs √(Rδ), uniform gel at ν = "
            f"{nu_gel:g}", "— (resolution: the mesh spacing)", "; ".join(parts), "")


def _symmetry_rows(rows: list[dict], cases: list[dict], tol_mm: float) -> list[tuple]:
    """One row per mesh the design was pressed on: centre marker sideways and mirrored markers' disagreement."""
    out = []
    for c in (c for c in cases if not c["uniform"]):
        first = not out
        mine = sorted((r for r in rows if r["case"] == c["case"]), key=lambda r: r["depth_mm"])
        if not mine or "centre_lateral_mm" not in mine[0]:
            continue
        deep = mine[-1]
        wc, wm = (max(mine, key=lambda r: r[k]) for k in ("centre_lateral_mm", "mirror_disagreement_mm"))
        centre, mirror = wc["centre_lateral_mm"], wm["mirror_disagreement_mm"]
        depths = _depths(mine)
        valid = sum(bool(r["valid"]) for r in mine)
        measured = (f"{_mm(deep['centre_lateral_mm'])} / {_mm(deep['mirror_disagreement_mm'])} mm at "
                    f"{deep['depth_mm']:g} mm; worst over {depths}: {_mm(centre)} mm (at {wc['depth_mm']:g} mm) / "
                    f"{_mm(mirror)} mm (at {wm['depth_mm']:g} mm); {valid} of "
                    f"{len(mine)} frames valid, skin ≤ {_mm(max(r['penetration_max_mm'] for r in mine))} mm inside")
        what = (f"symmetric press, the design on the {mesh_words(c)}: centre marker sideways / mirrored markers' "
                "disagreement" if first else f"the same on the {mesh_words(c)}")
        out.append((what, f"≤ {tol_mm:g} mm at every depth", measured,
                    _verdict(centre <= tol_mm and mirror <= tol_mm)))
    return out


def _production(conv: list[dict], production_mm: float) -> tuple[list[dict], dict]:
    """The convergence rows coarsest first (the finest last) and the production mesh's row among them."""
    conv = sorted(conv, key=lambda c: -c["fine_mm"])
    return conv, next((c for c in conv if np.isclose(c["fine_mm"], production_mm)), conv[0])


def _convergence_row(conv: list[dict], production_mm: float, tol_mm: float) -> tuple | None:
    """The design pressed on each resolution against the finest: markers, force and face-level penetration."""
    if len(conv) < 2:
        return None
    conv, prod = _production(conv, production_mm)
    finest, others = conv[-1], conv[:-1]
    diffs = [c["marker_diff_vs_finest_mm"] for c in others]
    shrinking = all(a >= b for a, b in zip(diffs, diffs[1:]))
    depth = f" at {finest['depth_mm']:g} mm" if "depth_mm" in finest else ""
    what = (f"mesh convergence, the design{depth}: " + " / ".join(f"{c['fine_mm']:g}" for c in others)
            + f" mm vs {finest['fine_mm']:g} mm in-plane (gel levels "
            + "; ".join(f"{_levels(c['gel_levels_mm'])}" for c in conv) + " mm)")
    target = (f"production ({production_mm:g} mm) within {tol_mm:g} mm of the finest on markers, differences "
              "shrinking")
    force = [f"{(c['force_n'] - finest['force_n']) / finest['force_n']:+.0%}".replace("%", " %") for c in others]
    measured = f"markers {' / '.join(_mm(d) for d in diffs)} mm"
    if all("pin_base_diff_vs_finest_mm" in c for c in others):     # records before the split have the sum only
        measured += (f" (pin bases {' / '.join(_mm(c['pin_base_diff_vs_finest_mm']) for c in others)} mm, pin tilt "
                     f"× height {' / '.join(_mm(c['pin_tilt_diff_vs_finest_mm']) for c in others)} mm)")
    measured += (f", force {' / '.join(force)}, face-level penetration "
                 + " / ".join(_mm(c["penetration_max_mm"]) for c in conv) + " mm")
    if len(others) < 2:
        measured += " (one resolution besides the finest: shrinking is not tested)"
    converged = prod["marker_diff_vs_finest_mm"] <= tol_mm
    verdict = ("" if len(others) < 2 else "shrinking, " if shrinking else "**not shrinking**, ") \
        + ("converged" if converged else "**not converged**")
    return what, target, measured, verdict


def _reference_row(conv: list[dict], ref: list[dict], production_mm: float, tol_mm: float,
                   offered: list[dict] = ()) -> tuple | None:
    """The production mesh (and the element-wise finest, and the contact meshes the experiments press) against
    the locking-free reference family's finest."""
    from benchmarks.experiments.physics_reference import REFERENCE_HALF_MM

    if not ref or not conv or "marker_diff_vs_reference_mm" not in conv[0]:
        return None
    conv, prod = _production(conv, production_mm)
    finest = ref[-1]
    what = ("the same against a locking-free refinement: " + " / ".join(f"{r['cells_mm']:g}" for r in ref)
            + f" mm cells out to r = {REFERENCE_HALF_MM:g} mm, {finest['skin_layers']} skin "
            + ("layers" if finest["skin_layers"] != 1 else "layer") + ", gel levels "
            + "; ".join(_levels(r["gel_levels_mm"]) for r in ref) + " mm, nodal volumetric stiffness")
    target = f"production ({production_mm:g} mm) within {tol_mm:g} mm of its finest on markers"
    family = " / ".join(_mm(r["marker_diff_vs_finest_mm"]) for r in ref[:-1])
    measured = (f"production {_mm(prod['marker_diff_vs_reference_mm'])} mm, the element-wise finest "
                f"({conv[-1]['fine_mm']:g} mm) {_mm(conv[-1]['marker_diff_vs_reference_mm'])} mm; force "
                f"{prod['force_n']:.2f} N against {finest['force_n']:.2f} N; "
                + (f"the family {family} mm from its finest " if family else "the finest ")
                + f"({finest['dofs']:,} DOFs, {finest['seconds']:.0f} s a press)")
    others = [r for r in offered if r["mesh"] != "default"]
    if others:
        measured += "; the contact meshes " + ", ".join(
            f"{r['mesh']} {_mm(r['marker_diff_vs_reference_mm'])} mm (RMS {_mm(r['marker_rms_vs_reference_mm'])} mm, "
            f"{r['dofs']:,} DOFs)" for r in others)
    return what, target, measured, _verdict(prod["marker_diff_vs_reference_mm"] <= tol_mm)


def _design_row(rows: list[dict], design: Mapping[str, Any]) -> tuple | None:
    """The design's own force (no closed-form layered solution): range and ratio to the uniform-gel theory."""
    mine = [r for r in rows if r["case"] == "design"]
    if not mine:
        return None
    skin, gel = design.get("skin") or {}, design.get("gel") or {}
    stiffer = (f": {skin.get('material', 'the')} skin {skin['youngs_modulus_mpa'] / gel['youngs_modulus_mpa']:.0f}× "
               "stiffer than the gel" if skin.get("youngs_modulus_mpa") and gel.get("youngs_modulus_mpa") else "")
    return (f"the design ({design.get('name', '')}{stiffer})", "no closed-form reference used",
            f"{_span([r['force_n'] for r in mine])} N over {_depths(mine)} "
            f"({_span([r['ratio'] for r in mine], 1)}× the uniform-gel solution)", "")


def physics_checks_markdown(records: Records, source: str) -> str:
    """The contact-mechanics checks of one ``bench physics`` record as a Markdown table with targets and
    verdicts (the experiment's tolerances: :mod:`benchmarks.experiments.physics`)."""
    from benchmarks.experiments.physics import (CONVERGENCE_TOL_MM, FORCE_TOL, PRODUCTION_FINE_MM,
                                                SYMMETRY_TOL_MM)

    rec = records["physics"]
    tables = rec.get("tables") or {}
    rows, cases, conv = (tables.get(k) or [] for k in ("force_depth", "cases", "convergence"))
    if not rows or not cases:
        raise ResultsError(f"{source}: the physics record has no force_depth and cases tables: rerun "
                           "`stereotactip bench physics`")
    design = rec.get("design") or {}
    gel = design.get("gel") or {}
    nu_gel = float(gel.get("poisson_ratio", cases[0]["nu"]))
    h_mm = float((design.get("skin") or {}).get("thickness_mm", 0)
                 + (design.get("optics") or {}).get("gel_thickness_mm", 0))
    radius = np.median([r["hertz_radius_mm"] ** 2 / r["depth_mm"] for r in rows])
    table = _uniform_rows(rows, cases, nu_gel, h_mm, FORCE_TOL)
    table += [r for r in (_contact_row(rows, cases, nu_gel),) if r]
    table += _symmetry_rows(rows, cases, SYMMETRY_TOL_MM)
    table += [r for r in (_convergence_row(conv, PRODUCTION_FINE_MM, CONVERGENCE_TOL_MM),
                          _reference_row(conv, tables.get("reference_family") or [], PRODUCTION_FINE_MM,
                                         CONVERGENCE_TOL_MM, tables.get("reference_meshes") or []),
                          _design_row(rows, design)) if r]
    lines = [f"Contact-mechanics checks from the {_provenance(rec, source)}: a rigid sphere (R = {radius:.3g} mm) "
             f"pressed {_depths(rows)} on the axis, E_gel = {gel.get('youngs_modulus_mpa', 0) * 1000:g} "
             f"kPa, ν = {nu_gel:g} (design file; an estimate):", "",
             "| check | target | measured | |", "| --- | --- | --- | --- |"]
    lines += [f"| {what} | {target} | {measured} | {verdict} |" for what, target, measured, verdict in table]
    return "\n".join(lines)
