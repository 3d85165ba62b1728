"""Pose-graph file I/O: the public datasets load with the right counts, every kind of bad input
is an InputError naming file and line, fuzzed input never escapes as anything else, saved graphs
reload to identical arrays, and writes are atomic.
"""

from __future__ import annotations

import bz2
import gzip
import logging
import math
import os
import stat
import sys
import time
from pathlib import Path

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from numpy.typing import NDArray

from hitl_slam.cli import main
from hitl_slam.errors import InputError
from hitl_slam.graph import PoseGraph
from hitl_slam.io import GraphFormat, load_graph, save_graph
from hitl_slam.io.atomic import atomic_write_text, atomic_writer
from hitl_slam.io.textfile import MAX_ANGLE, MAX_COORDINATE, MAX_INFORMATION

SHARED = Path(__file__).resolve().parents[1].parent / "shared"
POSE_GRAPHS = SHARED / "datasets" / "pose_graphs"
needs_shared = pytest.mark.skipif(
    not POSE_GRAPHS.is_dir(),
    reason=f"public datasets not found at {POSE_GRAPHS} (the project's ../shared folder)",
)

SQUARE_G2O = """\
# a unit square driven counter-clockwise
VERTEX_SE2 0 0 0 0
VERTEX_SE2 1 1 0 1.5707963267948966
VERTEX_SE2 2 1 1 3.141592653589793
VERTEX_SE2 3 0 1 -1.5707963267948966
EDGE_SE2 0 1 1 0 1.5707963267948966 1 0 0 1 0 1
EDGE_SE2 1 2 1 0 1.5707963267948966 1 0 0 1 0 1
EDGE_SE2 2 3 1 0 1.5707963267948966 1 0 0 1 0 1
EDGE_SE2 3 0 1 0 1.5707963267948966 1 0 0 1 0 1
"""
SQUARE_TORO = (
    SQUARE_G2O.replace("VERTEX_SE2", "VERTEX2")
    .replace("EDGE_SE2", "EDGE2")
    .replace(" 1 0 0 1 0 1\n", " 1 0 1 1 0 0\n")
)
IDENTITY6 = "1 0 0 1 0 1"  # g2o upper triangle of the identity


def write(tmp_path: Path, name: str, text: str) -> Path:
    path = tmp_path / name
    path.write_text(text, encoding="utf-8")
    return path


def error_message(path: Path) -> str:
    with pytest.raises(InputError) as excinfo:
        load_graph(path)
    return str(excinfo.value)


def assert_error(message: str, path: Path, line: int | None, *phrases: str) -> None:
    prefix = f"{path}:{line}: " if line is not None else f"{path}: "
    assert message.startswith(prefix), message
    assert "; " in message[len(prefix) :], f"no advice in: {message}"
    for phrase in phrases:
        assert phrase in message, f"{phrase!r} not in: {message}"


def with_line(text: str, line: str, at: int | None = None) -> str:
    lines = text.splitlines()
    lines.insert(len(lines) if at is None else at, line)
    return "\n".join(lines) + "\n"


# ---------------------------------------------------------------------------------------------
# Real data


DATASETS = [
    ("M3500_carlone.g2o", 3500, 5453),
    ("manhattanOlson3500.g2o", 3500, 5598),
    ("intel.g2o", 1728, 2512),
    ("city10000.g2o", 10000, 20687),
    ("mit_killian.g2o", 808, 827),
    ("ring.g2o", 434, 459),
    ("pose2example.txt", 11, 12),
    ("noisyToyGraph.txt", 4, 5),
]


@needs_shared
@pytest.mark.parametrize(("name", "num_poses", "num_edges"), DATASETS)
def test_public_g2o_files_load_with_their_counts(name: str, num_poses: int, num_edges: int) -> None:
    graph = load_graph(POSE_GRAPHS / name)
    report = graph.load_report
    assert report is not None
    assert (graph.num_poses, graph.num_edges) == (num_poses, num_edges)
    assert report.format is GraphFormat.G2O
    assert report.skipped == {}
    assert not report.poses_from_odometry
    assert graph.anchor == 0
    assert graph.vertex_ids is not None
    assert graph.vertex_ids[0] == 0
    assert graph.edges.min() >= 0
    assert graph.edges.max() < num_poses
    for theta in (graph.poses[:, 2], graph.measurements[:, 2]):
        assert np.all((theta > -math.pi) & (theta <= math.pi))
    assert np.allclose(graph.information, graph.information.transpose(0, 2, 1))


@needs_shared
def test_w100_merges_its_equiv_vertices() -> None:
    graph = load_graph(POSE_GRAPHS / "w100.graph")
    report = graph.load_report
    assert report is not None
    assert report.format is GraphFormat.TORO
    # 100 vertices and 300 edges in the file; EQUIV folds 21..40 and 41..60 onto 1..20.
    assert report.merged_vertices == 40
    assert report.dropped_self_loops == 60
    assert (graph.num_poses, graph.num_edges) == (60, 240)
    assert graph.vertex_ids is not None
    assert set(graph.vertex_ids.tolist()) == set(range(21)) | set(range(61, 100))
    assert graph.information[0].tolist() == np.eye(3).tolist()


