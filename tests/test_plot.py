"""Figures: files are written atomically with the asked size and format, the information-matrix
pattern has exactly the blocks of J^T J (checked against a numerical Jacobian of the
docs/ALGORITHM.md §4.3 residuals), bad inputs are InputErrors, and importing the package does not
import matplotlib.
"""

from __future__ import annotations

import math
import struct
import subprocess
import sys
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from matplotlib.figure import Figure
from matplotlib.quiver import Quiver
from numpy.typing import NDArray

from hitl_slam import plot
from hitl_slam.corrections import Correction, Interpretation, Mode
from hitl_slam.errors import InputError
from hitl_slam.map import Map
from hitl_slam.sim.corridor import (
    INNER_BOTTOM,
    OUTER_BOTTOM,
    OUTER_LEFT,
    World,
    corridor_loop,
    drawn_segment,
)

FloatArray = NDArray[np.float64]
IntArray = NDArray[np.int64]


def png_size(path: Path) -> tuple[int, int]:
    """(width, height) from the PNG's IHDR chunk."""
    head = path.read_bytes()[:24]
    assert head[:8] == b"\x89PNG\r\n\x1a\n"
    assert head[12:16] == b"IHDR"
    width, height = struct.unpack(">II", head[16:24])
    return int(width), int(height)


def _png_pixels(path: Path) -> NDArray[np.float64]:
    """The RGB pixels of a PNG in [0, 1], (H, W, 3)."""
    import matplotlib.image

    return np.asarray(matplotlib.image.imread(path), dtype=np.float64)[..., :3]


def _segment(points: FloatArray) -> tuple[tuple[float, float], tuple[float, float]]:
    c = points.mean(axis=0)
    _, vecs = np.linalg.eigh((points - c).T @ (points - c))
    d = vecs[:, 1]
    proj = (points - c) @ d
    a, b = c + proj.min() * d, c + proj.max() * d
    return (float(a[0]), float(a[1])), (float(b[0]), float(b[1]))


def _rows(world: World, wall: int, lo: int, hi: int) -> IntArray:
    m = world.map
    owner = m.pose_of_point()
    idx = np.flatnonzero((world.wall_of_point == wall) & (owner >= lo) & (owner < hi))
    poses = owner[idx]
    keep = np.isin(poses, np.flatnonzero(np.bincount(poses, minlength=m.num_poses) >= 8))
    idx, poses = idx[keep], poses[keep]
    return np.stack([poses, idx - m.offsets[poses]], axis=1)


def _interpretation(world: World, mode: Mode, a: IntArray, b: IntArray) -> Interpretation:
    m = world.map
    pts = m.world_points()
    return Interpretation(
        mode=mode,
        line_a=_segment(pts[m.offsets[a[:, 0]] + a[:, 1]]),
        line_b=_segment(pts[m.offsets[b[:, 0]] + b[:, 1]]),
        s_a=a,
        s_b=b,
        x_a=np.unique(a[:, 0]),
        x_b=np.unique(b[:, 0]),
    )


CASES = {
    Mode.COLOCATION: ((OUTER_BOTTOM, 0, 60), (OUTER_BOTTOM, 265, 325)),
    Mode.COLLINEAR: ((OUTER_BOTTOM, 0, 40), (OUTER_BOTTOM, 280, 325)),
    Mode.PARALLEL: ((OUTER_BOTTOM, 0, 60), (INNER_BOTTOM, 265, 325)),
    Mode.PERPENDICULAR: ((OUTER_BOTTOM, 0, 60), (OUTER_LEFT, 200, 280)),
}


@pytest.fixture(scope="module")
def world() -> World:
    return corridor_loop(seed=1, laps=1.25)


@pytest.fixture(scope="module")
def corrections(world: World) -> list[Interpretation]:
    out = []
    for mode, ((wa, la, ha), (wb, lb, hb)) in CASES.items():
        out.append(_interpretation(world, mode, _rows(world, wa, la, ha), _rows(world, wb, lb, hb)))
    return out


@pytest.fixture(scope="module")
def drawn(world: World) -> Correction:
    rng = np.random.default_rng(0)
    poses = world.map.poses
    a = drawn_segment(world, poses, OUTER_BOTTOM, (0, 60), rng, along=(0.3, 0.7))
    b = drawn_segment(world, poses, OUTER_BOTTOM, (265, 325), rng, along=(0.3, 0.7))
    return Correction.make(a, b, Mode.COLOCATION)


