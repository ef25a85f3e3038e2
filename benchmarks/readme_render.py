"""The renderers of the README's generated blocks (:mod:`benchmarks.readme_blocks` names each block, its
record and its markers, and writes it into the README): one function per block, holding the README's wording
next to the record fields it reads, and the number and provenance helpers they share. The error-sources block
is :mod:`benchmarks.readme_error_sources`.
"""

from __future__ import annotations

from typing import Any, Mapping

from benchmarks.report import (_fmt, _md_escape, _verdict, calibration_mode, comparison_table, designs_used,
                               invalid_cells, paper_figures)
from benchmarks.results import ResultsError
from benchmarks.thresholds import bounds_text, check, load_thresholds

__all__ = ["CALIBRATION_METRICS", "Records", "VALIDATE_SUMMARY", "gate_figures_markdown"]

Records = Mapping[str, Mapping[str, Any]]


def _value(rec: Mapping[str, Any], metric: str, digits: int = 3) -> str:
    m = (rec.get("metrics") or {}).get(metric) or {}
    unit = m.get("unit", "")
    return f"{_fmt(m.get('value'), digits)} {unit if unit != '1' else ''}".strip()


def _provenance(rec: Mapping[str, Any], source: str) -> str:
    """Where a block's figures come from: directory, commit, quick or full, calibration mode and seed."""
    mode = (rec.get("calibration") or {}).get("mode", "oracle")
    return (f"`{rec['experiment']}` record in `{source}` (commit {str(rec.get('commit', 'unknown'))[:10]}, "
            f"{'quick' if rec.get('quick') else 'full'} run, calibration {mode}, seed {rec.get('seed')})")


# ----- gate-figures: every metric the CI gate guards ---------------------------------------------

def gate_figures_markdown(records: Records, source: str) -> str:
    """The quick gate's figures as a Markdown table: every metric ``benchmarks/thresholds.toml`` guards, the
    value the records in ``source`` give it, its golden and sanity bounds and whether it passes."""
    thresholds = load_thresholds()
    recs = {n: r for n, r in sorted(records.items()) if r.get("quick")}
    if not recs:
        raise ResultsError(f"{source}: no quick records: the gate figures come from a --quick run")
    commits = sorted({str(r.get("commit", "unknown"))[:10] for r in recs.values()})
    modes = sorted({(r.get("calibration") or {}).get("mode", "oracle") for r in recs.values()})
    violations = {(v.experiment, v.metric) for v in check(recs, thresholds, experiments=list(recs))}
    lines = [f"Quick gate figures from `{source}` (commit {', '.join(commits)}, calibration "
             f"{', '.join(modes)}, seed {', '.join(sorted({str(r.get('seed')) for r in recs.values()}))}):", "",
             "| experiment | metric | this run | golden | sanity | kind | gate |",
             "| --- | --- | --- | --- | --- | --- | --- |"]
    for exp, table in thresholds.items():
        rec = recs.get(exp)
        if rec is None:
            continue
        mode = (rec.get("calibration") or {}).get("mode", "oracle")
        for th in table.values():
            if th.mode is not None and th.mode != mode:
                continue
            m = rec.get("metrics", {}).get(th.metric) or {}
            unit = m.get("unit", "")
            shown = th.metric if th.mode is None else f"{th.metric} ({th.mode})"
            value = f"{_fmt(m.get('value'))} {unit if unit != '1' else ''}".strip()
            golden = bounds_text(th.golden_min, th.golden_max, table=True)
            sanity = bounds_text(th.min, th.max, table=True)
            ok = "**fails**" if (exp, shown) in violations else "passes"
            lines.append(f"| {exp} | {shown} | {value} | {golden} | {sanity} | {th.kind or '—'} | {ok} |")
    return "\n".join(lines)


# ----- quick-experiments / full-suite: one row per experiment of a run ----------------------------------

