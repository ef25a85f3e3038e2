"""The pipeline is the real-hardware product: it must not import the twin, mujoco or pyrender."""

import ast
import pathlib

import pytest

ROOT = pathlib.Path(__file__).resolve().parents[1]
FORBIDDEN_IN_PIPELINE = {"twin", "mujoco", "pyrender", "benchmarks"}
# pipeline.io.atomic is the project's one atomic-write helper (every output of both halves goes through
# it); it holds no pipeline algorithm and imports nothing from the pipeline (checked below).
TWIN_MAY_IMPORT = {"pipeline.types", "pipeline.design", "pipeline.errors", "pipeline.io.atomic"}


def _imports(path: pathlib.Path):
    tree = ast.parse(path.read_text(), filename=str(path))
    for node in ast.walk(tree):  # walks function bodies too: lazy imports count
        if isinstance(node, ast.Import):
            for alias in node.names:
                yield alias.name
        elif isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
            yield node.module


@pytest.mark.parametrize("path", sorted((ROOT / "pipeline").rglob("*.py")), ids=lambda p: p.name)
def test_pipeline_never_imports_the_twin(path):
    bad = [m for m in _imports(path) if m.split(".")[0] in FORBIDDEN_IN_PIPELINE]
    assert not bad, f"{path.relative_to(ROOT)} imports {bad}"


@pytest.mark.parametrize("path", sorted((ROOT / "twin").rglob("*.py")), ids=lambda p: p.name)
def test_twin_imports_only_types_and_design_from_pipeline(path):
    bad = [m for m in _imports(path) if m.split(".")[0] == "pipeline" and m not in TWIN_MAY_IMPORT]
    assert not bad, f"{path.relative_to(ROOT)} imports {bad} (allowed: {sorted(TWIN_MAY_IMPORT)})"


def test_the_shared_write_helper_imports_nothing_from_the_pipeline():
    bad = [m for m in _imports(ROOT / "pipeline" / "io" / "atomic.py") if m.split(".")[0] in {"pipeline", *FORBIDDEN_IN_PIPELINE}]
    assert not bad, f"pipeline/io/atomic.py imports {bad}"
