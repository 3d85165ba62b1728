"""Issue 13, readers: malformed corrections lines, values whose arithmetic overflows, non-ASCII
digits and non-regular files (FIFOs) are each a one-line InputError naming the file (and the line),
never a traceback, a hang or a silently useless map; what the writers write reads back."""

from __future__ import annotations

import json
import os
import signal
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from hitl_slam.corrections_file import read_corrections
from hitl_slam.errors import InputError
from hitl_slam.graph import PoseGraph
from hitl_slam.io import load_graph, save_graph
from hitl_slam.io.carmen import read_carmen
from hitl_slam.io.covars import read_covars, write_covars
from hitl_slam.io.export import write_g2o_map
from hitl_slam.io.maps import load_map
from hitl_slam.io.relations import read_relations
from hitl_slam.map import Map

ARABIC_THREE = "\u0663"  # ARABIC-INDIC DIGIT THREE: float() reads it as 3
FULLWIDTH_THREE = "\uff13"  # FULLWIDTH DIGIT THREE: float() reads it as 3
SEGMENT_A = [[1.2, 3.4], [4.1, 3.45]]
SEGMENT_B = [[10.0, 3.9], [13.2, 4.0]]


def write(tmp_path: Path, name: str, text: str) -> Path:
    path = tmp_path / name
    path.write_text(text, encoding="utf-8")
    return path


def error_of(function: Callable[..., Any], path: Path) -> str:
    with pytest.raises(InputError) as info:
        function(path)
    return str(info.value)


def assert_located(message: str, path: Path, line: int | None) -> None:
    prefix = f"{path}:{line}: " if line is not None else f"{path}: "
    assert message.startswith(prefix), message
    assert "; " in message[len(prefix) :], f"no advice in: {message}"


def correction(**extra: Any) -> dict[str, Any]:
    return {"mode": "collinear", "a": SEGMENT_A, "b": SEGMENT_B, **extra}


# ---------------------------------------------------------------------------------------------
# Finding 1: corrections file lines that used to end in a traceback


def test_corrections_deeply_nested_json_is_an_input_error(tmp_path: Path) -> None:
    good = json.dumps(correction())
    path = write(tmp_path, "c.jsonl", good + "\n" + "[" * 100_000 + "]" * 100_000 + "\n")
    message = error_of(read_corrections, path)
    assert_located(message, path, 2)
    assert "nested" in message


def test_corrections_moderately_nested_json_is_an_input_error(tmp_path: Path) -> None:
    # Deep enough to break json.dumps in the error message, not json.loads.
    a = "[" * 900 + "]" * 900
    path = write(tmp_path, "c.jsonl", f'{{"mode": "collinear", "a": {a}, "b": {a}}}\n')
    assert_located(error_of(read_corrections, path), path, 1)


@pytest.mark.parametrize(
    "line",
    [
        '{"mode": "collinear", "a": [[1, 2], [3, 4]], "b": [[5, 6], [7, 8]], "sigma_h": N}',
        '{"mode": "collinear", "a": [[N, 2], [3, 4]], "b": [[5, 6], [7, 8]]}',
        '{"version": N}',
        '{"action": "undo", "version": N}',
        "[N]",
        "N",
    ],
)
def test_corrections_integer_of_thousands_of_digits_is_an_input_error(
    tmp_path: Path, line: str
) -> None:
    path = write(tmp_path, "c.jsonl", line.replace("N", "9" * 5000) + "\n")
    message = error_of(read_corrections, path)
    assert_located(message, path, 1)
    assert "5000 digits" in message


@pytest.mark.parametrize(
    ("sigma", "phrase"),
    [("1" + "0" * 400, "401 digits"), ("1e308", "sigma_h"), ("1e-320", "sigma_h")],
)
def test_corrections_sigma_beyond_the_limits_is_an_input_error(
    tmp_path: Path, sigma: str, phrase: str
) -> None:
    line = json.dumps(correction(sigma_h=0.5)).replace("0.5", sigma)
    path = write(tmp_path, "c.jsonl", line + "\n")
    message = error_of(read_corrections, path)
    assert_located(message, path, 1)
    assert phrase in message


