"""Pose-graph files: load g2o or TORO text into a :class:`~hitl_slam.graph.PoseGraph` and save one.

The format modules parse lines (:mod:`.g2o`, :mod:`.toro` over :mod:`.textfile`); this module
picks the format, checks the graph as a whole (ids, information, connectivity) and builds arrays.
"""

from __future__ import annotations

import enum
import logging
import os
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import ArrayLike, NDArray

# scipy ships no type information; "unused-ignore" keeps this clean once scipy-stubs is added.
from scipy.sparse import coo_array  # type: ignore[import-untyped, unused-ignore]
from scipy.sparse.csgraph import connected_components  # type: ignore[import-untyped, unused-ignore]

from hitl_slam.errors import InputError
from hitl_slam.geometry import compose, integrate, invert, wrap
from hitl_slam.graph import PoseGraph
from hitl_slam.io import g2o, toro
from hitl_slam.io.atomic import atomic_write_text
from hitl_slam.io.textfile import (
    ANGLE_LIMIT,
    COMPRESSED_SUFFIXES,
    COORDINATE_LIMIT,
    MAX_INFORMATION,
    PathLike,
    RawGraph,
    Syntax,
    first_beyond,
    input_error,
    read_lines,
    sci,
)

__all__ = ["GraphFormat", "LoadReport", "load_graph", "save_graph"]

_log = logging.getLogger("hitl_slam")
_MAX_TAGS_SHOWN = 10


class GraphFormat(enum.Enum):
    """A pose-graph text format."""

    G2O = "g2o"
    TORO = "toro"

    @property
    def syntax(self) -> Syntax:
        return g2o.SYNTAX if self is GraphFormat.G2O else toro.SYNTAX

    @property
    def extension(self) -> str:
        return ".g2o" if self is GraphFormat.G2O else ".graph"


_BY_EXTENSION = {f.extension: f for f in GraphFormat}


@dataclass(frozen=True)
class LoadReport:
    """What loading did besides reading: lines it skipped, vertices it merged, poses it made up."""

    path: str
    format: GraphFormat
    skipped: dict[str, int] = field(default_factory=dict)
    """Count per tag of lines the reader does not use (g2o: FIX'd vertices after the first)."""
    merged_vertices: int = 0
    """TORO: vertices merged into another by EQUIV lines."""
    dropped_self_loops: int = 0
    """TORO: edges dropped because an EQUIV merge turned them into self-loops."""
    poses_from_odometry: bool = False
    """The file had no vertex lines: the initial poses were chained from the edges."""


def load_graph(path: PathLike) -> PoseGraph:
    """Read a g2o (``.g2o``) or TORO (``.graph``) 2D pose graph, optionally ``.gz``/``.bz2``.

    Other extensions are recognised by the first data line (``VERTEX_SE2``/``EDGE_SE2`` or
    ``VERTEX2``/``EDGE2``). Rows follow the order in which vertices first appear in the file;
    a file with edges but no vertex lines gets rows in sorted id order and initial poses chained
    along the odometry edges (consecutive ids) from the origin. Angles are wrapped to (-pi, pi].
    The anchor is row 0 unless a g2o ``FIX`` line names another vertex. What the reader met is
    in ``graph.load_report`` (:class:`LoadReport`); skipped tags are also logged as a warning on
    the ``hitl_slam`` logger.

    Raises:
        InputError: for any problem with the file, as ``{path}:{line}: {what}; {what to do}``.
    """
    name = os.fspath(path)
    lines = read_lines(name)
    fmt = _detect_format(name, lines)
    raw = g2o.parse(name, lines) if fmt is GraphFormat.G2O else toro.parse(name, lines)
    graph = _build(raw, fmt)
    report = LoadReport(
        path=name,
        format=fmt,
        skipped=dict(raw.skipped),
        merged_vertices=raw.merged_vertices,
        dropped_self_loops=raw.dropped_self_loops,
        poses_from_odometry=not raw.vertex_ids,
    )
    _log_report(report, raw)
    graph.load_report = report
    return graph


