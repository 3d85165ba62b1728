"""Line-oriented text shared by the pose-graph readers and writers.

Reads a (possibly compressed) file into lines, parses numbers with their file and line, builds every
error message, and runs the tagged-line loop that g2o and TORO differ in only by their syntax.
"""

from __future__ import annotations

import bz2
import gzip
import math
import os
import re
import stat
import zlib
from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray

from hitl_slam.errors import InputError

__all__ = [
    "ANGLE_LIMIT",
    "COMPRESSED_SUFFIXES",
    "COORDINATE_LIMIT",
    "FULL_TURN_SLACK",
    "MAX_ANGLE",
    "MAX_COORDINATE",
    "MAX_INFORMATION",
    "MIN_BEAM_SPACING",
    "STRICT_FLOAT",
    "Limit",
    "PathLike",
    "RawGraph",
    "Syntax",
    "beam_spacing_problem",
    "check_regular_file",
    "first_beyond",
    "format_graph",
    "input_error",
    "limit_error",
    "parse_int",
    "parse_tagged_lines",
    "read_lines",
    "sci",
    "shorten",
]

PathLike = str | os.PathLike[str]

COMPRESSED_SUFFIXES = frozenset({".gz", ".bz2"})

_INT64_MIN, _INT64_MAX = -(2**63), 2**63 - 1
# float() also accepts "1_000" and non-ASCII digits; a pose graph that contains them is more likely
# corrupted than meant, so lines holding either are checked token by token against this grammar.
STRICT_FLOAT = re.compile(
    r"[+-]?(?:(?:\d+\.?\d*|\.\d+)(?:[eE][+-]?\d+)?|nan|inf|infinity)", re.ASCII | re.IGNORECASE
)
"""A decimal number as the text readers accept it: ASCII digits only, no ``_`` separators (both
of which Python's and numpy's float parsing would take)."""
_FIX_LINE = "fix the line or delete it"

# Largest magnitudes the readers accept. A finite value can still be unusable: the solver squares
# residuals weighted by the information (chi2 = r^T Omega r, Hessian J^T Omega J), so a weight near
# float64's 1.8e308 overflows to inf on the first iteration and the solve "converges" at once.
# Values past these limits are unit mistakes or damaged files, never real data, and are refused at
# load with file and line.

MAX_INFORMATION = 1e30
"""Largest |entry| of an information matrix (inverse covariance). Its square root, 1e15, is the
largest whitening factor: whitened residuals and the Hessian stay inside float64's range for any
residual within :data:`MAX_COORDINATE`. It is a range limit, not a conditioning one: weights far
apart (1e30 next to 1) still leave the linear system with no usable precision, so an edge meant
to be exact is better written with a large but sane value such as 1e12, or a vertex held still
with a g2o ``FIX`` line."""

MAX_COORDINATE = 1e9
"""Largest |x|, |y| of a vertex pose or |dx|, |dy| of a measurement, in metres. 1e9 m is 2.6 times
the distance to the Moon, so anything larger is a unit mistake or corruption; within it float64
holds a position to better than a micrometre (the spacing of doubles near 1e9 is 1.2e-7), and
squared residuals (about 1e19) weighted by :data:`MAX_INFORMATION` stay far from overflow."""

MAX_ANGLE = 1e6
"""Largest |theta| of a vertex pose or |dtheta| of a measurement, in radians (160,000 turns).
Angles are wrapped to (-pi, pi] at load, but a double keeps only its absolute spacing through
the wrap (1.2e-10 rad near 1e6, 2 rad near 1e16, where cos and sin mean nothing); an
angle this large is in the wrong unit or damaged, not a heading."""


@dataclass(frozen=True)
class Limit:
    """The largest magnitude a field may have, and the message parts for one that exceeds it."""

    bound: float
    what: str
    todo: str


MIN_BEAM_SPACING = 1e-5
"""Smallest angle between neighbouring laser beams, in radians (0.0006 degrees, 630,000 beams a
turn; real 2D lasers space theirs 0.01 degrees or more). A spacing of 0 or 1e-30 puts every beam
on one ray: the field is damaged, not a laser."""