def test_corrections_coordinate_beyond_the_limit_is_an_input_error(tmp_path: Path) -> None:
    path = write(
        tmp_path,
        "c.jsonl",
        json.dumps({"mode": "collinear", "a": [[1e300, 0], [1, 1]], "b": SEGMENT_B}),
    )
    message = error_of(read_corrections, path)
    assert_located(message, path, 1)
    assert "1e9" in message


def test_corrections_within_the_limits_still_read(tmp_path: Path) -> None:
    path = write(
        tmp_path,
        "c.jsonl",
        json.dumps(correction(sigma_h=1e-6)) + "\n" + json.dumps(correction(sigma_h=2)) + "\n",
    )
    steps = read_corrections(path)
    assert len(steps) == 2


# ---------------------------------------------------------------------------------------------
# Finding 2: extreme values refused at load, with the limit, file and line


def covars_line(pose: tuple[float, float, float], obs: tuple[float, float]) -> str:
    values = [*pose, *obs, 0.0, 0.0] + [0.0] * 9
    return ", ".join(repr(float(v)) for v in values)


def test_covars_pose_of_1e300_is_refused_at_load(tmp_path: Path) -> None:
    lines = [covars_line((i * 1e300, 0.0, 0.0), (i * 1e300 + 1.0, 0.0)) for i in range(3)]
    path = write(tmp_path, "m.covars", "m\n0\n" + "\n".join(lines) + "\n")
    message = error_of(read_covars, path)
    assert_located(message, path, 4)
    assert "1e9" in message


@pytest.mark.parametrize(
    ("column", "value", "limit"),
    [(2, "1e7", "1e6"), (5, "1e300", "1e9"), (7, "1e300", "1e18"), (3, "-2e9", "1e9")],
)
def test_covars_field_beyond_its_limit_is_refused(
    tmp_path: Path, column: int, value: str, limit: str
) -> None:
    fields = ["0.5"] * 16
    fields[column] = value
    good = covars_line((0.0, 0.0, 0.0), (1.0, 0.0))
    path = write(tmp_path, "m.covars", "m\n0\n" + good + "\n" + ", ".join(fields) + "\n")
    message = error_of(read_covars, path)
    assert_located(message, path, 4)
    assert limit in message


def flaser(pose: tuple[str, str, str], ranges: tuple[str, ...] = ("1", "2", "3")) -> str:
    return f"FLASER {len(ranges)} {' '.join(ranges)} {' '.join(pose)} {' '.join(pose)} 1.0 h 1.0"


def test_carmen_pose_of_1e300_is_refused_at_load(tmp_path: Path) -> None:
    text = flaser(("0", "0", "0")) + "\n" + flaser(("1e300", "0", "0")) + "\n"
    path = write(tmp_path, "a.clf", text)
    message = error_of(read_carmen, path)
    assert_located(message, path, 2)
    assert "1e9" in message


@pytest.mark.parametrize(
    ("line", "limit"),
    [
        ("PARAM robot_front_laser_max 1e300", "1e9"),
        ("PARAM robot_frontlaser_offset 1e300", "1e9"),
        ("PARAM robot_frontlaser_angular_offset 1e300", "1e6"),
        (
            "ROBOTLASER1 0 0.0 1e306 1e306 80.0 0.01 0 3 1 2 3 0 0 0 0 0 0 0 0 0 0 0 0 1.0 h 1.0",
            "1e6",
        ),
        (
            "ROBOTLASER1 0 0.0 3.1 1.0 1e300 0.01 0 3 1 2 3 0 0 0 0 0 0 0 0 0 0 0 0 1.0 h 1.0",
            "1e9",
        ),
    ],
)
def test_carmen_laser_geometry_beyond_its_limit_is_refused(
    tmp_path: Path, line: str, limit: str
) -> None:
    text = line + "\n" + (flaser(("0", "0", "0")) if line.startswith("PARAM") else "") + "\n"
    path = write(tmp_path, "a.clf", text)
    message = error_of(read_carmen, path)
    assert_located(message, path, 1)
    assert limit in message


def test_carmen_max_range_argument_beyond_the_limit_is_refused(tmp_path: Path) -> None:
    path = write(tmp_path, "a.clf", flaser(("0", "0", "0")) + "\n")
    with pytest.raises(InputError, match="1e9"):
        read_carmen(path, max_range=1e300)


