"""Figures in the paper's visual language: maps with observations and poses (Figs. 1, 6, 8), the
information matrix with the human corrections' off-diagonal blocks (Fig. 5) and inconsistency heat
maps. The only module that imports matplotlib (the ``[plot]`` extra): import it lazily, never from
the package root; without matplotlib importing it raises :class:`~hitl_slam.errors.MissingExtra`.
"""

from __future__ import annotations

import math
import os
from collections.abc import Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

# scipy ships no type information; "unused-ignore" keeps this clean once scipy-stubs is added.
from scipy.sparse import csr_array  # type: ignore[import-untyped, unused-ignore]

from hitl_slam.corrections import Correction, Interpretation, Mode
from hitl_slam.errors import InputError
from hitl_slam.extras import missing_extra
from hitl_slam.geometry import principal_axes
from hitl_slam.io.atomic import atomic_binary_writer
from hitl_slam.map import Map

if TYPE_CHECKING:
    from hitl_slam.metrics import Inconsistency

try:
    from matplotlib.axes import Axes
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.colors import LogNorm, Normalize, to_rgb
    from matplotlib.figure import Figure
    from matplotlib.lines import Line2D
    from matplotlib.patches import Patch
except ImportError as exc:  # one line naming the extra, not a traceback from matplotlib's import
    raise missing_extra("plot", "hitl_slam.plot") from exc

__all__ = [
    "MODE_COLOURS",
    "information_matrix",
    "plot_map",
    "write_before_after",
    "write_heat_map",
    "write_inconsistency_heat_map",
    "write_information_matrix",
    "write_map",
]

FloatArray = NDArray[np.float64]
IntArray = NDArray[np.int64]
PathLike = str | os.PathLike[str]

# The paper's palette: observations orange, poses black, poses in a human constraint blue,
# feature a red and feature b blue (Fig. 2); Fig. 5 colours corrections by mode.
OBSERVATION_COLOUR = "#f28e1c"
POSE_COLOUR = "#303030"
CONSTRAINED_POSE_COLOUR = "#1f4fd8"
A_COLOUR = "#d62728"
B_COLOUR = "#1f4fd8"
MODE_COLOURS: dict[Mode, str] = {
    Mode.COLOCATION: "#1f4fd8",  # blue, as in Fig. 5
    Mode.COLLINEAR: "#d61fd6",  # magenta, as in Fig. 5
    Mode.PARALLEL: "#2ca02c",
    Mode.PERPENDICULAR: "#00a0a0",  # teal: orange is the observations
}
_FORMATS = {".png": "png", ".svg": "svg"}
_MAX_MATRIX_PIXELS = 1000
_SUBSAMPLE_SEED = 0  # fixed: the same map always shows the same points
_DEFAULT_MAX_ARROWS = 600


# --------------------------------------------------------------------------------------------
# Input checks: every public function validates before drawing anything.


def _check_map(map: Any) -> Map:
    if not isinstance(map, Map):
        raise InputError(f"map must be a hitl_slam.map.Map, got {type(map).__name__}")
    return map


def _check_poses(map: Map, poses: Any, name: str = "poses") -> FloatArray:
    try:
        arr = np.asarray(poses, dtype=np.float64)
    except (TypeError, ValueError):
        raise InputError(f"{name} must be a numeric (N, 3) array") from None
    if arr.shape != (map.num_poses, 3):
        raise InputError(
            f"{name} must have shape ({map.num_poses}, 3), one (x, y, theta) row per pose of the "
            f"map, got {arr.shape}"
        )
    if not np.all(np.isfinite(arr)):
        raise InputError(f"{name} has non-finite values")
    return np.ascontiguousarray(arr)


def _check_rows(map: Map, rows: Any, what: str) -> IntArray:
    arr = np.asarray(rows)
    if arr.ndim != 2 or arr.shape[1] != 2 or arr.shape[0] == 0:
        raise InputError(f"{what} must be a non-empty (K, 2) array of (pose, point) rows")
    if not np.issubdtype(arr.dtype, np.integer):
        raise InputError(f"{what} must hold integer indices, got {arr.dtype}")
    arr = arr.astype(np.int64)
    pose, point = arr[:, 0], arr[:, 1]
    if np.any(pose < 0) or np.any(pose >= map.num_poses):
        raise InputError(f"{what} names a pose outside 0..{map.num_poses - 1}")
    counts = np.diff(map.offsets)
    if np.any(point < 0) or np.any(point >= counts[pose]):
        raise InputError(f"{what} names a point index past the end of its pose's scan")
    return arr


