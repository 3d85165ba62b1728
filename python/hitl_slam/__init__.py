"""hitl-slam: Human-in-the-Loop SLAM (Nashed and Biswas, AAAI 2018), fast.

Load a pose graph, optimize it, save it::

    import hitl_slam
    graph = hitl_slam.load_graph("M3500.g2o")
    poses, report = hitl_slam.optimize(graph)
    hitl_slam.save_graph(graph, poses, "M3500-optimized.g2o")

The numerical work is done by the Rust extension ``hitl_slam._core``; this package loads data,
orchestrates, and talks to people.
"""

from __future__ import annotations

import logging

from hitl_slam._core import IterationRecord, SolveReport, __version__
from hitl_slam.errors import CorrectionRejected, HitlSlamError, InputError, SolverError
from hitl_slam.graph import PoseGraph
from hitl_slam.io import LoadReport, load_graph, load_graph_with_report, save_graph
from hitl_slam.solve import Init, Method, chi2, downweighted, marginals, optimize

logging.getLogger("hitl_slam").addHandler(logging.NullHandler())

__all__ = [
    "CorrectionRejected",
    "HitlSlamError",
    "Init",
    "InputError",
    "IterationRecord",
    "LoadReport",
    "Method",
    "PoseGraph",
    "SolveReport",
    "SolverError",
    "__version__",
    "chi2",
    "downweighted",
    "load_graph",
    "load_graph_with_report",
    "marginals",
    "optimize",
    "save_graph",
]
