"""What an editing session (:class:`hitl_slam.session.Session`) shows: its map, poses, lines,
history, loop closures and alignment as they stand, each read under the session's guard lock
(safe from another thread while a correction computes).
"""

from __future__ import annotations

import dataclasses
import threading

import numpy as np
from numpy.typing import NDArray

from hitl_slam.config import Config
from hitl_slam.corrections import Correction, Interpretation
from hitl_slam.journal import Journal
from hitl_slam.loop_closures import AUTO_REJECTED, EDGES, LoopClosure
from hitl_slam.map import Map
from hitl_slam.session_outcomes import refit_lines
from hitl_slam.session_state import _State
from hitl_slam.session_steps import (
    AlignStep,
    CorrectionStats,
    HistoryEntry,
    LoopClosureStep,
    _Entry,
    _frozen,
)
from hitl_slam.workspace import Workspace


class _SessionView:
    """The reading half of :class:`hitl_slam.session.Session` (which sets these attributes)."""

    _journal: Journal
    _map: Map
    _config: Config
    _state: _State
    _workspace: Workspace
    _guard: threading.Lock

    @property
    def path(self) -> str | None:
        """The session file, or ``None`` for an in-memory session."""
        return self._journal.path

    @property
    def config(self) -> Config:
        return self._config

    @property
    def input_map(self) -> Map:
        """The map the session started from (its poses are the input poses)."""
        return self._map

    @property
    def poses(self) -> NDArray[np.float64]:
        """``(N, 3)`` the current poses (a read-only array; copy it to modify)."""
        with self._guard:
            return self._state.poses

    def current_map(self) -> Map:
        """The input map with the current poses (observation arrays shared with the input),
        without the rejected loop closures: the map as it stands. Its remaining loop closures
        (if any) are listed in its metadata, none marked as rejected by the front end, so a
        session started from it starts where this one is."""
        with self._guard:
            poses = self._state.poses.copy()
            target = self._state.graph(self._workspace)
        metadata = target.metadata
        if EDGES in metadata:
            metadata = dict(metadata)
            metadata[AUTO_REJECTED] = np.zeros(np.shape(metadata[EDGES]), dtype=bool)
        return dataclasses.replace(target, poses=poses, metadata=metadata)

    def solved_map(self) -> Map:
        """The map the session's corrections solve over now: the input map without the rejected
        loop closures (the input map itself when none is rejected), or while an alignment with
        the scans is in effect the aligned map (its graph instead of the map's factors); with
        the input poses."""
        with self._guard:
            return self._state.graph(self._workspace)

    def _solve_config(self) -> Config:
        """The configuration corrections solve with now (called with the guard held): the
        session's, or while an alignment is in effect its :func:`aligned_config`."""
        aligned = self._state.alignment()
        return self._config if aligned is None else aligned.config(self._config)

    @property
    def alignment(self) -> AlignStep | None:
        """The alignment with the scans in effect (:meth:`align`), None when there is none."""
        with self._guard:
            step = self._state.alignment()
            return None if step is None else step.snapshot(self._config)

    @property
    def aligned(self) -> bool:
        """Whether an alignment with the scans is in effect (:meth:`align`): every solve then
        runs over its graph, and the map's own loop closures cannot be rejected or reinstated."""
        with self._guard:
            return self._state.alignment() is not None

    @property
    def loop_closures(self) -> list[LoopClosure]:
        """Every loop closure of the map (a map built by the front end; empty for any other),
        each with its pair of poses, the front end's trust in it (weight, 0..1), its score, and
        whether it is rejected now (left out of every solve)."""
        with self._guard:
            loops = self._state.loops
            return [] if loops is None else loops.items(self._state.rejected())

    @property
    def rejected_loop_closures(self) -> frozenset[int]:
        """The indices of the loop closures left out of the solve now."""
        with self._guard:
            return self._state.rejected()

    @property
    def loop_closure_steps(self) -> list[LoopClosureStep]:
        """Every loop closure rejected or reinstated in this session, in order, with its
        status (applied, undone, or discarded by a later step)."""
        with self._guard:
            return [t.snapshot() for t in self._state.toggles]

    @property
    def last_stats(self) -> CorrectionStats | None:
        """The numbers of the step in effect (the top of the undo stack: a correction or a loop
        closure step); None for the input map."""
        with self._guard:
            top = self._state.applied[-1] if self._state.applied else None
            return None if top is None else top.stats

    @property
    def history(self) -> list[HistoryEntry]:
        """Every requested correction in order, with its status."""
        with self._guard:
            return [e.snapshot() for e in self._state.entries]

    @property
    def active(self) -> list[Interpretation]:
        """The interpretations of the applied corrections, in the order they were applied."""
        with self._guard:
            return self._state.active()

    @property
    def lines(self) -> NDArray[np.float64]:
        """``(2K, 2)`` read-only: the solved ``(phi, rho)`` of each applied correction's lines a
        and b, in the order of :attr:`active`, as the solve of the map in effect left them
        (undo and redo restore them with the poses). For a step of a journal written before
        lines were journaled, or of an applier that returns none, they are refit (total least
        squares) to S_a and S_b under that step's poses, once."""
        with self._guard:
            top = self._state.applied[-1] if self._state.applied else None
            if top is None:
                return _frozen(np.empty((0, 2), dtype=np.float64))
            if top.lines is None:
                assert top.poses is not None
                top.lines = refit_lines(self._map, top.poses, self._state.active())
            return top.lines

    @property
    def corrections(self) -> list[Correction]:
        """The raw input of the applied corrections, in order."""
        with self._guard:
            return [e.drawn for e in self._state.applied if isinstance(e, _Entry)]

    @property
    def can_undo(self) -> bool:
        with self._guard:
            return bool(self._state.applied)

    @property
    def can_redo(self) -> bool:
        with self._guard:
            return bool(self._state.redo)
