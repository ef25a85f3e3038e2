"""docs/ARCHITECTURE.md is the newcomer's map: every module of the code base is named in it, every module it
names exists, and no product module runs past ~400 lines without saying at its top why."""

from __future__ import annotations

import re
import subprocess
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
#: Lines past which a module must state at its top why it stays whole (the "~400" of the style guide, with
#: the tolerance its "~" allows).
LONG_MODULE_LINES = 410


def _modules(with_tests: bool = False) -> list[str]:
    try:
        out = subprocess.run(["git", "ls-files", "*.py"], cwd=ROOT, capture_output=True, text=True, timeout=30)
    except (OSError, subprocess.TimeoutExpired):
        pytest.skip("git is not available: the module list comes from the checkout")
    if out.returncode != 0:
        pytest.skip("not a git checkout")
    return [m for m in out.stdout.split() if with_tests or not m.startswith("tests/")]


def test_every_module_is_named_in_the_architecture_and_every_named_module_exists():
    text = (ROOT / "docs" / "ARCHITECTURE.md").read_text(encoding="utf-8")
    modules = _modules()
    missing = [m for m in modules if Path(m).name != "__init__.py"
               and not re.search(r"(?<![\w.])" + re.escape(Path(m).name), text)]
    assert not missing, f"docs/ARCHITECTURE.md does not name these modules (one line each): {missing}"
    named = set(re.findall(r"[\w/]*\w\.py\b", text))
    every = _modules(with_tests=True)
    stale = [n for n in named if not any(m == n or m.endswith("/" + n) for m in every)]
    assert not stale, f"docs/ARCHITECTURE.md names modules that no longer exist: {sorted(stale)}"


def test_long_modules_say_why_at_their_top():
    long = []
    for m in _modules() + [str(p.relative_to(ROOT)) for p in (ROOT / "tests").glob("*.py")]:
        text = (ROOT / m).read_text(encoding="utf-8")
        if text.count("\n") > LONG_MODULE_LINES and "~400 lines" not in text[:4000]:
            long.append(f"{m} ({text.count(chr(10))} lines)")
    assert not long, f"split these along a seam, or say at their top why they stay whole (\"~400 lines\"): {long}"
