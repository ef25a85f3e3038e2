"""The ``stereotactip`` console entry point: one command, subcommands from each half.

``pipeline.cli`` (real hardware), ``twin.cli`` (simulation) and ``benchmarks.cli`` (experiments)
each expose ``register(subparsers)``; this module only composes them, so the pipeline never
imports the twin.
"""

from __future__ import annotations

import argparse
import sys

from pipeline.errors import UserError


def build_parser() -> argparse.ArgumentParser:
    from benchmarks import cli as bench_cli
    from pipeline import cli as pipeline_cli
    from twin import cli as twin_cli

    from stereotactip import demo

    parser = argparse.ArgumentParser(
        prog="stereotactip",
        description="StereoTacTip: stereo marker tactile pipeline, digital twin and benchmarks.",
    )
    sub = parser.add_subparsers(dest="command", metavar="COMMAND", required=True)
    for module in (pipeline_cli, twin_cli, bench_cli):
        module.register(sub)
    demo.register(sub)
    return parser


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    try:
        return int(args.func(args) or 0)
    except UserError as exc:
        print(f"stereotactip {args.command}: error: {exc}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print(f"stereotactip {args.command}: interrupted", file=sys.stderr)
        return 130
