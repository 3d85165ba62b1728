"""The README runs (issue 41): every ```python block of README.md, in order, each in a fresh
Python process of its own with the repository root as its working directory, as a reader pastes
them one after another. A block may use the shared datasets (``../shared/datasets``) and the
files an earlier block wrote (under ``build/readme/``), nothing else. Each block must also run
again over what an earlier run left behind: the quick ones are run a second time
(:data:`AGAIN_UNDER_S`). About 3 minutes on 2 cores; the front end over Freiburg 079 and the
"Repair a map" block, whose alignment is refused after a minute of scan matching, take nearly
all of it.
"""

from __future__ import annotations

import os
import re
import subprocess
import sys
import time
from pathlib import Path

import pytest

pytestmark = [pytest.mark.datasets, pytest.mark.slow]

ROOT = Path(__file__).resolve().parents[1]
README = ROOT / "README.md"
DATASETS = ROOT.parent / "shared" / "datasets"
FENCE = re.compile(r"^```(\S*)\s*$")
TIMEOUT_S = 1800  # one block; the front end over a whole log takes about a minute when quiet


def python_blocks(text: str) -> list[tuple[int, str]]:
    """Each ```python block of ``text``: the line number of its opening fence, and its code."""
    blocks: list[tuple[int, str]] = []
    start: int | None = None
    language = ""
    body: list[str] = []
    for number, line in enumerate(text.splitlines(), start=1):
        fence = FENCE.match(line)
        if fence is None:
            if start is not None:
                body.append(line)
            continue
        if start is None:
            start, language, body = number, fence.group(1), []
        else:
            if language == "python":
                blocks.append((start, "\n".join(body) + "\n"))
            start = None
    assert start is None, f"README.md:{start}: a code block is never closed"
    return blocks


def test_python_blocks_are_found() -> None:
    blocks = python_blocks(README.read_text(encoding="utf-8"))
    assert len(blocks) >= 5, blocks
    for line, code in blocks:
        compile(code, f"README.md:{line}", "exec")


def run_block(line: int, code: str) -> float:
    """Runs one block as a reader would; its time [s]."""
    started = time.perf_counter()
    done = subprocess.run(
        [sys.executable, "-c", code],
        cwd=ROOT,
        env={**os.environ, "MPLBACKEND": "Agg"},
        capture_output=True,
        text=True,
        timeout=TIMEOUT_S,
        check=False,
    )
    if done.returncode != 0:
        pytest.fail(
            f"README.md:{line}: the python block starting there failed (exit status "
            f"{done.returncode}):\n{done.stderr.strip()}",
            pytrace=False,
        )
    took = time.perf_counter() - started
    print(f"README.md:{line}: {took:.1f} s")  # shown with -rP or -s
    return took


AGAIN_UNDER_S = 30.0
"""The blocks that took less than this are run a second time, over the files the first run left
in build/readme/ (a reader running the README again). The two long ones (the front end over a
whole log, the repair whose alignment is refused after a minute of scan matching) make their
files again the same way, and running them twice would add five minutes to `make test`."""


def test_every_python_block_runs_and_runs_again() -> None:
    if not DATASETS.is_dir():
        pytest.skip("../shared/datasets is not beside the repository")
    blocks = python_blocks(README.read_text(encoding="utf-8"))
    quick = [(line, code) for line, code in blocks if run_block(line, code) < AGAIN_UNDER_S]
    for line, code in quick:
        run_block(line, code)
