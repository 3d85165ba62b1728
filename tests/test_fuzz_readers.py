"""Property-based fuzzing of every reader (issue 13): corrections JSON Lines, g2o, TORO,
``.covars``, CARMEN logs, relations and ROS bags. Each case is a mutated valid file or a
structurally generated one; the invariant is in :mod:`fuzz_support`: a valid object or an
InputError naming the file (and line), nothing else, no hang. Valid objects are checked (finite,
within the readers' limits) and written back where a writer exists: what a writer writes must
read back.

``make test`` runs a few cases per reader (profile ``fuzz-ci``); ``make fuzz`` runs 10^5 each.
"""

from __future__ import annotations

import importlib.util
import json
import math
import shutil
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st

from fuzz_support import (
    FUZZ_SETTINGS,
    assert_finite,
    byte_edits,
    check_path,
    check_reader,
    compressed_variant,
    mutated,
    number_tokens,
    tokens_line,
)
from hitl_slam.corrections_file import (
    MAX_SIGMA_H,
    MIN_SIGMA_H,
    Apply,
    Step,
    read_corrections,
    write_corrections,
)
from hitl_slam.errors import InputError
from hitl_slam.graph import PoseGraph
from hitl_slam.io import load_graph, save_graph
from hitl_slam.io.carmen import read_carmen
from hitl_slam.io.covars import read_covars, write_covars
from hitl_slam.io.export import write_g2o_map
from hitl_slam.io.relations import Relations, read_relations
from hitl_slam.io.textfile import MAX_COORDINATE, MAX_INFORMATION
from hitl_slam.map import Map

I6 = "1 0 0 1 0 1"
G2O_SEEDS = (
    "VERTEX_SE2 0 0 0 0\nVERTEX_SE2 1 1 0 0.1\nVERTEX_SE2 2 2 0.5 0.2\n"
    f"EDGE_SE2 0 1 1 0 0.1 {I6}\nEDGE_SE2 1 2 1 0.4 0.1 {I6}\nEDGE_SE2 0 2 2 0.5 0.2 {I6}\n",
    "# comment\nVERTEX_SE2 10 0 0 0\nVERTEX_SE2 11 1.5 -2e-3 3.14159\nFIX 11\n"
    "EDGE_SE2 10 11 1.5 0 3.1 100 0 0 100 0 1000\nVERTEX_XY 5 1 1\n",
    "EDGE_SE2 0 1 1 0 0 1 0 0 1 0 1\nEDGE_SE2 1 2 0 1 1.5 1 0 0 1 0 1\n"
    "EDGE_SE2 2 0 -1 -1 -1.5 1 0.1 0 1 0 1\n",
)
TORO_SEEDS = (
    "VERTEX2 0 0 0 0\nVERTEX2 1 1 0 0.1\nVERTEX2 2 2 0.5 0.2\n"
    f"EDGE2 0 1 1 0 0.1 {I6}\nEDGE2 1 2 1 0.4 0.1 {I6}\nEDGE2 0 2 2 0.5 0.2 {I6}\n",
    "VERTEX2 0 0 0 0\nVERTEX2 1 1 0 0\nVERTEX2 2 2 0 0\nEQUIV 1 2\n"
    "EDGE2 0 1 1 0 0 1 0 1 1 0 0\nEDGE2 1 2 1 0 0 1 0 1 1 0 0\nEDGE2 0 2 2 0 0 1 0 1 1 0 0\n",
    "EDGE2 0 1 1 0 0 1 0 1 1 0 0\nEDGE2 1 2 0 1 1.5 1 0 1 1 0 0\n",
)
COVARS_SEEDS = (
    "room\n100.5\n"
    "0, 0, 0, 1, 0, -1, 0, 0.1, 0, 0, 0, 0.1, 0, 0, 0, 0.01\n"
    "0, 0, 0, 1, 1, -1, 0, 0.1, 0, 0, 0, 0.1, 0, 0, 0, 0.01\n"
    "1, 0.5, 0.3, 2, 0.5, -0.7, 0.7, 0.1, 0, 0, 0, 0.1, 0, 0, 0, 0.01\n"
    "2, 1, 0.6, 2, 1, 0, 0, 0, 0, 0, 0, 0, 0, 0, 0, 0\n"
    "3, 1.5, -2.9, 4, 2, 1, 0, 0.2, 0.01, 0, 0.01, 0.2, 0, 0, 0, 0.02\n",
    "m\n0\n0,0,0,1,0,0,0,0,0,0,0,0,0,0,0,0\n1,0,0,2,0,0,0,0,0,0,0,0,0,0,0,0\n",
)


