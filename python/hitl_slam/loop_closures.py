"""The loop closures of a map built by the front end (docs/ALGORITHM.md §F.6), and the map a
session solves once some of them are rejected. Every loop closure the front end found is an edge
of its map; the map's metadata lists which edges they are, with the trust the front end's robust
solve gave each (its dynamic covariance scaling weight, 0..1), its correlative score, and which
it rejected by itself (weight below 0.5). A map without that metadata has no loop closures here
and behaves exactly as before.

:func:`effective_map` is the map without a set of rejected loop closures: a Map sharing every
array but the factors, made once per set (so each set's correction engine is built once), with
the per-map work that does not depend on loop closures (the scans held in the core, the odometry
check of the chain) taken from the full map instead of recomputed.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Iterable
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from hitl_slam.errors import InputError
from hitl_slam.map import Map

__all__ = [
    "AUTO_REJECTED",
    "EDGES",
    "KEYS",
    "SCORE",
    "WEIGHT",
    "LoopClosure",
    "LoopClosureTable",
    "effective_map",
    "loop_closure_metadata",
]

EDGES = "loop_closure_edges"
"""Metadata key: ``(L,)`` int64, the edge row of each loop closure in the map."""
WEIGHT = "loop_closure_weight"
"""Metadata key: ``(L,)`` float64, the front end's final robust weight (trust, 0..1)."""
SCORE = "loop_closure_score"
"""Metadata key: ``(L,)`` float64, the correlative score of its match (0..1)."""
AUTO_REJECTED = "loop_closure_auto_rejected"
"""Metadata key: ``(L,)`` bool, rejected by the front end (weight below 0.5)."""
KEYS = (EDGES, WEIGHT, SCORE, AUTO_REJECTED)

_CACHE_SIZE = 8
"""Effective maps kept per map (most recently used): each holds a correction engine."""


@dataclass(frozen=True)
class LoopClosure:
    """One loop closure of a session's map."""

    index: int  # its number among the map's loop closures, from 0
    edge: int  # its row among the map's edges
    pair: tuple[int, int]  # the two poses it joins
    weight: float  # the front end's trust in it, 0..1
    score: float  # the correlative score of its match, 0..1
    auto_rejected: bool  # rejected by the front end (weight below 0.5)
    rejected: bool  # left out of the solve now


@dataclass(frozen=True, eq=False)
class LoopClosureTable:
    """The loop closures a map's metadata lists (see the module's keys), checked."""

    edges: NDArray[np.int64]
    weights: NDArray[np.float64]
    scores: NDArray[np.float64]
    auto_rejected: NDArray[np.bool_]
    pairs: NDArray[np.int64]  # (L, 2) the poses each joins, from the map's edges

    @property
    def count(self) -> int:
        return int(self.edges.shape[0])

    @property
    def auto_rejected_set(self) -> frozenset[int]:
        return frozenset(int(k) for k in np.flatnonzero(self.auto_rejected))

    def items(self, rejected: Iterable[int]) -> list[LoopClosure]:
        """Every loop closure, ``rejected`` (indices) marked."""
        out = set(rejected)
        return [
            LoopClosure(
                index=k,
                edge=int(self.edges[k]),
                pair=(int(self.pairs[k, 0]), int(self.pairs[k, 1])),
                weight=float(self.weights[k]),
                score=float(self.scores[k]),
                auto_rejected=bool(self.auto_rejected[k]),
                rejected=k in out,
            )
            for k in range(self.count)
        ]

    @classmethod
    def of(cls, map: Map) -> LoopClosureTable | None:
        """The map's loop closures; None when its metadata lists none (any other input).

        Raises:
            InputError: the metadata lists them but is malformed (a missing or mistyped array,
                an edge row out of range or repeated, a weight or score not finite in 0..1).
        """
        present = [key for key in KEYS if key in map.metadata]
        if not present:
            return None
        what = f"{map.name}: the map's loop closures"
        if len(present) != len(KEYS):
            missing = ", ".join(k for k in KEYS if k not in map.metadata)
            raise InputError(f"{what} are incomplete ({missing} missing); rebuild the map")
        try:
            edges = np.asarray(map.metadata[EDGES])
            weights = np.asarray(map.metadata[WEIGHT])
            scores = np.asarray(map.metadata[SCORE])
            auto = np.asarray(map.metadata[AUTO_REJECTED])
            if edges.ndim != 1 or edges.dtype.kind not in "iu":
                raise ValueError("the edge rows are not a list of integers")
            count = edges.shape[0]
            for name, array, kinds in (
                ("weights", weights, "fiu"),
                ("scores", scores, "fiu"),
                ("rejection flags", auto, "b"),
            ):
                if array.shape != (count,) or array.dtype.kind not in kinds:
                    raise ValueError(f"the {name} are not {count} values of the right type")
            weights = weights.astype(np.float64)
            scores = scores.astype(np.float64)
            if not (np.isfinite(weights).all() and np.isfinite(scores).all()):
                raise ValueError("a weight or score is not finite")
            if count and (weights.min() < 0 or weights.max() > 1 + 1e-9):
                raise ValueError("a weight is outside 0..1")
            edges = edges.astype(np.int64)
            if count and (edges.min() < 0 or edges.max() >= map.edges.shape[0]):
                raise ValueError("an edge row is not an edge of the map")
            if np.unique(edges).shape[0] != count:
                raise ValueError("an edge is listed twice")
        except (ValueError, TypeError) as exc:
            raise InputError(f"{what} are malformed: {exc}; rebuild the map") from None
        for array in (edges, weights, scores, auto):
            array.flags.writeable = False
        pairs = np.ascontiguousarray(map.edges[edges])
        pairs.flags.writeable = False
        return cls(edges, weights, scores, auto.astype(bool), pairs)