def save_graph(graph: PoseGraph, poses: ArrayLike | None, path: PathLike) -> None:
    """Write ``graph`` with ``poses`` (``(N, 3)``; ``None`` for ``graph.poses``) atomically.

    The extension picks the format (``.g2o`` or ``.graph``). Vertex ids, edges, measurements and
    information come from ``graph``; floats are written exactly, so reloading gives identical
    arrays. g2o records a non-zero anchor as a ``FIX`` line; TORO cannot record it, so a TORO
    file reloads anchored at its first vertex.

    Raises:
        InputError: unsupported extension, arrays that do not fit the graph, values the reader
            would refuse (beyond its limits, information not positive definite, vertices not
            connected to the anchor; nothing is written then), or an unwritable path.
    """
    name = os.fspath(path)
    extension = os.path.splitext(name)[1].lower()
    fmt = _BY_EXTENSION.get(extension)
    if fmt is None:
        supported = ", ".join(_BY_EXTENSION)
        raise input_error(
            name,
            None,
            f"cannot save a pose graph as {extension or 'a file without extension'!r}",
            f"use one of the supported extensions: {supported}",
        )
    vertex_ids, out_poses = _checked_for_saving(name, graph, poses)
    edge_ids = vertex_ids[graph.edges]
    measurements = graph.measurements.copy()
    measurements[:, 2] = wrap(measurements[:, 2])
    _check_readable(name, fmt.syntax, out_poses, graph, measurements)
    if fmt is GraphFormat.G2O:
        text = g2o.format_text(
            vertex_ids, out_poses, edge_ids, measurements, graph.information, graph.anchor
        )
    else:
        if graph.anchor != 0:
            _log.warning(
                "%s: TORO cannot mark the anchor; the file reloads anchored at vertex %d, not %d",
                name,
                vertex_ids[0],
                vertex_ids[graph.anchor],
            )
        text = toro.format_text(vertex_ids, out_poses, edge_ids, measurements, graph.information)
    try:
        atomic_write_text(name, text)
    except OSError as exc:
        raise input_error(
            name,
            None,
            f"cannot write the file ({exc.strerror or exc})",
            "check that the directory exists and is writable",
        ) from None


def _log_report(report: LoadReport, raw: RawGraph) -> None:
    if report.skipped:
        syntax = report.format.syntax
        known = {t.upper(): t for t in (syntax.vertex_tag, syntax.edge_tag, *syntax.extra_tags)}

        def hint(tag: str) -> str:
            # The reference readers match tags exactly (g2o's factory, TORO's parser), so a
            # mis-cased tag is skipped as they would, but said plainly.
            if tag == "FIX":
                return "; only the first FIX'd vertex is held fixed, these ids are free"
            meant = known.get(tag.upper())
            return f"; tags are case-sensitive: {meant}?" if meant and meant != tag else ""

        details = ", ".join(
            f"{_shown(tag)} x{count} (first at line {raw.skipped_first_line[tag]}{hint(tag)})"
            for tag, count in list(report.skipped.items())[:_MAX_TAGS_SHOWN]
        )
        if len(report.skipped) > _MAX_TAGS_SHOWN:
            details += f", and {len(report.skipped) - _MAX_TAGS_SHOWN} more tags"
        _log.warning(
            "%s: ignored what the %s reader does not use: %s",
            report.path,
            report.format.syntax.name,
            details,
        )
    if report.merged_vertices:
        _log.info(
            "%s: EQUIV merged %d vertices; dropped %d edges that became self-loops",
            report.path,
            report.merged_vertices,
            report.dropped_self_loops,
        )
    if report.poses_from_odometry:
        _log.info("%s: no vertex lines; initial poses chained from the edges", report.path)


def _shown(tag: str) -> str:
    # Tags come from arbitrary files: keep them short and make control characters visible.
    short = tag if len(tag) <= 30 else tag[:30] + "..."
    return short if short.isprintable() else repr(short)


def _first_data_line(lines: list[str]) -> tuple[int, str] | None:
    for number, line in enumerate(lines, 1):
        tokens = line.split(None, 1)
        if tokens and not tokens[0].startswith("#"):
            return number, tokens[0]
    return None


def _detect_format(name: str, lines: list[str]) -> GraphFormat:
    first = _first_data_line(lines)
    if first is None:
        raise input_error(
            name,
            None,
            "the file is empty (nothing but blank lines and # comments)",
            "give a g2o (VERTEX_SE2/EDGE_SE2) or TORO (VERTEX2/EDGE2) pose graph",
        )
    base, extension = os.path.splitext(name.lower())
    if extension in COMPRESSED_SUFFIXES:
        extension = os.path.splitext(base)[1]
    if extension in _BY_EXTENSION:
        return _BY_EXTENSION[extension]
    number, tag = first
    for fmt in GraphFormat:
        if tag in (fmt.syntax.vertex_tag, fmt.syntax.edge_tag):
            return fmt
    raise input_error(
        name,
        number,
        f"neither a g2o nor a TORO pose graph (the first data line starts with {tag[:30]!r})",
        "g2o lines start with VERTEX_SE2/EDGE_SE2 and TORO lines with VERTEX2/EDGE2; "
        "name the file .g2o or .graph if it is one of these",
    )