def _check_pose_set(map: Map, x: Any, what: str) -> IntArray:
    arr = np.asarray(x)
    if arr.ndim != 1 or not np.issubdtype(arr.dtype, np.integer):
        raise InputError(f"{what} must be a 1-D array of pose indices")
    arr = arr.astype(np.int64)
    if np.any(arr < 0) or np.any(arr >= map.num_poses):
        raise InputError(f"{what} names a pose outside 0..{map.num_poses - 1}")
    return arr


def _check_interpretations(map: Map, interpretations: Any) -> tuple[Interpretation, ...]:
    if isinstance(interpretations, Interpretation):
        raise InputError("interpretations must be a sequence; wrap a single one as (h,)")
    try:
        items = tuple(interpretations)
    except TypeError:
        raise InputError("interpretations must be a sequence of Interpretation") from None
    for k, h in enumerate(items):
        if not isinstance(h, Interpretation):
            raise InputError(f"interpretations[{k}] is a {type(h).__name__}, not an Interpretation")
        _check_rows(map, h.s_a, f"interpretations[{k}].s_a")
        _check_rows(map, h.s_b, f"interpretations[{k}].s_b")
        _check_pose_set(map, h.x_a, f"interpretations[{k}].x_a")
        _check_pose_set(map, h.x_b, f"interpretations[{k}].x_b")
    return items


def _check_drawn(drawn: Any) -> tuple[Correction, ...]:
    if isinstance(drawn, Correction):
        raise InputError("drawn must be a sequence; wrap a single correction as (d,)")
    try:
        items = tuple(drawn)
    except TypeError:
        raise InputError("drawn must be a sequence of Correction") from None
    for k, d in enumerate(items):
        if not isinstance(d, Correction):
            raise InputError(f"drawn[{k}] is a {type(d).__name__}, not a Correction")
    return items


def _check_positive(value: Any, name: str) -> float:
    try:
        v = float(value)
    except (TypeError, ValueError):
        raise InputError(f"{name} must be a positive number, got {value!r}") from None
    if not (math.isfinite(v) and v > 0):
        raise InputError(f"{name} must be a positive number, got {value!r}")
    return v


def _check_count(value: Any, name: str) -> int:
    if isinstance(value, bool) or not isinstance(value, int | np.integer) or value < 1:
        raise InputError(f"{name} must be a positive integer, got {value!r}")
    return int(value)


def _check_size(size: Any) -> tuple[float, float]:
    try:
        w, h = size
    except (TypeError, ValueError):
        raise InputError(f"size must be (width, height) in inches, got {size!r}") from None
    return _check_positive(w, "size[0]"), _check_positive(h, "size[1]")


def _check_path(path: Any) -> tuple[Path, str]:
    try:
        target = Path(os.fspath(path))
    except TypeError:
        raise InputError(f"path must be a file name, got {type(path).__name__}") from None
    fmt = _FORMATS.get(target.suffix.lower())
    if fmt is None:
        raise InputError(f"cannot write {str(target)!r}: use a .png or .svg file name")
    parent = target.parent
    if not parent.is_dir():
        raise InputError(f"cannot write {str(target)!r}: directory {str(parent)!r} does not exist")
    return target, fmt


# --------------------------------------------------------------------------------------------
# Output


def _new_figure(size: tuple[float, float], dpi: float) -> Figure:
    # A Figure with its own Agg canvas: no pyplot, no global figure registry, no display.
    fig = Figure(figsize=size, dpi=dpi, layout="constrained")
    FigureCanvasAgg(fig)
    return fig


