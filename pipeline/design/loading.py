"""Design files: built-in names, reading TOML, ``extends`` chains merged into one document."""

from __future__ import annotations

import sys
from importlib import resources
from pathlib import Path
from typing import Any, Mapping

from pipeline.design.schema import TWIN_KEYS, DesignError
from pipeline.design.sensor import SensorDesign
from pipeline.design.validation import (_CAMERA_KEYS, _CHAIN_KEYS, _MONO_KEYS, _MONO_OPTIONAL, _OPTIONAL_SECTIONS,
                                        _PATTERN_OPTIONAL, _SCHEMA, _TOP, design_from_dict)

if sys.version_info >= (3, 11):
    import tomllib
else:  # pragma: no cover
    import tomli as tomllib

DEFAULT_DESIGN = "hexagon127"
MAX_DESIGN_FILE_BYTES = 1 << 20
MAX_EXTENDS_DEPTH = 8        # files in one extends chain, the design included


def _designs_dir():
    return resources.files("sim_assets").joinpath("designs")


def list_designs() -> list[str]:
    """Names of the built-in designs (files in ``sim_assets/designs``)."""
    return sorted(p.name[:-5] for p in _designs_dir().iterdir() if p.name.endswith(".toml"))


def design_path(name_or_path: str | Path) -> Path:
    """Resolve a built-in design name or a path to a TOML file."""
    p = Path(name_or_path)
    if p.suffix == ".toml" or p.exists():
        if not p.is_file():
            raise DesignError(f"design file {str(p)!r} does not exist")
        return p
    cand = _designs_dir().joinpath(f"{name_or_path}.toml")
    if not cand.is_file():
        raise DesignError(f"unknown design {str(name_or_path)!r}; built-in designs: {', '.join(list_designs())}")
    return Path(str(cand))


def _read_toml(path: Path) -> dict[str, Any]:
    """One file's TOML document; every failure is a one-line :class:`DesignError` naming the file."""
    try:
        data = path.read_bytes()
    except OSError as exc:
        raise DesignError(f"design file {path}: cannot be read ({exc.strerror or exc})") from None
    if len(data) > MAX_DESIGN_FILE_BYTES:
        raise DesignError(f"design file {path}: {len(data)} bytes; a design is a few kB of TOML "
                          f"(limit {MAX_DESIGN_FILE_BYTES} bytes)")
    try:
        text = data.decode("utf-8")
    except UnicodeDecodeError:
        raise DesignError(f"design file {path}: not a text file (not UTF-8); expected TOML") from None
    try:
        return tomllib.loads(text)
    except tomllib.TOMLDecodeError as exc:
        raise DesignError(f"{path}: not valid TOML: {exc}") from None


def _known_keys(raw: Mapping[str, Any], where: str) -> None:
    """Refuse a key no design has, in one file of an ``extends`` chain: the error names the file that
    introduces the key, before the chain is merged. Types, ranges and missing keys are checked on the
    merged document (:func:`design_from_dict`)."""
    allowed = set(_TOP) | set(_SCHEMA) | set(_OPTIONAL_SECTIONS) | set(_CHAIN_KEYS)
    unknown = sorted(set(raw) - allowed)
    if unknown:
        raise DesignError(f"{where}: unknown key {unknown[0]!r}")
    sections: dict[str, Mapping[str, Any]] = {
        **{k: {**v, **(_PATTERN_OPTIONAL if k == "pattern" else {})} for k, v in _SCHEMA.items()},
        "camera": {**_MONO_KEYS, **_MONO_OPTIONAL}, "twin": TWIN_KEYS,
        "cameras.left": _CAMERA_KEYS, "cameras.right": _CAMERA_KEYS}
    tables = [(k, v) for k, v in raw.items() if isinstance(v, Mapping)]
    if isinstance(raw.get("cameras"), Mapping):
        tables += [(f"cameras.{k}", v) for k, v in raw["cameras"].items() if isinstance(v, Mapping)]
    for name, table in tables:
        if name not in sections:
            continue          # a table where a value belongs: a type error of the merged document
        keys = sections[name]
        unknown = sorted(set(table) - set(keys))
        if unknown:
            raise DesignError(f"{where}: {name}: unknown key {unknown[0]!r} (allowed: {', '.join(keys)})")
    _abstract(raw, where)


def _merge(base: Mapping[str, Any], child: Mapping[str, Any]) -> dict[str, Any]:
    """``child`` over ``base``: tables merge key by key (recursively), anything else in ``child`` replaces."""
    out = dict(base)
    for k, v in child.items():
        out[k] = _merge(base[k], v) if isinstance(v, Mapping) and isinstance(base.get(k), Mapping) else v
    return out


