"""Pipeline subcommands of the ``stereotactip`` CLI (real hardware; never imports the twin)."""

from __future__ import annotations

import argparse

from pipeline.cli import geometry as cli_geometry, vision as cli_vision
from pipeline.design import list_designs, load_design


def _designs(args: argparse.Namespace) -> int:
    for name in list_designs():
        d = load_design(name)
        print(f"{name:22s} {d.pattern.kind:9s} {d.marker_count:4d} markers  sep {d.pattern.separation_mm:.2f} mm  "
              f"skin {d.skin.thickness_mm:.1f} mm  — {d.description}")
    return 0


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("designs", help="list the built-in sensor designs")
    p.set_defaults(func=_designs)
    cli_vision.register(sub)
    cli_geometry.register(sub)