def _fitted_size(
    size: tuple[float, float],
    extent: tuple[float, float, float, float],
    margins: tuple[float, float],
) -> tuple[float, float]:
    """The figure size [in] within ``size`` whose axes, drawn at equal aspect, fill their box
    for data spanning ``extent`` (x0, x1, y0, y1): the longer side keeps its length and the other
    shrinks, so the picture has no blank band beside the map. ``margins``: the width and height
    [in] of what is not the axes (colour bar, labels, title)."""
    width, height = size
    span_x, span_y = extent[1] - extent[0], extent[3] - extent[2]
    box_w, box_h = max(width - margins[0], 1.0), max(height - margins[1], 1.0)
    aspect = span_y / span_x if span_x > 0 and span_y > 0 else box_h / box_w
    if aspect > box_h / box_w:
        return (box_h / aspect + margins[0], height)
    return (width, box_w * aspect + margins[1])


def _save(fig: Figure, target: Path, fmt: str, dpi: float) -> Path:
    """Render ``fig`` to a temporary file next to ``target``, then rename it over ``target``
    (:func:`hitl_slam.io.atomic.atomic_binary_writer`: an unwritable target is an
    :class:`~hitl_slam.io.atomic.OutputError`, and no temporary file is left behind)."""
    # No date in SVG output, so the same figure gives the same file.
    metadata: dict[str, Any] = {"Date": None} if fmt == "svg" else {}
    with atomic_binary_writer(target) as f:
        fig.savefig(f, format=fmt, dpi=dpi, metadata=metadata)
    return target


# --------------------------------------------------------------------------------------------
# Maps


def _subsample(count: int, limit: int) -> IntArray | None:
    """Sorted indices of at most ``limit`` of ``count`` items, the same on every call (random,
    not strided: a stride aliases with the beams of a scan and shows stripes)."""
    if count <= limit:
        return None
    rng = np.random.default_rng(_SUBSAMPLE_SEED)
    return np.sort(rng.choice(count, size=limit, replace=False)).astype(np.int64)


def _observed(map: Map, world: FloatArray, rows: IntArray) -> FloatArray:
    points: FloatArray = world[map.point_rows(rows)]
    return points


def _fitted_segment(points: FloatArray) -> FloatArray:
    """(2, 2) endpoints of the total-least-squares line of ``points`` over their extent."""
    centre, _, direction = principal_axes(points)
    proj = (points - centre) @ direction
    ends: FloatArray = np.stack([centre + proj.min() * direction, centre + proj.max() * direction])
    return ends


def _arrow_length(poses: FloatArray) -> float:
    """Twice the median step between poses, kept between 0.8% and 2.5% of the map's span."""
    xy = poses[:, :2]
    span = float(np.max(np.ptp(xy, axis=0))) if len(xy) > 1 else 1.0
    span = span if span > 0 else 1.0
    steps = np.hypot(*np.diff(xy, axis=0).T) if len(xy) > 1 else np.zeros(0)
    step = float(np.median(steps)) if steps.size else 0.0
    return float(np.clip(2.0 * step, 0.008 * span, 0.025 * span))


def _arrows(ax: Axes, poses: FloatArray, length: float, colour: str, zorder: float) -> None:
    if len(poses) == 0:
        return
    ax.quiver(
        poses[:, 0],
        poses[:, 1],
        length * np.cos(poses[:, 2]),
        length * np.sin(poses[:, 2]),
        color=colour,
        angles="xy",
        scale_units="xy",
        scale=1.0,
        units="xy",
        width=0.14 * length,
        headwidth=3.0,
        headlength=3.5,
        headaxislength=3.0,
        pivot="tail",
        zorder=zorder,
    )


