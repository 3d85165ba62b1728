"""The ``hitl-slam`` command line: argument parsing, progress, tables, exit codes.

The only package that prints. One module per command (its parser and its ``run``), the options
and helpers they share in :mod:`.common`. Exit codes: 0 success, 2 bad input or an output that
cannot be written (one-line reason on stderr; then no output was written), 1 a solver failure, 3
(``solve``) the solve did not converge (the best estimate is still written). A command's outputs
appear together or not at all (:func:`hitl_slam.io.atomic.atomic_outputs`), and an output that
is one of its inputs (the same file, also through a link) is refused unless ``--force``.
"""

from __future__ import annotations

import argparse
import logging
from collections.abc import Sequence

from hitl_slam import __version__
from hitl_slam.cli import (
    correct,
    demo,
    evaluate,
    export,
    generate,
    metrics,
    recover,
    serve,
    slam,
    solve,
)
from hitl_slam.cli.common import StderrNotices, run_command

__all__ = ["build_parser", "main"]

COMMANDS = (solve, generate, correct, slam, export, recover, metrics, demo, serve, evaluate)
"""The command modules, in the order ``hitl-slam --help`` lists them."""


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="hitl-slam",
        description=(
            "Human-in-the-Loop SLAM: repair a globally inconsistent 2D map by drawing a few lines "
            "(Nashed and Biswas, AAAI 2018). Start with `hitl-slam demo`."
        ),
    )
    parser.add_argument("--version", action="version", version=f"hitl-slam {__version__}")
    sub = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")
    for command in COMMANDS:
        command.add_parser(sub)
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    # Only the CLI prints: the library's loggers keep their NullHandler (no output on import).
    package = logging.getLogger("hitl_slam")
    atomic = logging.getLogger("hitl_slam.io.atomic")
    handler = StderrNotices(logging.INFO)
    levels = package.level, atomic.level
    package.addHandler(handler)
    if package.getEffectiveLevel() > logging.WARNING:
        package.setLevel(logging.WARNING)
    atomic.setLevel(logging.INFO)
    try:
        return run_command(args)
    finally:
        package.removeHandler(handler)
        package.setLevel(levels[0])
        atomic.setLevel(levels[1])