FULL_TURN_SLACK = 0.05
"""How far (radians, about 3 degrees) a scan's span may exceed a full turn: 360-degree drivers
write ``n * increment`` or ``angle_max - angle_min`` a little over 2 pi (rounding, an overlapping
last beam), which is harmless; far beyond it the beam angles mean nothing."""


def beam_spacing_problem(beams: int, spacing: float, field_of_view: float | None = None) -> str:
    """What is wrong with ``beams`` beams ``spacing`` rad apart (and a declared field of view),
    or "" when they make sense: a spacing finite and at least :data:`MIN_BEAM_SPACING` in
    magnitude (negative: beams counted clockwise, as upside-down mounts do), and a span of at
    most a full turn plus :data:`FULL_TURN_SLACK`."""
    turn = 2.0 * math.pi + FULL_TURN_SLACK
    if not math.isfinite(spacing) or (beams > 1 and abs(spacing) < MIN_BEAM_SPACING):
        return (
            f"the beam spacing is {spacing:.6g} rad; it must be a finite number of at least "
            f"{MIN_BEAM_SPACING:g} rad (a 1-degree laser: 0.0174533)"
        )
    span = max(beams - 1, 0) * abs(spacing)
    if span > turn:
        return (
            f"{beams} beams {spacing:.6g} rad apart span {span:.6g} rad, more than a full turn "
            f"(2 pi = 6.28319 rad); the beam spacing is wrong (a 1-degree laser: 0.0174533)"
        )
    if field_of_view is not None and not (
        math.isfinite(field_of_view) and abs(field_of_view) <= turn
    ):
        return (
            f"the field of view is {field_of_view:.6g} rad; it must be at most a full turn "
            "(2 pi = 6.28319 rad)"
        )
    return ""


def sci(value: float) -> str:
    """``1e9``, not Python's ``1e+09``: how limits are written in messages."""
    mantissa, exponent = f"{value:.0e}".split("e")  # 1e9, not Python's 1e+09
    return f"{mantissa}e{int(exponent)}"


COORDINATE_LIMIT = Limit(
    MAX_COORDINATE,
    f"a coordinate beyond +/-{sci(MAX_COORDINATE)} m, larger than any map (a unit mistake or a "
    "damaged file)",
    "write positions and translations in metres, or fix the line",
)
ANGLE_LIMIT = Limit(
    MAX_ANGLE,
    f"an angle beyond +/-{sci(MAX_ANGLE)} rad (160,000 turns): a unit mistake or a damaged "
    "file, not a heading",
    "write angles in radians, preferably within (-pi, pi], or fix the line",
)
_POSE_LIMITS = (COORDINATE_LIMIT, COORDINATE_LIMIT, ANGLE_LIMIT)


def _information_limit(syntax: Syntax) -> Limit:
    fix = ", or hold a vertex still with a FIX line" if "FIX" in syntax.extra_tags else ""
    return Limit(
        MAX_INFORMATION,
        f"an information entry beyond +/-{sci(MAX_INFORMATION)}, too large for the solver to "
        "weight squared residuals with in float64 (they overflow to inf)",
        "for an edge meant to be exact write a large but sane weight such as 1e12 (information "
        f"is the inverse covariance){fix}",
    )


_MAX_ECHOED = 80
"""Longest run of non-blank input a message repeats; longer ones are cut (a 10 MB token in a
file must not become a 10 MB error message)."""


def shorten(text: str) -> str:
    """``text`` with every run of more than :data:`_MAX_ECHOED` non-blank characters cut to its
    start, an ellipsis and its length."""
    return re.sub(
        rf"\S{{{_MAX_ECHOED + 1},}}",
        lambda m: f"{m[0][: _MAX_ECHOED - 20]}... ({len(m[0])} characters)",
        text,
    )


def input_error(path: str, line: int | None, what: str, todo: str) -> InputError:
    """The one place messages are shaped: ``{path}:{line}: {what is wrong}; {what to do}``.
    Input quoted in ``what`` is shortened (:func:`shorten`); the path is not."""
    where = path if line is None else f"{path}:{line}"
    return InputError(f"{where}: {shorten(what)}; {shorten(todo)}")


