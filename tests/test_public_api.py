"""The public API: every name of ``hitl_slam.__all__`` imports and is documented, a small map goes
from a file through a session and back using only ``hitl_slam.*`` names, a tiny graph optimizes;
the optional extras ([web], [plot]) are not imported by the library and a missing one is one line
naming it; a Map shows itself in a notebook."""

from __future__ import annotations

import base64
import importlib
import math
import re
import struct
import subprocess
import sys
from pathlib import Path
from typing import Any

import numpy as np
import pytest

import hitl_slam
import hitl_slam.plot  # imported before the tests that hide matplotlib
from hitl_slam.cli import main
from hitl_slam.extras import EXTRAS, require
from hitl_slam.sim.corridor import OUTER_BOTTOM, World, corridor_loop, drawn_segment

OPTIONAL = ("fastapi", "uvicorn", "pydantic", "matplotlib")
WEB = (
    "needs the web extra: pip install 'fastapi>=0.110' 'uvicorn>=0.29' 'pydantic>=2.6' "
    "(or, in a clone of hitl-slam: pip install '.[web]')"
)
"""The one line a missing [web] extra gives: what installs it from an index or a clone."""


@pytest.fixture(scope="module")
def world() -> World:
    return corridor_loop(seed=1)


# -- the names -------------------------------------------------------------------------------


def test_every_name_of_all_imports_and_is_documented() -> None:
    namespace: dict[str, Any] = {}
    exec("from hitl_slam import *", namespace)
    assert sorted(hitl_slam.__all__) == hitl_slam.__all__, "keep __all__ sorted"
    assert len(set(hitl_slam.__all__)) == len(hitl_slam.__all__)
    for name in hitl_slam.__all__:
        value = namespace[name]
        assert value is getattr(hitl_slam, name)
        if name == "__version__":
            assert isinstance(value, str)
            assert value
            continue
        assert (value.__doc__ or "").strip(), f"hitl_slam.{name} has no docstring"


def test_the_names_the_issue_asks_for_are_there() -> None:
    for name in ("load_map", "Map", "Session", "Correction", "optimize", "load_graph", "Mode"):
        assert name in hitl_slam.__all__, name


def test_a_drawn_correction_has_one_name() -> None:
    from hitl_slam import corrections

    assert hitl_slam.Correction is corrections.Correction
    assert not hasattr(hitl_slam, "DrawnCorrection")
    assert not hasattr(corrections, "DrawnCorrection")
    c = hitl_slam.Correction.make([[0, 0], [1, 0]], [[0, 1], [1, 1]], "parallel")
    assert c.mode is hitl_slam.Mode.PARALLEL


def test_errors_are_one_family() -> None:
    for name in ("InputError", "SolverError", "CorrectionRejected", "MissingExtra"):
        assert issubclass(getattr(hitl_slam, name), hitl_slam.HitlSlamError), name
    assert issubclass(hitl_slam.MissingExtra, hitl_slam.InputError)
    assert issubclass(hitl_slam.MissingExtra, ImportError)


# -- a small end-to-end use --------------------------------------------------------------------


def _offset_from_line(points: np.ndarray, line_points: np.ndarray) -> float:
    """Mean distance of ``points`` from the total-least-squares line of ``line_points``."""
    centre = line_points.mean(axis=0)
    _, vecs = np.linalg.eigh((line_points - centre).T @ (line_points - centre))
    normal = vecs[:, 0]
    return float(np.abs((points - centre) @ normal).mean())


def test_load_correct_save_through_the_public_api(world: World, tmp_path: Path) -> None:
    source = tmp_path / "corridor.covars"
    hitl_slam.export(world.map, world.map.poses, source)
    m = hitl_slam.load_map(source)
    assert isinstance(m, hitl_slam.Map)
    assert (m.num_poses, m.num_points) == (world.map.num_poses, world.map.num_points)

    rng = np.random.default_rng(0)
    correction = hitl_slam.Correction.make(
        drawn_segment(world, m.poses, OUTER_BOTTOM, (0, 60), rng),
        drawn_segment(world, m.poses, OUTER_BOTTOM, (265, 325), rng),
        "colocation",
    )
    interpretation = hitl_slam.interpret(m, m.poses, correction)
    assert isinstance(interpretation, hitl_slam.Interpretation)

    owner = m.pose_of_point()
    bottom = world.wall_of_point == OUTER_BOTTOM
    first, second = bottom & (owner < 60), bottom & (owner >= 265) & (owner < 325)

    def gap(poses: np.ndarray) -> float:
        world_points = m.world_points(poses)
        return _offset_from_line(world_points[second], world_points[first])

    session_path = tmp_path / "corridor.hitl"
    with hitl_slam.Session.new(m, session_path) as session:
        outcome = session.apply(correction)
        assert session.history[-1].status is hitl_slam.EntryStatus.APPLIED
        # What a person prints reads as a line per part, not thousands of point indices.
        shown = repr(session.history[-1])
        assert len(shown) < 800, shown
        assert "interpretation=Interpretation(" in shown
        assert " points from " in shown
        after = session.poses.copy()
        session.save(tmp_path / "fixed.covars")
    # The fault bent the second pass 4 degrees off the wall; the correction puts it back on.
    assert gap(m.poses) > 0.1
    assert gap(after) < 0.03
    np.testing.assert_array_equal(outcome.poses, after)
    np.testing.assert_allclose(hitl_slam.load_map(tmp_path / "fixed.covars").poses, after)

    with hitl_slam.Session.open(session_path) as reopened:
        np.testing.assert_array_equal(reopened.poses, after)
        assert reopened.corrections == [correction]

    # The same step without a session, and the scores.
    result = hitl_slam.apply_correction(m, m.poses, correction)
    assert isinstance(result, hitl_slam.CorrectionResult)
    np.testing.assert_allclose(result.poses, after, atol=1e-9)
    before_score = hitl_slam.inconsistency(m)
    after_score = hitl_slam.inconsistency(m, after, like=before_score)
    assert isinstance(after_score, hitl_slam.Inconsistency)
    assert after_score.total_m2 < before_score.total_m2
    assert hitl_slam.ate(after, world.truth) < hitl_slam.ate(m.poses, world.truth)


