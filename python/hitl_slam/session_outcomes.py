"""What computing a step of a session returns: an applier (:data:`Applier`) and its outcome
(:class:`CorrectionOutcome`), the checks of the poses and lines it returns, the numbers of a step
computed from them, and the result of one step of a corrections file (:class:`StepResult`).
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Any, Protocol

import numpy as np
from numpy.typing import NDArray

from hitl_slam.config import Config
from hitl_slam.corrections import Correction, Interpretation
from hitl_slam.errors import CorrectionRejected, SolverError
from hitl_slam.geometry import fit_line
from hitl_slam.map import Map
from hitl_slam.session_steps import (
    AlignStep,
    CorrectionStats,
    HistoryEntry,
    LoopClosureStep,
    _frozen,
    moved_poses,
)


class CorrectionOutcome(Protocol):
    """What an applier returns (``hitl_slam.pipeline.CorrectionResult`` is one).

    An outcome may also carry ``lines``: ``(2K, 2)`` the solved ``(phi, rho)`` of every active
    correction's two lines, in order (the new one last); the session keeps and journals them.
    An outcome without them (a stand-in applier) has its lines refit to S_a / S_b instead.
    """

    @property
    def poses(self) -> NDArray[np.float64]: ...
    @property
    def interpretation(self) -> Interpretation: ...
    @property
    def iterations(self) -> int: ...
    @property
    def initial_chi2(self) -> float: ...
    @property
    def final_chi2(self) -> float: ...
    @property
    def time_s(self) -> float: ...


Applier = Callable[
    [Map, NDArray[np.float64], Correction, Sequence[Interpretation], Config],
    CorrectionOutcome,
]
"""``(map, poses, drawn, active, config) -> outcome``: interpret ``drawn`` on ``poses`` and solve
with the ``active`` corrections plus the new one, without mutating any input; raise
:class:`CorrectionRejected` when the drawing cannot be interpreted."""


def _stats(
    before: NDArray[np.float64], after: NDArray[np.float64], outcome: CorrectionOutcome
) -> CorrectionStats:
    count, largest = moved_poses(before, after)
    return CorrectionStats(
        iterations=int(outcome.iterations),
        initial_chi2=float(outcome.initial_chi2),
        final_chi2=float(outcome.final_chi2),
        time_s=float(outcome.time_s),
        poses_moved=count,
        max_move_m=largest,
    )


def _solve_stats(
    before: NDArray[np.float64], after: NDArray[np.float64], solve: Any, elapsed: float
) -> CorrectionStats:
    """The stats of a re-solve (a loop closure step's, an alignment's): ``solve`` has its
    ``iterations``, ``initial_chi2`` and ``final_chi2``."""
    moved, largest = moved_poses(before, after)
    return CorrectionStats(
        iterations=int(solve.iterations),
        initial_chi2=float(solve.initial_chi2),
        final_chi2=float(solve.final_chi2),
        time_s=elapsed,
        poses_moved=moved,
        max_move_m=largest,
    )


def _checked_poses(poses: Any, shape: tuple[int, ...]) -> NDArray[np.float64]:
    out = np.array(poses, dtype=np.float64, order="C")
    if out.shape != shape:
        raise SolverError(f"the correction returned poses of shape {out.shape}, expected {shape}")
    if not np.isfinite(out).all():
        raise SolverError("the correction returned non-finite poses; the map was not changed")
    return out


def _checked_lines(outcome: Any, count: int) -> NDArray[np.float64] | None:
    """The outcome's solved lines as a ``(count, 2)`` float64 array; None when it has none."""
    lines = getattr(outcome, "lines", None)
    if lines is None:
        return None
    out = np.array(lines, dtype=np.float64, order="C")
    if out.shape != (count, 2):
        raise SolverError(f"the correction returned lines of shape {out.shape}, expected {count}")
    if not np.isfinite(out).all():
        raise SolverError("the correction returned non-finite lines; the map was not changed")
    return out


def refit_lines(
    map: Map, poses: NDArray[np.float64], active: Sequence[Interpretation]
) -> NDArray[np.float64]:
    """``(2K, 2)`` total-least-squares ``(phi, rho)`` of each correction's S_a and S_b under
    ``poses``: the lines of a step whose solved lines were not journaled."""
    out = np.empty((2 * len(active), 2), dtype=np.float64)
    for k, h in enumerate(active):
        out[2 * k] = fit_line(map.observed_points(h.s_a, poses))
        out[2 * k + 1] = fit_line(map.observed_points(h.s_b, poses))
    return _frozen(out)


@dataclass(frozen=True)
class StepResult:
    """What :meth:`Session.run_step` did: ``action`` "apply", "undo" or "redo"; the applier's
    ``outcome`` (apply only); the history entry the step concerned; its wall time [s]."""

    action: str
    outcome: CorrectionOutcome | None
    entry: HistoryEntry | LoopClosureStep | AlignStep
    time_s: float


def _apply_next(
    apply: Applier,
    map: Map,
    poses: NDArray[np.float64],
    drawn: Correction,
    active: list[Interpretation],
    outcomes: list[Any],
    config: Config,
    where: str,
) -> NDArray[np.float64]:
    """Applies ``drawn`` on top of ``active`` at ``poses``, appends its interpretation and
    outcome, and returns the new poses; a refusal names ``where``."""
    try:
        outcome = apply(map, poses, drawn, list(active), config)
    except CorrectionRejected as exc:
        raise CorrectionRejected(f"{where}: {exc}") from exc
    active.append(outcome.interpretation)
    outcomes.append(outcome)
    return _checked_poses(outcome.poses, poses.shape)