def _build(raw: RawGraph, fmt: GraphFormat) -> PoseGraph:
    """Check the parsed file as a graph and turn it into arrays."""
    syntax = fmt.syntax
    path = raw.path
    if not raw.vertex_ids and not raw.edge_ids:
        raise _nothing_usable(raw, fmt)
    if raw.vertex_ids:
        ids, vertex_lines = raw.vertex_ids, raw.vertex_lines
    else:
        first_seen: dict[int, int] = {}
        for (i, j), line in zip(raw.edge_ids, raw.edge_lines, strict=True):
            first_seen.setdefault(i, line)
            first_seen.setdefault(j, line)
        ids = sorted(first_seen)
        vertex_lines = [first_seen[v] for v in ids]
    row_of = {v: row for row, v in enumerate(ids)}

    try:
        pairs = [(row_of[i], row_of[j]) for i, j in raw.edge_ids]
    except KeyError:
        k, missing = next(
            (k, v) for k, ij in enumerate(raw.edge_ids) for v in ij if v not in row_of
        )
        raise input_error(
            path,
            raw.edge_lines[k],
            f"unknown vertex id {missing}: the edge refers to a vertex with no "
            f"{syntax.vertex_tag} line",
            f"add a '{syntax.vertex_tag} {missing} x y theta' line, or delete the edge",
        ) from None
    edges = np.array(pairs, dtype=np.int64).reshape(-1, 2)
    values = np.array(raw.edge_values, dtype=np.float64).reshape(-1, 9)
    measurements = np.ascontiguousarray(values[:, :3])
    measurements[:, 2] = wrap(measurements[:, 2])
    information = np.zeros((len(edges), 3, 3))
    rows = [r for r, _ in syntax.info_index]
    cols = [c for _, c in syntax.info_index]
    information[:, rows, cols] = values[:, 3:]
    information[:, cols, rows] = values[:, 3:]
    _check_information(raw, syntax, information)

    anchor = 0
    if raw.anchor is not None:
        anchor_id, line = raw.anchor
        if anchor_id not in row_of:
            raise input_error(
                path,
                line,
                f"the fixed (anchor) vertex {anchor_id} has no {syntax.vertex_tag} line",
                "fix the id or delete the line",
            )
        anchor = row_of[anchor_id]

    if raw.vertex_ids:
        poses = np.array(raw.poses, dtype=np.float64).reshape(-1, 3)
    else:
        poses = _chain_poses(len(ids), edges, measurements)
        if not np.isfinite(poses).all():
            raise input_error(
                path,
                None,
                "chaining the edges into initial poses overflowed (measurements too large)",
                f"add {syntax.vertex_tag} lines with initial poses, or check the edge units",
            )
    poses[:, 2] = wrap(poses[:, 2])
    _check_connected(path, ids, vertex_lines, edges, anchor)
    return PoseGraph(
        poses=poses,
        edges=edges,
        measurements=measurements,
        information=information,
        vertex_ids=np.array(ids, dtype=np.int64),
        anchor=anchor,
        source=path,
    )


def _nothing_usable(raw: RawGraph, fmt: GraphFormat) -> InputError:
    syntax = fmt.syntax
    skipped = ", ".join(
        f"{_shown(tag)} x{count}" for tag, count in list(raw.skipped.items())[:_MAX_TAGS_SHOWN]
    )
    if len(raw.skipped) > _MAX_TAGS_SHOWN:
        skipped += ", ..."
    what = f"no {syntax.vertex_tag} or {syntax.edge_tag} lines"
    if skipped:
        what += f" (skipped: {skipped})"
    todo = f"a {syntax.name} pose graph needs {syntax.usage()} lines"
    for other in GraphFormat:
        if (
            other is not fmt
            and {other.syntax.vertex_tag, other.syntax.edge_tag} & raw.skipped.keys()
        ):
            todo = f"this looks like a {other.syntax.name} file: name it *{other.extension}"
    return input_error(raw.path, None, what, todo)


