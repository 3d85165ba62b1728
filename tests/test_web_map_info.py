"""GET /api/map/info (issue 39, point 6): what the served map is. The front end's verdict and its
doubtful stretches (metadata ``front_end_verdict``, ``front_end_doubtful``) reach the page as
given, kept across a restart, with entries that are not scan ranges left out; the comparison of a
bag's own SLAM trajectory with the front end's map; which poses the map holds. The maps are the
generated lost-poses room with metadata set here."""

from __future__ import annotations

import dataclasses
import logging
import warnings
from pathlib import Path
from typing import Any

import numpy as np
import pytest

pytest.importorskip("fastapi", reason="the [web] extra is not installed")

from hitl_slam.map import Map
from hitl_slam.session import Session
from hitl_slam.sim import lost_poses_room
from hitl_slam.web import SessionHost, create_app
from hitl_slam.web.verdict import summary

with warnings.catch_warnings():
    warnings.simplefilter("ignore", UserWarning)
    from starlette.testclient import TestClient

STRETCHES = [
    {"first": 120, "last": 160, "reason": "match failed"},
    {"first": 300, "last": 301, "reason": "ambiguous match"},
    {"first": 410, "last": 480, "reason": "contradicts the loop closures"},
    {"first": 490, "last": 498, "reason": "match failed"},
]


def front_end_map(**metadata: Any) -> Map:
    m = lost_poses_room(0).map
    return dataclasses.replace(
        m,
        name=f"{m.name} (hitl-slam front end)",
        metadata={**m.metadata, "front_end": "hitl-slam", **metadata},
    )


def info_of(m: Map, path: Path | None = None) -> dict[str, Any]:
    session = Session.new(m, None if path is None else str(path))
    host = SessionHost(session, metrics=False)
    try:
        with TestClient(create_app(host, token=None), base_url="http://127.0.0.1:8765") as client:
            r = client.get("/api/map/info")
            assert r.status_code == 200
            result: dict[str, Any] = r.json()
            return result
    finally:
        host.close()


def test_the_front_ends_verdict_and_doubtful_stretches_reach_the_page(tmp_path: Path) -> None:
    m = front_end_map(front_end_verdict="doubtful", front_end_doubtful=STRETCHES)
    info = info_of(m, tmp_path / "room.hitl")
    assert info["poses"] == "front_end"
    assert info["description"] == "the front end's map"
    assert info["front_end_verdict"] == "doubtful"
    assert info["front_end_doubtful"] == STRETCHES
    assert summary(m) == (
        "front end: doubtful map: 4 stretches, scans 120-160 (match failed), 300-301 (ambiguous "
        "match), 410-480 (contradicts the loop closures), ... 1 more"
    )
    assert info["comparison"] is None
    # Kept in the session file: a restart serves them again.
    with Session.open(tmp_path / "room.hitl") as session:
        host = SessionHost(session, metrics=False)
        assert host.map_info() == info
        host.close()


def test_numpy_indices_a_good_verdict_and_entries_that_are_not_ranges(
    caplog: pytest.LogCaptureFixture,
) -> None:
    good = front_end_map(front_end_verdict="good", front_end_doubtful=[])
    info = info_of(good)
    assert info["front_end_verdict"] == "good"
    assert info["front_end_doubtful"] == []
    assert summary(good) == "front end: good map"
    n = good.num_poses
    odd = [
        {"first": np.int64(5), "last": np.int64(9), "reason": "match failed"},  # kept
        {"first": 490, "last": 10_000, "reason": "match failed"},  # cut at the last scan
        {"first": 30, "last": 20, "reason": "backwards"},
        {"first": -1, "last": 3, "reason": "negative"},
        {"first": n, "last": n + 5, "reason": "beyond the map"},
        {"first": 1.5, "last": 3, "reason": "not an index"},
        {"first": True, "last": 3, "reason": "a bool"},
        {"last": 3},
        "scans 1-3",
        {"first": 7, "last": 7},  # no reason: an empty one
    ]
    with caplog.at_level(logging.WARNING, logger="hitl_slam"):
        info = info_of(front_end_map(front_end_verdict="doubtful", front_end_doubtful=odd))
    assert info["front_end_doubtful"] == [
        {"first": 5, "last": 9, "reason": "match failed"},
        {"first": 490, "last": n - 1, "reason": "match failed"},
        {"first": 7, "last": 7, "reason": ""},
    ]
    assert sum("is not a scan range" in r.getMessage() for r in caplog.records) == 7
    assert summary(front_end_map(front_end_doubtful="1-3")) is None  # not a list: none
    # No verdict at all: nothing said (a map from before the front end gave one).
    assert summary(front_end_map()) is None
    assert info_of(front_end_map())["front_end_verdict"] is None


def test_the_comparison_and_which_poses_the_map_holds() -> None:
    compared = {"trajectory": "slam (map -> base_link)", "bag_slam_m2": 12.5, "front_end_m2": 9.25}
    m = front_end_map(trajectory_comparison=compared, replaced_trajectory="slam (map -> base_link)")
    info = info_of(m)
    assert info["comparison"] == compared
    assert info["description"] == (
        "the front end's map, in place of the bag's own trajectory (map -> base_link)"
    )
    room = lost_poses_room(0).map
    info = info_of(room)
    assert (info["poses"], info["description"]) == ("as_input", "the map's own poses")
    assert info["front_end_doubtful"] == []
    assert info["comparison"] is None
    own = dataclasses.replace(
        room, metadata={**room.metadata, "format": "rosbag", "trajectory": "slam (map -> base)"}
    )
    info = info_of(own)
    assert (info["poses"], info["description"]) == (
        "own_slam",
        "the bag's own SLAM trajectory (map -> base)",
    )
    # A comparison this version cannot read is none, not an error.
    assert info_of(front_end_map(trajectory_comparison={"bag_slam_m2": "x"}))["comparison"] is None