def _experiments_table(records: Records, source: str, quick: bool) -> str:
    """One row per experiment of a quick (``quick``) or full run: its designs, the twin cells that failed the
    physics checks, and the paper's figures and claims (or the twin's goals) beside this run's, with the
    verdict: the same facts as the report's summary and "Paper figure vs this run" tables, taken from the
    same helpers. A full run's table also gives each experiment's wall time."""
    kind = "quick" if quick else "full"
    recs = {n: r for n, r in sorted(records.items()) if bool(r.get("quick")) == quick}
    if not recs:
        raise ResultsError(f"{source}: no {kind} records: the experiments table comes from a "
                           f"{'--quick ' if quick else ''}run of `stereotactip bench all`")
    commits = sorted({str(r.get("commit", "unknown"))[:10] for r in recs.values()})
    modes = sorted({(r.get("calibration") or {}).get("mode", "oracle") for r in recs.values()})
    seeds = sorted({str(r.get("seed")) for r in recs.values()})
    head = (f"{kind.capitalize()}-run records in `{source}` (commit {', '.join(commits)}, calibration "
            f"{', '.join(modes)}, seed {', '.join(seeds)})")
    if not quick:
        wall = sum(float(r.get("wall_time_s") or 0.0) for r in recs.values())
        head += f", {_minutes(wall)} of experiment wall time in all"
    lines = [head + "; each claim is the paper's (or, for `twin`, the twin's goal), each figure the "
             "experiment's own record:", "",
             "| experiment | designs | " + ("" if quick else "wall time | ") +
             "invalid twin cells | paper / goal | this run | verdict |",
             "| --- | --- | " + ("" if quick else "--- | ") + "--- | --- | --- | --- |"]
    for name, r in recs.items():
        paper, run, verdict = [], [], []
        for metric, value, measured, unit, where in paper_figures(r):
            unit = "" if unit == "1" else f" {unit}"
            paper.append(f"{metric} {value}{unit} ({where})")
            run.append(f"{metric} {measured}{unit}")
            verdict.append("—")
        for f in r.get("findings", []):
            paper.append(f["claim"])
            run.append(f["observed"])
            verdict.append(_verdict(f["agrees"]))
        if r.get("status") != "ok":
            run.append(f"status {r.get('status')}")
        cells = ["<br>".join(_md_escape(x) for x in col) or "—" for col in (paper, run, verdict)]
        wall = "" if quick else f"{_minutes(float(r.get('wall_time_s') or 0.0))} | "
        lines.append(f"| {name} | {_md_escape(designs_used(r))} | {wall}{invalid_cells(r)} | " + " | ".join(cells) + " |")
    return "\n".join(lines)


def _minutes(seconds: float) -> str:
    """A wall time as the README writes it: 42 s, 3 min 05 s."""
    seconds = int(round(seconds))
    return f"{seconds} s" if seconds < 60 else f"{seconds // 60} min {seconds % 60:02d} s"


def _quick_experiments(records: Records, source: str) -> str:
    """One row per experiment of a quick run (:func:`_experiments_table`)."""
    return _experiments_table(records, source, quick=True)


def _full_suite(records: Records, source: str) -> str:
    """One row per experiment of a full run, with its wall time (:func:`_experiments_table`)."""
    return _experiments_table(records, source, quick=False)


# ----- oracle-vs-estimated: the accuracy a user gets ------------------------------------------------

# The figures that show what a user's calibration costs: the markers at rest (patterns), the pressed skin
# (gaussian), the fitted index and depth (refraction), and the experiments that reconstruct through the twin.
CALIBRATION_METRICS: dict[str, tuple[str, ...]] = {
    "patterns": ("localisation_rms_mm_circular", "localisation_rms_mm_hexagon", "localisation_rms_mm_square",
                 "localisation_max_mm", "identity_correct_fraction_min"),
    "gaussian": ("rms_vs_true_skin_mm", "rms_vs_cad_mm", "centre_error_mm_skin050", "centre_error_mm_skin150",
                 "matched_fraction_min"),
    "refraction": ("n_fit", "exact_depth_error_rms_mm", "exact_absolute_error_rms_mm", "linear_depth_error_rms_mm"),
    "tracking": ("dtrc_correct_rate_min", "dtrc_wrong_ids", "nn_correct_rate_min", "nn_wrong_ids"),
    "sine": ("valid_cells", "upper_rms_mm", "lowest_point_rms_mm", "wrong_ids"),
    "terrain": ("rms_err_mm_mean_all", "rms_err_reachable_mm_mean_all", "resolved_fraction_all"),
}


