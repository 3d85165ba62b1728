"""Corrections files (JSON Lines, FORMATS.md): the scripted form of what a person does in the UI,
one correction or undo/redo per line, read with every error located at ``{path}:{line}``.

Decisions where FORMATS.md is silent: blank (whitespace-only) lines are skipped; there are no
comments (a line starting with ``#`` is an error that says so); a line holding only
``{"version": 1}`` is a header and yields no step; duplicate keys and NaN/Infinity are errors;
coordinates must be JSON numbers (a string such as ``"1.5"`` is an error); UTF-8, BOM tolerated.

Limits (so that no arithmetic on what is read overflows): coordinates within +/-1e9 m
(:data:`~hitl_slam.io.textfile.MAX_COORDINATE`), ``sigma_h`` within [1e-15, 1e9] m (its weight
``1/sigma_h^2`` stays within :data:`~hitl_slam.io.textfile.MAX_INFORMATION`), integers of at most
:data:`MAX_DIGITS` digits, JSON nested at most :data:`MAX_DEPTH` levels (a correction needs 3).
Only regular files are read (a FIFO is refused up front instead of waiting forever).
"""

from __future__ import annotations

import difflib
import json
import math
import os
from collections.abc import Iterable
from dataclasses import dataclass
from typing import Any

from hitl_slam.corrections import Correction, Mode
from hitl_slam.errors import InputError
from hitl_slam.io.atomic import atomic_writer
from hitl_slam.io.textfile import MAX_COORDINATE, MAX_INFORMATION, check_regular_file, sci

__all__ = [
    "FORMAT_VERSION",
    "MAX_DEPTH",
    "MAX_DIGITS",
    "MAX_SIGMA_H",
    "MIN_SIGMA_H",
    "Apply",
    "Redo",
    "Step",
    "Undo",
    "read_corrections",
    "write_corrections",
]

FORMAT_VERSION = 1
"""The only ``"version"`` value this module reads."""

MAX_DEPTH = 32
"""Deepest nesting of arrays and objects a line may have (a correction has 3: object, segment,
endpoint); deeper lines are refused before parsing, which would exhaust the recursion limit."""

MAX_DIGITS = 30
"""Most digits an integer may have; every integer the format uses is far shorter, and a number of
thousands of digits is refused instead of reaching Python's integer-conversion limit."""

MIN_SIGMA_H = 1.0 / math.sqrt(MAX_INFORMATION)
"""Smallest ``sigma_h`` [m] (1e-15): its weight ``1/sigma_h^2`` is the largest information
the readers accept."""

MAX_SIGMA_H = MAX_COORDINATE
"""Largest ``sigma_h`` [m] (1e9): beyond it a correction weighs nothing."""

_CORRECTION_KEYS = ("mode", "a", "b", "sigma_h", "version")
_ACTION_KEYS = ("action", "version")
_ACTIONS = ("undo", "redo")
_EXAMPLE = '{"mode": "collinear", "a": [[x0, y0], [x1, y1]], "b": [[x0, y0], [x1, y1]]}'


@dataclass(frozen=True)
class Apply:
    """Apply a drawn correction; ``line`` is where it was read (0 when not from a file)."""

    drawn: Correction
    line: int = 0


@dataclass(frozen=True)
class Undo:
    """Undo the last applied correction."""

    line: int = 0


@dataclass(frozen=True)
class Redo:
    """Redo the last undone correction."""

    line: int = 0


Step = Apply | Undo | Redo


class _LineError(Exception):
    def __init__(self, what: str, todo: str) -> None:
        super().__init__(what)
        self.what = what
        self.todo = todo


def _no_constants(name: str) -> Any:
    raise _LineError(f"{name} is not a number JSON allows", "write a finite number")


def _parse_int(text: str) -> int:
    digits = len(text) - text.startswith("-")
    if digits > MAX_DIGITS:
        raise _LineError(
            f"a number of {digits} digits (at most {MAX_DIGITS} are read)",
            f"write numbers such as 1.5 or 2e3 (coordinates in metres, within "
            f"+/-{sci(MAX_COORDINATE)})",
        )
    return int(text)


