"""What a person says about a map: two drawn segments and a mode, and what the system understood
from them (docs/ALGORITHM.md §2). Plain data with a JSON form, shared by the interpreter, the solver
pipeline, the session journal and the JSON Lines corrections files.
"""

from __future__ import annotations

import enum
import math
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import NDArray

from hitl_slam.errors import InputError

__all__ = ["Correction", "Interpretation", "Mode", "Segment"]

Segment = tuple[tuple[float, float], tuple[float, float]]


class Mode(enum.Enum):
    """The relation a person asserts between two features (the paper's GUI keys in brackets)."""

    COLOCATION = "colocation"  # same feature: same place and orientation [Ctrl], rank 3
    COLLINEAR = "collinear"  # same line, free to slide along it [Shift], rank 2
    PERPENDICULAR = "perpendicular"  # at 90 degrees, free translation [Shift+Alt], rank 1
    PARALLEL = "parallel"  # parallel, free translation [Shift+Ctrl], rank 1

    @classmethod
    def parse(cls, value: Mode | str) -> Mode:
        if isinstance(value, Mode):
            return value
        try:
            return cls(value)
        except ValueError:
            names = ", ".join(m.value for m in cls)
            raise InputError(f"unknown mode {value!r}; use one of {names}") from None


def _segment(name: str, value: Any) -> Segment:
    try:
        (x0, y0), (x1, y1) = value
        seg = ((float(x0), float(y0)), (float(x1), float(y1)))
    except (TypeError, ValueError):
        raise InputError(
            f"segment {name} must be two [x, y] endpoints, e.g. [[1.0, 2.0], [3.0, 2.0]]; "
            f"got {value!r}"
        ) from None
    if not all(math.isfinite(v) for p in seg for v in p):
        raise InputError(f"segment {name} has a non-finite coordinate: {value!r}")
    return seg


@dataclass(frozen=True)
class Correction:
    """Two segments drawn on the map as displayed (world frame, metres) and a mode.

    ``sigma_h`` is the drawer's accuracy in metres (None: the configuration's default).
    """

    mode: Mode
    a: Segment
    b: Segment
    sigma_h: float | None = None

    @classmethod
    def make(cls, a: Any, b: Any, mode: Mode | str, sigma_h: float | None = None) -> Correction:
        """Validated construction from loose input (lists, arrays, strings)."""
        if sigma_h is not None and not (math.isfinite(sigma_h) and sigma_h > 0):
            raise InputError(f"sigma_h must be a positive number of metres, got {sigma_h!r}")
        return cls(Mode.parse(mode), _segment("a", a), _segment("b", b), sigma_h)

    def to_json(self) -> dict[str, Any]:
        out: dict[str, Any] = {
            "mode": self.mode.value,
            "a": [list(self.a[0]), list(self.a[1])],
            "b": [list(self.b[0]), list(self.b[1])],
        }
        if self.sigma_h is not None:
            out["sigma_h"] = self.sigma_h
        return out


@dataclass(frozen=True)
class Interpretation:
    """The correction ``h = <P_a, P_b, S_a, S_b, X_a, X_b, m>`` as understood by EM (§3).

    Observation sets are fixed once chosen, as (pose index, point index within that pose's scan)
    rows, even as poses move in later solves. ``a`` is the feature observed earlier (its poses all
    precede ``b``'s); ``swapped`` says the drawn segments were exchanged to make it so.
    """

    mode: Mode
    line_a: Segment  # P_a: fitted extent, world frame at interpretation time
    line_b: Segment  # P_b
    s_a: NDArray[np.int64]  # (K_a, 2) (pose, point) rows
    s_b: NDArray[np.int64]  # (K_b, 2)
    x_a: NDArray[np.int64]  # sorted pose indices
    x_b: NDArray[np.int64]
    swapped: bool = False
    iterations: tuple[int, int] = (0, 0)
    log_likelihood: tuple[float, float] = (0.0, 0.0)
    notes: tuple[str, ...] = ()

    def __repr__(self) -> str:
        """A line a person can read (the observation sets summarized, not listed)."""

        def side(rows: NDArray[np.int64], poses: NDArray[np.int64]) -> str:
            where = f"poses {poses.min()}-{poses.max()}" if len(poses) else "no poses"
            return f"{len(rows)} points from {len(poses)} poses ({where})"

        def seg(s: Segment) -> str:
            return f"(({s[0][0]:.2f}, {s[0][1]:.2f}), ({s[1][0]:.2f}, {s[1][1]:.2f}))"

        return (
            f"Interpretation({self.mode.value}, a: {side(self.s_a, self.x_a)} on "
            f"{seg(self.line_a)}, b: {side(self.s_b, self.x_b)} on {seg(self.line_b)}, "
            f"{len(self.notes)} notes{', swapped' if self.swapped else ''})"
        )

    def to_json(self, *, arrays: bool = False) -> dict[str, Any]:
        """The JSON object (plain lists and numbers). ``arrays``: S_a, S_b, X_a and X_b as int64
        arrays (copies) instead of lists, for :meth:`hitl_slam.journal.Journal.append`, which
        writes them as the very same JSON text without building a list per row; ``from_json``
        reads either form."""

        def rows(values: NDArray[np.int64]) -> Any:
            return np.array(values, dtype=np.int64) if arrays else values.tolist()

        return {
            "mode": self.mode.value,
            "line_a": [list(self.line_a[0]), list(self.line_a[1])],
            "line_b": [list(self.line_b[0]), list(self.line_b[1])],
            "s_a": rows(self.s_a),
            "s_b": rows(self.s_b),
            "x_a": rows(self.x_a),
            "x_b": rows(self.x_b),
            "swapped": self.swapped,
            "iterations": list(self.iterations),
            "log_likelihood": list(self.log_likelihood),
            "notes": list(self.notes),
        }

    @classmethod
    def from_json(cls, data: dict[str, Any]) -> Interpretation:
        def rows(key: str, width: int) -> NDArray[np.int64]:
            return (
                np.asarray(data[key], dtype=np.int64).reshape(-1, width)
                if width > 1
                else np.asarray(data[key], dtype=np.int64).reshape(-1)
            )

        it = data.get("iterations", [0, 0])
        ll = data.get("log_likelihood", [0.0, 0.0])
        return cls(
            mode=Mode.parse(data["mode"]),
            line_a=_segment("line_a", data["line_a"]),
            line_b=_segment("line_b", data["line_b"]),
            s_a=rows("s_a", 2),
            s_b=rows("s_b", 2),
            x_a=rows("x_a", 1),
            x_b=rows("x_b", 1),
            swapped=bool(data.get("swapped", False)),
            iterations=(int(it[0]), int(it[1])),
            log_likelihood=(float(ll[0]), float(ll[1])),
            notes=tuple(str(n) for n in data.get("notes", [])),
        )