def _oracle_vs_estimated(records: Records, source: str, others: list[tuple[str, Records]]) -> str:
    """The :data:`CALIBRATION_METRICS` of two quick runs side by side (``report DIR --against DIR2``, the report's
    own comparison table): typically DIR run with ``--calibration oracle`` and DIR2 with ``estimated``."""
    [(against_source, against)] = others
    def run(recs: Records, where: str) -> tuple[str, str]:
        chosen = [r for n, r in sorted(recs.items()) if n in CALIBRATION_METRICS]
        if not chosen:
            raise ResultsError(f"{where}: none of the records {', '.join(CALIBRATION_METRICS)}")
        modes = sorted({calibration_mode(r) for r in chosen})
        commits = sorted({str(r.get("commit", "unknown"))[:10] for r in chosen})
        seeds = sorted({str(r.get("seed")) for r in chosen})
        quick = {bool(r.get("quick")) for r in chosen}
        kind = "quick" if quick == {True} else "full" if quick == {False} else "quick and full"
        return " / ".join(modes), (f"{' / '.join(modes)} records in `{where}` (commit {', '.join(commits)}, "
                                   f"{kind}, seed {', '.join(seeds)})")

    mode_a, about_a = run(records, source)
    mode_b, about_b = run(against, against_source)
    table = comparison_table(records, against, CALIBRATION_METRICS, columns=(mode_a, mode_b))
    if not table:
        raise ResultsError(f"{source} and {against_source}: no experiment of {', '.join(CALIBRATION_METRICS)} "
                           "ran in both")
    return "\n".join([f"The {about_a} beside the {about_b}:", ""] + table)


# ----- twin-speed: the twin's headline figures ----------------------------------------------------

