"""A ROS bag's own SLAM (``map -> odom`` on ``/tf``, as slam_toolbox, Cartographer, gmapping and
AMCL publish it): its trajectory as a map to correct, the odometry map the front end starts from
instead, and the two maps compared by the inconsistency metric (docs/ALGORITHM.md §F.7).
"""

from __future__ import annotations

import dataclasses
from typing import Any

import numpy as np

from hitl_slam.config import DEFAULT, Config
from hitl_slam.geometry import chain_steps
from hitl_slam.map import InformationSource, Map, motion_model_information

__all__ = [
    "COMPARISON",
    "REPLACED",
    "compare",
    "has_own_slam",
    "odometry_map",
    "own_slam_map",
    "trajectory_of",
]

REPLACED = "replaced_trajectory"
"""``metadata`` key of the front end's map of a bag with its own SLAM: the trajectory it replaced
(the reader's ``metadata["trajectory"]``, e.g. ``slam (map -> base_link)``)."""

COMPARISON = "trajectory_comparison"
"""``metadata`` key of that map: ``{"trajectory", "bag_slam_m2", "front_end_m2"}``, the
inconsistency [m^2] of the bag's own trajectory and of the front end's map, before any correction
(:func:`compare`)."""

_SLAM = "slam ("  # how the reader's metadata["trajectory"] names the SLAM's trajectory


def has_own_slam(m: Map) -> bool:
    """Whether ``m`` is a bag read with its map frame whose poses are the SLAM's trajectory
    (``metadata["trajectory"]`` ``slam (map -> base_link)``, the odometry kept in
    ``metadata["odometry_poses"]``)."""
    return trajectory_of(m).startswith(_SLAM) and "odometry_poses" in m.metadata


def trajectory_of(m: Map) -> str:
    """The reader's word on the poses of a bag's map (``slam (map -> base_link)``, ``odometry
    (odom -> base_link)``); "" for other maps."""
    value = m.metadata.get("trajectory")
    return value if isinstance(value, str) else ""


def own_slam_map(m: Map, config: Config = DEFAULT) -> Map:
    """The bag's own SLAM trajectory as a map to correct: its poses, and the chain of steps
    between consecutive scans measured from them (``z = x_i^-1 x_(i+1)``, motion-model
    information; docs/ALGORITHM.md §1.2-1.3), as for any map of absolute poses. The reader's chain
    is the odometry's steps: a correction's solve over it would pull the SLAM's map back towards
    the odometry wherever the SLAM closed a loop."""
    n = m.num_poses
    z = chain_steps(m.poses)
    return dataclasses.replace(
        m,
        edges=np.stack([np.arange(n - 1), np.arange(1, n)], axis=1).astype(np.int64),
        measurements=z,
        information=motion_model_information(z, config),
        information_source=np.full(n - 1, InformationSource.MOTION_MODEL, dtype=np.int8),
        metadata=dict(m.metadata),
    )


def odometry_map(m: Map, odom_frame: str = "odom") -> Map:
    """The map the front end starts from instead of the bag's own SLAM trajectory: the same scans
    at the odometry's poses (``metadata["odometry_poses"]``) with the reader's chain (the odometry's
    steps), as the bag read without its map frame gives it over these scans. Its metadata names
    the trajectory it replaces (:data:`REPLACED`)."""
    metadata = {k: v for k, v in m.metadata.items() if k != "odometry_poses"}
    base = str(m.metadata.get("pose_frame", "base_link"))
    metadata["trajectory"] = f"odometry ({odom_frame.lstrip('/')} -> {base})"
    metadata[REPLACED] = trajectory_of(m)
    return dataclasses.replace(
        m, poses=np.array(m.metadata["odometry_poses"], dtype=np.float64), metadata=metadata
    )


def compare(own: Map, front_end: Map, config: Config = DEFAULT) -> dict[str, Any]:
    """The :data:`COMPARISON` of the bag's own SLAM trajectory (``own``, :func:`own_slam_map`) and
    the front end's map of the same scans: the inconsistency of each under its own poses (lower
    is more consistent; docs/ALGORITHM.md §6)."""
    from hitl_slam.metrics import inconsistency

    return {
        "trajectory": trajectory_of(own),
        "bag_slam_m2": float(inconsistency(own, config=config).total_m2),
        "front_end_m2": float(inconsistency(front_end, config=config).total_m2),
    }
