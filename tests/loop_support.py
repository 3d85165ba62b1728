"""A small map with loop closures for the loop closure tests: the generated lost-poses room
with true loop closures (from its true poses) between passes of the room and one false one,
which the "front end" rejected; its poses solve the graph without the false one, as the front
end's do."""

from __future__ import annotations

import dataclasses

import numpy as np

from hitl_slam.geometry import compose_rows, invert
from hitl_slam.loop_closures import loop_closure_metadata
from hitl_slam.map import InformationSource, Map
from hitl_slam.sim import Scenario, lost_poses_room

TRUE_PAIRS = ((40, 371), (81, 243), (133, 300), (207, 370), (297, 463))
FALSE_PAIR = (60, 420)
FALSE_LOOP = len(TRUE_PAIRS)  # the index of the false loop closure
INFO = np.diag([400.0, 400.0, 3000.0])


def room() -> Scenario:
    return lost_poses_room(0)


def map_with_loops(scenario: Scenario | None = None) -> Map:
    """The room's map with five true loop closures (weights 1, 1, 0.7, 1, 1) and a false one
    (2 m and 40 degrees off; weight 0.01, rejected by the front end), poses solved over the graph
    without the false one."""
    from hitl_slam.loop_closures import effective_map
    from hitl_slam.pipeline import solve_all

    s = room() if scenario is None else scenario
    base = s.map
    truth = s.truth
    pairs = np.array([*TRUE_PAIRS, FALSE_PAIR], dtype=np.int64)
    z = compose_rows(invert(truth[pairs[:, 0]]), truth[pairs[:, 1]])
    z[-1] += [2.0, 0.5, np.radians(40.0)]
    m = base.edges.shape[0]
    count = pairs.shape[0]
    weights = np.array([1.0, 1.0, 0.7, 1.0, 1.0, 0.01])
    metadata = dict(base.metadata)
    metadata.update(
        loop_closure_metadata(
            np.arange(m, m + count),
            weights,
            np.array([0.9, 0.8, 0.6, 0.85, 0.9, 0.56]),
            weights < 0.5,
        )
    )
    metadata["front_end"] = "hitl-slam"
    full = dataclasses.replace(
        base,
        edges=np.concatenate([base.edges, pairs]),
        measurements=np.concatenate([base.measurements, z]),
        information=np.concatenate([base.information, np.repeat(INFO[None], count, axis=0)]),
        information_source=np.concatenate(
            [base.information_source, np.full(count, InformationSource.INPUT, dtype=np.int8)]
        ),
        metadata=metadata,
        name="room with loop closures",
    )
    poses, _, _ = solve_all(effective_map(full, frozenset({FALSE_LOOP})), [])
    return dataclasses.replace(full, poses=poses)
