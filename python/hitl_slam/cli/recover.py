"""``hitl-slam recover``: copy the intact part of a damaged session file to a new one."""

from __future__ import annotations

import argparse
from pathlib import Path
from typing import TYPE_CHECKING

if TYPE_CHECKING:
    from hitl_slam.cli.common import Commands


def add_parser(sub: Commands) -> None:
    recover = sub.add_parser(
        "recover",
        help="copy the intact part of a damaged session file to a new one",
        description=(
            "Open the last good checkpoint of a damaged session file: its map, configuration and "
            "every event before the first damaged one (checksums verified) are copied to a NEW "
            "session file (default: <stem>.recovered.hitl beside it). The damaged file is only "
            "read."
        ),
    )
    recover.add_argument("input", metavar="SESSION", help="the damaged session file (.hitl)")
    recover.add_argument(
        "-o", "--output", metavar="NEW", help="the new session file (must not exist)"
    )
    recover.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from hitl_slam.session import Session

    source = Path(args.input)
    target = Path(args.output) if args.output else None
    with Session.recover(source, target) as session:
        kept = len(session.history)
        where = session.path
    print(
        f"wrote {where}: the last good checkpoint of {source} ({kept} step(s) in its history); "
        f"{source} is unchanged. Continue with: hitl-slam serve {where}"
    )
    return 0
