"""A design written out: a plain mapping (JSON results, overrides), its digest, TOML text."""

from __future__ import annotations

import dataclasses
import math
from typing import Any, Mapping

from pipeline.design.schema import DesignError
from pipeline.design.sensor import SensorDesign


def to_dict(design: SensorDesign) -> dict[str, Any]:
    """The design as a plain TOML-shaped mapping (for JSON results and overrides)."""
    raw = dataclasses.asdict(design)
    raw.pop("source_file", None)
    if raw["cameras"] is None:
        raw.pop("cameras")
    else:
        for side in ("left", "right"):
            raw["cameras"][side]["dist"] = list(raw["cameras"][side]["dist"])
    if raw["camera"] is None:
        raw.pop("camera")
    else:
        raw["camera"]["dist"] = list(raw["camera"]["dist"])
    twin = dict(design.twin)
    raw.pop("twin")
    if twin:
        raw["twin"] = twin
    if raw["pattern"].get("mapping") == "vertical":
        raw["pattern"].pop("mapping")
    return raw


def design_digest(design: SensorDesign) -> str:
    """Digest of everything a design says (its merged content, not its file's bytes: a change in a base
    changes the digest of every design that extends it); 16 hex digits. The file it came from does not
    enter: the same design written out or extending a base has one digest."""
    import hashlib
    import json

    return hashlib.sha256(json.dumps(to_dict(design), sort_keys=True).encode()).hexdigest()[:16]


def _toml_value(v: Any) -> str:
    import json

    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, int):
        return str(v)
    if isinstance(v, float):
        return repr(v) if math.isfinite(v) else ("nan" if v != v else ("inf" if v > 0 else "-inf"))
    if isinstance(v, str):
        return json.dumps(v, ensure_ascii=False)  # a JSON string is a valid TOML basic string
    if isinstance(v, (list, tuple)):
        return "[" + ", ".join(_toml_value(x) for x in v) + "]"
    raise DesignError(f"cannot write {type(v).__name__} to TOML")


def mapping_to_toml(raw: Mapping[str, Any]) -> str:
    """A TOML-shaped mapping (a design's, or a base's: any part of one) as TOML text: its values first,
    then one ``[table]`` per nested mapping, sub-tables as ``[table.sub]``."""
    lines = [f"{k} = {_toml_value(v)}" for k, v in raw.items() if not isinstance(v, Mapping)]

    def table(name: str, d: Mapping[str, Any]) -> None:
        lines.append("")
        lines.append(f"[{name}]")
        lines.extend(f"{k} = {_toml_value(v)}" for k, v in d.items() if not isinstance(v, Mapping))
        for k, v in d.items():
            if isinstance(v, Mapping):
                table(f"{name}.{k}", v)

    for k, v in raw.items():
        if isinstance(v, Mapping):
            table(k, v)
    return "\n".join(lines) + "\n"


def to_toml(design: SensorDesign) -> str:
    """The design as TOML text that :func:`load_design` reads back to an equal design."""
    return mapping_to_toml(to_dict(design))