def _only(directory: Path, *names: str) -> None:
    """The directory holds exactly ``names``: no temporary file was left behind."""
    assert sorted(p.name for p in directory.iterdir()) == sorted(names)


# --------------------------------------------------------------------------------------------
# Files


def test_before_after_png_has_size_times_dpi_pixels(
    world: World, corrections: list[Interpretation], drawn: Correction, tmp_path: Path
) -> None:
    path = tmp_path / "before_after.png"
    out = plot.write_before_after(
        world.map, world.map.poses, world.truth, path, interpretations=corrections, drawn=[drawn]
    )
    assert out == path
    assert path.stat().st_size > 10_000
    assert png_size(path) == (12 * 150, 6 * 150)
    _only(tmp_path, "before_after.png")


def test_before_after_small_png_and_svg(world: World, tmp_path: Path) -> None:
    png = plot.write_before_after(
        world.map, world.map.poses, world.truth, tmp_path / "small.PNG", dpi=40, size=(5, 2.5)
    )
    assert png_size(png) == (200, 100)
    svg = plot.write_before_after(
        world.map, world.map.poses, world.truth, tmp_path / "map.svg", max_points=2000
    )
    text = svg.read_text(encoding="utf-8")
    assert text.lstrip().startswith(("<?xml", "<svg"))
    assert "</svg>" in text
    _only(tmp_path, "small.PNG", "map.svg")


def test_rewriting_replaces_the_file(world: World, tmp_path: Path) -> None:
    path = tmp_path / "map.png"
    path.write_bytes(b"old")
    plot.write_before_after(world.map, world.map.poses, world.truth, path, dpi=30, size=(4, 2))
    assert png_size(path) == (120, 60)
    _only(tmp_path, "map.png")


