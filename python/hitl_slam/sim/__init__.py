"""Simulation: generated worlds with ground truth, for tests, benchmarks and the demo.

Walls (:mod:`~hitl_slam.sim.worlds`), a lidar (:mod:`~hitl_slam.sim.lidar`), trajectories and
damaged odometry, packaged as a :class:`Scenario`; a :class:`SimulatedHuman` that repairs it.
Also generated pose graphs without observations (:mod:`~hitl_slam.sim.synthetic`, for the solver's
tests and benches) and straight walls found in a real log's point cloud
(:mod:`~hitl_slam.sim.walls`, standing in for a floor plan when simulating a person on real data).
"""

from __future__ import annotations

from hitl_slam.sim.corridor import WALLS, World, corridor_loop, drawn_segment
from hitl_slam.sim.human import (
    Inconsistency,
    RepairResult,
    RepairStep,
    SimulatedHuman,
    Visit,
    repair,
)
from hitl_slam.sim.lidar import Lidar, Scans, cast_rays
from hitl_slam.sim.odometry import (
    Fault,
    HeadingDrift,
    HeadingJump,
    OdometryNoise,
    compose_motions,
    odometry,
    relative_motions,
)
from hitl_slam.sim.scenario import (
    MapErrors,
    Scenario,
    WallFit,
    campus,
    hall,
    lost_poses_room,
    make_scenario,
    parallel_corridors,
    single_room,
)
from hitl_slam.sim.trajectory import travel_distance, waypoint_trajectory
from hitl_slam.sim.worlds import FeatureKind, FeaturePair, Floorplan

__all__ = [
    "WALLS",
    "Fault",
    "FeatureKind",
    "FeaturePair",
    "Floorplan",
    "HeadingDrift",
    "HeadingJump",
    "Inconsistency",
    "Lidar",
    "MapErrors",
    "OdometryNoise",
    "RepairResult",
    "RepairStep",
    "Scans",
    "Scenario",
    "SimulatedHuman",
    "Visit",
    "WallFit",
    "World",
    "campus",
    "cast_rays",
    "compose_motions",
    "corridor_loop",
    "drawn_segment",
    "hall",
    "lost_poses_room",
    "make_scenario",
    "odometry",
    "parallel_corridors",
    "relative_motions",
    "repair",
    "single_room",
    "travel_distance",
    "waypoint_trajectory",
]
