"""Property-based fuzzing of every text reader (issue 13): corrections JSON Lines, g2o, TORO,
``.covars``, CARMEN logs and relations. Each case is a mutated valid file or a structurally
generated one; the invariant is in :mod:`fuzz_support`: a valid object or an InputError naming
the file (and line), nothing else, no hang. Valid objects are checked (finite, within the
readers' limits) and written back where a writer exists: what a writer writes must read back.

``make test`` runs a few cases per reader (profile ``fuzz-ci``); ``make fuzz`` runs 10^5 each.
"""

from __future__ import annotations

import json
import math
from collections.abc import Callable
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st

from fuzz_support import (
    FUZZ_SETTINGS,
    assert_finite,
    byte_edits,
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
