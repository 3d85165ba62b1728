"""The JSON documents of the web API (shapes in :mod:`hitl_slam.web.schemas`) built from the
session's objects: a Preview of an interpretation, a history item, the ``last`` change, what the
served map is (its poses, the front end's verdict, a comparison with a bag's own SLAM).
"""

from __future__ import annotations

import base64
from typing import Any

import numpy as np
from numpy.typing import NDArray

from hitl_slam.corrections import Interpretation
from hitl_slam.loop_closures import LoopClosure
from hitl_slam.map import Map
from hitl_slam.own_slam import COMPARISON
from hitl_slam.session import AlignStep, HistoryEntry
from hitl_slam.web import origin, verdict

__all__ = [
    "alignment",
    "history_item",
    "last_change",
    "loop_closures",
    "map_info",
    "preview",
    "segment_json",
]


def segment_json(segment: Any) -> list[list[float]]:
    return [
        [float(segment[0][0]), float(segment[0][1])],
        [float(segment[1][0]), float(segment[1][1])],
    ]


def _indices_json(values: NDArray[np.int64]) -> list[int]:
    out: list[int] = values.astype(np.int64).tolist()
    return out


def _global(map: Map, rows: NDArray[np.int64]) -> str:
    index = map.point_rows(rows)
    return base64.b64encode(index.astype("<u4").tobytes()).decode("ascii")


def preview(map: Map, h: Interpretation) -> dict[str, Any]:
    """The accepted Preview of ``h``: lines where EM fitted them, X_a / X_b, and S_a / S_b as
    base64 uint32 LE global point indices."""
    return {
        "accepted": True,
        "mode": h.mode.value,
        "line_a": segment_json(h.line_a),
        "line_b": segment_json(h.line_b),
        "x_a": _indices_json(h.x_a),
        "x_b": _indices_json(h.x_b),
        "notes": list(h.notes),
        "s_a": _global(map, h.s_a),
        "s_b": _global(map, h.s_b),
    }


def history_item(entry: HistoryEntry) -> dict[str, Any]:
    h = entry.interpretation
    return {
        "index": entry.index,
        "mode": entry.mode.value,
        "status": entry.status.value,
        "reason": entry.reason,
        "line_a": None if h is None else segment_json(h.line_a),
        "line_b": None if h is None else segment_json(h.line_b),
        "drawn": entry.drawn.to_json(),
        "x_a": [] if h is None else _indices_json(h.x_a),
        "x_b": [] if h is None else _indices_json(h.x_b),
    }


def loop_closures(items: list[LoopClosure]) -> dict[str, Any]:
    """The LoopClosures document: per loop closure (in index order) its pair of poses, the front
    end's weight and score, and whether the front end rejected it; as columns, which the page
    reads once."""
    return {
        "pairs": [list(c.pair) for c in items],
        "weight": [c.weight for c in items],
        "score": [c.score for c in items],
        "auto_rejected": [c.auto_rejected for c in items],
    }


def map_info(map: Map) -> dict[str, Any]:
    """The MapInfo document: which poses the map holds (``poses``: ``front_end``, ``own_slam``
    or ``as_input``, and in words), the front end's verdict and doubtful stretches when it gave
    them (metadata ``front_end_verdict``, ``front_end_doubtful``; :mod:`hitl_slam.web.verdict`),
    and, for the front end's map of a bag with its own SLAM, the inconsistency of both
    (``comparison``). It never changes: the page fetches it once."""
    compared = map.metadata.get(COMPARISON)
    comparison = None
    if isinstance(compared, dict):
        try:
            comparison = {
                "trajectory": str(compared.get("trajectory", "")),
                "bag_slam_m2": float(compared["bag_slam_m2"]),
                "front_end_m2": float(compared["front_end_m2"]),
            }
        except (KeyError, TypeError, ValueError):
            comparison = None  # not this version's: shown as none
    return {
        "poses": origin.held(map).value,
        "description": origin.describe(map),
        verdict.VERDICT: verdict.verdict(map),
        verdict.DOUBTFUL: verdict.doubtful_stretches(map),
        "comparison": comparison,
    }


def last_change(
    kind: str,
    time_ms: float,
    *,
    cost: float = 0.0,
    initial_cost: float = 0.0,
    iterations: int = 0,
    reason: str | None = None,
    alignment: dict[str, Any] | None = None,
) -> dict[str, Any]:
    """The State's ``last``: what the latest change was and what it cost (and for an
    alignment with the scans, its figures: :func:`alignment`)."""
    return {
        "kind": kind,
        "time_ms": time_ms,
        "cost": cost,
        "initial_cost": initial_cost,
        "iterations": iterations,
        "reason": reason,
        "alignment": alignment,
    }


def _yields(phi: float, firm_dcs: float) -> bool:
    """Whether relations at DCS ``phi`` yield more than the session's own (``firm_dcs``); a Phi
    of 0 is no DCS at all: held firm."""
    return phi > 0 and (firm_dcs == 0 or phi < firm_dcs)


def alignment(step: AlignStep, firm_dcs: float, corrections: int) -> dict[str, Any]:
    """The figures of an alignment with the scans, for its ``last``: the loop closures the
    front end kept and rejected, the input map's odometry steps the guard checked and how many
    of them the aligned map contradicts, how far the poses moved, and the map's inconsistency
    [m^2] before and after, and the Phi of the statements in the solve kept, with whether they
    yielded to the scans there (a Phi below ``firm_dcs``, the session's ``relation_dcs``), held
    firm, or there were none (``corrections`` in effect: 0)."""
    return {
        "loop_closures": step.loop_closures,
        "loop_closures_rejected": step.loop_closures_rejected,
        "steps": step.steps,
        "contradicted": step.contradicted,
        "poses_moved": step.stats.poses_moved,
        "max_move_m": step.stats.max_move_m,
        "inconsistency": list(step.inconsistency),
        "relation_dcs": step.relation_dcs,
        "statements": (
            "none"
            if corrections == 0
            else "yield"
            if _yields(step.relation_dcs, firm_dcs)
            else "firm"
        ),
    }
