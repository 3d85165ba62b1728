"""Shared machinery of the reader fuzz tests (tests/test_fuzz_*.py, issue 13).

The invariant every reader is held to: for any input file it returns a valid object or raises
:class:`~hitl_slam.errors.InputError` whose message starts with the file's path (and, for text
formats when it names a line, a line the file has); never another exception, never a NumPy
overflow/invalid warning, never a hang (each case runs under a wall-clock alarm).

Profiles (``HITL_FUZZ_PROFILE``): ``fuzz-ci`` (default) runs a few derandomized cases per reader,
so that ``make test`` stays fast; ``fuzz`` (``make fuzz``) runs ``HITL_FUZZ_EXAMPLES`` cases per
reader (default 100,000) with fresh randomness. Inputs come from two sources alike: mutations
of valid files (token swaps for extreme and malformed numbers, deleted, duplicated or swapped
lines, flipped, inserted or truncated bytes) and structured generation (lines of the format's
tags with field counts near the right one and numbers drawn from the same pool).
"""

from __future__ import annotations

import bz2
import gzip
import json
import math
import os
import re
import signal
import warnings
from collections.abc import Callable, Iterator, Sequence
from contextlib import contextmanager
from pathlib import Path
from typing import Any, TypeVar

from hypothesis import HealthCheck, settings
from hypothesis import strategies as st

from hitl_slam.errors import InputError

T = TypeVar("T")

CASE_TIME_LIMIT = float(os.environ.get("HITL_FUZZ_CASE_SECONDS", "20"))
"""Seconds one case may take before it counts as a hang."""

_HEALTH = [
    HealthCheck.too_slow,
    HealthCheck.data_too_large,
    HealthCheck.filter_too_much,
    HealthCheck.large_base_example,
]
settings.register_profile(
    "fuzz-ci",
    max_examples=int(os.environ.get("HITL_FUZZ_CI_EXAMPLES", "30")),
    deadline=None,
    derandomize=True,
    database=None,
    suppress_health_check=_HEALTH,
)
settings.register_profile(
    "fuzz",
    max_examples=int(os.environ.get("HITL_FUZZ_EXAMPLES", "100000")),
    deadline=None,
    suppress_health_check=_HEALTH,
    print_blob=True,
)
PROFILE = os.environ.get("HITL_FUZZ_PROFILE", "fuzz-ci")
FUZZ_SETTINGS = settings.get_profile(PROFILE)
"""Apply as ``@FUZZ_SETTINGS`` to a fuzz test."""

# Numbers a reader must cope with: ordinary, at and past every limit, overflowing, non-finite,
# and text that Python's float() or int() would read but the formats do not allow.
SPECIAL_NUMBERS = (
    "0",
    "-0",
    "1",
    "-1",
    "0.5",
    "1.5",
    "-2e-3",
    "3.141592653589793",
    "1e9",
    "-1e9",
    "1000000001",
    "1e6",
    "-1000001",
    "2e9",
    "1e12",
    "1e30",
    "1.0000001e30",
    "1e-15",
    "1e-320",
    "1e300",
    "-1e300",
    "1.7976931348623157e308",
    "1e308",
    "1e999",
    "-1e999",
    "nan",
    "NaN",
    "inf",
    "-inf",
    "Infinity",
    "1_0",
    "1_000.5",
    "\u0663",
    "1\u0663",
    "\uff13",
    "\uff11.\uff15",
    "0x1f",
    "9" * 20,
    "9" * 30,
    "9" * 400,
    "9" * 5000,
    "-" + "9" * 5000,
    "1e" + "9" * 20,
    "",
    ".",
    "e5",
    "+.5",
    "--1",
    "1..2",
    "1e",
    "\x00",
    "\u00a0",
    "\ufeff",
    "\u2028",
    "#",
    "true",
    "null",
)