def loop_closure_metadata(
    edges: NDArray[np.int64],
    weights: NDArray[np.float64],
    scores: NDArray[np.float64],
    auto_rejected: NDArray[np.bool_],
) -> dict[str, NDArray[np.generic]]:
    """The metadata entries that list a map's loop closures (stored in a ``.hitl`` as arrays)."""
    return {
        EDGES: np.ascontiguousarray(edges, dtype=np.int64),
        WEIGHT: np.ascontiguousarray(weights, dtype=np.float64),
        SCORE: np.ascontiguousarray(scores, dtype=np.float64),
        AUTO_REJECTED: np.ascontiguousarray(auto_rejected, dtype=bool),
    }


def effective_map(map: Map, rejected: frozenset[int]) -> Map:
    """``map`` without the edges of the loop closures ``rejected`` (indices into its
    :class:`LoopClosureTable`): ``map`` itself when none is rejected, otherwise a Map sharing its
    poses, points and metadata-free observation arrays (a session's
    :class:`~hitl_slam.workspace.Workspace` keeps the ones it uses). The loop closures left in
    it are listed in its metadata with their new edge rows, none marked as rejected by the front
    end (this map is what a person chose); the corrections of a session solve over it.

    Raises:
        InputError: an index that is not one of the map's loop closures.
    """
    if not rejected:
        return map
    table = LoopClosureTable.of(map)
    count = 0 if table is None else table.count
    bad = sorted(k for k in rejected if not 0 <= k < count)
    if bad or table is None:
        raise InputError(
            f"{map.name}: no loop closure {bad[0] if bad else min(rejected)} (it has {count})"
        )
    return _derive(map, table, rejected)


def kept_edges(map: Map, rejected: frozenset[int]) -> NDArray[np.bool_]:
    """Which of ``map``'s edges :func:`effective_map` keeps without the loop closures
    ``rejected`` (checked there)."""
    keep = np.ones(map.edges.shape[0], dtype=bool)
    table = LoopClosureTable.of(map)
    if rejected and table is not None:
        keep[table.edges[sorted(rejected)]] = False
    return keep


def _derive(map: Map, table: LoopClosureTable, rejected: frozenset[int]) -> Map:
    keep = kept_edges(map, rejected)
    rows = np.full(map.edges.shape[0], -1, dtype=np.int64)
    rows[keep] = np.arange(int(keep.sum()), dtype=np.int64)
    kept = np.array([k for k in range(table.count) if k not in rejected], dtype=np.int64)
    metadata = dict(map.metadata)
    metadata.update(
        loop_closure_metadata(
            rows[table.edges[kept]],
            table.weights[kept],
            table.scores[kept],
            np.zeros(kept.shape[0], dtype=bool),
        )
    )
    return dataclasses.replace(
        map,
        edges=map.edges[keep],
        measurements=map.measurements[keep],
        information=map.information[keep],
        information_source=map.information_source[keep],
        metadata=metadata,
    )