def test_relations_displacement_of_1e300_is_refused(tmp_path: Path) -> None:
    path = write(tmp_path, "a.relations", "1 2 0.5 0 0 0 0 0.1\n1 2 1e300 0 0 0 0 0\n")
    message = error_of(read_relations, path)
    assert_located(message, path, 2)
    assert "1e9" in message


def big_graph(scale: float) -> PoseGraph:
    poses = np.array([[0.0, 0.0, 0.0], [scale, 0.0, 0.0]])
    return PoseGraph(
        poses=poses,
        edges=np.array([[0, 1]]),
        measurements=np.array([[scale, 0.0, 0.0]]),
        information=np.eye(3)[None],
    )


@pytest.mark.parametrize("extension", [".g2o", ".graph"])
def test_save_graph_refuses_what_the_reader_would_refuse(tmp_path: Path, extension: str) -> None:
    path = tmp_path / f"big{extension}"
    with pytest.raises(InputError, match="1e9") as info:
        save_graph(big_graph(1e300), None, path)
    assert str(info.value).startswith(f"{path}: ")
    assert not path.exists()


@pytest.mark.parametrize(
    ("information", "phrase"),
    [(np.diag([1e40, 1.0, 1.0]), "1e30"), (np.diag([1.0, -1.0, 1.0]), "positive definite")],
)
def test_save_graph_refuses_information_the_reader_would_refuse(
    tmp_path: Path, information: np.ndarray, phrase: str
) -> None:
    graph = big_graph(1.0)
    graph.information[0] = information
    path = tmp_path / "g.g2o"
    with pytest.raises(InputError, match=phrase):
        save_graph(graph, None, path)
    assert not path.exists()


def test_save_graph_refuses_a_disconnected_graph(tmp_path: Path) -> None:
    graph = PoseGraph(
        poses=np.zeros((3, 3)),
        edges=np.array([[0, 1]]),
        measurements=np.array([[1.0, 0.0, 0.0]]),
        information=np.eye(3)[None],
    )
    path = tmp_path / "g.g2o"
    with pytest.raises(InputError, match="not connected"):
        save_graph(graph, None, path)
    assert not path.exists()


def long_map(step: float) -> Map:
    n = 5
    poses = np.stack([np.arange(n) * step, np.zeros(n), np.zeros(n)], axis=1)
    return Map.from_poses_and_scans(poses, [np.array([[1.0, 0.5]])] * n, name="long")


@pytest.mark.parametrize("step", [1.0, 1e8, 2e8])
def test_exported_g2o_of_a_long_map_reads_back(tmp_path: Path, step: float) -> None:
    the_map = long_map(step)
    for name in ("m.g2o", "m.graph"):
        path = tmp_path / name
        write_g2o_map(the_map, the_map.poses, path)
        graph = load_graph(path)
        np.testing.assert_array_equal(graph.poses, the_map.poses)
        np.testing.assert_array_equal(graph.measurements, the_map.measurements)
        np.testing.assert_array_equal(graph.information, the_map.information)


def test_covars_written_beyond_the_limit_is_refused_not_written(tmp_path: Path) -> None:
    the_map = long_map(1.0)
    poses = the_map.poses.copy()
    poses[3, 0] = 1e300
    path = tmp_path / "m.covars"
    with pytest.raises(InputError, match="1e9"):
        write_covars(the_map, poses, path)
    assert not path.exists()


def test_covars_round_trip_of_a_long_map(tmp_path: Path) -> None:
    the_map = long_map(1e8)
    path = tmp_path / "m.covars"
    write_covars(the_map, the_map.poses, path)
    again = read_covars(path)
    np.testing.assert_array_equal(again.poses, the_map.poses)
    assert np.all(np.isfinite(again.information))
    assert np.all(again.information[:, 0, 0] > 0)


# ---------------------------------------------------------------------------------------------
# Finding 7: non-ASCII digits and non-regular files


@pytest.fixture(params=[ARABIC_THREE, FULLWIDTH_THREE], ids=["arabic-indic", "fullwidth"])
def digit(request: pytest.FixtureRequest) -> str:
    return str(request.param)


def covars_with(field_text: str, where: str) -> str:
    good = covars_line((0.0, 0.0, 0.0), (1.0, 0.0))
    if where == "stamp":
        return f"m\n{field_text}\n{good}\n"
    fields = good.split(", ")
    fields[int(where)] = field_text
    return "m\n0\n" + ", ".join(fields) + "\n"