def _depth(text: str) -> int:
    """How deeply arrays and objects nest in ``text`` (strings skipped); stops past MAX_DEPTH."""
    depth = deepest = 0
    in_string = escaped = False
    for char in text:
        if in_string:
            if escaped:
                escaped = False
            elif char == "\\":
                escaped = True
            elif char == '"':
                in_string = False
        elif char == '"':
            in_string = True
        elif char in "[{":
            depth += 1
            if depth > deepest:
                deepest = depth
                if deepest > MAX_DEPTH:
                    break
        elif char in "]}":
            depth -= 1
    return deepest


def _unique_keys(pairs: list[tuple[str, Any]]) -> dict[str, Any]:
    out: dict[str, Any] = {}
    for key, value in pairs:
        if key in out:
            raise _LineError(f"key {key[:40]!r} appears twice", "keep one of them")
        out[key] = value
    return out


def _is_number(value: Any) -> bool:
    return isinstance(value, int | float) and not isinstance(value, bool)


def _segment(name: str, value: Any) -> list[list[float]]:
    ok = (
        isinstance(value, list)
        and len(value) == 2
        and all(isinstance(p, list) and len(p) == 2 and all(map(_is_number, p)) for p in value)
    )
    if not ok:
        raise _LineError(
            f"{name!r} must be two [x, y] endpoints of numbers, got {json.dumps(value)[:80]}",
            f'write e.g. "{name}": [[1.0, 2.0], [3.0, 2.0]] (metres, world frame)',
        )
    try:
        out = [[float(v) for v in p] for p in value]
    except OverflowError:
        out = [[math.inf]]
    if not all(abs(v) <= MAX_COORDINATE for p in out for v in p):
        raise _LineError(
            f"{name!r} has a coordinate beyond +/-{sci(MAX_COORDINATE)} m, larger than any map "
            "(a unit mistake or a damaged file)",
            "write coordinates in metres in the map's world frame",
        )
    return out


def _unknown(keys: Iterable[str], allowed: tuple[str, ...]) -> None:
    unknown = [k for k in keys if k not in allowed]
    if not unknown:
        return
    key = unknown[0][:40]
    close = difflib.get_close_matches(key, allowed, n=1)
    hint = f"did you mean {close[0]!r}?" if close else f"the keys are {', '.join(allowed)}"
    raise _LineError(f"unknown key {key!r}", f"{hint} (a typo must not become a default)")


def _parse_line(text: str, number: int) -> Step | None:
    if text.startswith("#"):
        raise _LineError("JSON Lines has no comments", "delete the line (blank lines are allowed)")
    nested = _depth(text)
    try:
        if nested > MAX_DEPTH:
            raise RecursionError
        obj = json.loads(
            text,
            object_pairs_hook=_unique_keys,
            parse_constant=_no_constants,
            parse_int=_parse_int,
        )
    except json.JSONDecodeError as exc:
        raise _LineError(
            f"not valid JSON ({exc.msg} at column {exc.colno})",
            f"write one JSON object per line, e.g. {_EXAMPLE}",
        ) from None
    except RecursionError:
        raise _LineError(
            f"JSON nested more than {MAX_DEPTH} levels deep",
            f"a correction nests 3 levels, e.g. {_EXAMPLE}",
        ) from None
    if not isinstance(obj, dict):
        raise _LineError(
            f"expected a JSON object, got {type(obj).__name__ if obj is not None else 'null'}",
            f'write e.g. {_EXAMPLE} or {{"action": "undo"}}',
        )
    if "version" in obj:
        version = obj["version"]
        if not (type(version) is int and version == FORMAT_VERSION):
            raise _LineError(
                f"unsupported version {json.dumps(version)[:80]}",
                f"this hitl-slam reads version {FORMAT_VERSION}; upgrade hitl-slam or fix the line",
            )
    if "action" in obj:
        if "mode" in obj:
            raise _LineError(
                "both 'action' and 'mode'", "put the correction and the undo/redo on separate lines"
            )
        _unknown(obj, _ACTION_KEYS)
        action = obj["action"]
        if action == "undo":
            return Undo(number)
        if action == "redo":
            return Redo(number)
        raise _LineError(
            f"unknown action {json.dumps(action)[:80]}",
            'use {"action": "undo"} or {"action": "redo"}',
        )
    if not obj:
        raise _LineError("empty object", f"write e.g. {_EXAMPLE}")
    if set(obj) == {"version"}:
        return None
    _unknown(obj, _CORRECTION_KEYS)
    missing = [k for k in ("mode", "a", "b") if k not in obj]
    if missing:
        raise _LineError(
            f"missing {', '.join(repr(k) for k in missing)}",
            "a correction needs mode, a and b (and optionally sigma_h)",
        )
    mode = obj["mode"]
    modes = ", ".join(m.value for m in Mode)
    if not isinstance(mode, str) or mode not in {m.value for m in Mode}:
        raise _LineError(f"unknown mode {json.dumps(mode)[:80]}", f"use one of {modes}")
    a = _segment("a", obj["a"])
    b = _segment("b", obj["b"])
    sigma_h = obj.get("sigma_h")
    if sigma_h is not None and not (_is_number(sigma_h) and 0 < sigma_h < math.inf):
        raise _LineError(
            f"sigma_h must be a positive number of metres, got {json.dumps(sigma_h)[:80]}",
            "give the drawing accuracy in metres, e.g. 0.1, or leave sigma_h out",
        )
    if sigma_h is not None and not MIN_SIGMA_H <= sigma_h <= MAX_SIGMA_H:
        raise _LineError(
            f"sigma_h {json.dumps(sigma_h)} is outside [{sci(MIN_SIGMA_H)}, {sci(MAX_SIGMA_H)}] m "
            "(its weight 1/sigma_h^2 would overflow or vanish)",
            "give the drawing accuracy in metres, e.g. 0.1, or leave sigma_h out",
        )
    try:
        drawn = Correction.make(a, b, mode, None if sigma_h is None else float(sigma_h))
    except InputError as exc:
        raise _LineError(str(exc), "fix the line") from None
    return Apply(drawn, number)