def _base_path(value: Any, child: Path) -> Path:
    """The file ``extends = value`` in ``child`` names: a path ending in ``.toml`` (relative to ``child``'s
    folder unless absolute), else a name in the built-in designs folder (``base/stereotactip_module``)."""
    if not isinstance(value, str) or not value.strip() or not value.isprintable():
        raise DesignError(f"{child}: extends: expected a design name or a .toml path, got {value!r}")
    p = Path(value)
    if p.suffix == ".toml":
        cand = p if p.is_absolute() else child.parent / p
    else:
        cand = Path(str(_designs_dir().joinpath(f"{value}.toml")))
    try:
        found = cand.is_file()
    except OSError:                    # e.g. a name too long for the file system
        found = False
    if not found:
        shown = value if len(value) <= 200 else value[:200] + "..."
        raise DesignError(f"{child}: extends: no design or base {shown!r}" + (f" (looked for {cand})"
                                                                             if len(str(cand)) <= 300 else ""))
    return cand


def _abstract(raw: Mapping[str, Any], where: str) -> bool:
    value = raw.get("abstract", False)
    if not isinstance(value, bool):
        raise DesignError(f"{where}: abstract: expected true or false, got {value!r}")
    return value


def _load_chain(path: Path, chain: tuple[Path, ...] = ()) -> tuple[dict[str, Any], tuple[Path, ...]]:
    """``path``'s document with its bases merged in, and the files it came from (``path`` first);
    ``chain`` the files that extend ``path``, the loaded design first."""
    raw = _read_toml(path)
    if "extends" not in raw and not chain:
        return raw, (path,)                       # a standalone design: validated as it always was
    try:
        _known_keys(raw, str(path))
    except DesignError as exc:
        if not chain or raw.get("abstract") is True:
            raise
        raise DesignError(f"{chain[-1]}: extends {str(path)!r}, which is neither a design nor a base "
                          f"(abstract = true): {exc}") from None
    if "extends" not in raw:
        return raw, (path,)
    chain = (*chain, path)
    if len(chain) >= MAX_EXTENDS_DEPTH:
        raise DesignError(f"{chain[0]}: extends chain longer than {MAX_EXTENDS_DEPTH} files: "
                          + " -> ".join(str(p) for p in chain))
    base = _base_path(raw["extends"], path)
    if base.resolve() in [p.resolve() for p in chain]:
        raise DesignError(f"{chain[0]}: extends cycle: " + " -> ".join(str(p) for p in (*chain, base)))
    base_raw, base_files = _load_chain(base, chain)
    if not _abstract(base_raw, str(base)):
        try:   # a complete design may serve as a base: it must be one on its own
            design_from_dict(base_raw, source=str(base), where=_where(base_files))
        except DesignError as exc:
            raise DesignError(f"{path}: extends {raw['extends']!r}, which is neither a design nor a base "
                              f"(abstract = true): {exc}") from None
    inherited = {k: v for k, v in base_raw.items() if k not in _CHAIN_KEYS}
    return _merge(inherited, {k: v for k, v in raw.items() if k != "extends"}), (path, *base_files)


def _where(files: tuple[Path, ...]) -> str:
    """How errors name a design: its file, and the bases it extends."""
    return str(files[0]) + (f" (extends {' -> '.join(str(p) for p in files[1:])})" if len(files) > 1 else "")


def load_design(name_or_path: str | Path = DEFAULT_DESIGN) -> SensorDesign:
    """Load and validate a design by built-in name (e.g. ``"hexagon127"``) or TOML path.

    A file may say ``extends = "NAME"`` (a built-in name, e.g. ``"base/stereotactip_module"``, or a
    ``.toml`` path relative to the file): the base is loaded (recursively), its tables are merged key
    by key under the file's own (the file wins; arrays and scalars replace), and the merged document is
    validated as a standalone file is. ``name``, ``description``, ``abstract`` and ``extends`` are never
    inherited. A file with ``abstract = true`` is a base: it can only be extended."""
    path = design_path(name_or_path)
    raw, files = _load_chain(path)
    if _abstract(raw, str(path)):
        raise DesignError(f"{path}: is a base (abstract = true), not a design: a design file extends it "
                          f"with extends = {_extends_name(path)!r}")
    raw.pop("abstract", None)
    return design_from_dict(raw, source=str(path), where=_where(files))


def _extends_name(path: Path) -> str:
    """What a design file writes to extend ``path``: its built-in name, else its path."""
    try:
        rel = path.resolve().relative_to(Path(str(_designs_dir())).resolve())
        return rel.with_suffix("").as_posix()
    except ValueError:
        return str(path)