@pytest.mark.parametrize("where", ["stamp", "0", "4", "15"])
def test_covars_refuses_non_ascii_digits(tmp_path: Path, digit: str, where: str) -> None:
    path = write(tmp_path, "m.covars", covars_with(f"1{digit}", where))
    message = error_of(read_covars, path)
    assert_located(message, path, 2 if where == "stamp" else 3)
    assert f"1{digit}" in message


@pytest.mark.parametrize(
    "make",
    [
        lambda d: flaser(("0", f"1{d}", "0")),
        lambda d: flaser(("0", "0", "0"), ("1", f"2{d}", "3")),
        lambda d: f"PARAM robot_frontlaser_offset 0.{d}\n" + flaser(("0", "0", "0")),
        lambda d: (
            f"ROBOTLASER1 0 0.0 3.1 1.0 8{d} 0.01 0 3 1 2 3 0 0 0 0 0 0 0 0 0 0 0 0 1.0 h 1.0"
        ),
        lambda d: flaser(("0", "0", "0")).replace(" 1.0 h", f" 1{d} h"),
    ],
    ids=["pose", "range", "param", "robotlaser", "timestamp"],
)
def test_carmen_refuses_non_ascii_digits(
    tmp_path: Path, digit: str, make: Callable[[str], str]
) -> None:
    path = write(tmp_path, "a.clf", make(digit) + "\n")
    message = error_of(read_carmen, path)
    assert_located(message, path, 1)
    assert digit in message


@pytest.mark.parametrize("column", [0, 2, 7])
def test_relations_refuse_non_ascii_digits(tmp_path: Path, digit: str, column: int) -> None:
    fields = ["1", "2", "0", "0", "0", "0", "0", "0"]
    fields[column] = f"1{digit}"
    path = write(tmp_path, "a.relations", " ".join(fields) + "\n")
    assert_located(error_of(read_relations, path), path, 1)


@pytest.mark.parametrize("extension", [".g2o", ".graph"])
def test_pose_graphs_refuse_non_ascii_digits(tmp_path: Path, digit: str, extension: str) -> None:
    v, e = ("VERTEX_SE2", "EDGE_SE2") if extension == ".g2o" else ("VERTEX2", "EDGE2")
    text = f"{v} 0 0 0 0\n{v} 1 1{digit} 0 0\n{e} 0 1 1 0 0 1 0 0 1 0 1\n"
    path = write(tmp_path, f"g{extension}", text)
    assert_located(error_of(load_graph, path), path, 2)


def test_corrections_refuse_non_ascii_digits(tmp_path: Path, digit: str) -> None:
    line = json.dumps(correction()).replace("1.2", f"1{digit}", 1)
    path = write(tmp_path, "c.jsonl", line + "\n")
    assert_located(error_of(read_corrections, path), path, 1)


@pytest.fixture
def alarm() -> Iterator[None]:
    """Fail (instead of hanging the suite) when a reader blocks on a FIFO."""

    def timeout(signum: int, frame: object) -> None:
        raise TimeoutError("the reader blocked on the FIFO")

    previous = signal.signal(signal.SIGALRM, timeout)
    signal.alarm(5)
    try:
        yield
    finally:
        signal.alarm(0)
        signal.signal(signal.SIGALRM, previous)


@pytest.mark.skipif(not hasattr(os, "mkfifo"), reason="no FIFOs on this platform")
@pytest.mark.parametrize(
    ("name", "reader"),
    [
        ("c.jsonl", read_corrections),
        ("g.g2o", load_graph),
        ("g.graph", load_graph),
        ("m.covars", read_covars),
        ("m.covars", load_map),
        ("a.clf", read_carmen),
        ("a.clf.gz", load_map),
        ("a.relations", read_relations),
        ("s.hitl", load_map),
    ],
)
def test_a_fifo_is_refused_up_front(
    tmp_path: Path, alarm: None, name: str, reader: Callable[[Path], object]
) -> None:
    path = tmp_path / name
    os.mkfifo(path)
    message = error_of(reader, path)
    assert_located(message, path, None)
    assert "not a regular file" in message
    assert "FIFO" in message
