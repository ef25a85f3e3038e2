"""Tidy results tables: one row per cell, one column per variable, as Parquet with a CSV beside it.

A researcher opens ``sweep_<experiment>.parquet`` with ``pandas.read_parquet`` (or the CSV with any
spreadsheet) without this project's code: the rows are plain scalars (numbers, strings, booleans,
empty for missing), lists are joined with ``"; "`` and nested mappings flattened to ``parent.child``
columns. Both files are written atomically (:mod:`pipeline.io.atomic`). Parquet needs ``pyarrow``; without
it only the CSV is written and the caller is told so.
"""

from __future__ import annotations

import csv
import io
import math
from pathlib import Path
from typing import Any, Mapping, Sequence

from pipeline.io.atomic import atomic_write_bytes, atomic_write_text

__all__ = ["flatten", "write_table"]


def _scalar(value: Any) -> Any:
    if isinstance(value, (list, tuple)):
        return "; ".join(str(_scalar(v)) for v in value)
    if hasattr(value, "item") and not isinstance(value, (str, bytes)):  # numpy scalars
        try:
            value = value.item()
        except (TypeError, ValueError):
            return str(value)
    if isinstance(value, float) and not math.isfinite(value):
        return None
    if value is None or isinstance(value, (bool, int, float, str)):
        return value
    return str(value)


def flatten(row: Mapping[str, Any], prefix: str = "") -> dict[str, Any]:
    """One flat row of scalars: nested mappings become ``parent.child`` columns."""
    out: dict[str, Any] = {}
    for k, v in row.items():
        name = f"{prefix}{k}"
        if isinstance(v, Mapping):
            out.update(flatten(v, prefix=f"{name}."))
        else:
            out[name] = _scalar(v)
    return out


def _columns(rows: Sequence[Mapping[str, Any]]) -> list[str]:
    cols: list[str] = []
    seen = set()
    for r in rows:
        for k in r:
            if k not in seen:
                seen.add(k)
                cols.append(k)
    return cols


def _column_values(rows: Sequence[Mapping[str, Any]], col: str) -> list[Any]:
    """One column with a single type: ints mixed with floats become floats; any string makes it text."""
    vals = [r.get(col) for r in rows]
    kinds = {type(v) for v in vals if v is not None}
    if kinds and kinds <= {int, float}:
        return [None if v is None else float(v) for v in vals] if float in kinds else vals
    if len(kinds) > 1:
        return [None if v is None else str(v) for v in vals]
    return vals


def write_table(rows: Sequence[Mapping[str, Any]], stem: Path) -> dict[str, Path | None]:
    """Write ``stem.csv`` and ``stem.parquet`` (flat rows, columns in first-seen order).

    Returns ``{"csv": path, "parquet": path or None}`` (None when pyarrow is not installed).
    """
    stem = Path(stem)
    flat = [flatten(r) for r in rows]
    cols = _columns(flat) or ["cell"]
    data = {c: _column_values(flat, c) for c in cols}
    buf = io.StringIO(newline="")
    w = csv.writer(buf)
    w.writerow(cols)
    for i in range(len(flat)):
        w.writerow(["" if data[c][i] is None else data[c][i] for c in cols])
    csv_path = stem.with_suffix(".csv")
    atomic_write_text(csv_path, buf.getvalue())
    try:
        import pyarrow as pa
        import pyarrow.parquet as pq
    except ImportError:
        return {"csv": csv_path, "parquet": None}
    table = pa.table({c: pa.array(data[c]) for c in cols})
    sink = io.BytesIO()
    pq.write_table(table, sink)
    pq_path = stem.with_suffix(".parquet")
    atomic_write_bytes(pq_path, sink.getvalue())
    return {"csv": csv_path, "parquet": pq_path}