@needs_shared
def test_ring_headings_are_wrapped() -> None:
    graph = load_graph(POSE_GRAPHS / "ring.g2o")
    # The file writes vertex 2's heading as 6.282233, just under 2 pi.
    assert graph.poses[2, 2] == pytest.approx(6.282233 - 2 * math.pi)


@needs_shared
def test_city10000_loads_fast() -> None:
    start = time.perf_counter()
    load_graph(POSE_GRAPHS / "city10000.g2o")
    assert time.perf_counter() - start < 2.0


@needs_shared
@pytest.mark.parametrize("name", ["M3500_carlone.g2o", "w100.graph"])
@pytest.mark.parametrize("extension", [".g2o", ".graph"])
def test_public_files_round_trip(tmp_path: Path, name: str, extension: str) -> None:
    graph = load_graph(POSE_GRAPHS / name)
    out = tmp_path / f"copy{extension}"
    save_graph(graph, graph.poses, out)
    assert_same_graph(load_graph(out), graph)


# ---------------------------------------------------------------------------------------------
# What the readers accept


def test_small_g2o_file_gives_the_expected_arrays(tmp_path: Path) -> None:
    graph = load_graph(write(tmp_path, "square.g2o", SQUARE_G2O))
    assert graph.poses.dtype == np.float64
    assert graph.edges.dtype == np.int64
    assert graph.poses.shape == (4, 3)
    assert graph.edges.tolist() == [[0, 1], [1, 2], [2, 3], [3, 0]]
    assert graph.poses[2].tolist() == [1.0, 1.0, math.pi]
    assert graph.information.tolist() == [np.eye(3).tolist()] * 4
    assert graph.source == str(tmp_path / "square.g2o")


def test_toro_information_is_mapped_from_toro_order(tmp_path: Path) -> None:
    # EDGE2 ... Ixx Ixy Iyy Itt Ixt Iyt
    text = "VERTEX2 0 0 0 0\nVERTEX2 1 1 0 0\nEDGE2 0 1 1 0 0 4 1 3 2 0.5 0.25\n"
    graph = load_graph(write(tmp_path, "t.graph", text))
    assert graph.information[0].tolist() == [[4, 1, 0.5], [1, 3, 0.25], [0.5, 0.25, 2]]


def test_g2o_information_is_the_upper_triangle_row_major(tmp_path: Path) -> None:
    text = "VERTEX_SE2 0 0 0 0\nVERTEX_SE2 1 1 0 0\nEDGE_SE2 0 1 1 0 0 4 1 0.5 3 0.25 2\n"
    graph = load_graph(write(tmp_path, "t.g2o", text))
    assert graph.information[0].tolist() == [[4, 1, 0.5], [1, 3, 0.25], [0.5, 0.25, 2]]


def test_angles_are_wrapped_to_minus_pi_exclusive_pi_inclusive(tmp_path: Path) -> None:
    text = (
        f"VERTEX_SE2 0 0 0 {-math.pi!r}\nVERTEX_SE2 1 1 0 7.0\nEDGE_SE2 0 1 1 0 -7.0 {IDENTITY6}\n"
    )
    graph = load_graph(write(tmp_path, "w.g2o", text))
    assert graph.poses[0, 2] == math.pi
    assert graph.poses[1, 2] == pytest.approx(7.0 - 2 * math.pi, abs=1e-15)
    assert graph.measurements[0, 2] == pytest.approx(-7.0 + 2 * math.pi, abs=1e-15)


def test_rows_follow_first_appearance_and_edges_use_rows(tmp_path: Path) -> None:
    text = (
        f"VERTEX_SE2 10 0 0 0\nVERTEX_SE2 3 1 0 0\nVERTEX_SE2 7 2 0 0\n"
        f"EDGE_SE2 10 3 1 0 0 {IDENTITY6}\nEDGE_SE2 7 3 -1 0 0 {IDENTITY6}\n"
    )
    graph = load_graph(write(tmp_path, "ids.g2o", text))
    assert graph.vertex_ids is not None
    assert graph.vertex_ids.tolist() == [10, 3, 7]
    assert graph.edges.tolist() == [[0, 1], [2, 1]]