number_tokens: st.SearchStrategy[str] = st.one_of(
    st.sampled_from(SPECIAL_NUMBERS),
    st.floats(allow_nan=True, allow_infinity=True).map(repr),
    st.floats(min_value=-10.0, max_value=10.0).map(repr),
    st.integers(min_value=-(2**70), max_value=2**70).map(str),
    st.integers(min_value=-3, max_value=400).map(str),
)

junk_text: st.SearchStrategy[str] = st.text(
    st.characters(codec="utf-8", exclude_characters="\n\r"), max_size=12
)


def tokens_line(
    tags: Sequence[str], counts: Sequence[int], sep: str = " "
) -> st.SearchStrategy[str]:
    """One structured line: a tag then about the right number of number tokens."""

    @st.composite
    def build(draw: st.DrawFn) -> str:
        tag = draw(st.one_of(st.sampled_from(tags), junk_text))
        count = draw(st.sampled_from(counts)) + draw(st.integers(-2, 2))
        fields = draw(
            st.lists(
                st.one_of(number_tokens, junk_text), min_size=max(count, 0), max_size=max(count, 0)
            )
        )
        return sep.join([tag, *fields]) if tag else sep.join(fields)

    return build()


@st.composite
def mutated(draw: st.DrawFn, seeds: Sequence[str]) -> bytes:
    """A valid file (one of ``seeds``) with 1 to 6 random edits at the token, line or byte level."""
    text = draw(st.sampled_from(seeds))
    lines = text.split("\n")
    for _ in range(draw(st.integers(1, 6))):
        op = draw(
            st.sampled_from(
                (
                    "token",
                    "token",
                    "token",
                    "delete_token",
                    "insert_token",
                    "line",
                    "drop_line",
                    "dup_line",
                    "swap_lines",
                    "tag",
                )
            )
        )
        k = draw(st.integers(0, max(len(lines) - 1, 0)))
        words = lines[k].split(" ") if lines else [""]
        w = draw(st.integers(0, max(len(words) - 1, 0)))
        if op == "token":
            words[w] = draw(number_tokens)
        elif op == "delete_token" and words:
            del words[w]
        elif op == "insert_token":
            words.insert(w, draw(st.one_of(number_tokens, junk_text)))
        elif op == "tag":
            words[0] = draw(junk_text)
        if lines:
            lines[k] = " ".join(words)
        if op == "line":
            lines.insert(k, draw(junk_text))
        elif op == "drop_line" and lines:
            del lines[k]
        elif op == "dup_line" and lines:
            lines.insert(k, lines[k])
        elif op == "swap_lines" and len(lines) > 1:
            j = draw(st.integers(0, len(lines) - 1))
            lines[k], lines[j] = lines[j], lines[k]
    data = "\n".join(lines).encode("utf-8", "surrogatepass")
    return draw(byte_edits(data))


@st.composite
def byte_edits(draw: st.DrawFn, data: bytes, max_edits: int = 3) -> bytes:
    """``data`` with up to ``max_edits`` byte-level edits (flip, insert, delete, truncate)."""
    out = bytearray(data)
    for _ in range(draw(st.integers(0, max_edits))):
        op = draw(st.sampled_from(("flip", "insert", "delete", "truncate", "none", "none")))
        at = draw(st.integers(0, max(len(out) - 1, 0)))
        if op == "flip" and out:
            out[at] ^= 1 << draw(st.integers(0, 7))
        elif op == "insert":
            out[at:at] = draw(st.binary(min_size=1, max_size=8))
        elif op == "delete" and out:
            del out[at : at + draw(st.integers(1, 16))]
        elif op == "truncate":
            del out[at:]
    return bytes(out)


def compressed_variant(data: bytes, suffix: str) -> bytes:
    if suffix == ".gz":
        return gzip.compress(data, mtime=0)
    if suffix == ".bz2":
        return bz2.compress(data)
    return data


