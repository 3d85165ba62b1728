"""Corrections files (JSON Lines, FORMATS.md): the scripted form of what a person does in the UI,
one correction or undo/redo per line, read with every error located at ``{path}:{line}``.

Decisions where FORMATS.md is silent: blank (whitespace-only) lines are skipped; there are no
comments (a line starting with ``#`` is an error that says so); a line holding only
``{"version": 1}`` is a header and yields no step; duplicate keys and NaN/Infinity are errors;
coordinates must be JSON numbers (a string such as ``"1.5"`` is an error); UTF-8, BOM tolerated.
"""

from __future__ import annotations

import difflib
import json
import math
import os
from collections.abc import Iterable
from dataclasses import dataclass
from typing import Any

from hitl_slam.corrections import DrawnCorrection, Mode
from hitl_slam.errors import InputError
from hitl_slam.io.atomic import atomic_writer

__all__ = [
    "FORMAT_VERSION",
    "Apply",
    "Redo",
    "Step",
    "Undo",
    "read_corrections",
    "write_corrections",
]

FORMAT_VERSION = 1
"""The only ``"version"`` value this module reads."""

_CORRECTION_KEYS = ("mode", "a", "b", "sigma_h", "version")
_ACTION_KEYS = ("action", "version")
_ACTIONS = ("undo", "redo")
_EXAMPLE = '{"mode": "collinear", "a": [[x0, y0], [x1, y1]], "b": [[x0, y0], [x1, y1]]}'


@dataclass(frozen=True)
class Apply:
    """Apply a drawn correction; ``line`` is where it was read (0 when not from a file)."""

    drawn: DrawnCorrection
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


def _unique_keys(pairs: list[tuple[str, Any]]) -> dict[str, Any]:
    out: dict[str, Any] = {}
    for key, value in pairs:
        if key in out:
            raise _LineError(f"key {key!r} appears twice", "keep one of them")
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
    if not all(math.isfinite(v) for p in out for v in p):
        raise _LineError(f"{name!r} has a coordinate too large for a float", "fix the number")
    return out


def _unknown(keys: Iterable[str], allowed: tuple[str, ...]) -> None:
    unknown = [k for k in keys if k not in allowed]
    if not unknown:
        return
    key = unknown[0]
    close = difflib.get_close_matches(key, allowed, n=1)
    hint = f"did you mean {close[0]!r}?" if close else f"the keys are {', '.join(allowed)}"
    raise _LineError(f"unknown key {key!r}", f"{hint} (a typo must not become a default)")


def _parse_line(text: str, number: int) -> Step | None:
    if text.startswith("#"):
        raise _LineError("JSON Lines has no comments", "delete the line (blank lines are allowed)")
    try:
        obj = json.loads(text, object_pairs_hook=_unique_keys, parse_constant=_no_constants)
    except json.JSONDecodeError as exc:
        raise _LineError(
            f"not valid JSON ({exc.msg} at column {exc.colno})",
            f"write one JSON object per line, e.g. {_EXAMPLE}",
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
                f"unsupported version {json.dumps(version)}",
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
            f"unknown action {json.dumps(action)}", 'use {"action": "undo"} or {"action": "redo"}'
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
        raise _LineError(f"unknown mode {json.dumps(mode)}", f"use one of {modes}")
    a = _segment("a", obj["a"])
    b = _segment("b", obj["b"])
    sigma_h = obj.get("sigma_h")
    if sigma_h is not None and not (_is_number(sigma_h) and 0 < sigma_h < math.inf):
        raise _LineError(
            f"sigma_h must be a positive number of metres, got {json.dumps(sigma_h)}",
            "give the drawing accuracy in metres, e.g. 0.1, or leave sigma_h out",
        )
    try:
        drawn = DrawnCorrection.make(a, b, mode, None if sigma_h is None else float(sigma_h))
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


def _as_json(step: Step | DrawnCorrection) -> dict[str, Any]:
    if isinstance(step, DrawnCorrection):
        return step.to_json()
    if isinstance(step, Apply):
        return step.drawn.to_json()
    return {"action": "undo" if isinstance(step, Undo) else "redo"}


def write_corrections(
    path: str | os.PathLike[str], steps: Iterable[Step | DrawnCorrection]
) -> None:
    """Write ``steps`` as a corrections file, one JSON object per line, atomically.

    Numbers are written exactly (shortest round-trip form), so reading the file back gives equal
    corrections.
    """
    lines = [json.dumps(_as_json(s), allow_nan=False) + "\n" for s in steps]
    name = os.fspath(path)
    try:
        with atomic_writer(name) as f:
            f.writelines(lines)
    except OSError as exc:
        raise InputError(
            f"{name}: cannot write the file ({exc.strerror or exc}); check that the directory "
            "exists and is writable"
        ) from None