def test_optimize_a_tiny_graph() -> None:
    # A unit square driven counter-clockwise with a loop closure; the start is off.
    quarter = [1.0, 0.0, math.pi / 2]
    graph = hitl_slam.PoseGraph(
        poses=[[0, 0, 0], [1.1, 0.1, 1.4], [1.2, 0.9, 3.0], [0.1, 1.2, -1.4]],
        edges=[[0, 1], [1, 2], [2, 3], [3, 0]],
        measurements=[quarter] * 4,
        information=[np.eye(3) * 100.0] * 4,
    )
    poses, report = hitl_slam.optimize(graph)
    assert isinstance(report, hitl_slam.SolveReport)
    assert report.converged
    assert report.final_chi2 < 1e-12 < report.initial_chi2
    square = np.array([[0, 0, 0], [1, 0, math.pi / 2], [1, 1, math.pi], [0, 1, -math.pi / 2]])
    np.testing.assert_allclose(poses[:, :2], square[:, :2], atol=1e-9)
    turn = np.angle(np.exp(1j * (poses[:, 2] - square[:, 2])))  # pi and -pi are one heading
    np.testing.assert_allclose(turn, 0.0, atol=1e-9)
    assert hitl_slam.chi2(graph, poses) == pytest.approx(report.final_chi2, abs=1e-12)


# -- extras ------------------------------------------------------------------------------------


def test_a_library_import_pulls_neither_extra() -> None:
    for module in ("hitl_slam", "hitl_slam.cli"):
        code = (
            f"import sys, {module}\n"
            f"loaded = [m for m in {OPTIONAL!r} if m in sys.modules]\n"
            "assert not loaded, loaded\n"
        )
        result = subprocess.run(
            [sys.executable, "-c", code], capture_output=True, text=True, check=False
        )
        assert result.returncode == 0, (module, result.stderr)


def test_pyproject_extras_list_the_modules_the_code_checks() -> None:
    import tomllib

    project = tomllib.loads((Path(__file__).parents[1] / "pyproject.toml").read_text())["project"]
    extras = project["optional-dependencies"]

    def names(requirements: list[str]) -> set[str]:
        return {re.split(r"[<>=\[ ;]", r, maxsplit=1)[0] for r in requirements}

    core = names(project["dependencies"])
    for extra, modules in EXTRAS.items():
        assert names(extras[extra]) == set(modules), extra
        assert not core & set(modules), f"{extra} modules are also core dependencies"
        # `make test` (the [test] extra) and the benches keep installing them.
        assert set(modules) <= names(extras["test"]), extra
        assert set(modules) <= names(extras["bench"]), extra


