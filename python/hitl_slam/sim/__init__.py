"""Simulation: generated worlds with ground truth, for tests, benchmarks and the demo."""

from __future__ import annotations

from hitl_slam.sim.corridor import WALLS, World, corridor_loop, drawn_segment

__all__ = ["WALLS", "World", "corridor_loop", "drawn_segment"]