def _draw_map(
    ax: Axes,
    map: Map,
    poses: FloatArray,
    interpretations: Sequence[Interpretation],
    drawn: Sequence[Correction],
    *,
    max_points: int,
    arrows_every: int | None,
    colour_by_mode: bool = False,
) -> list[Any]:
    """Draw the map into ``ax``; returns the legend handles."""
    handles: list[Any] = []
    world = map.world_points(poses)
    keep = _subsample(len(world), max_points)
    shown = world if keep is None else world[keep]
    if len(shown):
        ax.scatter(
            shown[:, 0],
            shown[:, 1],
            s=0.8,
            c=OBSERVATION_COLOUR,
            marker=".",
            linewidths=0,
            rasterized=True,
            zorder=1,
        )
        label = "observations" if keep is None else f"observations ({len(shown):,} shown)"
        handles.append(
            Line2D([], [], ls="none", marker="o", ms=4, color=OBSERVATION_COLOUR, label=label)
        )

    every = arrows_every or max(1, math.ceil(map.num_poses / _DEFAULT_MAX_ARROWS))
    length = _arrow_length(poses)
    constrained = np.zeros(map.num_poses, dtype=bool)
    for h in interpretations:
        constrained[h.x_a] = True
        constrained[h.x_b] = True
    plain = np.zeros(map.num_poses, dtype=bool)
    plain[::every] = True
    plain &= ~constrained
    _arrows(ax, poses[plain], length, POSE_COLOUR, 3)
    pose_label = "poses" if every == 1 else f"poses (every {every})"
    handles.append(Line2D([], [], ls="none", marker=">", ms=5, color=POSE_COLOUR, label=pose_label))
    if np.any(constrained):
        _arrows(ax, poses[constrained], length, CONSTRAINED_POSE_COLOUR, 4)
        handles.append(
            Line2D(
                [],
                [],
                ls="none",
                marker=">",
                ms=5,
                color=CONSTRAINED_POSE_COLOUR,
                label="poses in human constraints",
            )
        )

    for k, h in enumerate(interpretations):
        colours = (MODE_COLOURS[h.mode],) * 2 if colour_by_mode else (A_COLOUR, B_COLOUR)
        for rows, colour, tag in ((h.s_a, colours[0], "a"), (h.s_b, colours[1], "b")):
            pts = _observed(map, world, np.asarray(rows, dtype=np.int64))
            ax.scatter(
                pts[:, 0],
                pts[:, 1],
                s=1.5,
                c=colour,
                marker=".",
                linewidths=0,
                rasterized=True,
                zorder=2,
            )
            seg = _fitted_segment(pts)
            ax.plot(seg[:, 0], seg[:, 1], ls="--", lw=1.6, color=colour, zorder=6)
            # a's label above the line's middle, b's below: colocated lines keep both legible.
            ax.annotate(
                f"{k + 1}{tag}",
                seg.mean(axis=0),
                xytext=(3, 3) if tag == "a" else (3, -10),
                textcoords="offset points",
                fontsize="x-small",
                color=colour,
                zorder=7,
            )
    if interpretations:
        if colour_by_mode:
            for mode in dict.fromkeys(h.mode for h in interpretations):
                handles.append(
                    Line2D([], [], ls="--", lw=1.6, color=MODE_COLOURS[mode], label=mode.value)
                )
        else:
            handles.append(Line2D([], [], ls="--", lw=1.6, color=A_COLOUR, label="$P_a$, $S_a$"))
            handles.append(Line2D([], [], ls="--", lw=1.6, color=B_COLOUR, label="$P_b$, $S_b$"))

    for d in drawn:
        for stroke, colour in ((d.a, A_COLOUR), (d.b, B_COLOUR)):
            xy = np.asarray(stroke, dtype=np.float64)
            ax.plot(xy[:, 0], xy[:, 1], ls="-", lw=3.0, alpha=0.55, color=colour, zorder=5)
    if drawn:
        handles.append(Line2D([], [], lw=3.0, alpha=0.55, color=A_COLOUR, label="drawn a"))
        handles.append(Line2D([], [], lw=3.0, alpha=0.55, color=B_COLOUR, label="drawn b"))

    ax.set_aspect("equal", adjustable="datalim")
    ax.set_xlabel("x [m]")
    ax.set_ylabel("y [m]")
    ax.grid(True, lw=0.3, alpha=0.4)
    return handles