def flaser(n: int, pose: str, stamp: str) -> str:
    ranges = " ".join(f"{1 + 0.01 * k:.2f}" for k in range(n))
    return f"FLASER {n} {ranges} {pose} {pose} {stamp} host {stamp}"


CARMEN_SEEDS = (
    "PARAM robot_frontlaser_offset 0.1\nPARAM robot_front_laser_max 8.0\n"
    + flaser(5, "0 0 0", "1.0")
    + "\nODOM 0 0 0 0 0 0 1.0 host 1.0\n"
    + flaser(5, "0.5 0.1 0.2", "2.0")
    + "\n"
    + flaser(5, "1.0 0.2 0.4", "3.0")
    + "\n",
    "ROBOTLASER1 0 -1.5 3.0 1.0 8.0 0.01 0 4 1 2 3 9 2 0.5 0.5 0 0 0 0 0 0 0.1 0.2 0.3 0.4 0.5 "
    "5.0 host 5.0\n"
    "ROBOTLASER1 0 -1.5 3.0 1.0 8.0 0.01 0 4 1 2 3 4 0 1 0.5 0 1 0.5 0 0.1 0.2 0.3 0.4 0.5 "
    "6.0 host 6.0\nFLASER 2 1 2 0 0 0 0 0 0 1 h 1\n",
)
RELATIONS_SEEDS = (
    "1.0 2.0 0.5 0.1 0 0 0 0.2\n# comment\n2.0 3.0 0.5 -0.1 0 0 0 -0.2\n",
    "100.25 101.5 1e-3 -2e-3 0.0 0.0 0.0 3.14159\n",
)
CORRECTIONS_SEEDS = (
    '{"version": 1}\n'
    '{"mode": "collinear", "a": [[1.2, 3.4], [4.1, 3.45]], "b": [[10.0, 3.9], [13.2, 4.0]]}\n'
    '{"action": "undo"}\n{"action": "redo"}\n',
    '{"mode": "colocation", "a": [[0, 0], [1, 1]], "b": [[2, 2], [3, 3]], "sigma_h": 0.1}\n\n'
    '{"mode": "perpendicular", "a": [[0, 0], [1, 0]], "b": [[0, 1], [0, 2]], "version": 1}\n',
)