def _twin_speed(records: Records, source: str) -> str:
    """Seconds per press, ms per frame, gap and penetration of one ``bench twin`` record against the goals
    :data:`benchmarks.twin_bench.GOALS` (the one place they are set)."""
    from benchmarks.twin_bench import GOALS

    rec = records["twin"]
    metric = lambda name: ((rec.get("metrics") or {}).get(name) or {}).get("value")    # noqa: E731

    def verdict(*pairs: tuple[str, str]) -> str:
        met = [metric(m) is not None and metric(m) <= GOALS[g] for m, g in pairs]
        return "met" if all(met) else "**not met**"

    dofs = metric("mesh_dofs")
    mu = metric("friction")
    pen_goal = f"≤ {GOALS['penetration_max_mm']:g} mm"
    rows = [
        (f"5 mm press to equilibrium on σ² = 10 mm² (default design, {_fmt(dofs)} dofs, μ = {_fmt(mu)}: the path "
         "followed to the captured pose)",
         f"{_value(rec, 'press_s_median')} median",
         f"≤ {GOALS['press_s']:g} s — {verdict(('press_s_median', 'press_s'))}"),
        ("the same press frictionless: the captured pose solved directly / the followed path",
         f"{_value(rec, 'frictionless_direct_press_s')} / {_value(rec, 'followed_press_s')}; markers within "
         f"{_value(rec, 'direct_vs_followed_marker_max_mm')} of each other", "(comparison)"),
        ("rendered stereo frame (flat shading, 640×480 × 2)", f"{_value(rec, 'frame_ms_median')} median",
         f"≤ {GOALS['frame_ms']:g} ms — {verdict(('frame_ms_median', 'frame_ms'))}"),
        ("skin–indenter gap on σ² = 10 mm² (contacting vertices)",
         f"{_value(rec, 'gap_max_mm')} max, {_value(rec, 'gap_rms_mm')} RMS",
         f"≤ {GOALS['gap_max_mm']:g} mm — {verdict(('gap_max_mm', 'gap_max_mm'))}"),
        ("default mesh (1.5 mm, vertex contact): outer skin inside the indenter, face level, σ² = 10 / 5/3",
         f"{_value(rec, 'penetration_max_mm')} (vertices {_value(rec, 'penetration_vertex_max_mm')}) / "
         f"{_value(rec, 'sharp_penetration_max_mm')}; {_value(rec, 'press_s_median')} / {_value(rec, 'sharp_press_s')}",
         f"{pen_goal} — {verdict(('penetration_max_mm', 'penetration_max_mm'), ('sharp_penetration_max_mm', 'penetration_max_mm'))}"),
        ("the same mesh with face contact, σ² = 10 / 5/3",
         f"{_value(rec, 'face_contact_penetration_max_mm')} / {_value(rec, 'face_contact_sharp_penetration_max_mm')} "
         f"inside; apex {_value(rec, 'face_contact_apex_beyond_tip_mm')} beyond the σ² = 10 tip; "
         f"{_value(rec, 'face_contact_press_s')} / {_value(rec, 'face_contact_sharp_press_s')}",
         f"{pen_goal} — {verdict(('face_contact_penetration_max_mm', 'penetration_max_mm'), ('face_contact_sharp_penetration_max_mm', 'penetration_max_mm'))}; "
         f"≤ {GOALS['face_contact_press_s']:g} / {GOALS['face_contact_sharp_press_s']:g} s — "
         f"{verdict(('face_contact_press_s', 'face_contact_press_s'), ('face_contact_sharp_press_s', 'face_contact_sharp_press_s'))}"),
        ("the axis contact mesh (0.5 mm core, mirrored split, face contact), σ² = 10 / 5/3",
         f"{_value(rec, 'axis_mesh_penetration_max_mm')} / {_value(rec, 'axis_mesh_sharp_penetration_max_mm')} "
         f"inside; apex {_value(rec, 'axis_mesh_apex_beyond_tip_mm')} beyond the σ² = 10 tip; "
         f"{_value(rec, 'axis_mesh_press_s')} / {_value(rec, 'axis_mesh_sharp_press_s')}",
         f"{pen_goal} — {verdict(('axis_mesh_penetration_max_mm', 'penetration_max_mm'), ('axis_mesh_sharp_penetration_max_mm', 'penetration_max_mm'))}; "
         f"≤ {GOALS['axis_mesh_press_s']:g} / {GOALS['axis_mesh_sharp_press_s']:g} s — "
         f"{verdict(('axis_mesh_press_s', 'axis_mesh_press_s'), ('axis_mesh_sharp_press_s', 'axis_mesh_sharp_press_s'))}"),
    ]
    lines = [f"Twin figures from the {_provenance(rec, source)}; speed is this machine's (2 shared cores):", "",
             "| what | measured | goal |", "| --- | --- | --- |"]
    lines += [f"| {what} | {measured} | {goal} |" for what, measured, goal in rows]
    return "\n".join(lines)


# ----- identification-coverage: coverage per condition and pattern --------------------------------

# The README's words for the benchmark's conditions (benchmarks.experiments.identification.CONDITIONS).
_CONDITION_LABELS = {
    "defects_0": "clean", "defects_1": "1 % missing + 1 % spurious", "defects_3": "3 % + 3 %",
    "defects_5": "5 % + 5 %", "defects_10": "10 % + 10 %", "occlusion_15": "contiguous 15 % patch occluded",
    "occlusion_15_rest": "the same patch in a first frame read from rest (±2°)",
    "jitter_30": "centre jitter 0.3 separations", "rotation_30": "turned ±30°",
    "press_stereo": "Gaussian press 1–5 mm, stereo, 3 % + 3 % per view",
    "press_first_frame": "the same press read as a sequence's first frame (ring coding, the rest pattern, ±2°)",
    "twin_sequence": "the twin's presses from rest, frame by frame, stereo, 3 % + 3 % per view and frame",
}
_DESIGN_LABELS = {"hexagon61_sep354": "hex 61", "hexagon127": "hex 127", "hexagon217_sep180": "hex 217",
                  "square121": "sq 121", "circular217_dome": "circ 217"}