def plot_map(
    map: Map,
    poses: ArrayLike,
    *,
    interpretations: Sequence[Interpretation] = (),
    drawn: Sequence[Correction] = (),
    title: str | None = None,
    ax: Axes | None = None,
    max_points: int = 200_000,
    arrows_every: int | None = None,
    size: tuple[float, float] = (8.0, 6.0),
    dpi: float = 150.0,
    legend: bool = True,
) -> Figure:
    """Draw ``map`` under ``poses`` as in the paper's Figs. 6 and 8: observations as small
    orange dots, poses as arrows (black; blue when in a human constraint, X_a or X_b), each
    correction's observations S_a/S_b in red/blue with the line fitted to them under ``poses``
    dashed (P_a/P_b, labelled 1a, 1b, ...), and the segments a person drew (``drawn``) as wide
    translucent red (a) and blue (b) strokes. Metres on equal axes.

    More than ``max_points`` observations are subsampled (the same subset every time); every
    ``arrows_every``-th pose gets an arrow (default: at most ~600 arrows; constrained poses always
    do). Draws into ``ax`` when given, else into a new Figure of ``size`` inches at ``dpi``;
    returns the Figure. ``title`` defaults to the map's name and size.
    """
    m = _check_map(map)
    p = _check_poses(m, poses)
    hs = _check_interpretations(m, interpretations)
    ds = _check_drawn(drawn)
    limit = _check_count(max_points, "max_points")
    every = None if arrows_every is None else _check_count(arrows_every, "arrows_every")
    if ax is None:
        fig = _new_figure(_check_size(size), _check_positive(dpi, "dpi"))
        ax = fig.add_subplot()
    elif not isinstance(ax, Axes):
        raise InputError(f"ax must be a matplotlib Axes, got {type(ax).__name__}")
    else:
        root = ax.get_figure(root=True)
        if not isinstance(root, Figure):
            raise InputError("ax must belong to a matplotlib Figure")
        fig = root
    handles = _draw_map(ax, m, p, hs, ds, max_points=limit, arrows_every=every)
    ax.set_title(title if title is not None else f"{m.name}: {m.num_poses} poses")
    if legend:
        ax.legend(handles=handles, loc="upper right", fontsize="x-small", framealpha=0.85)
    return fig


def write_map(
    map: Map,
    poses: ArrayLike,
    path: PathLike,
    *,
    title: str | None = None,
    size: tuple[float, float] = (8.0, 6.0),
    dpi: float = 150.0,
    max_points: int = 200_000,
) -> Path:
    """Write the picture of ``map`` under ``poses`` (:func:`plot_map`) as a ``.png`` or ``.svg``
    file, atomically. Returns the path written."""
    target, fmt = _check_path(path)
    dpi_v = _check_positive(dpi, "dpi")
    fig = plot_map(map, poses, title=title, size=size, dpi=dpi_v, max_points=max_points)
    return _save(fig, target, fmt, dpi_v)


def write_before_after(
    map: Map,
    before: ArrayLike,
    after: ArrayLike,
    path: PathLike,
    *,
    interpretations: Sequence[Interpretation] = (),
    drawn: Sequence[Correction] = (),
    titles: tuple[str, str] = ("before", "after"),
    dpi: float = 150.0,
    size: tuple[float, float] = (12.0, 6.0),
    max_points: int = 200_000,
    arrows_every: int | None = None,
) -> Path:
    """The paper's Fig. 1 / Fig. 6 pair: ``map`` under ``before`` (left) and ``after`` (right)
    poses, side by side, written to ``path`` (.png or .svg; ``size`` inches at ``dpi``, so a PNG
    is exactly size * dpi pixels). The drawn segments appear on the left panel only (they were
    drawn on that map); the interpretations on both. Returns the path written."""
    m = _check_map(map)
    p0 = _check_poses(m, before, "before")
    p1 = _check_poses(m, after, "after")
    hs = _check_interpretations(m, interpretations)
    ds = _check_drawn(drawn)
    target, fmt = _check_path(path)
    dpi_v = _check_positive(dpi, "dpi")
    fig_size = _check_size(size)
    limit = _check_count(max_points, "max_points")
    every = None if arrows_every is None else _check_count(arrows_every, "arrows_every")
    if not (len(titles) == 2 and all(isinstance(t, str) for t in titles)):
        raise InputError(f"titles must be two strings, got {titles!r}")

    fig = _new_figure(fig_size, dpi_v)
    axes = fig.subplots(1, 2)
    handles: dict[str, Any] = {}
    for ax, poses, shown_drawn, title in (
        (axes[0], p0, ds, titles[0]),
        (axes[1], p1, (), titles[1]),
    ):
        for handle in _draw_map(
            ax, m, poses, hs, shown_drawn, max_points=limit, arrows_every=every
        ):
            handles.setdefault(handle.get_label(), handle)
        ax.set_title(title)
    fig.legend(
        handles=list(handles.values()),
        loc="outside lower center",
        ncols=min(len(handles), 7),
        fontsize="small",
        frameon=False,
    )
    return _save(fig, target, fmt, dpi_v)


