"""Benchmarks subcommands of the ``stereotactip`` CLI."""

from __future__ import annotations

import argparse


def register(sub: argparse._SubParsersAction) -> None:
    """Add this package's subcommands to the top-level parser."""