def read_corrections(path: str | os.PathLike[str]) -> list[Step]:
    """The steps of a corrections file, in order, each with its line number.

    Raises:
        InputError: ``{path}:{line}: what is wrong; what to do`` for the first bad line, or
            ``{path}: ...`` when the file cannot be read.
    """
    name = os.fspath(path)
    check_regular_file(name, missing_ok=True)
    try:
        with open(name, "rb") as f:
            data = f.read()
    except FileNotFoundError:
        raise InputError(f"{name}: no such file; give a JSON Lines corrections file") from None
    except OSError as exc:
        raise InputError(f"{name}: cannot read the file ({exc.strerror or exc})") from None
    try:
        text = data.decode("utf-8-sig")
    except UnicodeDecodeError as exc:
        bad_line = data[: exc.start].count(b"\n") + 1
        raise InputError(f"{name}:{bad_line}: not UTF-8 text; save the file as UTF-8") from None
    steps: list[Step] = []
    # split("\n"), not splitlines(): the latter also breaks at \x0c, \u2028 ... and would shift
    # the line numbers away from what an editor shows.
    for number, raw in enumerate(text.split("\n"), 1):
        line = raw.strip()
        if not line:
            continue
        try:
            step = _parse_line(line, number)
        except _LineError as exc:
            raise InputError(f"{name}:{number}: {exc.what}; {exc.todo}") from None
        if step is not None:
            steps.append(step)
    return steps


def _as_json(step: Step | Correction) -> dict[str, Any]:
    if isinstance(step, Correction):
        return step.to_json()
    if isinstance(step, Apply):
        return step.drawn.to_json()
    return {"action": "undo" if isinstance(step, Undo) else "redo"}


def write_corrections(path: str | os.PathLike[str], steps: Iterable[Step | Correction]) -> None:
    """Write ``steps`` as a corrections file, one JSON object per line, atomically.

    Numbers are written exactly (shortest round-trip form), so reading the file back gives equal
    corrections.

    Raises:
        InputError: a step :func:`read_corrections` would refuse (e.g. a coordinate beyond its
            limit; nothing is written then), or an unwritable path.
    """
    name = os.fspath(path)
    lines = [json.dumps(_as_json(s), allow_nan=False) + "\n" for s in steps]
    for number, line in enumerate(lines, 1):
        try:  # what is written must read back: the reader's checks, before anything is written
            _parse_line(line.strip(), number)
        except _LineError as exc:
            raise InputError(
                f"{name}: cannot write step {number} (it would not read back): {exc.what}; "
                f"{exc.todo}"
            ) from None
    try:
        with atomic_writer(name) as f:
            f.writelines(lines)
    except OSError as exc:
        raise InputError(
            f"{name}: cannot write the file ({exc.strerror or exc}); check that the directory "
            "exists and is writable"
        ) from None
