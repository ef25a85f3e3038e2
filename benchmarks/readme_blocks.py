"""The README's figures, written from benchmark records (``stereotactip report DIR --readme README.md``).

A generated block in the README is the text between two marker lines::

    <!-- report:NAME:begin (written by `stereotactip report DIR --readme README.md --block NAME`; do not edit) -->
    ...
    <!-- report:NAME:end -->

and :data:`BLOCKS` names what each block is made of: the gate figures of a quick run (``gate-figures``, every
metric ``benchmarks/thresholds.toml`` guards), the quick run's experiments (``quick-experiments``, one row per
experiment: the paper's figures and claims beside the run's) and a full run's (``full-suite``, the same with each
experiment's wall time), the twin's speed and fidelity table
(``twin-speed``, from a ``bench twin`` record), the Pipeline and renderer tables (``pipeline-accuracy`` and
``renderer-accuracy``, from a ``bench accuracy`` record and, for the Pipeline table's latency row, a ``bench latency``
record beside it), the certainty rule's headline (``identification-summary``) and the identification coverage table
(``identification-coverage``), both from a ``bench identification`` record, the tracking table (``tracking-identity``, from a ``bench tracking``
record), the contact-mechanics checks (``physics-checks``, from a ``bench physics`` record), the TacTip twin
against labelled real frames (``tactip-validation``, from the ``summary.json`` that ``stereotactip validate``
writes), an oracle and an estimated quick run side by side (``oracle-vs-estimated``, ``report DIR --against DIR2``) and each error source
of the estimated calibration alone (``error-sources``, three ``bench patterns,gaussian --quick --calibration
estimated --error-sources SOURCE`` runs: ``report DIR --against DIR2 --against DIR3``). Each block's first line
names the results directories it was written from; the records behind the README's headline blocks are kept in
``docs/records/`` so that
``tests/test_benchmarks.py`` can write each block again and fail when the README has drifted from them. A block
may stand in a document under ``docs/`` instead of the README (a long section moved there: ``ReadmeBlock.doc``,
which its begin marker names); the test reads README.md and every ``docs/*.md``, each block once.

The blocks' renderers are :mod:`benchmarks.readme_render` (and :mod:`benchmarks.readme_error_sources`,
:mod:`benchmarks.readme_physics`); this module holds the markers, the registry and the writing of the README.

A block is written from benchmark records (``experiment`` names the record) or, where the figures are a command's
own output rather than a benchmark's, from that command's summary file: ``experiment`` is then a file name
(``summary.json``) that :func:`load_block_records` reads as JSON, as it stands, under that name. The validate summary
is read this way rather than copied into a benchmark record so that the block and the kept summary are one file and
cannot disagree, and neither ``validate``'s output nor the benchmark record format changes for it; ``report`` writes
no report pages for such a block (they are the command's own: ``validate`` writes ``report.md`` itself).
"""

from __future__ import annotations

import re
from dataclasses import dataclass
from pathlib import Path
from typing import Callable, Sequence

from benchmarks.readme_error_sources import error_sources_markdown
from benchmarks.readme_physics import physics_checks_markdown
from benchmarks.readme_pipeline import (identification_summary_markdown, pipeline_accuracy_markdown,
                                        renderer_accuracy_markdown)
from benchmarks.readme_render import (CALIBRATION_METRICS, VALIDATE_SUMMARY, Records, _identification_coverage,
                                      _full_suite, _oracle_vs_estimated, _quick_experiments, _tactip_validation, _tracking_identity,
                                      _twin_speed, gate_figures_markdown)
from benchmarks.results import ResultsError, load_records, read_json_object

__all__ = ["BLOCKS", "CALIBRATION_METRICS", "ReadmeBlock", "begin_marker", "end_marker", "render_block", "update_readme",
           "readme_blocks", "load_block_records", "gate_figures_markdown", "README_BEGIN", "README_END"]