def limit_error(path: str, line: int | None, what: str, limit: Limit) -> InputError:
    """``what`` (e.g. ``"x is '1e300' (field 2)"``) is beyond ``limit``."""
    return input_error(path, line, f"{what}: {limit.what}", limit.todo)


def first_beyond(
    values: NDArray[np.float64], bounds: NDArray[np.float64]
) -> tuple[int, int] | None:
    """``(row, column)`` of the first entry of the 2D ``values`` whose magnitude exceeds its
    column's bound (NaN counts as beyond), or None when every entry is within."""
    with np.errstate(invalid="ignore"):
        bad = ~(np.abs(values) <= bounds)
    if not bad.any():
        return None
    row, column = np.argwhere(bad)[0]
    return int(row), int(column)


_NOT_REGULAR = (
    (stat.S_ISFIFO, "a FIFO (named pipe)"),
    (stat.S_ISSOCK, "a socket"),
    (stat.S_ISCHR, "a character device"),
    (stat.S_ISBLK, "a block device"),
)


def check_regular_file(path: PathLike, *, missing_ok: bool = False) -> None:
    """Refuse, before opening it, anything but a regular file (or a symlink to one): reading a
    FIFO waits for a writer forever, a device never ends. Missing files and directories get their
    own messages (``missing_ok``: a missing file passes, for a caller with its own message)."""
    name = os.fspath(path)
    try:
        mode = os.stat(name).st_mode
    except FileNotFoundError:
        if missing_ok:
            return
        raise input_error(
            name, None, "no such file", "check the path and the working directory"
        ) from None
    except PermissionError:
        raise input_error(name, None, "permission denied", "make the file readable") from None
    except (OSError, ValueError) as exc:
        raise input_error(
            name, None, f"cannot be read ({exc})", "check the path and the file"
        ) from None
    if stat.S_ISREG(mode):
        return
    if stat.S_ISDIR(mode):
        raise input_error(name, None, "is a directory, not a file", "give the path of a file")
    kind = next((label for test, label in _NOT_REGULAR if test(mode)), "a special file")
    raise input_error(
        name,
        None,
        f"is {kind}, not a regular file (reading it could wait forever)",
        "save the data to a regular file and give its path",
    )


def _read_bytes(name: str, suffix: str) -> bytes:
    if suffix == ".gz":
        with gzip.open(name, "rb") as f:
            return f.read()
    if suffix == ".bz2":
        with bz2.open(name, "rb") as f:
            return f.read()
    with open(name, "rb") as f:
        return f.read()


def read_lines(path: PathLike) -> list[str]:
    """The file's lines (``.gz``/``.bz2`` decompressed, UTF-8 with or without BOM).

    Any line ending (LF, CRLF, CR) counts, so line numbers match what an editor shows.
    """
    name = os.fspath(path)
    compressed = os.path.splitext(name)[1].lower()
    check_regular_file(name)
    try:
        data = _read_bytes(name, compressed)
    except FileNotFoundError:
        raise input_error(
            name, None, "no such file", "check the path and the working directory"
        ) from None
    except IsADirectoryError:
        raise input_error(
            name, None, "is a directory, not a file", "give the path of a file"
        ) from None
    except PermissionError:
        raise input_error(name, None, "permission denied", "make the file readable") from None
    except (OSError, EOFError, zlib.error, ValueError) as exc:
        what = "cannot be decompressed" if compressed in COMPRESSED_SUFFIXES else "cannot be read"
        raise input_error(
            name, None, f"{what} ({exc})", "check that the file is complete and not damaged"
        ) from None
    if data.startswith(b"\xef\xbb\xbf"):
        data = data[3:]
    try:
        text = data.decode("utf-8")
    except UnicodeDecodeError as exc:
        line = data.count(b"\n", 0, exc.start) + 1
        column = exc.start - data.rfind(b"\n", 0, exc.start)
        raise input_error(
            name,
            line,
            f"not UTF-8 text (byte 0x{data[exc.start]:02x} at column {column})",
            "save the file as UTF-8 or plain ASCII text",
        ) from None
    return text.replace("\r\n", "\n").replace("\r", "\n").split("\n")