# --------------------------------------------------------------------------------------------
# The information matrix (Fig. 5)


def _pairs(rows: IntArray, cols: IntArray) -> tuple[IntArray, IntArray]:
    r, c = np.meshgrid(rows, cols, indexing="ij")
    return r.ravel(), c.ravel()


def information_matrix(map: Map, interpretations: Sequence[Interpretation]) -> Any:
    """The block sparsity of the normal equations ``J^T J`` of the joint problem
    (docs/ALGORITHM.md §4.3), one entry per variable block, in natural order: poses ``0..N-1``,
    then lines ``N + 2k`` (a) and ``N + 2k + 1`` (b) of correction k. Returns a symmetric
    ``scipy.sparse.csr_array`` (int32) whose entries say where a block comes from: 1 relative-pose
    factors (and the anchor's prior), ``2 + k`` the human factors of correction k (a block already
    present keeps the first source).

    The blocks are those of the Jacobian's actual dependencies: R_a couples each pose of X_a
    with line a (R_b likewise); R_p couples the two lines, and for colocation and collinear all
    pose pairs of X_a and X_b (through the centroids), collinear also line a with those poses (its
    normal n_a). Parallel and perpendicular R_p involve the two lines only. (The solver reserves
    each factor's variables as a clique, a superset of this.) X_a, X_b are the poses of the
    rows of S_a, S_b, as the solver builds them."""
    m = _check_map(map)
    hs = _check_interpretations(m, interpretations)
    n_poses = m.num_poses
    n = n_poses + 2 * len(hs)
    rows: list[IntArray] = []
    cols: list[IntArray] = []
    codes: list[IntArray] = []

    def add(r: IntArray, c: IntArray, code: int) -> None:
        # Both triangles, so the pattern is symmetric by construction.
        rows.extend((r, c))
        cols.extend((c, r))
        full = np.full(len(r), code, dtype=np.int64)
        codes.extend((full, full))

    e = m.edges
    touched = np.zeros(n_poses, dtype=bool)
    touched[e.ravel()] = True
    touched[m.anchor] = True
    diag = np.flatnonzero(touched).astype(np.int64)
    add(diag, diag, 1)
    add(e[:, 0].astype(np.int64), e[:, 1].astype(np.int64), 1)

    for k, h in enumerate(hs):
        code = 2 + k
        line_a, line_b = n_poses + 2 * k, n_poses + 2 * k + 1
        x_a = np.unique(np.asarray(h.s_a, dtype=np.int64)[:, 0])
        x_b = np.unique(np.asarray(h.s_b, dtype=np.int64)[:, 0])
        lines = np.array([line_a, line_b], dtype=np.int64)
        add(*_pairs(lines, lines), code)  # both line diagonals and R_p's line-line block
        for x, line in ((x_a, line_a), (x_b, line_b)):  # R_a, R_b
            add(x, x, code)
            add(x, np.full(len(x), line, dtype=np.int64), code)
        if h.mode in (Mode.COLOCATION, Mode.COLLINEAR):
            union = np.union1d(x_a, x_b)
            add(*_pairs(union, union), code)
            if h.mode is Mode.COLLINEAR:
                add(union, np.full(len(union), line_a, dtype=np.int64), code)

    r = np.concatenate(rows)
    c = np.concatenate(cols)
    v = np.concatenate(codes)
    linear = r * n + c
    order = np.lexsort((v, linear))  # per block, the smallest code (first source) first
    linear, v = linear[order], v[order]
    unique, first = np.unique(linear, return_index=True)
    return csr_array(
        (v[first].astype(np.int32), (unique // n, unique % n)), shape=(n, n), dtype=np.int32
    )


def _pattern_image(pattern: Any, pixels: int) -> tuple[IntArray, int]:
    """A (m, m) code image of at most ``pixels`` per side; a binned cell shows its largest code,
    so a human block is never hidden behind the relative-pose band."""
    n = int(pattern.shape[0])
    factor = max(1, math.ceil(n / pixels))
    size = math.ceil(n / factor)
    coo = pattern.tocoo()
    image = np.zeros((size, size), dtype=np.int64)
    np.maximum.at(
        image,
        (np.asarray(coo.row) // factor, np.asarray(coo.col) // factor),
        np.asarray(coo.data, dtype=np.int64),
    )
    return image, factor


def write_information_matrix(
    map: Map,
    interpretations: Sequence[Interpretation],
    path: PathLike,
    *,
    dpi: float = 150.0,
    poses: ArrayLike | None = None,
    size: tuple[float, float] | None = None,
) -> Path:
    """The paper's Fig. 5: the block pattern of :func:`information_matrix`, relative-pose blocks
    black on white, the blocks each correction adds in its mode's colour (colocation blue,
    collinear magenta, parallel green, perpendicular teal). Drawn as an image of at most
    ~1000 x 1000 pixels (one per block when it fits; binned for large maps). With ``poses``,
    the map with its corrections is drawn on the left, as Fig. 5a. Returns the path written."""
    m = _check_map(map)
    hs = _check_interpretations(m, interpretations)
    target, fmt = _check_path(path)
    dpi_v = _check_positive(dpi, "dpi")
    p = None if poses is None else _check_poses(m, poses)
    fig_size = _check_size(
        size if size is not None else ((14.0, 6.5) if p is not None else (9.0, 7.0))
    )
    pattern = information_matrix(m, hs)

    fig = _new_figure(fig_size, dpi_v)
    if p is not None:
        ax_map, ax = fig.subplots(1, 2, width_ratios=(1.3, 1.0))
        map_handles = _draw_map(
            ax_map, m, p, hs, (), max_points=200_000, arrows_every=None, colour_by_mode=True
        )
        ax_map.legend(handles=map_handles, loc="upper right", fontsize="x-small", framealpha=0.85)
        ax_map.set_title(f"(a) {m.name} with {len(hs)} corrections")
    else:
        ax = fig.add_subplot()
    # Never more image pixels than the axes has, so nearest-neighbour display drops no block.
    bbox = ax.get_position()
    axes_px = int(min(bbox.width * fig_size[0], bbox.height * fig_size[1]) * dpi_v)
    image, factor = _pattern_image(pattern, max(50, min(_MAX_MATRIX_PIXELS, axes_px)))

    palette = np.ones((len(hs) + 2, 3))  # code 0: white
    palette[1] = 0.0  # relative-pose blocks: black
    for k, h in enumerate(hs):
        palette[2 + k] = to_rgb(MODE_COLOURS[h.mode])
    n = pattern.shape[0]
    extent = (-0.5, image.shape[1] * factor - 0.5, image.shape[0] * factor - 0.5, -0.5)
    ax.imshow(palette[image], interpolation="nearest", extent=extent, aspect="equal")
    ax.set_xlim(-0.5, n - 0.5)
    ax.set_ylim(n - 0.5, -0.5)
    if hs:
        for at in (m.num_poses - 0.5,):
            ax.axhline(at, color="0.6", lw=0.6, ls=":")
            ax.axvline(at, color="0.6", lw=0.6, ls=":")
    ax.set_xlabel(f"variable block (poses 0..{m.num_poses - 1}, then 2 lines per correction)")
    ax.set_ylabel("variable block")
    binned = "" if factor == 1 else f", {factor} x {factor} blocks per pixel"
    prefix = "(b) " if p is not None else ""
    ax.set_title(f"{prefix}$J^T J$ block pattern: {pattern.nnz:,} of {n}$^2$ blocks{binned}")
    handles: list[Any] = [Patch(color="black", label="relative-pose factors")]
    for mode in dict.fromkeys(h.mode for h in hs):
        handles.append(Patch(color=MODE_COLOURS[mode], label=f"human: {mode.value}"))
    # Outside the matrix: its right-hand columns are the lines, the most telling part.
    ax.legend(handles=handles, loc="upper left", bbox_to_anchor=(1.02, 1.0), fontsize="small")
    return _save(fig, target, fmt, dpi_v)


# --------------------------------------------------------------------------------------------
# Inconsistency heat map (docs/ALGORITHM.md §6.1)


def write_heat_map(
    heat: ArrayLike,
    origin: ArrayLike,
    resolution: float,
    path: PathLike,
    *,
    map: Map | None = None,
    poses: ArrayLike | None = None,
    dpi: float = 150.0,
    size: tuple[float, float] = (10.0, 6.0),
    log_scale: bool = False,
    title: str | None = None,
    max_points: int = 200_000,
) -> Path:
    """The inconsistency per cell, ``heat`` (H, W) counts of inconsistent scan pairs (cell
    ``(iy, ix)`` covers ``origin + res * [ix, ix + 1) x [iy, iy + 1)``, row 0 at the bottom), in
    the world frame, empty cells white, a colour bar in counts (``log_scale`` for a log one) and
    the total ``I = res^2 sum(heat)`` in the title. With ``map`` its observations (under
    ``poses``, default the map's) are drawn faintly on top. Returns the path written."""
    try:
        h = np.asarray(heat, dtype=np.float64)
    except (TypeError, ValueError):
        raise InputError("heat must be a numeric (H, W) array") from None
    if h.ndim != 2 or h.shape[0] == 0 or h.shape[1] == 0:
        raise InputError(f"heat must be a non-empty (H, W) array, got shape {h.shape}")
    if not np.all(np.isfinite(h)) or np.any(h < 0):
        raise InputError("heat must hold finite, non-negative counts")
    try:
        o = np.asarray(origin, dtype=np.float64)
    except (TypeError, ValueError):
        raise InputError(
            "origin must be the world (x, y) of the grid's lower-left corner"
        ) from None
    if o.shape != (2,) or not np.all(np.isfinite(o)):
        raise InputError(f"origin must be two finite numbers (x, y), got {origin!r}")
    res = _check_positive(resolution, "resolution")
    target, fmt = _check_path(path)
    dpi_v = _check_positive(dpi, "dpi")
    fig_size = _check_size(size)
    limit = _check_count(max_points, "max_points")
    world: FloatArray | None = None
    if map is not None:
        m = _check_map(map)
        p = m.poses if poses is None else _check_poses(m, poses)
        world = m.world_points(p)
    elif poses is not None:
        raise InputError("poses given without a map; pass map= too")

    height, width = h.shape
    extent = (float(o[0]), float(o[0] + width * res), float(o[1]), float(o[1] + height * res))
    fig = _new_figure(_fitted_size(fig_size, extent, (2.4, 1.0)), dpi_v)
    ax = fig.add_subplot()
    shown = np.ma.masked_less_equal(h, 0.0)
    top = float(h.max()) if h.max() > 0 else 1.0
    norm: Normalize
    if log_scale:
        positive = h[h > 0]
        norm = LogNorm(vmin=float(positive.min()) if positive.size else 1.0, vmax=max(top, 1.0))
    else:
        norm = Normalize(vmin=0.0, vmax=top)
    image = ax.imshow(
        shown,
        origin="lower",
        extent=extent,
        cmap="inferno_r",
        norm=norm,
        interpolation="nearest",
        aspect="equal",
        zorder=1,
    )
    if world is not None and len(world):
        keep = _subsample(len(world), limit)
        pts = world if keep is None else world[keep]
        ax.scatter(
            pts[:, 0],
            pts[:, 1],
            s=0.4,
            c="#4a7fb5",
            alpha=0.35,
            marker=".",
            linewidths=0,
            rasterized=True,
            zorder=2,
        )
    fig.colorbar(image, ax=ax, shrink=0.85, label="inconsistent scan pairs per cell (count)")
    total = res * res * float(h.sum())
    ax.set_title(
        title
        if title is not None
        else f"inconsistency I = {total:.2f} m$^2$ ({res:g} m cells, {width} x {height})"
    )
    ax.set_xlabel("x [m]")
    ax.set_ylabel("y [m]")
    ax.set_xlim(extent[0], extent[1])
    ax.set_ylim(extent[2], extent[3])
    return _save(fig, target, fmt, dpi_v)


def write_inconsistency_heat_map(map: Map, result: Inconsistency, path: PathLike) -> Path:
    """The figure ``hitl-slam metrics --heat-map`` writes: :func:`write_heat_map` of ``result``
    (:func:`hitl_slam.metrics.inconsistency` of ``map``) on a log colour scale, with the map's
    observations under its own poses and the total in the title. Returns the path written."""
    return write_heat_map(
        result.heat,
        result.origin,
        result.resolution,
        path,
        map=map,
        log_scale=True,
        title=f"{map.name}: inconsistency {result.total_m2:.2f} m$^2$",
    )