@dataclass(frozen=True)
class ReadmeBlock:
    """One generated README block: its ``name`` (the marker's), the ``experiment`` whose record it needs (None:
    every quick record in the directory; a name ending in ``.json``: that file of the directory, read as JSON by
    :func:`load_block_records`) and ``body(records, source) -> str`` the Markdown between the markers.
    A block that compares runs (``against`` > 0: how many other runs besides DIR) is written by
    ``body(records, source, others)``, ``others`` the list of (directory, records) from ``report DIR --against
    DIR2 [--against DIR3]``. ``doc`` is the file the block stands in, relative to the repository root (the README,
    or a document under ``docs/`` that a long section was moved to); its begin marker names it."""

    name: str
    experiment: str | None
    body: Callable[..., str]
    about: str
    against: int = 0
    doc: str = "README.md"

    @property
    def reads_file(self) -> bool:
        """Written from a command's summary file (``experiment`` is its name), not from benchmark records."""
        return self.experiment is not None and self.experiment.endswith(".json")


def begin_marker(name: str) -> str:
    """The line that opens block ``name``, naming the file it stands in (the gate figures keep their original,
    shorter command)."""
    against = "".join(f" --against DIR{k + 2}" for k in range(BLOCKS[name].against if name in BLOCKS else 0))
    doc = BLOCKS[name].doc if name in BLOCKS else "README.md"
    command = (f"stereotactip report DIR{against} --readme {doc}"
               + ("" if name == "gate-figures" else f" --block {name}"))
    return f"<!-- report:{name}:begin (written by `{command}`; do not edit) -->"


def end_marker(name: str) -> str:
    return f"<!-- report:{name}:end -->"


BLOCKS: dict[str, ReadmeBlock] = {b.name: b for b in (
    ReadmeBlock("gate-figures", None, gate_figures_markdown, "every metric the CI gate guards, from a quick run"),
    ReadmeBlock("quick-experiments", None, _quick_experiments,
                "one row per experiment of a quick run: the paper's figures and claims beside this run's"),
    ReadmeBlock("full-suite", None, _full_suite,
                "one row per experiment of a full run (`stereotactip bench all`): wall time, invalid twin cells, "
                "the paper's figures and claims beside the run's"),
    ReadmeBlock("oracle-vs-estimated", None, _oracle_vs_estimated,
                "the calibration-sensitive figures of an oracle and an estimated quick run side by side",
                against=1),
    ReadmeBlock("error-sources", None, error_sources_markdown,
                "patterns and gaussian figures of estimated quick runs that each keep one error source, with "
                "each run's drawn build, chessboard calibration and press-fitted index",
                against=2),
    ReadmeBlock("pipeline-accuracy", "accuracy", pipeline_accuracy_markdown,
                "the pipeline's stages against analytic truth and real frames, with its latency, from a directory "
                "holding a `bench accuracy` and a `bench latency` record"),
    ReadmeBlock("renderer-accuracy", "accuracy", renderer_accuracy_markdown,
                "the twin's rendered marker centres against the exact projection and a ray-traced reference"),
    ReadmeBlock("twin-speed", "twin", _twin_speed, "the twin's press and frame times, gap and penetration"),
    ReadmeBlock("identification-summary", "identification", identification_summary_markdown,
                "the certainty rule's headline: wrong ids over every trial and the worst pattern's coverage per "
                "condition, against the coverage goals"),
    ReadmeBlock("identification-coverage", "identification", _identification_coverage,
                "wrong ids and coverage per defect condition and pattern", doc="docs/IDENTIFICATION.md"),
    ReadmeBlock("tracking-identity", "tracking", _tracking_identity,
                "DTRC vs nearest-neighbour ids per letter motion, with the frames' physics verdicts"),
    ReadmeBlock("physics-checks", "physics", physics_checks_markdown,
                "the contact mechanics against the bonded-layer Hertz solution, symmetry and mesh convergence, "
                "with targets and verdicts", doc="docs/CONTACT_MODEL.md"),
    ReadmeBlock("tactip-validation", VALIDATE_SUMMARY, _tactip_validation,
                "the TacTip twin against labelled real frames: held-out marker RMS beside the static and ridge "
                "baselines, displacement error and image statistics, with the goals' verdicts, from the "
                "summary.json of `stereotactip validate`"),
)}


