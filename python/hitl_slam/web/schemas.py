"""The JSON the web API reads and writes, as pydantic models: requests are validated strictly
(finite JSON numbers, exactly two points per segment, no unknown keys: anything else is a 422),
responses are checked against the documented shapes before they leave the server.
"""

from __future__ import annotations

from typing import Annotated, Any, Literal

from pydantic import BaseModel, ConfigDict, Field, Strict

from hitl_slam.corrections import DrawnCorrection

__all__ = [
    "Applied",
    "AppliedAccepted",
    "CorrectionLines",
    "Drawn",
    "ExportRequest",
    "Files",
    "HistoryItem",
    "JournalInfo",
    "Last",
    "Preview",
    "PreviewAccepted",
    "PreviewRejected",
    "Rejected",
    "Relation",
    "SaveRequest",
    "SolvedLine",
    "State",
]

# Strict: a coordinate must be a JSON number (a string such as "1.5" is an error, as in a
# corrections file), and finite (Python's JSON reader accepts NaN and Infinity).
Coordinate = Annotated[float, Strict(), Field(allow_inf_nan=False)]
Point = tuple[Coordinate, Coordinate]
Segment = tuple[Point, Point]
ModeName = Literal["colocation", "collinear", "perpendicular", "parallel"]


class _Request(BaseModel):
    model_config = ConfigDict(extra="forbid")


class Drawn(_Request):
    """Two segments drawn on the map as displayed (world frame, metres) and a mode."""

    mode: ModeName
    a: Segment
    b: Segment
    sigma_h: Annotated[float, Strict(), Field(gt=0, allow_inf_nan=False)] | None = None

    def to_correction(self) -> DrawnCorrection:
        return DrawnCorrection.make(self.a, self.b, self.mode, self.sigma_h)


class SaveRequest(_Request):
    name: str | None = None


class ExportRequest(_Request):
    path: str


class Files(BaseModel):
    files: list[str]


class _Response(BaseModel):
    model_config = ConfigDict(extra="forbid")


class Last(_Response):
    kind: Literal["apply", "undo", "redo", "reject"]
    time_ms: float
    cost: float
    initial_cost: float
    iterations: int
    reason: str | None


class HistoryItem(_Response):
    index: int
    mode: ModeName
    status: Literal["applied", "undone", "discarded", "rejected", "interrupted", "pending"]
    reason: str | None
    line_a: list[list[float]] | None
    line_b: list[list[float]] | None
    drawn: dict[str, Any]  # as the corrections file writes it: mode, a, b (and sigma_h if set)
    x_a: list[int]
    x_b: list[int]


class JournalInfo(_Response):
    loaded: int
    next: int
    source: str | None


class SolvedLine(_Response):
    phi: float  # [rad] the line is x cos(phi) + y sin(phi) = rho (world frame)
    rho: float  # [m]
    segment: list[list[float]]  # the stretch its observations (S_a or S_b) cover, as drawn


class CorrectionLines(_Response):
    """A correction in effect with its solved lines a and b (an addition to the contract)."""

    index: int  # its history index
    mode: ModeName
    a: SolvedLine
    b: SolvedLine


class State(_Response):
    version: int
    map_version: int  # the version at which the poses last changed (an addition to the contract)
    name: str
    session: str
    num_poses: int
    num_points: int
    bounds: tuple[float, float, float, float]
    applied: int
    can_undo: bool
    can_redo: bool
    last: Last | None
    inconsistency_m2: float | None
    history: list[HistoryItem]
    lines: list[CorrectionLines]  # the corrections in effect, in order, with their solved lines
    journal: JournalInfo


class PreviewAccepted(_Response):
    accepted: Literal[True]
    mode: ModeName
    line_a: list[list[float]]
    line_b: list[list[float]]
    x_a: list[int]
    x_b: list[int]
    notes: list[str]
    s_a: str  # base64 of uint32 LE global point indices
    s_b: str


class PreviewRejected(_Response):
    accepted: Literal[False]
    reason: str


Preview = Annotated[PreviewAccepted | PreviewRejected, Field(discriminator="accepted")]


class AppliedAccepted(_Response):
    accepted: Literal[True]
    state: State
    solve_ms: float
    preview: PreviewAccepted | None  # None only for an undo/redo line of a --journal file


class Rejected(_Response):
    accepted: Literal[False]
    reason: str
    state: State


Applied = Annotated[AppliedAccepted | Rejected, Field(discriminator="accepted")]


class Relation(_Response):
    index: int
    mode: ModeName
    angle_deg: float
    offset_m: float | None