def _identification_coverage(records: Records, source: str) -> str:
    """Wrong ids and mean coverage per condition (rows) and pattern (columns) of one ``bench identification``
    record's ``conditions`` table."""
    rec = records["identification"]
    rows = (rec.get("tables") or {}).get("conditions") or []
    if not rows:
        raise ResultsError(f"{source}: the identification record has no conditions table")
    designs = list(dict.fromkeys(r["design"] for r in rows))
    conditions = [c for c in _CONDITION_LABELS if any(r["condition"] == c for r in rows)]
    conditions += [c for c in dict.fromkeys(r["condition"] for r in rows) if c not in conditions]
    cell = {(r["condition"], r["design"]): r for r in rows}
    trials = sorted({int(r["trials"]) for r in rows})
    lines = [f"Identification from the {_provenance(rec, source)}: {', '.join(map(str, trials))} seeded trials per "
             f"condition and pattern, {sum(int(r['trials']) for r in rows):,} in all; coverage = present markers "
             "given their correct id, mean over trials:", "",
             "| condition | wrong ids | " + " | ".join(_DESIGN_LABELS.get(d, d) for d in designs) + " |",
             "| --- | --- | " + " | ".join("---" for _ in designs) + " |"]
    for c in conditions:
        cov = [f"{100 * cell[c, d]['coverage_mean']:.2f} %" if (c, d) in cell else "—" for d in designs]
        wrong = sum(int(cell[c, d]["wrong_ids"]) for d in designs if (c, d) in cell)
        lines.append(f"| {_CONDITION_LABELS.get(c, c)} | {wrong} | " + " | ".join(cov) + " |")
    return "\n".join(lines)


_LETTER_MOTIONS = {"G": "rest; pressed 1, 2, 3 mm", "e": "rest; 3 mm, then slid 1 and 2 mm",
                   "o": "rest; touch, then a rapid 2 mm + 2 mm diagonal"}


def _tracking_identity(records: Records, source: str) -> str:
    """Per letter of one ``bench tracking`` record: DTRC's and nearest neighbour's correct-id rates and wrong ids,
    the largest lateral marker step between frames, and the frames that failed the twin's physics checks."""
    rec = records["tracking"]
    rows = (rec.get("tables") or {}).get("per_frame") or []
    if not rows:
        raise ResultsError(f"{source}: the tracking record has no per_frame table")
    letters = list(dict.fromkeys(r["letter"] for r in rows))
    mu = ((rec.get("metrics") or {}).get("friction") or {}).get("value")
    lines = [f"Tracking from the {_provenance(rec, source)}; skin/letter friction μ = {_fmt(mu)}; a frame's id is "
             "correct when the nearest true marker has it within half a separation:", "",
             "| letter | motion | frames (invalid) | DTRC correct rate, wrong ids | nearest neighbour correct rate, "
             "wrong ids | largest lateral marker step |", "| --- | --- | --- | --- | --- | --- |"]
    def rate(rs) -> str:      # one tracker's frames of one letter: worst correct rate, wrong ids in all
        return (f"{_fmt(min(r['correct_rate'] for r in rs))} (worst frame), {sum(int(r['wrong']) for r in rs)}"
                if rs else "—")

    for ch in letters:
        dtrc, nn = ([r for r in rows if r["letter"] == ch and r["tracker"] == t] for t in ("dtrc", "nn"))
        invalid = sum(1 for r in dtrc if not r.get("physics_valid", True))
        lines.append(f"| {ch} | {_LETTER_MOTIONS.get(ch, '')} | {len(dtrc)} ({invalid}) | {rate(dtrc)} | "
                     f"{rate(nn)} | {_value(rec, f'max_lateral_step_mm_{ch}')} |")
    return "\n".join(lines)


# ----- tactip-validation: the TacTip twin against labelled real frames ------------------------------

#: the validate summary file the tactip-validation block is written from (read as it stands: not a benchmark record)
VALIDATE_SUMMARY = "summary.json"


def _names(frames: list[str]) -> str:
    """Frame names without their extension; the first two, …, the last when there are more than four."""
    stems = [f.rsplit(".", 1)[0] for f in frames]
    return ", ".join(stems if len(stems) <= 4 else [*stems[:2], "…", stems[-1]])


def _px(value: float | None) -> str:
    return "—" if value is None else f"{value:.2f}"


def _twin_parameters(s: Mapping[str, Any]) -> str:
    """The twin's fitted position parameters: the count and, where the summary holds them, the groups."""
    groups = s.get("fitted_position_parameter_groups") or {}
    words = ", ".join(name if n == 1 else f"{n} {name}" for name, n in groups.items())
    return f"{s['fitted_position_parameters']['twin']}" + (f" ({words})" if words else "")