def test_a_failed_render_leaves_the_old_file_and_no_temporary(
    world: World, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    path = tmp_path / "map.png"
    path.write_bytes(b"old")

    def broken(self: Figure, fname: Any, **kwargs: Any) -> None:
        fname.write(b"partial")
        raise RuntimeError("disk full")

    monkeypatch.setattr(Figure, "savefig", broken)
    with pytest.raises(RuntimeError, match="disk full"):
        plot.write_before_after(world.map, world.map.poses, world.truth, path)
    assert path.read_bytes() == b"old"
    _only(tmp_path, "map.png")


def test_information_matrix_figure(
    world: World, corrections: list[Interpretation], tmp_path: Path
) -> None:
    out = plot.write_information_matrix(world.map, corrections, tmp_path / "h.png", dpi=60)
    assert png_size(out) == (9 * 60, 7 * 60)
    both = plot.write_information_matrix(
        world.map, corrections, tmp_path / "h_map.png", dpi=40, poses=world.map.poses
    )
    assert png_size(both) == (14 * 40, 260)
    svg = plot.write_information_matrix(world.map, corrections[:1], tmp_path / "h.svg")
    assert svg.read_text(encoding="utf-8").lstrip().startswith(("<?xml", "<svg"))
    _only(tmp_path, "h.png", "h_map.png", "h.svg")


def test_information_matrix_of_a_large_map_is_binned(tmp_path: Path) -> None:
    m = _chain_map(2600, points_per_pose=1)
    rows = np.array([[k, 0] for k in range(5, 60)] + [[k, 0] for k in range(2500, 2550)])
    h = _hand_interpretation(Mode.COLOCATION, rows[:55], rows[55:])
    image, factor = plot._pattern_image(plot.information_matrix(m, [h]), 1000)
    assert factor == 3
    assert image.shape == (868, 868)
    assert image[2520 // 3, 20 // 3] == 2  # the human block survives the binning
    out = plot.write_information_matrix(m, [h], tmp_path / "big.png", dpi=50)
    assert png_size(out) == (450, 350)


def test_heat_map(world: World, tmp_path: Path) -> None:
    rng = np.random.default_rng(0)
    heat = rng.poisson(0.3, size=(120, 220)).astype(np.int64)
    out = plot.write_heat_map(heat, (-1.0, -1.0), 0.1, tmp_path / "heat.png", dpi=50)
    # A wide grid keeps the figure's width and sheds height: no blank band above and below.
    width, height = png_size(out)
    assert width == 500
    assert height < 300
    over = plot.write_heat_map(
        heat,
        np.array([-1.0, -1.0]),
        0.1,
        tmp_path / "heat_map.svg",
        map=world.map,
        poses=world.truth,
        log_scale=True,
    )
    assert over.read_text(encoding="utf-8").lstrip().startswith(("<?xml", "<svg"))
    zeros = plot.write_heat_map(np.zeros((3, 4)), (0, 0), 1.0, tmp_path / "zeros.png", dpi=20)
    assert png_size(zeros)[1] == 120
    # A tall grid keeps the height and sheds width: the picture is mostly map, not white margin.
    tall = plot.write_heat_map(heat.T, (0, 0), 0.1, tmp_path / "tall.png", dpi=50)
    tall_width, tall_height = png_size(tall)
    assert tall_height == 300
    assert tall_width < 300
    pixels = _png_pixels(tall)
    blank_columns = np.all(pixels > 0.97, axis=(0, 2)).mean()
    assert blank_columns < 0.15, blank_columns
    _only(tmp_path, "heat.png", "heat_map.svg", "zeros.png", "tall.png")


# --------------------------------------------------------------------------------------------
# plot_map


def test_plot_map_draws_constrained_poses_blue(
    world: World, corrections: list[Interpretation], drawn: Correction
) -> None:
    m = world.map
    fig = plot.plot_map(m, m.poses, interpretations=corrections, drawn=[drawn], arrows_every=1)
    assert isinstance(fig, Figure)
    (ax,) = fig.axes
    constrained = np.unique(np.concatenate([np.r_[h.x_a, h.x_b] for h in corrections]))
    arrows = {q.N: q for q in ax.collections if isinstance(q, Quiver)}
    assert set(arrows) == {m.num_poses - len(constrained), len(constrained)}
    blue = arrows[len(constrained)]
    assert np.allclose(
        np.asarray(blue.get_facecolor())[0, :3], [0x1F / 255, 0x4F / 255, 0xD8 / 255]
    )
    assert np.allclose(blue.get_offsets(), m.poses[constrained, :2])
    legend = ax.get_legend()
    assert legend is not None
    labels = [t.get_text() for t in legend.get_texts()]
    assert "poses in human constraints" in labels
    assert "drawn a" in labels
    assert ax.get_aspect() == 1.0
    assert ax.get_xlabel() == "x [m]"


def test_plot_map_subsamples_deterministically(world: World) -> None:
    m = world.map
    shown = []
    for _ in range(2):
        fig = plot.plot_map(m, m.poses, max_points=1000, legend=False)
        offsets = fig.axes[0].collections[0].get_offsets()
        shown.append(np.asarray(offsets))
    assert shown[0].shape == (1000, 2)
    assert np.array_equal(shown[0], shown[1])
    everything = m.world_points()
    assert np.all(np.isin(shown[0][:, 0], everything[:, 0]))


def test_plot_map_into_given_axes(world: World) -> None:
    fig = Figure()
    ax = fig.add_subplot()
    out = plot.plot_map(world.map, world.truth, ax=ax, title="truth", arrows_every=5)
    assert out is fig
    assert ax.get_title() == "truth"
    quivers = [q for q in ax.collections if isinstance(q, Quiver)]
    assert [q.N for q in quivers] == [math.ceil(world.map.num_poses / 5)]


# --------------------------------------------------------------------------------------------
# The information matrix pattern


def _chain_map(n: int, *, points_per_pose: int = 3, seed: int = 0) -> Map:
    rng = np.random.default_rng(seed)
    poses = np.column_stack(
        [np.arange(n) * 0.5, 0.1 * rng.standard_normal(n), 0.1 * rng.standard_normal(n)]
    )
    scans = [rng.uniform(-2.0, 2.0, size=(points_per_pose, 2)) for _ in range(n)]
    return Map.from_poses_and_scans(poses, scans)


def _hand_interpretation(mode: Mode, s_a: Any, s_b: Any) -> Interpretation:
    a = np.asarray(s_a, dtype=np.int64).reshape(-1, 2)
    b = np.asarray(s_b, dtype=np.int64).reshape(-1, 2)
    seg = ((0.0, 0.0), (1.0, 0.0))
    return Interpretation(mode, seg, seg, a, b, np.unique(a[:, 0]), np.unique(b[:, 0]))


N_TINY = 12
TINY = [
    _hand_interpretation(Mode.COLOCATION, [[1, 0], [1, 2], [2, 1]], [[8, 0], [9, 1], [9, 2]]),
    _hand_interpretation(Mode.COLLINEAR, [[3, 0], [3, 1]], [[10, 0], [11, 2]]),
    _hand_interpretation(Mode.PARALLEL, [[0, 0], [1, 1]], [[6, 0], [6, 1]]),
    _hand_interpretation(Mode.PERPENDICULAR, [[4, 2]], [[7, 0], [7, 1]]),
]


def _tiny_map() -> Map:
    m = _chain_map(N_TINY)
    # One loop closure besides the chain, so the relative-pose blocks are not just the band.
    edges = np.vstack([m.edges, [[2, 9]]])
    return Map(
        poses=m.poses,
        points=m.points,
        offsets=m.offsets,
        edges=edges,
        measurements=np.vstack([m.measurements, np.zeros(3)]),
        information=np.concatenate([m.information, np.eye(3)[None]]),
        information_source=np.concatenate([m.information_source, [0]]),
    )


def _residuals(m: Map, corrections: list[Interpretation], x: FloatArray) -> FloatArray:
    """Every residual of docs/ALGORITHM.md §4.3 (unweighted; the pattern is what matters) as a
    function of the stacked variables: 3 per pose, then (phi, rho) per line."""
    n = m.num_poses
    poses = x[: 3 * n].reshape(n, 3)
    lines = x[3 * n :].reshape(-1, 2)
    out: list[Any] = [poses[m.anchor]]  # the gauge prior
    for i, j in m.edges:
        c, s = math.cos(poses[i, 2]), math.sin(poses[i, 2])
        d = poses[j, :2] - poses[i, :2]
        out.append([c * d[0] + s * d[1], -s * d[0] + c * d[1], poses[j, 2] - poses[i, 2]])
    world = m.world_points(poses)
    for k, h in enumerate(corrections):
        (phi_a, rho_a), (phi_b, rho_b) = lines[2 * k], lines[2 * k + 1]
        n_a = np.array([math.cos(phi_a), math.sin(phi_a)])
        n_b = np.array([math.cos(phi_b), math.sin(phi_b)])
        p_a = world[m.offsets[h.s_a[:, 0]] + h.s_a[:, 1]]
        p_b = world[m.offsets[h.s_b[:, 0]] + h.s_b[:, 1]]
        out.append(p_a @ n_a - rho_a)
        out.append(p_b @ n_b - rho_b)
        e_phi = phi_b - phi_a - (math.pi / 2 if h.mode is Mode.PERPENDICULAR else 0.0)
        cm = p_b.mean(axis=0) - p_a.mean(axis=0)
        if h.mode is Mode.COLOCATION:
            out.append(cm)
        elif h.mode is Mode.COLLINEAR:
            out.append([n_a @ cm])
        out.append([e_phi])
    return np.concatenate([np.ravel(r) for r in out])


def _numerical_block_pattern(m: Map, corrections: list[Interpretation]) -> NDArray[np.bool_]:
    rng = np.random.default_rng(1)
    n = m.num_poses
    lines = rng.uniform(-1.0, 1.0, size=(2 * len(corrections), 2))
    x = np.concatenate([m.poses.ravel(), lines.ravel()])
    eps = 1e-6
    columns = []
    for v in range(len(x)):
        step = np.zeros_like(x)
        step[v] = eps
        columns.append(
            (_residuals(m, corrections, x + step) - _residuals(m, corrections, x - step))
            / (2 * eps)
        )
    jac = np.stack(columns, axis=1)
    hessian = np.abs(jac.T @ jac) > 1e-8
    sizes = [3] * n + [2] * (2 * len(corrections))
    starts = np.concatenate([[0], np.cumsum(sizes)])
    blocks = len(sizes)
    out = np.zeros((blocks, blocks), dtype=bool)
    for r in range(blocks):
        for c in range(blocks):
            out[r, c] = hessian[starts[r] : starts[r + 1], starts[c] : starts[c + 1]].any()
    return out


def test_pattern_equals_the_numerical_jacobian_structure() -> None:
    m = _tiny_map()
    pattern = plot.information_matrix(m, TINY).toarray()
    assert pattern.shape == (N_TINY + 8, N_TINY + 8)
    assert np.array_equal(pattern != 0, _numerical_block_pattern(m, TINY))
    assert np.array_equal(pattern, pattern.T)


def test_pattern_blocks_by_mode() -> None:
    m = _tiny_map()
    p = plot.information_matrix(m, TINY).toarray()
    n = N_TINY

    def line(k: int, which: str) -> int:
        return n + 2 * k + (0 if which == "a" else 1)

    # Relative-pose factors: chain, loop closure and every pose's own block, code 1.
    for i in range(n - 1):
        assert p[i, i + 1] == p[i + 1, i] == p[i, i] == 1
    assert p[2, 9] == p[9, 2] == 1
    # Colocation (code 2): all pose pairs of X_a u X_b, both lines coupled, the lines only with
    # their own poses (R_a, R_b; the centroid rows do not involve the lines).
    union = [1, 2, 8, 9]
    for i in union:
        for j in union:
            assert p[i, j] == (1 if abs(i - j) <= 1 or {i, j} == {2, 9} else 2)
    assert p[line(0, "a"), line(0, "b")] == 2
    assert all(p[i, line(0, "a")] == 2 for i in (1, 2))
    assert all(p[i, line(0, "a")] == 0 for i in (8, 9))
    assert all(p[i, line(0, "b")] == 2 for i in (8, 9))
    assert all(p[i, line(0, "b")] == 0 for i in (1, 2))
    # Collinear (code 3): pose pairs of X_a u X_b, and line a with all of them (n_a in R_p).
    assert p[3, 10] == p[3, 11] == p[11, 3] == 3
    assert all(p[i, line(1, "a")] == 3 for i in (3, 10, 11))
    assert p[3, line(1, "b")] == 0
    # Parallel (code 4) and perpendicular (code 5): no pose-pose coupling, only R_a/R_b and the
    # line pair.
    for code, k, a, b in ((4, 2, [0, 1], [6]), (5, 3, [4], [7])):
        assert p[line(k, "a"), line(k, "b")] == code
        assert all(p[i, line(k, "a")] == code for i in a)
        assert all(p[i, line(k, "b")] == code for i in b)
        assert all(p[i, line(k, "b")] == 0 for i in a)
        assert all(p[i, line(k, "a")] == 0 for i in b)
        assert all(p[i, j] == 0 for i in a for j in b)
    # Lines of different corrections are never coupled.
    assert p[line(0, "a"), line(1, "a")] == 0


def test_pattern_on_the_corridor(world: World, corrections: list[Interpretation]) -> None:
    m = world.map
    p = plot.information_matrix(m, corrections).tocsr()
    colocation, _, parallel, _ = corrections
    block = p[np.ix_(colocation.x_a, colocation.x_b)].toarray()
    assert np.all(block == 2)  # every X_a x X_b pair
    # The parallel correction couples no poses of its own (its sets overlap the colocation's,
    # whose code those blocks keep) ...
    assert not np.any(p.toarray()[: m.num_poses, : m.num_poses] == 4)
    alone = plot.information_matrix(m, [parallel]).tocsr()
    assert alone[np.ix_(parallel.x_a, parallel.x_b)].nnz == 0
    # ... only its lines, each with the poses that observed it.
    n = m.num_poses
    assert np.all(p[np.ix_(parallel.x_a, np.array([n + 4]))].toarray() == 4)
    assert np.all(p[np.ix_(parallel.x_b, np.array([n + 5]))].toarray() == 4)
    assert p[n + 4, n + 5] == 4
    without = plot.information_matrix(m, [])
    assert without.shape == (n, n)
    assert without.nnz == n + 2 * (n - 1)


# --------------------------------------------------------------------------------------------
# Bad input and import hygiene


def _bad_calls(world: World, tmp: Path) -> list[tuple[str, Callable[[], object]]]:
    m = world.map
    h = _interpretation(world, Mode.PARALLEL, *(_rows(world, OUTER_BOTTOM, 0, 60),) * 2)
    far = Interpretation(
        h.mode, h.line_a, h.line_b, np.array([[m.num_poses, 0]]), h.s_b, h.x_a, h.x_b
    )
    past_scan = Interpretation(
        h.mode, h.line_a, h.line_b, np.array([[0, 10_000]]), h.s_b, h.x_a, h.x_b
    )
    png = tmp / "out.png"
    nan_poses = m.poses.copy()
    nan_poses[3, 1] = np.nan
    before_after = plot.write_before_after
    return [
        ("short poses", lambda: plot.plot_map(m, m.poses[:-1])),
        ("nan poses", lambda: plot.plot_map(m, nan_poses)),
        ("not a map", lambda: plot.plot_map(m.pose_graph(), m.poses)),  # type: ignore[arg-type]
        ("one interp", lambda: plot.plot_map(m, m.poses, interpretations=h)),  # type: ignore[arg-type]
        ("pose out of range", lambda: plot.plot_map(m, m.poses, interpretations=[far])),
        ("point out of range", lambda: plot.information_matrix(m, [past_scan])),
        ("not interp", lambda: plot.information_matrix(m, ["h"])),  # type: ignore[list-item]
        ("zero points", lambda: plot.plot_map(m, m.poses, max_points=0)),
        ("zero arrows", lambda: plot.plot_map(m, m.poses, arrows_every=0)),
        ("bad ax", lambda: plot.plot_map(m, m.poses, ax="ax")),  # type: ignore[arg-type]
        ("jpg", lambda: before_after(m, m.poses, m.poses, tmp / "out.jpg")),
        ("no extension", lambda: before_after(m, m.poses, m.poses, tmp / "out")),
        ("no directory", lambda: before_after(m, m.poses, m.poses, tmp / "nope" / "out.png")),
        ("after shape", lambda: before_after(m, m.poses, m.poses[:, :2], png)),
        ("titles", lambda: before_after(m, m.poses, m.poses, png, titles=("a",))),  # type: ignore[arg-type]
        ("dpi", lambda: before_after(m, m.poses, m.poses, png, dpi=0)),
        ("size", lambda: before_after(m, m.poses, m.poses, png, size=(0.0, 3.0))),
        ("drawn", lambda: before_after(m, m.poses, m.poses, png, drawn=[h])),  # type: ignore[list-item]
        ("pdf", lambda: plot.write_information_matrix(m, [h], tmp / "h.pdf")),
        ("heat 1-D", lambda: plot.write_heat_map(np.ones(5), (0, 0), 0.1, png)),
        ("heat empty", lambda: plot.write_heat_map(np.ones((0, 5)), (0, 0), 0.1, png)),
        ("heat negative", lambda: plot.write_heat_map(-np.ones((2, 2)), (0, 0), 0.1, png)),
        ("heat nan", lambda: plot.write_heat_map(np.full((2, 2), np.nan), (0, 0), 0.1, png)),
        ("origin", lambda: plot.write_heat_map(np.ones((2, 2)), (0, 0, 0), 0.1, png)),
        ("resolution", lambda: plot.write_heat_map(np.ones((2, 2)), (0, 0), -0.1, png)),
        (
            "poses w/o map",
            lambda: plot.write_heat_map(np.ones((2, 2)), (0, 0), 1, png, poses=m.poses),
        ),
        ("heat svgz", lambda: plot.write_heat_map(np.ones((2, 2)), (0, 0), 1, tmp / "h.svgz")),
    ]


def test_bad_inputs_raise_input_error_and_write_nothing(world: World, tmp_path: Path) -> None:
    for name, call in _bad_calls(world, tmp_path):
        with pytest.raises(InputError):
            call()
        assert list(tmp_path.iterdir()) == [], name


def test_importing_the_package_does_not_import_matplotlib() -> None:
    code = """
import importlib, pkgutil, sys
import hitl_slam
assert "matplotlib" not in sys.modules, "import hitl_slam pulled in matplotlib"
for info in pkgutil.walk_packages(hitl_slam.__path__, "hitl_slam."):
    if info.name == "hitl_slam.plot":
        continue
    importlib.import_module(info.name)  # every module imports: a broken one fails here
    assert "matplotlib" not in sys.modules, f"{info.name} imports matplotlib"
import hitl_slam.plot
assert "matplotlib" in sys.modules
assert "matplotlib.pyplot" not in sys.modules, "hitl_slam.plot must not use pyplot"
"""
    result = subprocess.run(
        [sys.executable, "-c", code], capture_output=True, text=True, check=False
    )
    assert result.returncode == 0, result.stderr