README_BEGIN = begin_marker("gate-figures")
README_END = end_marker("gate-figures")


def render_block(name: str, records: Records, source: str,
                 against: Sequence[tuple[str, Records]] = ()) -> str:
    """Block ``name`` written from ``records`` (the results directory ``source``; for a block that compares
    runs, also ``against``, the (directory, records) of each other run), marker lines included."""
    block = BLOCKS.get(name)
    if block is None:
        raise ResultsError(f"README block {name!r}: unknown; known blocks: {', '.join(BLOCKS)}")
    if block.reads_file and block.experiment not in records:
        raise ResultsError(f"{source}: no {block.experiment}: the {name} block is written from a folder holding it "
                           f"({block.about})")
    if block.experiment is not None and block.experiment not in records:
        raise ResultsError(f"{source}: no {block.experiment!r} record: the {name} block is written from a "
                           f"`stereotactip bench {block.experiment}` results directory")
    if len(against) != block.against:
        command = begin_marker(name).split("`")[1]
        runs = f"compares {('two', 'three')[block.against - 1]} runs" if block.against else "is written from one run"
        raise ResultsError(f"README block {name}: {runs}: `{command}`")
    body = block.body(records, source, list(against)) if block.against else block.body(records, source)
    return "\n".join([begin_marker(name), "", body, "", end_marker(name)])


def load_block_records(directory: Path) -> dict[str, dict]:
    """What the blocks are written from in ``directory``: its benchmark records by experiment
    (:func:`benchmarks.results.load_records`) and, for each block that reads a summary file, that file as JSON
    under its name (``summary.json``) when the directory holds it."""
    directory = Path(directory)
    records = load_records(directory)
    for name in sorted({b.experiment for b in BLOCKS.values() if b.reads_file}):
        path = directory / name
        if path.is_file():
            records[name] = read_json_object(path)
    return records


_BEGIN = re.compile(r"^<!-- report:([a-z0-9-]+):begin\b.*-->$", re.M)


def readme_blocks(text: str) -> dict[str, str]:
    """The generated blocks of a README's text, by name, marker lines included (as :func:`render_block`
    writes them)."""
    out = {}
    for m in _BEGIN.finditer(text):
        end = text.find(end_marker(m.group(1)), m.end())
        if end >= 0:
            out[m.group(1)] = text[m.start():end + len(end_marker(m.group(1)))]
    return out


def update_readme(readme: Path, records_dir: Path, blocks: tuple[str, ...] = ("gate-figures",),
                  against_dir: Path | Sequence[Path] | None = None) -> Path:
    """Rewrite the named ``blocks`` of ``readme`` from the records in ``records_dir`` (and, for a block that
    compares runs, the other runs' directories ``against_dir``) atomically; everything else is kept. Each block
    must stand exactly once, its begin line before its end line."""
    from pipeline.io.atomic import atomic_write_text

    readme = Path(readme)
    try:
        text = readme.read_text(encoding="utf-8")
    except (OSError, UnicodeDecodeError) as exc:
        raise ResultsError(f"README {readme}: unreadable ({type(exc).__name__})") from None
    records = load_block_records(Path(records_dir))
    against_dirs = [] if against_dir is None else [against_dir] if isinstance(against_dir, (str, Path)) \
        else list(against_dir)
    against = [(str(d), load_block_records(Path(d))) for d in against_dirs]
    for name in blocks:
        begin, end = begin_marker(name), end_marker(name)
        if text.count(begin) != 1 or text.count(end) != 1 or text.index(begin) > text.index(end):
            raise ResultsError(f"README {readme}: needs exactly one {name} block, the line {begin!r} "
                               f"followed by {end!r}")
        head, rest = text.split(begin, 1)
        _, tail = rest.split(end, 1)
        others = against if name in BLOCKS and BLOCKS[name].against else ()
        text = head + render_block(name, records, str(records_dir), others) + tail
    atomic_write_text(readme, text)
    return readme