def _tactip_validation(records: Records, source: str) -> str:
    """Held-out marker RMS of the twin (projected pin tips; rendered → detected → identified) and of the static
    and ridge baselines with their fitted position parameters, the twin's displacement error and the image
    statistics twin vs real, from one ``stereotactip validate`` summary (``summary.json``). The goals and their
    verdicts are :mod:`benchmarks.tactip_validate`'s, as the summary records them (``goals``)."""
    from benchmarks.tactip_validate import GOAL_IMAGE, GOAL_IMAGE_KEYS, GOAL_RIDGE, GOAL_STATIC, STAT_KEYS

    s = records[VALIDATE_SUMMARY]
    try:
        held, common, stats = s["held_out_rms_px"], s["held_out_rms_px_common_markers"], s["image_stats_median"]
        counts, goals = s["fitted_position_parameters"], s["goals"]
    except KeyError as exc:
        raise ResultsError(f"{source}/{VALIDATE_SUMMARY}: not a `stereotactip validate` summary (no {exc})") from None
    twin, static, ridge = common.get("twin"), common.get("static"), common.get("ridge")
    ratio = lambda base: twin / base if twin is not None and base else None      # noqa: E731
    to_static, to_ridge = ratio(static), ratio(ridge)
    lines = [f"TacTip twin vs real frames from the `validate` summary record in `{source}` (commit "
             f"{str(s.get('commit', 'unknown'))[:10]}, design {s.get('design')}, {s['frames']} labelled frames: "
             f"{s['train']} train / {s['held_out']} held out ({_names(s.get('held_out_frames') or [])}); reference "
             f"{_names([s['reference']]) if s.get('reference') else '—'}):", "",
             "| held-out marker RMS, px | fitted position parameters | RMS, markers all methods identify | "
             "RMS, all its markers |", "| --- | --- | --- | --- |",
             f"| twin, projected pin tips | {_twin_parameters(s)} | {_px(common.get('twin_truth'))} | "
             f"{_px(held.get('twin_truth'))} |",
             f"| twin, rendered → detected → identified | same | {_px(twin)} | {_px(held.get('twin'))} |",
             f"| (a) static: training mean per marker | {counts['static']} | {_px(static)} | {_px(held.get('static'))} |",
             f"| (b) ridge on [d, tx, ty, products, squares] | {counts['ridge']} | {_px(ridge)} | "
             f"{_px(held.get('ridge'))} |", "",
             f"Goal ≤ {GOAL_STATIC:g}× static {_verdict_met(goals['twin_le_half_static'])}, ≤ {GOAL_RIDGE:g}× ridge "
             f"{_verdict_met(goals['twin_within_1p5_ridge'])}: through render → detect → identify the twin is "
             f"{_px(to_static)}× the static baseline and {_px(to_ridge)}× the ridge (markers all methods "
             f"identify); its held-out displacement error (against the reference tap) is "
             f"{_px(held.get('displacement_twin'))} px."]
    shown = [k for k in STAT_KEYS if k in stats]
    rel = {k: stats[k].get("relative_difference") for k in shown}
    unit = lambda k: " px" if k.endswith("_px") else ""                          # noqa: E731
    figures = ", ".join(f"{k.removesuffix('_px')} {_fmt(stats[k].get('twin'), 3)} / {_fmt(stats[k].get('real'), 3)}"
                        f"{unit(k)}" for k in shown)
    worst = max((rel[k] for k in shown if rel[k] is not None), default=None)
    lines += ["", f"Image statistics (median over frames, twin / real): {figures}"
              + (f" (all within {100 * worst:.1f} %)" if worst is not None else "")
              + f"; goal {', '.join(k.removesuffix('_px') for k in GOAL_IMAGE_KEYS)} within {100 * GOAL_IMAGE:g} % "
              f"{_verdict_met(goals['image_stats_within_10pct'])}."]
    return "\n".join(lines)


def _verdict_met(met: bool) -> str:
    return "**met**" if met else "**not met**"