@pytest.fixture
def no_fastapi(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setitem(sys.modules, "fastapi", None)


@pytest.fixture
def no_matplotlib(monkeypatch: pytest.MonkeyPatch) -> None:
    """As if matplotlib were not installed (and hitl_slam.plot not yet imported); both restored
    afterwards."""
    for name in [m for m in sys.modules if m == "matplotlib" or m.startswith("matplotlib.")]:
        monkeypatch.setitem(sys.modules, name, None)
    monkeypatch.setitem(sys.modules, "matplotlib", None)
    monkeypatch.delitem(sys.modules, "hitl_slam.plot")
    monkeypatch.delattr(hitl_slam, "plot")


def _one_line_error(capsys: pytest.CaptureFixture[str]) -> str:
    captured = capsys.readouterr()
    lines = captured.err.splitlines()
    assert len(lines) == 1, captured.err
    assert "Traceback" not in captured.err
    return lines[0]


@pytest.mark.usefixtures("no_fastapi")
def test_serve_without_the_web_extra_is_one_line(
    capsys: pytest.CaptureFixture[str], tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.chdir(tmp_path)
    assert main(["serve", "--demo", "--port", "0"]) == 2
    assert _one_line_error(capsys) == f"hitl-slam: error: hitl-slam serve {WEB}"
    assert list(tmp_path.iterdir()) == []  # nothing generated, no server started


@pytest.mark.usefixtures("no_matplotlib")
def test_figures_without_the_plot_extra_are_one_line(
    capsys: pytest.CaptureFixture[str], tmp_path: Path, world: World
) -> None:
    needs = (
        "needs the plot extra: pip install 'matplotlib>=3.8' "
        "(or, in a clone of hitl-slam: pip install '.[plot]')"
    )
    assert main(["demo", "-o", str(tmp_path / "demo"), "--quiet"]) == 2
    assert _one_line_error(capsys) == f"hitl-slam: error: hitl-slam demo {needs}"
    assert main(["evaluate", "--quick", "-o", str(tmp_path / "eval")]) == 2
    assert _one_line_error(capsys) == f"hitl-slam: error: hitl-slam evaluate {needs}"
    source = tmp_path / "corridor.covars"
    hitl_slam.export(world.map, world.map.poses, source)
    heat = tmp_path / "heat.png"
    assert main(["metrics", str(source), "--heat-map", str(heat)]) == 2
    assert _one_line_error(capsys) == f"hitl-slam: error: hitl-slam metrics --heat-map {needs}"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["corridor.covars"]
    with pytest.raises(hitl_slam.MissingExtra, match=re.escape(f"hitl_slam.plot {needs}")):
        importlib.import_module("hitl_slam.plot")


def test_a_missing_extra_in_a_real_process_exits_2_with_one_line(tmp_path: Path) -> None:
    code = (
        "import sys\n"
        "sys.modules['fastapi'] = None\n"
        "from hitl_slam.cli import main\n"
        "sys.exit(main(['serve', '--demo', '--port', '0']))\n"
    )
    result = subprocess.run(
        [sys.executable, "-c", code], capture_output=True, text=True, check=False, cwd=tmp_path
    )
    assert result.returncode == 2
    assert result.stderr == f"hitl-slam: error: hitl-slam serve {WEB}\n"
    assert result.stdout == ""


def test_require_passes_when_the_extra_is_installed_and_names_unknown_ones() -> None:
    require("web", "x")
    require("plot", "x")
    with pytest.raises(ValueError, match="unknown extra"):
        require("gui", "x")


# -- notebooks -----------------------------------------------------------------------------------


def _png_size(png: bytes) -> tuple[int, int]:
    assert png[:8] == b"\x89PNG\r\n\x1a\n"
    width, height = struct.unpack(">II", png[16:24])
    return width, height


def test_map_shows_itself_as_png_and_html(world: World) -> None:
    m = world.map
    png = m._repr_png_()
    assert png is not None
    assert _png_size(png) == (640, 480)
    page = m._repr_html_()
    found = re.search(r'<img src="data:image/png;base64,([A-Za-z0-9+/=]+)"', page)
    assert found is not None
    assert _png_size(base64.b64decode(found.group(1))) == (640, 480)
    summary = m.summary()
    assert summary in page
    assert re.fullmatch(
        rf"corridor-loop: {m.num_poses} poses, {m.num_points:,} points, extent "
        r"\d+\.\d m x \d+\.\d m",
        summary,
    )
    # The corridor loop is 20 m x 10 m; the faulty second pass pokes out of it.
    width, height = (float(v) for v in re.findall(r"(\d+\.\d) m", summary))
    assert 19.0 < width < 25.0
    assert 9.0 < height < 15.0


def test_the_notebook_picture_of_a_big_map_is_downsampled(
    world: World, monkeypatch: pytest.MonkeyPatch
) -> None:
    m = world.map
    big = hitl_slam.Map.from_poses_and_scans(
        np.repeat(m.poses, 4, axis=0),
        [m.points[m.offsets[i] : m.offsets[i + 1]] for i in range(m.num_poses)] * 4,
        name="big",
    )
    assert big.num_points > 100_000
    drawn: list[int] = []
    plot = importlib.import_module("hitl_slam.plot")
    plot_map = plot.plot_map

    def spy(*args: Any, **kwargs: Any) -> Any:
        figure = plot_map(*args, **kwargs)
        drawn.append(len(figure.axes[0].collections[0].get_offsets()))
        return figure

    monkeypatch.setattr(plot, "plot_map", spy)
    assert big._repr_png_() is not None
    assert drawn == [20_000]


@pytest.mark.usefixtures("no_matplotlib")
def test_without_matplotlib_a_map_shows_its_summary(world: World) -> None:
    m = world.map
    assert m._repr_png_() is None
    page = m._repr_html_()
    assert "<img" not in page
    assert m.summary() in page
    assert "pip install &#x27;.[plot]&#x27;" in page


def test_a_map_without_points_still_shows_itself() -> None:
    m = hitl_slam.Map.from_poses_and_scans(
        np.array([[0.0, 0.0, 0.0], [1.0, 2.0, 0.0]]), [np.zeros((0, 2))] * 2, name="bare"
    )
    assert m.summary() == "bare: 2 poses, 0 points, extent 1.0 m x 2.0 m"
    png = m._repr_png_()
    assert png is not None
    assert _png_size(png) == (640, 480)
    assert "bare: 2 poses" in m._repr_html_()