def test_fix_names_the_anchor_and_extra_fixed_vertices_are_reported(
    tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    path = write(tmp_path, "fix.g2o", with_line(SQUARE_G2O, "FIX 2 3"))
    with caplog.at_level(logging.WARNING, logger="hitl_slam"):
        graph = load_graph(path)
        report = graph.load_report
        assert report is not None
    assert graph.anchor == 2
    assert report.skipped == {"FIX": 1}
    assert "FIX x1" in caplog.text


def test_other_tags_are_skipped_counted_and_logged(
    tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    text = with_line(SQUARE_G2O, "PARAMS_SE2OFFSET 0 0 0 0", at=1)
    text = with_line(text, "VERTEX_XY 9 1 2")
    text = with_line(text, "VERTEX_XY 10 1 2")
    text = with_line(text, "EDGE_SE2_XY 0 9 1 1 1 0 1")
    path = write(tmp_path, "extra.g2o", text)
    with caplog.at_level(logging.WARNING, logger="hitl_slam"):
        graph = load_graph(path)
        report = graph.load_report
        assert report is not None
    assert graph.num_poses == 4
    assert report.skipped == {"PARAMS_SE2OFFSET": 1, "VERTEX_XY": 2, "EDGE_SE2_XY": 1}
    [record] = [r for r in caplog.records if r.name == "hitl_slam"]
    assert record.levelno == logging.WARNING
    assert str(path) in record.getMessage()
    assert "VERTEX_XY x2 (first at line 11)" in record.getMessage()


def test_equiv_merges_onto_the_first_appearing_vertex(tmp_path: Path) -> None:
    text = (
        "VERTEX2 0 0 0 0\nVERTEX2 1 1 0 0\nVERTEX2 2 2 0 0\nVERTEX2 3 1.1 0 0\n"
        "VERTEX2 4 2.1 0 0\n"
        "EDGE2 0 1 1 0 0 1 0 1 1 0 0\nEDGE2 1 2 1 0 0 1 0 1 1 0 0\n"
        "EDGE2 2 3 -0.9 0 0 1 0 1 1 0 0\nEDGE2 3 1 0.1 0 0 1 0 1 1 0 0\n"
        "EDGE2 3 4 1 0 0 1 0 1 1 0 0\n"
        "EQUIV 3 1\nEQUIV 4 3\n"  # 4 ~ 3 ~ 1: both fold onto 1, which appears first
    )
    graph = load_graph(write(tmp_path, "eq.graph", text))
    report = graph.load_report
    assert report is not None
    assert graph.vertex_ids is not None
    assert graph.vertex_ids.tolist() == [0, 1, 2]
    assert (report.merged_vertices, report.dropped_self_loops) == (2, 2)
    # 2->3 becomes 2->1; 3->1 and 3->4 become self-loops and are dropped.
    assert graph.edges.tolist() == [[0, 1], [1, 2], [2, 1]]
    assert graph.poses[1].tolist() == [1.0, 0.0, 0.0]


def chain_measurement(a: NDArray[np.float64], b: NDArray[np.float64]) -> list[float]:
    """Pose of b in the frame of a."""
    x, y, th = (float(v) for v in a)
    c, s = math.cos(th), math.sin(th)
    dx, dy = float(b[0]) - x, float(b[1]) - y
    return [c * dx + s * dy, -s * dx + c * dy, math.remainder(float(b[2]) - th, 2 * math.pi)]


def test_edges_without_vertices_chain_the_odometry(tmp_path: Path) -> None:
    rng = np.random.default_rng(7)
    truth = np.cumsum(rng.uniform(-1, 1, size=(6, 3)), axis=0)
    truth -= truth[0]
    truth[:, 2] = np.remainder(truth[:, 2] + math.pi, 2 * math.pi) - math.pi
    ids = [10, 11, 12, 13, 20, 21]  # a gap between 13 and 20, reached through 11 -> 20
    lines = []
    for i, j in [(0, 1), (2, 1), (2, 3), (1, 4), (4, 5)]:  # 2 -> 1 runs backwards
        m = " ".join(map(repr, chain_measurement(truth[i], truth[j])))
        lines.append(f"EDGE_SE2 {ids[i]} {ids[j]} {m} {IDENTITY6}")
    graph = load_graph(write(tmp_path, "e.g2o", "\n".join(lines[::-1])))
    report = graph.load_report
    assert report is not None
    assert report.poses_from_odometry
    assert graph.vertex_ids is not None
    assert graph.vertex_ids.tolist() == ids
    assert graph.anchor == 0
    np.testing.assert_allclose(graph.poses, truth, atol=1e-12)


def test_compressed_files_load(tmp_path: Path) -> None:
    (tmp_path / "a.g2o.gz").write_bytes(gzip.compress(SQUARE_G2O.encode()))
    (tmp_path / "a.graph.bz2").write_bytes(bz2.compress(SQUARE_TORO.encode()))
    g = load_graph(tmp_path / "a.g2o.gz")
    t = load_graph(tmp_path / "a.graph.bz2")
    assert_same_graph(g, t)


def test_crlf_bom_and_content_sniffing(tmp_path: Path) -> None:
    path = tmp_path / "square.txt"
    path.write_bytes(b"\xef\xbb\xbf" + SQUARE_TORO.replace("\n", "\r\n").encode())
    graph = load_graph(path)
    report = graph.load_report
    assert report is not None
    assert report.format is GraphFormat.TORO
    assert graph.num_edges == 4


def test_a_single_vertex_is_a_graph(tmp_path: Path) -> None:
    graph = load_graph(write(tmp_path, "one.g2o", "VERTEX_SE2 5 1 2 3\n"))
    assert graph.num_poses == 1
    assert graph.num_edges == 0


# ---------------------------------------------------------------------------------------------
# One test per kind of bad input: file, line and what is wrong, plus what to do


@pytest.mark.parametrize(
    ("line", "phrases"),
    [
        ("VERTEX_SE2 9 1.0 abc 0", ["bad number 'abc' for y (field 3 of VERTEX_SE2)"]),
        ("VERTEX_SE2 9 1.0 1_0 0", ["bad number '1_0'"]),
        ("VERTEX_SE2 9 1.0 \u0663 0", ["bad number '\u0663'"]),
        (f"EDGE_SE2 0 1 1 0 0x1 {IDENTITY6}", ["bad number '0x1' for dtheta"]),
        ("VERTEX_SE2 x 0 0 0", ["bad vertex id 'x' (expected an integer)"]),
        ("VERTEX_SE2 1.0 0 0 0", ["bad vertex id '1.0'"]),
        ("VERTEX_SE2 99999999999999999999 0 0 0", ["does not fit in 64 bits"]),
    ],
)
def test_bad_number(tmp_path: Path, line: str, phrases: list[str]) -> None:
    path = write(tmp_path, "bad.g2o", with_line(SQUARE_G2O, line, at=3))
    assert_error(error_message(path), path, 4, *phrases)


@pytest.mark.parametrize(
    ("name", "text", "line", "phrase"),
    [
        ("f.g2o", "EDGE_SE2 0 1 1 0 0 1 0 0 1", 9, "EDGE_SE2 needs 11 fields after the tag"),
        ("f.g2o", "VERTEX_SE2 4 0 0", 9, "VERTEX_SE2 needs 4 fields after the tag (id x y theta)"),
        ("f.graph", "EDGE2 0 1 1 0 0 1 0 1 1 0 0 7", 9, "(i j dx dy dtheta Ixx Ixy Iyy Itt"),
        ("f.graph", "EQUIV 1", 9, "EQUIV needs 2 fields after the tag (a b), got 1"),
        ("f.g2o", "FIX", 9, "FIX needs at least one vertex id"),
    ],
)
def test_wrong_field_count(tmp_path: Path, name: str, text: str, line: int, phrase: str) -> None:
    base = SQUARE_TORO if name.endswith(".graph") else SQUARE_G2O
    path = write(tmp_path, name, with_line(base, text, at=line - 1))
    message = error_message(path)
    assert_error(message, path, line, phrase)


def test_wrong_field_count_says_expected_and_got(tmp_path: Path) -> None:
    path = write(tmp_path, "f.g2o", with_line(SQUARE_G2O, "EDGE_SE2 0 1 1 0 0 1 0 0 1"))
    assert_error(error_message(path), path, 10, "needs 11 fields", "got 9")


@pytest.mark.parametrize(
    ("text", "phrase"),
    [
        ("VERTEX_SE2 4 nan 0 0", "x is 'nan'"),
        ("VERTEX_SE2 4 0 0 -Infinity", "theta is '-Infinity'"),
        (f"EDGE_SE2 0 2 1 1e999 0 {IDENTITY6}", "dy is '1e999'"),
        ("EDGE_SE2 0 2 1 0 0 1 0 0 inf 0 1", "I22 is 'inf'"),
    ],
)
def test_nan_and_inf(tmp_path: Path, text: str, phrase: str) -> None:
    path = write(tmp_path, "n.g2o", with_line(SQUARE_G2O, text, at=5))
    assert_error(error_message(path), path, 6, phrase, "NaN/inf")


def test_unknown_vertex_id(tmp_path: Path) -> None:
    path = write(tmp_path, "u.g2o", with_line(SQUARE_G2O, f"EDGE_SE2 3 42 1 0 0 {IDENTITY6}"))
    assert_error(error_message(path), path, 10, "unknown vertex id 42", "VERTEX_SE2 42 x y theta")


def test_duplicate_vertex_id_names_the_first_definition(tmp_path: Path) -> None:
    path = write(tmp_path, "d.g2o", with_line(SQUARE_G2O, "VERTEX_SE2 1 5 5 0", at=5))
    assert_error(error_message(path), path, 6, "duplicate vertex id 1 (first defined at line 3)")


@pytest.mark.parametrize(
    ("name", "text"),
    [("s.g2o", f"EDGE_SE2 2 2 0 0 0 {IDENTITY6}"), ("s.graph", "EDGE2 2 2 0 0 0 1 0 1 1 0 0")],
)
def test_self_loop_edge(tmp_path: Path, name: str, text: str) -> None:
    base = SQUARE_TORO if name.endswith(".graph") else SQUARE_G2O
    path = write(tmp_path, name, with_line(base, text))
    assert_error(error_message(path), path, 10, "edge from vertex 2 to itself (self-loop)")


@pytest.mark.parametrize(
    ("name", "info", "eigenvalues"),
    [
        ("p.g2o", "1 0 0 1 0 -1", "eigenvalues -1, 1, 1"),
        ("p.g2o", "1 2 0 1 0 1", "eigenvalues -1, 1, 3"),
        ("p.g2o", "0 0 0 0 0 0", "eigenvalues 0, 0, 0"),
        ("p.graph", "1 0 1 0 0 0", "eigenvalues 0, 1, 1"),  # Itt = 0 in TORO's 4th field
    ],
)
def test_information_not_positive_definite(
    tmp_path: Path, name: str, info: str, eigenvalues: str
) -> None:
    base, tag = (SQUARE_TORO, "EDGE2") if name.endswith(".graph") else (SQUARE_G2O, "EDGE_SE2")
    path = write(tmp_path, name, with_line(base, f"{tag} 0 2 1 1 0 {info}"))
    assert_error(
        error_message(path), path, 10, "information matrix is not positive definite", eigenvalues
    )


def test_information_error_counts_the_other_bad_edges(tmp_path: Path) -> None:
    text = SQUARE_G2O.replace(IDENTITY6, "1 0 0 1 0 -1")
    path = write(tmp_path, "p.g2o", text)
    assert_error(error_message(path), path, 6, "and so is that of 3 more edges (lines 7, 8, 9)")


# Finite but unusable values: too large to solve with, refused at load like NaN/inf.

FORMATS = {".g2o": (SQUARE_G2O, GraphFormat.G2O), ".graph": (SQUARE_TORO, GraphFormat.TORO)}
Field = str | tuple[int, int]  # a pose/measurement field name, or (row, col) of the information


def bad_line(fmt: GraphFormat, kind: str, field: Field, value: str) -> tuple[str, str, int]:
    """A vertex (id 4) or edge (0 -> 2) line with one field set to ``value``, identity elsewhere;
    also the field's name in this format and its field number (the tag is field 0)."""
    syntax = fmt.syntax
    if kind == "vertex":
        tag, ids, names, values = syntax.vertex_tag, ["4"], ["x", "y", "theta"], ["1", "1", "0"]
    else:
        tag, ids, names = syntax.edge_tag, ["0", "2"], list(syntax.edge_fields)
        values = ["1", "1", "0", *("1" if r == c else "0" for r, c in syntax.info_index)]
    name = syntax.info_fields[syntax.info_index.index(field)] if isinstance(field, tuple) else field
    k = names.index(name)
    values[k] = value
    return " ".join([tag, *ids, *values]), name, 1 + len(ids) + k


OUT_OF_RANGE: list[tuple[str, Field, str, str]] = [
    ("edge", (0, 0), "1e308", "an information entry beyond +/-1e30"),
    ("edge", (1, 1), "1e31", "an information entry beyond +/-1e30"),
    ("edge", (2, 2), "-1e308", "an information entry beyond +/-1e30"),
    ("edge", (0, 2), "1e31", "an information entry beyond +/-1e30"),
    ("edge", "dx", "1e308", "a coordinate beyond +/-1e9 m"),
    ("edge", "dy", "-1e10", "a coordinate beyond +/-1e9 m"),
    ("edge", "dtheta", "1e7", "an angle beyond +/-1e6 rad"),
    ("vertex", "x", "1e308", "a coordinate beyond +/-1e9 m"),
    ("vertex", "y", "-1e308", "a coordinate beyond +/-1e9 m"),
    ("vertex", "theta", "-1e7", "an angle beyond +/-1e6 rad"),
]
NON_FINITE: list[tuple[str, Field, str, str]] = [
    ("edge", (0, 0), "nan", "NaN/inf"),
    ("edge", (1, 2), "inf", "NaN/inf"),
    ("edge", "dy", "1e999", "NaN/inf"),
    ("edge", "dtheta", "-inf", "NaN/inf"),
    ("vertex", "x", "NaN", "NaN/inf"),
    ("vertex", "theta", "inf", "NaN/inf"),
    ("vertex", "y", "-inf", "NaN/inf"),
]


@pytest.mark.parametrize("suffix", list(FORMATS))
@pytest.mark.parametrize(("kind", "field", "value", "phrase"), OUT_OF_RANGE + NON_FINITE)
def test_unusable_value_names_file_line_and_field(
    tmp_path: Path, suffix: str, kind: str, field: Field, value: str, phrase: str
) -> None:
    base, fmt = FORMATS[suffix]
    line, name, number = bad_line(fmt, kind, field, value)
    tag = line.split()[0]
    # Line 6, with edges after it: the error is the bad line's, not the file's last.
    path = write(tmp_path, f"big{suffix}", with_line(base, line, at=5))
    message = error_message(path)
    assert_error(message, path, 6, f"{name} is {value!r} (field {number} of {tag})", phrase)
    assert message.count("\n") == 0


@pytest.mark.parametrize("suffix", list(FORMATS))
def test_information_advice_says_what_to_write_instead(tmp_path: Path, suffix: str) -> None:
    base, fmt = FORMATS[suffix]
    line = bad_line(fmt, "edge", (0, 0), "1e308")[0]
    message = error_message(write(tmp_path, f"big{suffix}", with_line(base, line, at=5)))
    assert "such as 1e12" in message
    # Only g2o has FIX lines to hold a vertex still.
    assert ("FIX line" in message) is (fmt is GraphFormat.G2O)


@pytest.mark.parametrize("suffix", list(FORMATS))
def test_the_first_unusable_value_of_a_line_is_named(tmp_path: Path, suffix: str) -> None:
    _, fmt = FORMATS[suffix]
    syntax = fmt.syntax
    text = f"{syntax.vertex_tag} 0 0 0 0\n{syntax.vertex_tag} 1 1e308 0 1e7\n"
    path = write(tmp_path, f"two{suffix}", text)
    assert_error(error_message(path), path, 2, "x is '1e308' (field 2 of", "coordinate")


def test_limits_are_the_documented_values() -> None:
    assert (MAX_INFORMATION, MAX_COORDINATE, MAX_ANGLE) == (1e30, 1e9, 1e6)


@pytest.mark.parametrize("suffix", list(FORMATS))
@pytest.mark.parametrize("sign", [1.0, -1.0])
def test_values_at_the_limits_are_accepted(tmp_path: Path, suffix: str, sign: float) -> None:
    _, fmt = FORMATS[suffix]
    syntax = fmt.syntax
    c, a, i = sign * MAX_COORDINATE, sign * MAX_ANGLE, MAX_INFORMATION
    info = " ".join(repr(i) if r == col else "0" for r, col in syntax.info_index)
    text = (
        f"{syntax.vertex_tag} 0 0 0 0\n"
        f"{syntax.vertex_tag} 1 {c!r} {-c!r} {a!r}\n"
        f"{syntax.edge_tag} 0 1 {c!r} {-c!r} {-a!r} {info}\n"
    )
    graph = load_graph(write(tmp_path, f"edge{suffix}", text))
    assert graph.poses[1, :2].tolist() == [c, -c]
    assert graph.measurements[0, :2].tolist() == [c, -c]
    assert graph.information[0].tolist() == (i * np.eye(3)).tolist()
    assert np.isfinite(graph.poses).all()
    assert np.isfinite(graph.measurements).all()


@pytest.mark.parametrize("suffix", list(FORMATS))
@pytest.mark.parametrize(
    ("kind", "field", "value"),
    [("edge", (0, 0), "1e308"), ("edge", "dx", "1e308"), ("vertex", "x", "1e308")],
)
def test_cli_refuses_an_unusable_value_and_writes_nothing(
    tmp_path: Path,
    capsys: pytest.CaptureFixture[str],
    suffix: str,
    kind: str,
    field: Field,
    value: str,
) -> None:
    base, fmt = FORMATS[suffix]
    bad = write(tmp_path, f"bad{suffix}", with_line(base, bad_line(fmt, kind, field, value)[0], 5))
    out = tmp_path / f"out{suffix}"
    assert main(["solve", str(bad), "-o", str(out)]) == 2
    captured = capsys.readouterr()
    assert captured.err.count("\n") == 1
    assert captured.err.startswith(f"hitl-slam: error: {bad}:6: ")
    assert captured.out == ""
    assert not out.exists()
    assert sorted(p.name for p in tmp_path.iterdir()) == [bad.name]


@pytest.mark.parametrize("suffix", list(FORMATS))
def test_cli_leaves_an_existing_output_byte_for_byte(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], suffix: str
) -> None:
    base, fmt = FORMATS[suffix]
    bad = write(
        tmp_path, f"bad{suffix}", with_line(base, bad_line(fmt, "edge", (1, 1), "1e308")[0])
    )
    out = tmp_path / f"out{suffix}"
    before = SQUARE_G2O.replace("\n", "\r\n").encode() if suffix == ".g2o" else b"\x00old\xff"
    out.write_bytes(before)
    assert main(["solve", str(bad), "-o", str(out)]) == 2
    assert f"{bad}:10: " in capsys.readouterr().err
    assert out.read_bytes() == before
    assert sorted(p.name for p in tmp_path.iterdir()) == sorted([bad.name, out.name])


@pytest.mark.parametrize("text", ["", "\n\n", "# only a comment\n   \n#another\n"])
def test_empty_file(tmp_path: Path, text: str) -> None:
    path = write(tmp_path, "empty.g2o", text)
    assert_error(error_message(path), path, None, "the file is empty")


def test_file_with_no_usable_lines(tmp_path: Path) -> None:
    path = write(tmp_path, "xy.g2o", "VERTEX_XY 1 0 0\nVERTEX_XY 2 1 0\nPARAMS 1\n")
    assert_error(
        error_message(path),
        path,
        None,
        "no VERTEX_SE2 or EDGE_SE2 lines (skipped: VERTEX_XY x2, PARAMS x1)",
        "VERTEX_SE2 id x y theta",
    )


def test_toro_content_in_a_g2o_file_says_so(tmp_path: Path) -> None:
    path = write(tmp_path, "really_toro.g2o", SQUARE_TORO)
    assert_error(error_message(path), path, None, "looks like a TORO file: name it *.graph")


def test_file_in_neither_format(tmp_path: Path) -> None:
    path = write(tmp_path, "notes.txt", "# header\n\nhello world\nVERTEX_SE2 0 0 0 0\n")
    assert_error(error_message(path), path, 3, "neither a g2o nor a TORO", "'hello'")


def test_missing_file(tmp_path: Path) -> None:
    path = tmp_path / "nowhere.g2o"
    assert_error(error_message(path), path, None, "no such file")


def test_directory_instead_of_file(tmp_path: Path) -> None:
    path = tmp_path / "dir.g2o"
    path.mkdir()
    assert_error(error_message(path), path, None, "is a directory")


def test_damaged_compressed_file(tmp_path: Path) -> None:
    path = tmp_path / "broken.g2o.gz"
    path.write_bytes(gzip.compress(SQUARE_G2O.encode())[:-12])
    assert_error(error_message(path), path, None, "cannot be decompressed")


def test_not_utf8(tmp_path: Path) -> None:
    path = tmp_path / "latin1.g2o"
    path.write_bytes(SQUARE_G2O.encode() + "# caf\u00e9\n".encode("latin-1"))
    assert_error(error_message(path), path, 10, "not UTF-8 text (byte 0xe9 at column 6)")


def test_vertices_not_connected_to_the_anchor(tmp_path: Path) -> None:
    text = SQUARE_G2O + "".join(f"VERTEX_SE2 {v} {v} 0 0\n" for v in range(100, 107))
    text += f"EDGE_SE2 100 101 1 0 0 {IDENTITY6}\n"
    path = write(tmp_path, "c.g2o", text)
    assert_error(
        error_message(path),
        path,
        10,
        "7 vertices are not connected to the anchor vertex 0 through edges",
        "(ids 100, 101, 102, 103, 104, ...)",
        "add edges linking them, or remove them",
    )


def test_one_unconnected_vertex_and_a_fixed_anchor(tmp_path: Path) -> None:
    text = with_line(SQUARE_G2O, "VERTEX_SE2 8 0 0 0", at=1) + "FIX 3\n"
    path = write(tmp_path, "c.g2o", text)
    assert_error(error_message(path), path, 2, "1 vertex is not connected to the anchor vertex 3")


def test_fix_of_an_unknown_vertex(tmp_path: Path) -> None:
    path = write(tmp_path, "f.g2o", SQUARE_G2O + "FIX 17\n")
    assert_error(error_message(path), path, 10, "anchor) vertex 17 has no VERTEX_SE2 line")


def test_equiv_of_an_unknown_vertex(tmp_path: Path) -> None:
    path = write(tmp_path, "e.graph", SQUARE_TORO + "EQUIV 3 17\n")
    assert_error(error_message(path), path, 10, "EQUIV names vertex 17")


def assert_valid(graph: PoseGraph) -> None:
    """What every loaded graph promises the solver."""
    assert np.isfinite(graph.poses).all()
    assert np.isfinite(graph.measurements).all()
    for theta in (graph.poses[:, 2], graph.measurements[:, 2]):
        assert np.all((theta > -math.pi) & (theta <= math.pi))
    if graph.num_edges:
        assert graph.edges.min() >= 0
        assert graph.edges.max() < graph.num_poses
        assert (graph.edges[:, 0] != graph.edges[:, 1]).all()
        np.linalg.cholesky(graph.information)
    assert 0 <= graph.anchor < graph.num_poses


# ---------------------------------------------------------------------------------------------
# Fuzzing: garbage never escapes as anything but InputError

TAGS = ["VERTEX_SE2", "EDGE_SE2", "VERTEX2", "EDGE2", "EQUIV", "FIX", "VERTEX_XY", "PARAMS", "#"]
TOKENS = st.one_of(
    st.integers(-3, 6).map(str),
    st.floats(allow_nan=True, allow_infinity=True).map(repr),
    st.sampled_from(["nan", "-inf", "1e999", "1_0", "0x1f", "\u0663", "99999999999999999999"]),
    st.text(max_size=6),
)
GARBAGE_LINE = st.one_of(
    st.builds(
        lambda tag, rest: " ".join([tag, *rest]),
        st.sampled_from(TAGS),
        st.lists(TOKENS, max_size=13),
    ),
    st.text(max_size=30),
)


@pytest.mark.parametrize(
    ("suffix", "base"), [(".g2o", SQUARE_G2O), (".graph", SQUARE_TORO), (".txt", SQUARE_G2O)]
)
@settings(max_examples=150, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(insertions=st.lists(st.tuples(st.integers(0, 9), GARBAGE_LINE), max_size=4))
def test_garbage_lines_only_ever_raise_input_error(
    tmp_path_factory: pytest.TempPathFactory,
    suffix: str,
    base: str,
    insertions: list[tuple[int, str]],
) -> None:
    lines = base.splitlines()
    for at, line in insertions:
        lines.insert(at, line)
    path = tmp_path_factory.getbasetemp() / f"fuzz{suffix}"
    path.write_text("\n".join(lines), encoding="utf-8", errors="surrogatepass")
    try:
        graph = load_graph(path)
    except InputError as exc:
        message = str(exc)
    else:
        assert_valid(graph)
        return
    assert message.startswith(f"{path}:"), message


# ---------------------------------------------------------------------------------------------
# Writers


def assert_same_graph(a: PoseGraph, b: PoseGraph) -> None:
    for name in ("poses", "edges", "measurements", "information", "vertex_ids"):
        np.testing.assert_array_equal(getattr(a, name), getattr(b, name), err_msg=name)
    assert a.anchor == b.anchor


def random_graph(rng: np.random.Generator, n: int, m: int) -> PoseGraph:
    poses = rng.normal(scale=50, size=(n, 3))
    poses[:, 2] = rng.uniform(-math.pi, math.pi, n)
    edges = np.array(
        [(k, k + 1) for k in range(n - 1)]
        + [tuple(rng.choice(n, 2, replace=False)) for _ in range(m - n + 1)],
        dtype=np.int64,
    ).reshape(-1, 2)
    measurements = rng.normal(size=(m, 3))
    measurements[:, 2] = rng.uniform(-math.pi, math.pi, m)
    factors = rng.normal(size=(m, 3, 3))
    information = factors @ factors.transpose(0, 2, 1) + np.eye(3)
    vertex_ids = rng.permutation(10 * n)[:n]
    return PoseGraph(poses, edges, measurements, information, vertex_ids)


@settings(max_examples=25, deadline=None)
@given(
    seed=st.integers(0, 2**32 - 1),
    n=st.integers(1, 30),
    extension=st.sampled_from([".g2o", ".graph"]),
)
def test_round_trip_is_exact(
    tmp_path_factory: pytest.TempPathFactory, seed: int, n: int, extension: str
) -> None:
    graph = random_graph(np.random.default_rng(seed), n, n + 5 if n > 1 else 0)
    path = tmp_path_factory.getbasetemp() / f"round{extension}"
    save_graph(graph, graph.poses, path)
    assert_same_graph(load_graph(path), graph)


def test_saved_file_uses_the_given_poses_ids_and_toro_order(tmp_path: Path) -> None:
    graph = load_graph(
        write(
            tmp_path,
            "in.g2o",
            "VERTEX_SE2 5 0 0 0\nVERTEX_SE2 9 1 0 0\nEDGE_SE2 5 9 1 0 0 4 1 0.5 3 0.25 2\n",
        )
    )
    save_graph(graph, [[0.1, 0.2, 0.3], [1.5, -2.0, -0.25]], tmp_path / "out.graph")
    assert (tmp_path / "out.graph").read_text().splitlines() == [
        "VERTEX2 5 0.1 0.2 0.3",
        "VERTEX2 9 1.5 -2.0 -0.25",
        "EDGE2 5 9 1.0 0.0 0.0 4.0 1.0 3.0 2.0 0.5 0.25",
    ]


def test_g2o_keeps_a_moved_anchor_as_fix(tmp_path: Path) -> None:
    graph = load_graph(write(tmp_path, "fix.g2o", SQUARE_G2O + "FIX 2\n"))
    save_graph(graph, None, tmp_path / "again.g2o")
    assert "FIX 2" in (tmp_path / "again.g2o").read_text()
    assert_same_graph(load_graph(tmp_path / "again.g2o"), graph)


@pytest.mark.parametrize(
    ("name", "poses", "phrase"),
    [
        ("out.txt", None, "use one of the supported extensions: .g2o, .graph"),
        ("out", None, "supported extensions"),
        ("out.g2o", np.zeros((3, 3)), "poses have shape (3, 3) but the graph has 4 vertices"),
        ("out.g2o", np.full((4, 3), np.nan), "poses row 0 is not finite"),
        ("missing_dir/out.g2o", None, "cannot write the file"),
    ],
)
def test_save_errors(
    tmp_path: Path, name: str, poses: NDArray[np.float64] | None, phrase: str
) -> None:
    graph = load_graph(write(tmp_path, "in.g2o", SQUARE_G2O))
    with pytest.raises(InputError) as excinfo:
        save_graph(graph, poses, tmp_path / name)
    assert_error(str(excinfo.value), tmp_path / name, None, phrase)


# ---------------------------------------------------------------------------------------------
# Atomic writes


def test_atomic_write_replaces_and_leaves_no_temp_files(tmp_path: Path) -> None:
    path = tmp_path / "a.txt"
    atomic_write_text(path, "one\n")
    atomic_write_text(path, "two\n")
    assert path.read_text() == "two\n"
    assert os.listdir(tmp_path) == ["a.txt"]


def test_failed_rename_keeps_the_old_file(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    path = tmp_path / "graph.g2o"
    path.write_text("old contents\n")
    graph = load_graph(write(tmp_path, "in.g2o", SQUARE_G2O))

    def refuse(*_paths: object) -> None:
        raise OSError(28, "No space left on device")

    monkeypatch.setattr(os, "replace", refuse)
    with pytest.raises(OSError, match="No space left"):
        atomic_write_text(path, "new contents\n")
    with pytest.raises(InputError, match="cannot write the file"):
        save_graph(graph, None, path)
    assert path.read_text() == "old contents\n"
    assert sorted(os.listdir(tmp_path)) == ["graph.g2o", "in.g2o"]


def test_exception_mid_write_keeps_the_old_file(tmp_path: Path) -> None:
    path = tmp_path / "a.txt"
    path.write_text("old\n")

    def interrupted() -> None:
        with atomic_writer(path) as f:
            f.write("half of the ne")
            raise RuntimeError("interrupted")

    with pytest.raises(RuntimeError, match="interrupted"):
        interrupted()
    assert path.read_text() == "old\n"
    assert os.listdir(tmp_path) == ["a.txt"]


@pytest.mark.skipif(sys.platform == "win32", reason="POSIX permission bits")
def test_atomic_write_keeps_the_permissions_of_the_file_it_replaces(tmp_path: Path) -> None:
    path = tmp_path / "a.txt"
    path.write_text("old\n")
    path.chmod(0o640)
    atomic_write_text(path, "new\n")
    assert stat.S_IMODE(path.stat().st_mode) == 0o640