class Hang(BaseException):
    """A case ran past :data:`CASE_TIME_LIMIT` (a BaseException, so no reader can swallow it)."""


@contextmanager
def time_limit(seconds: float) -> Iterator[None]:
    def on_alarm(signum: int, frame: object) -> None:
        raise Hang(f"no answer within {seconds:g} s")

    previous = signal.signal(signal.SIGALRM, on_alarm)
    signal.setitimer(signal.ITIMER_REAL, seconds)
    try:
        yield
    finally:
        signal.setitimer(signal.ITIMER_REAL, 0)
        signal.signal(signal.SIGALRM, previous)


_LOCATED = re.compile(r":(\d+): ")
_STATS_FILE = os.environ.get("HITL_FUZZ_STATS")
_stats: dict[str, dict[str, int]] = {}


def _count(outcome: str) -> None:
    """Tally the case (per test) and, with ``HITL_FUZZ_STATS`` set, write the tallies there
    every 500 cases, so a long run shows how far it got."""
    test = os.environ.get("PYTEST_CURRENT_TEST", "?").split(" ")[0]
    tally = _stats.setdefault(test, {"cases": 0, "valid": 0, "input_error": 0})
    tally["cases"] += 1
    tally[outcome] += 1
    if _STATS_FILE and tally["cases"] % 500 == 0:
        Path(_STATS_FILE).write_text(json.dumps(_stats, indent=1) + "\n")


def check_reader(
    read: Callable[[Path], T],
    path: Path,
    data: bytes,
    *,
    lines: bool = True,
    validate: Callable[[T], None] | None = None,
) -> T | None:
    """Write ``data`` to ``path``, read it, and hold the reader to the invariant (module doc).

    Returns what the reader returned, or None when it raised InputError. ``lines``: the format is
    text, so an error naming a line must name one the file has.
    """
    path.write_bytes(data)
    shown = repr(data[:300]) + ("..." if len(data) > 300 else "")
    line_count = data.count(b"\n") + data.count(b"\r") + 1 if lines else None
    return check_path(read, path, shown, line_count=line_count, validate=validate)


def check_path(
    read: Callable[[Path], T],
    path: Path,
    shown: str,
    *,
    line_count: int | None = None,
    validate: Callable[[T], None] | None = None,
) -> T | None:
    """Read ``path`` as it is (a file or a directory; ``shown`` describes it in a failure) and
    hold the reader to the invariant; ``line_count``: the lines of a text file (+1 for a missing
    last one), which an error naming a line must stay within.
    """
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        try:
            with time_limit(CASE_TIME_LIMIT):
                result: T | None = read(path)
        except Hang as exc:
            raise AssertionError(f"hang: {exc} on {path.name} = {shown}") from None
        except InputError as exc:
            message = str(exc)
            assert message.startswith(f"{path}"), f"error does not name the file: {message!r}"
            rest = message[len(str(path)) :]
            assert rest.startswith((": ", ":")), f"error does not start with the file: {message!r}"
            located = _LOCATED.match(rest)
            if located and line_count is not None:
                assert 1 <= int(located.group(1)) <= line_count + 1, (
                    f"line out of range: {message!r}"
                )
            assert "Traceback" not in message
            result = None
            _count("input_error")
        else:
            _count("valid")
    numeric = [w for w in caught if issubclass(w.category, RuntimeWarning)]
    assert not numeric, f"RuntimeWarning {numeric[0].message} on {path.name} = {shown}"
    if result is not None and validate is not None:
        validate(result)
    return result


def assert_finite(label: str, value: Any, bound: float = math.inf) -> None:
    import numpy as np

    array = np.asarray(value, dtype=np.float64)
    assert np.all(np.isfinite(array)), f"{label} not finite"
    assert np.all(np.abs(array) <= bound), f"{label} beyond {bound:g}"


def examples_note() -> str:
    return f"profile {PROFILE}: {FUZZ_SETTINGS.max_examples} cases per reader"