@pytest.fixture(scope="module")
def workdir(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return tmp_path_factory.mktemp("fuzz")


def text_file(
    seeds: tuple[str, ...], tags: tuple[str, ...], counts: tuple[int, ...], sep: str = " "
) -> st.SearchStrategy[bytes]:
    structured = st.lists(tokens_line(tags, counts, sep), min_size=0, max_size=8).map(
        lambda lines: "\n".join(lines).encode("utf-8", "surrogatepass")
    )
    return st.one_of(mutated(seeds), structured.flatmap(lambda data: byte_edits(data, 2)))


# ---------------------------------------------------------------------------------------------
# Pose graphs


def check_graph(graph: PoseGraph) -> None:
    assert_finite("poses", graph.poses[:, :2], MAX_COORDINATE)
    assert np.all(np.abs(graph.poses[:, 2]) <= math.pi)
    assert_finite("measurements", graph.measurements[:, :2], MAX_COORDINATE)
    assert_finite("information", graph.information, MAX_INFORMATION)
    for info in graph.information:
        np.linalg.cholesky(info)  # positive definite, or LinAlgError fails the case


def graph_round_trip(graph: PoseGraph, out: Path) -> None:
    save_graph(graph, None, out)
    again = load_graph(out)
    np.testing.assert_array_equal(again.poses, graph.poses)
    np.testing.assert_array_equal(again.edges, graph.edges)
    np.testing.assert_array_equal(again.measurements, graph.measurements)
    np.testing.assert_array_equal(again.information, graph.information)


@FUZZ_SETTINGS
@given(
    data=text_file(G2O_SEEDS, ("VERTEX_SE2", "EDGE_SE2", "FIX", "VERTEX_XY", "#"), (4, 11, 1)),
    suffix=st.sampled_from(["", "", "", "", ".gz", ".bz2"]),
    damage=st.booleans(),
)
def test_fuzz_g2o(workdir: Path, data: bytes, suffix: str, damage: bool) -> None:
    path = workdir / f"case.g2o{suffix}"
    payload = compressed_variant(data, suffix)
    if suffix and damage:
        payload = payload[: len(payload) // 2]
    graph = check_reader(load_graph, path, payload, lines=not suffix, validate=check_graph)
    if graph is not None:
        graph_round_trip(graph, workdir / "again.g2o")
        graph_round_trip(graph, workdir / "again.graph")


@FUZZ_SETTINGS
@given(data=text_file(TORO_SEEDS, ("VERTEX2", "EDGE2", "EQUIV", "#"), (4, 11, 2)))
def test_fuzz_toro(workdir: Path, data: bytes) -> None:
    graph = check_reader(load_graph, workdir / "case.graph", data, validate=check_graph)
    if graph is not None:
        graph_round_trip(graph, workdir / "again.graph")


# ---------------------------------------------------------------------------------------------
# Maps


def check_map(the_map: Map) -> None:
    assert_finite("poses", the_map.poses[:, :2], MAX_COORDINATE)
    assert np.all(np.abs(the_map.poses[:, 2]) <= math.pi)
    assert_finite("points", the_map.points, 3 * MAX_COORDINATE)
    assert_finite("measurements", the_map.measurements)
    assert_finite("information", the_map.information, MAX_INFORMATION)
    for info in the_map.information:
        np.linalg.cholesky(info)


def written(write: Callable[[Path], None], out: Path) -> bool:
    """Run a writer: True when it wrote ``out``, False when it refused (InputError) because
    the result would not read back, having written nothing; any other refusal fails."""
    out.unlink(missing_ok=True)
    try:
        write(out)
    except InputError as exc:
        if "could not read back" not in str(exc) or out.exists():
            raise AssertionError(f"writer refused badly: {exc}") from None
        return False
    return True


def export_round_trip(the_map: Map, workdir: Path) -> None:
    """What the g2o/TORO exporters write of a map read back as the same graph (or is refused,
    with a message, before anything is written)."""
    for name in ("export.g2o", "export.graph"):
        out = workdir / name
        if not written(lambda path: write_g2o_map(the_map, the_map.poses, path), out):
            continue
        graph = load_graph(out)
        np.testing.assert_array_equal(graph.poses, the_map.poses)
        np.testing.assert_array_equal(graph.information, the_map.information)


@FUZZ_SETTINGS
@given(data=text_file(COVARS_SEEDS, ("0", "1", "m"), (15,), ", "))
def test_fuzz_covars(workdir: Path, data: bytes) -> None:
    the_map = check_reader(read_covars, workdir / "case.covars", data, validate=check_map)
    if the_map is None:
        return
    out = workdir / "again.covars"
    if written(lambda path: write_covars(the_map, the_map.poses, path), out):
        again = read_covars(out)
        np.testing.assert_array_equal(again.poses, the_map.poses)
        assert again.num_points == the_map.num_points
    export_round_trip(the_map, workdir)


@FUZZ_SETTINGS
@given(
    data=text_file(
        CARMEN_SEEDS,
        ("FLASER", "ROBOTLASER1", "PARAM", "ODOM", "#"),
        (12, 13, 15, 2, 9, 27, 28),
    ),
    suffix=st.sampled_from([".clf", ".clf", ".log", ".clf.gz"]),
)
def test_fuzz_carmen(workdir: Path, data: bytes, suffix: str) -> None:
    payload = compressed_variant(data, ".gz") if suffix.endswith(".gz") else data
    the_map = check_reader(
        read_carmen,
        workdir / f"case{suffix}",
        payload,
        lines=not suffix.endswith(".gz"),
        validate=check_map,
    )
    if the_map is not None:
        export_round_trip(the_map, workdir)


# ---------------------------------------------------------------------------------------------
# Relations and corrections


def check_relations(relations: Relations) -> None:
    assert len(relations) > 0
    assert_finite("t1", relations.t1)
    assert_finite("t2", relations.t2)
    assert_finite("relative", relations.relative[:, :2], MAX_COORDINATE)
    assert np.all(np.abs(relations.relative[:, 2]) <= math.pi)


@FUZZ_SETTINGS
@given(data=text_file(RELATIONS_SEEDS, ("1.0", "100", "#"), (7,)))
def test_fuzz_relations(workdir: Path, data: bytes) -> None:
    check_reader(read_relations, workdir / "case.relations", data, validate=check_relations)


def check_steps(steps: list[Step]) -> None:
    for step in steps:
        if isinstance(step, Apply):
            drawn = step.drawn
            assert_finite("segments", [drawn.a, drawn.b], MAX_COORDINATE)
            if drawn.sigma_h is not None:
                assert MIN_SIGMA_H <= drawn.sigma_h <= MAX_SIGMA_H


json_values = st.recursive(
    st.one_of(
        st.sampled_from(["null", "true", "false"]),
        number_tokens.map(lambda t: t if t and t[0] in "-0123456789" else json.dumps(t)),
        st.text(max_size=8).map(json.dumps),
        st.sampled_from(['"collinear"', '"undo"', '"redo"', "1", "[[1, 2], [3, 4]]"]),
    ),
    lambda inner: st.one_of(
        st.lists(inner, max_size=4).map(lambda items: "[" + ", ".join(items) + "]"),
        st.lists(
            st.tuples(
                st.sampled_from(["mode", "a", "b", "sigma_h", "version", "action", "x"]), inner
            ),
            max_size=5,
        ).map(lambda pairs: "{" + ", ".join(f'"{k}": {v}' for k, v in pairs) + "}"),
    ),
    max_leaves=12,
)


@FUZZ_SETTINGS
@given(
    data=st.one_of(
        mutated(CORRECTIONS_SEEDS),
        st.lists(json_values, max_size=5).map(lambda lines: "\n".join(lines).encode()),
        st.integers(1, 200_000).map(lambda depth: ("[" * depth + "]" * depth + "\n").encode()),
    )
)
def test_fuzz_corrections(workdir: Path, data: bytes) -> None:
    steps = check_reader(read_corrections, workdir / "case.jsonl", data, validate=check_steps)
    if steps:
        out = workdir / "again.jsonl"
        write_corrections(out, steps)
        again = read_corrections(out)
        assert [type(s) for s in again] == [type(s) for s in steps]
        assert [s.drawn for s in again if isinstance(s, Apply)] == [
            s.drawn for s in steps if isinstance(s, Apply)
        ]


# ---------------------------------------------------------------------------------------------
# ROS bags: binary files (ROS 1 .bag, ROS 2 .db3 and .mcap), mutated byte by byte or written by
# rosbags' own writers from hostile values; a bag directory's metadata.yaml mutated as text.

needs_rosbags = pytest.mark.skipif(
    importlib.util.find_spec("rosbags") is None, reason="the [ros] extra (rosbags) is not installed"
)
BAG_KINDS = {".bag": "ros1", ".db3": "db3-file", ".mcap": "mcap-file"}
SEC = 1_000_000_000


def seed_bags() -> list[Any]:
    """Small valid bags (bag_support.Bag): TF with a static mount, an Odometry topic, a SLAM's
    map -> odom, two scan topics."""
    from bag_support import Bag, Scan, Transform

    def scans(n: int, frame: str = "laser") -> list[Scan]:
        ranges = np.array([1.0, 2.5, np.inf, np.nan, 0.05, 9.0])
        return [
            Scan(100 * SEC + k * SEC // 4, ranges, -1.0, 0.4, 0.1, 8.0, frame, np.arange(6.0))
            for k in range(n)
        ]

    def poses(n: int, parent: str = "odom", child: str = "base_link") -> list[Transform]:
        return [
            Transform(100 * SEC + k * SEC // 4, parent, child, (0.3 * k, 0.1 * k, 0.2 * k))
            for k in range(n)
        ]

    mount = [Transform(0, "base_link", "laser", (0.2, 0.0, 0.1), z=0.3)]
    tf = Bag(scans=scans(4), tf=[[t] for t in poses(4)], tf_static=mount)
    odometry = Bag(scans=scans(3, "base_link"), odometry=poses(3))
    slam = Bag(
        scans=scans(4),
        tf=[[a, b] for a, b in zip(poses(4), poses(4, "map", "odom"), strict=True)],
        tf_static=mount,
    )
    two = Bag(scans=scans(2, "base_link"), tf=[[t] for t in poses(2)])
    two.more_scans["/rear"] = scans(2, "base_link")
    return [tf, odometry, slam, two]


@pytest.fixture(scope="module")
def bag_seeds(tmp_path_factory: pytest.TempPathFactory) -> dict[str, list[bytes]]:
    """The seed bags' bytes, per file extension."""
    if importlib.util.find_spec("rosbags") is None:
        pytest.skip("the [ros] extra (rosbags) is not installed")
    from bag_support import write_bag

    folder = tmp_path_factory.mktemp("bag-seeds")
    out: dict[str, list[bytes]] = {}
    for k, bag in enumerate(seed_bags()):
        for suffix, kind in BAG_KINDS.items():
            out.setdefault(suffix, []).append(
                write_bag(bag, folder / f"{k}{kind}", kind).read_bytes()
            )
    return out


# Byte patterns that hit a binary reader's weak spots when they land on a length, a count, an
# offset or a float: zero, all ones, the sign bit, NaN and infinities, huge floats.
SPECIAL_BYTES = (
    b"\x00\x00\x00\x00",
    b"\xff\xff\xff\xff",
    b"\xff\xff\xff\x7f",
    b"\x00\x00\x00\x80",
    b"\x00\x00\xc0\x7f",  # float32 NaN
    b"\x00\x00\x80\x7f",  # float32 +inf
    b"\x00\x00\x80\xff",  # float32 -inf
    b"\xff\xff\x7f\x7f",  # float32 max
    b"\x00\x00\x00\x00\x00\x00\xf8\x7f",  # float64 NaN
    b"\x00\x00\x00\x00\x00\x00\xf0\x7f",  # float64 +inf
    b"\x9c\x75\x88\x3c\xe4\x37\x7e\x7e",  # float64 1e300
    b"\xff\xff\xff\xff\xff\xff\xff\xff",
    b"\x00\x00\x00\x00\x00\x00\x00\x40",
)


@st.composite
def binary_mutated(draw: st.DrawFn, seeds: list[bytes]) -> bytes:
    """A seed with 1 to 6 edits: a special pattern written over any place, a random byte, a bit
    flipped; then maybe byte-level insertions, deletions, a truncation."""
    out = bytearray(draw(st.sampled_from(seeds)))
    for _ in range(draw(st.integers(1, 6))):
        at = draw(st.integers(0, len(out) - 1))
        op = draw(st.sampled_from(("special", "special", "byte", "flip")))
        if op == "special":
            pattern = draw(st.sampled_from(SPECIAL_BYTES))
            out[at : at + len(pattern)] = pattern[: max(len(out) - at, 0)]
        elif op == "byte":
            out[at] = draw(st.integers(0, 255))
        else:
            out[at] ^= 1 << draw(st.integers(0, 7))
    return draw(byte_edits(bytes(out), 2))


def read_bag(path: Path) -> Map:
    from hitl_slam.io.rosbag import read_rosbag

    return read_rosbag(path)


@needs_rosbags
@FUZZ_SETTINGS
@given(suffix=st.sampled_from(sorted(BAG_KINDS)), data=st.data())
def test_fuzz_rosbag_bytes(
    workdir: Path, bag_seeds: dict[str, list[bytes]], suffix: str, data: st.DataObject
) -> None:
    payload = data.draw(binary_mutated(bag_seeds[suffix]))
    the_map = check_reader(
        read_bag, workdir / f"case{suffix}", payload, lines=False, validate=check_map
    )
    if the_map is not None:
        export_round_trip(the_map, workdir)


hostile32 = st.one_of(
    st.floats(width=32),
    st.sampled_from([0.0, -0.0, 1e-30, 3e38, -3e38, np.nan, np.inf, -np.inf]),
)
hostile64 = st.one_of(
    st.floats(),
    st.sampled_from([1e9, -1e9, 1.0000001e9, 1e300, np.nan, np.inf, -np.inf]),
)
frames = st.sampled_from(["odom", "base_link", "laser", "map", "", "/odom", "base_footprint"])
stamps = st.one_of(  # ROS 2's sec is an int32
    st.integers(0, 2**31 - 1).map(lambda sec: sec * SEC),
    st.integers(0, (2**31 - 1) * SEC + SEC - 1),
    st.just(0),
)


def mostly(
    usual: st.SearchStrategy[Any], odd: st.SearchStrategy[Any], one_in: int = 10
) -> st.SearchStrategy[Any]:
    """``odd`` once in ``one_in`` draws, else ``usual``: values that keep a bag readable, with a
    few hostile ones among them, reach the reader's arithmetic rather than its first check."""
    return st.integers(1, one_in).flatmap(lambda k: odd if k == 1 else usual)


@st.composite
def hostile_bag(draw: st.DrawFn) -> Any:
    """A bag whose container is valid: a consistent skeleton (scans of a laser mounted on
    base_link, odom -> base_link on /tf or /odom, maybe map -> odom) with values that are
    anything the messages can hold, and now and then frames and stamps that do not fit."""
    from bag_support import Bag, Scan, Transform

    n = draw(mostly(st.integers(1, 4), st.just(0)))
    times = [100 * SEC + k * SEC // 4 for k in range(max(n, 2))]
    one_in = draw(st.sampled_from([10, 40, 200, 10**9]))  # how hostile the values are

    def f32(low: float, high: float) -> st.SearchStrategy[float]:
        usual = st.floats(low, high).map(lambda x: float(np.float32(x)))
        return mostly(usual, hostile32, one_in)

    def f64(low: float, high: float) -> st.SearchStrategy[float]:
        return mostly(st.floats(low, high), hostile64, one_in)

    def transform(stamp: int, parent: str, child: str) -> Transform:
        quaternion = draw(st.one_of(st.none(), st.tuples(*[f64(-1, 1)] * 4)))
        return Transform(
            draw(mostly(st.just(stamp), stamps, one_in)),
            draw(mostly(st.just(parent), frames, one_in)),
            draw(mostly(st.just(child), frames, one_in)),
            (draw(f64(-50, 50)), draw(f64(-50, 50)), draw(f64(-4, 4))),
            z=draw(f64(-1, 1)),
            quaternion=quaternion,
        )

    scans = []
    for k in range(n):
        beams = draw(st.integers(0, 6))
        scans.append(
            Scan(
                draw(mostly(st.just(times[k]), stamps, one_in)),
                np.array(draw(st.lists(f32(0, 30), min_size=beams, max_size=beams))),
                draw(f32(-3.2, 3.2)),
                draw(f32(-0.5, 0.5)),
                draw(f32(0, 1)),
                draw(f32(0, 40)),
                draw(mostly(st.just("laser"), frames, one_in)),
                np.array(draw(st.lists(f32(0, 1e4), max_size=7))),
            )
        )
    poses = [transform(t, "odom", "base_link") for t in times]
    bag = Bag(scans=scans, tf_static=[transform(0, "base_link", "laser")])
    if draw(st.booleans()):
        bag.odometry = poses
    else:
        bag.tf = [[p] for p in poses]
    if draw(st.booleans()):
        for group, t in zip(bag.tf or [[] for _ in times], times, strict=True):
            group.append(transform(t, "map", "odom"))
        if not bag.tf:
            bag.tf = [[transform(t, "map", "odom")] for t in times]
    if draw(st.integers(0, 9)) == 0:
        bag.more_scans["/rear"] = scans[:2]
    return bag


OPTION_VALUES: dict[str, st.SearchStrategy[Any]] = {
    "scan_topic": st.sampled_from(["/scan", "/rear", "/odom", "/none"]),
    "odom_topic": st.sampled_from(["/odom", "/scan"]),
    "odom_frame": frames,
    "base_frame": frames,
    "map_frame": st.one_of(st.none(), frames),
}
OPTION = st.sampled_from(sorted(OPTION_VALUES)).flatmap(
    lambda key: OPTION_VALUES[key].map(lambda value: {key: value})
)


@needs_rosbags
@FUZZ_SETTINGS
@given(
    bag=hostile_bag(),
    kind=st.sampled_from(["ros1", "sqlite3", "mcap-file", "db3-file"]),
    options=st.one_of(
        st.just({}),
        OPTION,
        OPTION.map(lambda option: {**option, "scan_topic": "/rear"}),
    ),
    max_range=st.one_of(st.none(), st.sampled_from([0.5, 10.0, 1e9, 2e9, np.nan])),
)
def test_fuzz_rosbag_values(
    workdir: Path, bag: Any, kind: str, options: dict[str, Any], max_range: float | None
) -> None:
    import warnings

    from bag_support import write_bag
    from hitl_slam.io.rosbag import BagOptions, read_rosbag

    target = workdir / "values"
    for old in workdir.glob("values*"):
        shutil.rmtree(old) if old.is_dir() else old.unlink()
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # the writer's own float32 casts
        path = write_bag(bag, target, kind)
    check_path(
        lambda p: read_rosbag(p, BagOptions(**options), max_range=max_range),
        path,
        f"{kind} bag {bag!r:.2000} with {options}, max_range {max_range}",
        validate=check_map,
    )


@needs_rosbags
@FUZZ_SETTINGS
@given(data=st.data())
def test_fuzz_rosbag_metadata(workdir: Path, data: st.DataObject) -> None:
    from bag_support import write_bag

    folder = workdir / "directory-bag"
    if not folder.exists():
        write_bag(seed_bags()[0], folder, "sqlite3")
        _METADATA_SEED.append((folder / "metadata.yaml").read_text())
    text = data.draw(mutated(_METADATA_SEED[:1]))
    (folder / "metadata.yaml").write_bytes(text)
    check_path(read_bag, folder, repr(text[:300]), validate=check_map)


_METADATA_SEED: list[str] = []  # a valid metadata.yaml, kept from the first case
