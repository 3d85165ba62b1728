"""The JSON the web API reads and writes, as pydantic models: requests are validated strictly
(finite JSON numbers, exactly two points per segment, no unknown keys: anything else is a 422),
responses are checked against the documented shapes before they leave the server.
"""

from __future__ import annotations

from typing import Annotated, Any, Literal

from pydantic import AfterValidator, BaseModel, ConfigDict, Field, Strict

from hitl_slam.corrections import Correction

__all__ = [
    "MAX_COORDINATE",
    "MAX_SIGMA_H",
    "AlignmentFigures",
    "Applied",
    "AppliedAccepted",
    "CorrectionLines",
    "DoubtfulStretch",
    "Drawn",
    "ExportRequest",
    "Files",
    "HistoryItem",
    "JournalInfo",
    "Last",
    "LoopClosureRequest",
    "LoopClosureState",
    "LoopClosures",
    "MapInfo",
    "Preview",
    "PreviewAccepted",
    "PreviewRejected",
    "Rejected",
    "Relation",
    "SaveRequest",
    "SolvedLine",
    "State",
    "TrajectoryComparison",
]

MAX_COORDINATE = 1e9
"""[m] Largest drawn coordinate (in absolute value): far beyond any map (UTM northings reach
1e7), small enough that differences and squares of coordinates stay finite."""

MAX_SIGMA_H = 1e3
"""[m] Largest drawing uncertainty: beyond it the candidate search covers whole cities and the
interpretation takes seconds to minutes (and overflows near 1e200)."""


def _within_map_range(value: float) -> float:
    if abs(value) > MAX_COORDINATE:
        raise ValueError(
            f"a coordinate of {value:g} m is out of range; draw on the map (coordinates in "
            f"metres, at most {MAX_COORDINATE:g} in absolute value)"
        )
    return value


# Strict: a coordinate must be a JSON number (a string such as "1.5" is an error, as in a
# corrections file), finite (Python's JSON reader accepts NaN and Infinity), and within
# MAX_COORDINATE (1e308 would overflow the arithmetic).
Coordinate = Annotated[
    float, Strict(), Field(allow_inf_nan=False), AfterValidator(_within_map_range)
]
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
    sigma_h: Annotated[float, Strict(), Field(gt=0, le=MAX_SIGMA_H, allow_inf_nan=False)] | None = (
        None
    )

    def to_correction(self) -> Correction:
        return Correction.make(self.a, self.b, self.mode, self.sigma_h)


class LoopClosureRequest(_Request):
    """Reject loop closure ``index`` (``rejected: true``) or reinstate it (``false``)."""

    index: Annotated[int, Strict(), Field(ge=0)]
    rejected: Annotated[bool, Strict()]


class SaveRequest(_Request):
    name: str | None = None


class ExportRequest(_Request):
    path: str


class Files(BaseModel):
    files: list[str]


class _Response(BaseModel):
    model_config = ConfigDict(extra="forbid")


class AlignmentFigures(_Response):
    """What an alignment with the scans found (``last.alignment`` of kind ``"align"``)."""

    loop_closures: int  # loop closures the front end kept
    loop_closures_rejected: int  # and those it rejected
    steps: int  # odometry steps of the input map the guard checked
    contradicted: int  # of them, contradicted by the aligned poses beyond their 99.9% bound
    poses_moved: int  # poses that moved (more than 1 mm or 1 mrad)
    max_move_m: float  # [m] the largest change of a pose position
    inconsistency: tuple[float, float]  # [m^2] of the map before and after
    relation_dcs: float  # the Phi of the statements' relations in the solve kept
    statements: Literal["yield", "firm", "none"]  # whether they yielded to the scans there


class Last(_Response):
    kind: Literal["apply", "undo", "redo", "reject", "loop_closure", "align"]
    time_ms: float
    cost: float
    initial_cost: float
    iterations: int
    reason: str | None
    alignment: AlignmentFigures | None = None  # kind "align" only (an addition to the contract)


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


class LoopClosureState(_Response):
    """How many loop closures the map has and which are rejected now (left out of the solve)."""

    count: int
    rejected: list[int]


class LoopClosures(_Response):
    """The map's loop closures, column by column (index order); they never change."""

    pairs: list[tuple[int, int]]  # the two poses each joins
    weight: list[float]  # the front end's trust, 0..1 (below 0.5: it rejected it)
    score: list[float]  # the correlative score of its match, 0..1
    auto_rejected: list[bool]


class DoubtfulStretch(_Response):
    """Scans ``first``..``last`` (0-based, inclusive) the front end doubts, and why."""

    first: int
    last: int
    reason: str


class TrajectoryComparison(_Response):
    """The front end's map of a bag beside the bag's own SLAM trajectory, before any correction."""

    trajectory: str  # the bag's, e.g. "slam (map -> base_link)"
    bag_slam_m2: float  # [m^2] the inconsistency of the bag's own SLAM trajectory
    front_end_m2: float  # [m^2] and of the front end's map, over the same scans


class MapInfo(_Response):
    """What the served map is; it never changes (an addition to the contract, issue 39)."""

    poses: Literal["front_end", "own_slam", "as_input"]
    description: str  # the same in words, e.g. "the bag's own SLAM trajectory (map -> base_link)"
    front_end_verdict: str | None  # "good" or "doubtful"; None: the front end gave none
    front_end_doubtful: list[DoubtfulStretch]
    comparison: TrajectoryComparison | None


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
    loop_closures: LoopClosureState  # an addition to the contract (issue 14)
    # An alignment with the scans is in effect: its graph replaced the map's factors, so the
    # map's own loop closures are out of the solve and cannot be rejected or reinstated.
    aligned: bool
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