def _check_information(raw: RawGraph, syntax: Syntax, information: NDArray[np.float64]) -> None:
    if _positive_definite(information):
        return
    # Only on failure: find which edges, one Cholesky each.
    bad = [k for k in range(len(information)) if not _positive_definite(information[k])]
    if not bad:
        return
    try:
        eigenvalues = ", ".join(f"{e:.6g}" for e in np.linalg.eigvalsh(information[bad[0]]))
    except np.linalg.LinAlgError:
        eigenvalues = "not computable"
    more = ""
    if len(bad) > 1:
        lines = ", ".join(str(raw.edge_lines[k]) for k in bad[1:6])
        etc = ", ..." if len(bad) > 6 else ""
        more = f", and so is that of {len(bad) - 1} more edges (lines {lines}{etc})"
    raise input_error(
        raw.path,
        raw.edge_lines[bad[0]],
        f"information matrix is not positive definite (eigenvalues {eigenvalues}){more}",
        "give the inverse of the measurement covariance, a symmetric positive-definite matrix, "
        f"as {' '.join(syntax.info_fields)}",
    )


def _positive_definite(matrix: NDArray[np.float64]) -> bool:
    try:
        np.linalg.cholesky(matrix)
    except np.linalg.LinAlgError:
        return False
    return True


def _chain_poses(
    n: int, edges: NDArray[np.int64], measurements: NDArray[np.float64]
) -> NDArray[np.float64]:
    """Initial poses composed from row 0 at the origin: odometry (row r-1 to row r) first, then
    breadth-first over any edge for rows the odometry chain does not reach (one vectorised
    :func:`~hitl_slam.geometry.compose` per breadth-first level)."""
    neighbours: list[list[tuple[int, int]]] = [[] for _ in range(n)]
    for k, (i, j) in enumerate(edges.tolist()):
        neighbours[i].append((j, k))
        neighbours[j].append((i, k))
    placed = np.zeros(n, dtype=bool)
    placed[0] = True

    def steps(src: list[int], ks: list[int]) -> NDArray[np.float64]:
        """The measurements ``ks`` as steps from ``src``: inverted where an edge measures
        ``src`` in the other pose's frame."""
        z = measurements[ks].reshape(-1, 3).copy()
        backwards = edges[ks, 0].reshape(-1) != np.array(src, dtype=np.int64)
        z[backwards] = invert(z[backwards])
        return z

    with np.errstate(over="ignore", invalid="ignore"):
        # The odometry chain: a prefix of rows, each placed from the one before.
        chain: list[int] = []
        for row in range(1, n):
            odometry = next((k for other, k in neighbours[row - 1] if other == row), None)
            if odometry is None:
                break
            chain.append(odometry)
        poses = np.zeros((n, 3))
        rows = len(chain) + 1
        poses[:rows] = integrate(np.zeros(3), steps(list(range(rows - 1)), chain))
        placed[:rows] = True
        frontier = list(range(rows))
        while frontier:
            src, dst, ks = [], [], []
            for a in frontier:
                for b, k in neighbours[a]:
                    if not placed[b]:
                        placed[b] = True
                        src.append(a)
                        dst.append(b)
                        ks.append(k)
            if dst:
                poses[dst] = compose(poses[src], steps(src, ks))
            frontier = dst
    return poses


def _check_connected(
    path: str, ids: list[int], vertex_lines: list[int], edges: NDArray[np.int64], anchor: int
) -> None:
    unreachable = _unreachable(len(ids), edges, anchor)
    if unreachable.size == 0:
        return
    count = int(unreachable.size)
    shown = ", ".join(str(ids[r]) for r in unreachable[:5]) + (", ..." if count > 5 else "")
    noun = "vertex is" if count == 1 else "vertices are"
    raise input_error(
        path,
        vertex_lines[int(unreachable[0])],
        f"{count} {noun} not connected to the anchor vertex {ids[anchor]} through edges "
        f"(ids {shown})",
        "add edges linking them, or remove them",
    )


def _unreachable(n: int, edges: NDArray[np.int64], anchor: int) -> NDArray[np.int64]:
    """Rows not connected to ``anchor`` through ``edges``."""
    if n < 2:
        return np.zeros(0, dtype=np.int64)
    adjacency = coo_array((np.ones(len(edges)), (edges[:, 0], edges[:, 1])), shape=(n, n))
    _, labels = connected_components(adjacency.tocsr(), directed=False)
    return np.flatnonzero(labels != labels[anchor]).astype(np.int64)


