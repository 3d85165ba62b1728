"""hitl-slam: Human-in-the-Loop SLAM (Nashed and Biswas, AAAI 2018), fast.

Load a pose graph, optimize it, save it::

    import hitl_slam
    graph = hitl_slam.load_graph("M3500.g2o")
    poses, report = hitl_slam.optimize(graph)
    hitl_slam.save_graph(graph, poses, "M3500-optimized.g2o")

Repair a laser map by drawing corrections on it, journaled in a session file::

    from hitl_slam import Session, load_map

    m = load_map("fr079.clf.bz2")               # .covars, CARMEN .clf/.log(.gz/.bz2), .hitl
    with Session.new(m, "fr079.hitl") as s:      # every step journaled before the map changes
        s.correct([[1.2, 3.4], [4.1, 3.45]], [[10.0, 3.9], [13.2, 4.0]], "collinear")
        s.save("fr079-fixed.covars")             # or .g2o, .txt (TUM), .pgm (occupancy grid)
    print(hitl_slam.inconsistency(s.current_map()).total_m2)

In a notebook a :class:`Map` shows itself as a picture (with the ``[plot]`` extra). The
numerical work is done by the Rust extension ``hitl_slam._core``; this package loads data,
orchestrates, and talks to people. ``import hitl_slam`` imports neither the web server's
dependencies (the ``[web]`` extra) nor matplotlib (the ``[plot]`` extra).

What is here, by task:

- pose graphs: :func:`load_graph` (what it met while reading: ``graph.load_report``, a
  :class:`LoadReport`), :func:`save_graph`, :class:`PoseGraph`; solving: :func:`optimize`
  (:class:`Method`, :class:`Init`, :class:`SolveReport`, :class:`IterationRecord`),
  :func:`chi2`, :func:`downweighted`, :func:`marginals`.
- maps with observations: :func:`load_map`, :class:`Map`, :func:`export`.
- corrections: :class:`Correction` (two drawn segments and a :class:`Mode`), :class:`Session`
  (:meth:`Session.new`, :meth:`Session.open`; :class:`HistoryEntry`, :class:`EntryStatus`; what
  :meth:`Session.undo` and :meth:`Session.redo` return: a :class:`HistoryEntry`, a
  :class:`LoopClosureStep` or an :class:`AlignStep`), :class:`Config`; the steps a session runs:
  :func:`interpret` (what a drawing selects, an :class:`Interpretation`) and
  :func:`apply_correction` (one correction end to end, a :class:`CorrectionResult`); JSON Lines
  corrections files: :func:`read_corrections`, :func:`write_corrections`.
- scores: :func:`inconsistency` (:class:`Inconsistency`), :func:`ate`.
- errors (all in :mod:`hitl_slam.errors`): :class:`HitlSlamError` and its subclasses
  :class:`InputError` (bad input; also :class:`MissingExtra`, :class:`OutputError` for a file
  that could not be written, :class:`DamagedSession`, :class:`StepRefused` for an undo or redo
  with nothing to undo, :class:`AlignmentRefused`), :class:`SolverError` and
  :class:`CorrectionRejected`.
"""

from __future__ import annotations

import logging

from hitl_slam._core import IterationRecord, SolveReport, __version__
from hitl_slam.config import Config
from hitl_slam.corrections import Correction, Interpretation, Mode
from hitl_slam.corrections_file import read_corrections, write_corrections
from hitl_slam.errors import (
    AlignmentRefused,
    CorrectionRejected,
    DamagedSession,
    HitlSlamError,
    InputError,
    MissingExtra,
    OutputError,
    SolverError,
    StepRefused,
)
from hitl_slam.graph import PoseGraph
from hitl_slam.interpret import interpret
from hitl_slam.io import LoadReport, load_graph, save_graph
from hitl_slam.io.export import export
from hitl_slam.io.maps import load_map
from hitl_slam.map import Map
from hitl_slam.metrics import Inconsistency, ate, inconsistency
from hitl_slam.pipeline import CorrectionResult, apply_correction
from hitl_slam.session import AlignStep, EntryStatus, HistoryEntry, LoopClosureStep, Session
from hitl_slam.solve import Init, Method, chi2, downweighted, marginals, optimize

logging.getLogger("hitl_slam").addHandler(logging.NullHandler())

__all__ = [
    "AlignStep",
    "AlignmentRefused",
    "Config",
    "Correction",
    "CorrectionRejected",
    "CorrectionResult",
    "DamagedSession",
    "EntryStatus",
    "HistoryEntry",
    "HitlSlamError",
    "Inconsistency",
    "Init",
    "InputError",
    "Interpretation",
    "IterationRecord",
    "LoadReport",
    "LoopClosureStep",
    "Map",
    "Method",
    "MissingExtra",
    "Mode",
    "OutputError",
    "PoseGraph",
    "Session",
    "SolveReport",
    "SolverError",
    "StepRefused",
    "__version__",
    "apply_correction",
    "ate",
    "chi2",
    "downweighted",
    "export",
    "inconsistency",
    "interpret",
    "load_graph",
    "load_map",
    "marginals",
    "optimize",
    "read_corrections",
    "save_graph",
    "write_corrections",
]
