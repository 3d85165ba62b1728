"""What is computed once about one map and kept while it is worked on (issue 40): its scans
held in the core, the graphs its corrections solve over (the map without some loop closures, an
aligned map), the odometry check of each graph's chain, and each graph's correction engine with
the lock that serializes calls into it. A :class:`~hitl_slam.session.Session` owns one, so all
of a session's state has one owner; a call without one (``apply_correction(map, ...)``) makes
its own for that call.

Graphs are found by what they are (the set of rejected loop closures) or, for a graph a caller
made (an aligned map), by the object the caller holds and hands back: the workspace keeps a
reference to every graph it serves, so nothing is keyed on an address that could be reused.
"""

from __future__ import annotations

import dataclasses
import threading
from collections import OrderedDict
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray

from hitl_slam import _core
from hitl_slam.config import DEFAULT, Config
from hitl_slam.map import Map

__all__ = ["Workspace"]

GRAPHS_KEPT = 6
"""Graphs other than the input map kept with their engines (the last used): undo and redo of
loop closure toggles, and a guard's second solve, come back to a graph of a moment ago."""


@dataclass
class _Graph:
    """One graph and what was computed for it, made on first use."""

    graph: Map
    keep: NDArray[np.bool_] | None  # the input map's edges it keeps (a loop-derived graph)
    # Per odometry_check setting: the entry of the checked graph (this one where the check
    # changed nothing) and the chain steps the scans could not check.
    checked: dict[float, tuple[_Graph, NDArray[np.bool_]]] = field(default_factory=dict)
    engine: _core.CorrectionEngine | None = None
    lock: threading.Lock = field(default_factory=threading.Lock)

    def all(self) -> list[_Graph]:
        return [self, *(c for c, _ in self.checked.values() if c is not self)]


class Workspace:
    """The state kept for ``map`` (see the module's docstring). Thread-safe: one lock guards the
    workspace's own tables (briefly); each engine has its own lock for the calls into it."""

    def __init__(self, map: Map) -> None:
        self.map = map
        self._lock = threading.Lock()
        self._scans: _core.MapScans | None = None
        self._input = _Graph(map, None)
        self._derived: OrderedDict[frozenset[int], _Graph] = OrderedDict()
        self._other: list[_Graph] = []  # graphs callers made (aligned maps), the last used last

    def scans(self) -> _core.MapScans:
        """The map's scans held in the core (robot-frame points, offsets and the bounding circles
        of their blocks), shared by every graph: they all have the map's points."""
        with self._lock:
            if self._scans is None:
                self._scans = _core.MapScans(self.map.points, self.map.offsets)
            return self._scans

    def graph(self, rejected: frozenset[int]) -> Map:
        """The map without the loop closures ``rejected`` (indices into its loop closure table;
        :func:`hitl_slam.loop_closures.effective_map`), made once.

        Raises:
            InputError: an index that is not one of the map's loop closures."""
        if not rejected:
            return self.map
        with self._lock:
            hit = self._derived.get(rejected)
            if hit is not None:
                self._derived.move_to_end(rejected)
                return hit.graph
        from hitl_slam.loop_closures import effective_map, kept_edges

        entry = _Graph(effective_map(self.map, rejected), kept_edges(self.map, rejected))
        with self._lock:
            entry = self._derived.setdefault(rejected, entry)
            while len(self._derived) > GRAPHS_KEPT:
                self._derived.popitem(last=False)
        return entry.graph

    def _entries(self) -> list[_Graph]:
        return [
            e for top in (self._input, *self._derived.values(), *self._other) for e in top.all()
        ]

    def _entry(self, graph: Map) -> _Graph:
        """The entry of ``graph``: the input map, a graph :meth:`graph` or :meth:`checked`
        made, or one a caller made (held from now on, the last :data:`GRAPHS_KEPT`)."""
        with self._lock:
            for entry in self._entries():
                if entry.graph is graph:
                    return entry
            if not (
                graph.points.shape == self.map.points.shape
                and np.may_share_memory(graph.points, self.map.points)
                and np.array_equal(graph.offsets, self.map.offsets)
            ):
                raise ValueError("a workspace serves graphs with its map's points and offsets")
            entry = _Graph(graph, None)
            self._other.append(entry)
            del self._other[:-GRAPHS_KEPT]
            return entry

    def checked(self, graph: Map, config: Config = DEFAULT) -> tuple[Map, NDArray[np.bool_]]:
        """``graph`` with its chain checked against the scans
        (:func:`hitl_slam.odometry_check.checked_chain`), and the chain steps the scans could not
        check; computed once per graph and setting. A graph without some loop closures has the
        input map's chain: its checked edges are the input map's, less the dropped rows."""
        entry = self._entry(graph)
        setting = config.odometry_check
        hit = entry.checked.get(setting)
        if hit is not None:
            return hit[0].graph, hit[1]
        from hitl_slam.odometry_check import checked_chain

        if entry.keep is not None:
            full, unchecked = self.checked(self.map, config)
            keep = entry.keep
            out = (
                graph
                if full is self.map
                else dataclasses.replace(
                    graph,
                    measurements=full.measurements[keep],
                    information=full.information[keep],
                )
            )
        else:
            out, unchecked = checked_chain(graph, config)
        made = entry if out is graph else _Graph(out, None)
        with self._lock:
            kept, steps = entry.checked.setdefault(setting, (made, unchecked))
        return kept.graph, steps

    def engine(self, graph: Map) -> tuple[_core.CorrectionEngine, threading.Lock]:
        """The correction engine of ``graph`` (its relative-pose factors, and the symbolic
        analyses of the structures it solved recently), made once, and the lock every call into
        it holds (the engine releases the GIL while it solves)."""
        entry = self._entry(graph)
        with entry.lock:
            if entry.engine is None:
                from hitl_slam.pipeline import new_engine

                entry.engine = new_engine(graph)
            return entry.engine, entry.lock

    def prepare(self, graph: Map, config: Config = DEFAULT) -> None:
        """Makes now what the first correction on ``graph`` would otherwise wait for: the scans
        in the core, the graph's odometry check and the checked graph's engine (e.g. in a
        thread while a person looks at the map before drawing)."""
        self.scans()
        checked, _ = self.checked(graph, config)
        self.engine(checked)

    def engines(self) -> list[_core.CorrectionEngine]:
        """Every engine made so far (e.g. to clear their cached analyses in a benchmark)."""
        with self._lock:
            return [e.engine for e in self._entries() if e.engine is not None]