def parse_int(path: str, line: int, token: str, name: str) -> int:
    """An int64 field such as a vertex id; anything else is an error naming the field."""
    try:
        value = int(token) if token.isascii() and "_" not in token else None
    except ValueError:
        value = None
    if value is None:
        raise input_error(path, line, f"bad {name} {token!r} (expected an integer)", _FIX_LINE)
    if not _INT64_MIN <= value <= _INT64_MAX:
        raise input_error(path, line, f"{name} {token} does not fit in 64 bits", _FIX_LINE)
    return value


def _parse_floats(
    path: str,
    line: int,
    tokens: Sequence[str],
    names: Sequence[str],
    tag: str,
    strict: bool,
    limits: Sequence[Limit],
) -> list[float]:
    # The values are the last len(names) tokens; messages number fields with the tag as field 0.
    offset = len(tokens) - len(names)
    values: list[float] | None
    try:
        values = [float(t) for t in tokens[offset:]]
    except ValueError:
        values = None
    if values is None or strict:
        for k, token in enumerate(tokens[offset:]):
            if not STRICT_FLOAT.fullmatch(token):
                raise input_error(
                    path,
                    line,
                    f"bad number {token!r} for {names[k]} (field {offset + k} of {tag})",
                    "write a decimal number such as 1.5 or -2e-3",
                )
        values = [float(t) for t in tokens[offset:]]
    if not all(map(math.isfinite, values)):
        k = next(k for k, v in enumerate(values) if not math.isfinite(v))
        raise input_error(
            path,
            line,
            f"{names[k]} is {tokens[offset + k]!r} (field {offset + k} of {tag}): NaN/inf "
            "or a number too large for float64",
            "replace it with a finite number or delete the line",
        )
    for k, (value, limit) in enumerate(zip(values, limits, strict=True)):
        if not -limit.bound <= value <= limit.bound:
            raise input_error(
                path,
                line,
                f"{names[k]} is {tokens[offset + k]!r} (field {offset + k} of {tag}): {limit.what}",
                limit.todo,
            )
    return values


@dataclass(frozen=True)
class Syntax:
    """What distinguishes one pose-graph text format from another."""

    name: str
    vertex_tag: str
    edge_tag: str
    info_fields: tuple[str, str, str, str, str, str]
    """The six information entries in the order the file writes them."""
    info_index: tuple[tuple[int, int], ...]
    """``(row, col)`` in the ``(x, y, theta)`` matrix of each of ``info_fields``."""
    extra_tags: frozenset[str] = frozenset()
    """Tags the format module interprets itself (collected, not skipped)."""

    @property
    def edge_fields(self) -> tuple[str, ...]:
        return ("dx", "dy", "dtheta", *self.info_fields)

    def usage(self) -> str:
        edge = " ".join(("i", "j", *self.edge_fields))
        return f"'{self.vertex_tag} id x y theta' and '{self.edge_tag} {edge}'"


@dataclass
class RawGraph:
    """A parsed file before validation: ids as written, values as parsed, line numbers kept."""

    path: str
    vertex_ids: list[int] = field(default_factory=list)
    vertex_lines: list[int] = field(default_factory=list)
    poses: list[list[float]] = field(default_factory=list)
    edge_ids: list[tuple[int, int]] = field(default_factory=list)
    edge_lines: list[int] = field(default_factory=list)
    edge_values: list[list[float]] = field(default_factory=list)
    """Per edge: dx, dy, dtheta, then the six information entries in the file's order."""
    extra: list[tuple[int, list[str]]] = field(default_factory=list)
    """``(line, tokens)`` of every line whose tag is one of ``Syntax.extra_tags``."""
    skipped: dict[str, int] = field(default_factory=dict)
    skipped_first_line: dict[str, int] = field(default_factory=dict)
    anchor: tuple[int, int] | None = None
    """``(vertex id, line)`` of the vertex the file says to hold fixed, if it says so."""
    merged_vertices: int = 0
    dropped_self_loops: int = 0