def _check_readable(
    name: str,
    syntax: Syntax,
    poses: NDArray[np.float64],
    graph: PoseGraph,
    measurements: NDArray[np.float64],
) -> None:
    """Refuse to write what :func:`load_graph` would refuse to read: values beyond the readers'
    limits, information that is not positive definite as the file records it (its upper
    triangle), vertices not connected to the anchor."""
    position = np.full(3, COORDINATE_LIMIT.bound)
    position[2] = ANGLE_LIMIT.bound
    limits = (COORDINATE_LIMIT, COORDINATE_LIMIT, ANGLE_LIMIT)
    for label, array, fields in (
        ("pose", poses, ("x", "y", "theta")),
        ("measurement", measurements, ("dx", "dy", "dtheta")),
    ):
        beyond = first_beyond(array, position)
        if beyond is not None:
            row, col = beyond
            raise input_error(
                name,
                None,
                f"cannot write a file hitl-slam could not read back: {label} {row} has "
                f"{fields[col]} = {float(array[row, col])!r}, {limits[col].what}",
                "bring the values within the limit before saving",
            )
    information = graph.information
    rows = [r for r, _ in syntax.info_index]
    cols = [c for _, c in syntax.info_index]
    recorded = np.zeros_like(information)
    recorded[:, rows, cols] = information[:, rows, cols]
    recorded[:, cols, rows] = information[:, rows, cols]
    flat = recorded.reshape(len(recorded), 9)
    beyond = first_beyond(flat, np.full(9, MAX_INFORMATION))
    if beyond is not None:
        row = beyond[0]
        raise input_error(
            name,
            None,
            f"cannot write a file hitl-slam could not read back: the information of edge {row} "
            f"has an entry beyond +/-{sci(MAX_INFORMATION)} (largest {np.abs(flat[row]).max()!r})",
            "scale the information down (it is the inverse covariance) before saving",
        )
    if not _positive_definite(recorded):
        row = next(k for k in range(len(recorded)) if not _positive_definite(recorded[k]))
        raise input_error(
            name,
            None,
            f"cannot write a file hitl-slam could not read back: the information of edge {row} is "
            "not positive definite (the file records its upper triangle)",
            "give every edge a symmetric positive-definite information matrix",
        )
    unreachable = _unreachable(len(poses), graph.edges, graph.anchor)
    if unreachable.size:
        raise input_error(
            name,
            None,
            f"cannot write a file hitl-slam could not read back: {unreachable.size} vertices are "
            f"not connected to the anchor through edges (first row {int(unreachable[0])})",
            "add edges linking them, or remove them",
        )


def _checked_for_saving(
    name: str, graph: PoseGraph, poses: ArrayLike | None
) -> tuple[NDArray[np.int64], NDArray[np.float64]]:
    """The vertex ids and poses to write, after checking the graph would read back."""
    n = graph.num_poses
    if n == 0:
        raise input_error(name, None, "the graph has no vertices", "there is nothing to save")

    def bad(what: str, todo: str) -> InputError:
        return input_error(name, None, what, todo)

    try:
        out = np.array(graph.poses if poses is None else poses, dtype=np.float64)
    except (TypeError, ValueError) as exc:
        raise bad(f"poses are not a numeric array ({exc})", "pass an (N, 3) float array") from None
    if out.shape != (n, 3):
        raise bad(
            f"poses have shape {out.shape} but the graph has {n} vertices",
            "pass one (x, y, theta) row per vertex",
        )
    out[:, 2] = wrap(out[:, 2])
    vertex_ids = np.arange(n, dtype=np.int64) if graph.vertex_ids is None else graph.vertex_ids
    for label, array in (
        ("poses", out),
        ("measurements", graph.measurements),
        ("information", graph.information),
    ):
        finite = np.isfinite(array).all(axis=tuple(range(1, array.ndim)))
        if not finite.all():
            row = int(np.argmin(finite))
            raise bad(f"{label} row {row} is not finite", "replace NaN/inf before saving")
    if len(np.unique(vertex_ids)) != n:
        raise bad("vertex_ids has duplicates", "give every vertex its own id")
    edges = graph.edges
    if edges.size and (edges.min() < 0 or edges.max() >= n):
        raise bad(f"edges index rows outside 0..{n - 1}", "edges hold row indices into poses")
    if (edges[:, 0] == edges[:, 1]).any():
        raise bad("edges contain a self-loop (i == j)", "remove edges from a vertex to itself")
    if not 0 <= graph.anchor < n:
        raise bad(f"anchor {graph.anchor} is not a row of poses", f"use a row in 0..{n - 1}")
    return vertex_ids, out