def _field_count_error(
    path: str, line: int, tag: str, fields: Sequence[str], got: int
) -> InputError:
    return input_error(
        path,
        line,
        f"{tag} needs {len(fields)} fields after the tag ({' '.join(fields)}), got {got}",
        _FIX_LINE,
    )


def parse_tagged_lines(path: str, lines: Sequence[str], syntax: Syntax) -> RawGraph:
    """Parse vertex and edge lines; collect ``extra_tags`` lines; count every other tag.

    Blank lines and lines starting with ``#`` are ignored. Errors found on a single line (bad
    numbers, field counts, NaN/inf, values beyond :data:`MAX_COORDINATE`, :data:`MAX_ANGLE` or
    :data:`MAX_INFORMATION`, duplicate vertex ids, self-loops) are raised here.
    """
    raw = RawGraph(path)
    vertex_tag, edge_tag = syntax.vertex_tag, syntax.edge_tag
    vertex_fields = ("x", "y", "theta")
    edge_fields = syntax.edge_fields
    edge_usage = ("i", "j", *edge_fields)
    edge_limits = (*_POSE_LIMITS, *[_information_limit(syntax)] * len(syntax.info_fields))
    first_definition: dict[int, int] = {}
    for number, line in enumerate(lines, 1):
        tokens = line.split()
        if not tokens or tokens[0].startswith("#"):
            continue
        tag = tokens[0]
        if tag not in (edge_tag, vertex_tag):
            if tag in syntax.extra_tags:
                raw.extra.append((number, tokens))
            else:
                raw.skipped[tag] = raw.skipped.get(tag, 0) + 1
                raw.skipped_first_line.setdefault(tag, number)
            continue
        strict = not line.isascii() or line.count("_") != tag.count("_")
        if tag == edge_tag:
            if len(tokens) != 12:
                raise _field_count_error(path, number, tag, edge_usage, len(tokens) - 1)
            i = parse_int(path, number, tokens[1], "vertex id i")
            j = parse_int(path, number, tokens[2], "vertex id j")
            if i == j:
                raise input_error(
                    path,
                    number,
                    f"edge from vertex {i} to itself (self-loop)",
                    "an edge must join two different vertices; fix the ids or delete the line",
                )
            raw.edge_values.append(
                _parse_floats(path, number, tokens, edge_fields, tag, strict, edge_limits)
            )
            raw.edge_ids.append((i, j))
            raw.edge_lines.append(number)
        else:
            if len(tokens) != 5:
                raise _field_count_error(path, number, tag, ("id", *vertex_fields), len(tokens) - 1)
            vertex_id = parse_int(path, number, tokens[1], "vertex id")
            first = first_definition.setdefault(vertex_id, number)
            if first != number:
                raise input_error(
                    path,
                    number,
                    f"duplicate vertex id {vertex_id} (first defined at line {first})",
                    "give every vertex its own id, or delete one of the two lines",
                )
            raw.poses.append(
                _parse_floats(path, number, tokens, vertex_fields, tag, strict, _POSE_LIMITS)
            )
            raw.vertex_ids.append(vertex_id)
            raw.vertex_lines.append(number)
    return raw


def format_graph(
    syntax: Syntax,
    vertex_ids: NDArray[np.int64],
    poses: NDArray[np.float64],
    edge_ids: NDArray[np.int64],
    measurements: NDArray[np.float64],
    information: NDArray[np.float64],
    extra_lines: Sequence[str] = (),
) -> str:
    """The file text: vertices, then ``extra_lines``, then edges, floats written exactly (repr)."""
    rows = [r for r, _ in syntax.info_index]
    cols = [c for _, c in syntax.info_index]
    edge_values = np.hstack([measurements, information[:, rows, cols]])
    # Python's float repr is the shortest text that reads back to the same double.
    out = [
        f"{syntax.vertex_tag} {vid} {' '.join(map(repr, pose))}"
        for vid, pose in zip(vertex_ids.tolist(), poses.tolist(), strict=True)
    ]
    out.extend(extra_lines)
    out.extend(
        f"{syntax.edge_tag} {i} {j} {' '.join(map(repr, values))}"
        for (i, j), values in zip(edge_ids.tolist(), edge_values.tolist(), strict=True)
    )
    return "\n".join(out) + "\n"
