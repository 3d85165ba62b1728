"""The TORO 2D pose-graph format: ``VERTEX2 id x y th``, ``EDGE2 i j dx dy dth`` plus the
information in TORO's order ``Ixx Ixy Iyy Itt Ixt Iyt``, and ``EQUIV a b`` (same place) lines.

EQUIV is honoured by merging vertices (see :func:`parse`); other tags are skipped.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
from numpy.typing import NDArray

from hitl_slam.io.textfile import (
    RawGraph,
    Syntax,
    format_graph,
    input_error,
    parse_int,
    parse_tagged_lines,
)

__all__ = ["SYNTAX", "format_text", "parse"]

SYNTAX = Syntax(
    name="TORO",
    vertex_tag="VERTEX2",
    edge_tag="EDGE2",
    info_fields=("Ixx", "Ixy", "Iyy", "Itt", "Ixt", "Iyt"),
    # [[Ixx, Ixy, Ixt], [Ixy, Iyy, Iyt], [Ixt, Iyt, Itt]] in (x, y, theta) order.
    info_index=((0, 0), (0, 1), (1, 1), (2, 2), (0, 2), (1, 2)),
    extra_tags=frozenset({"EQUIV"}),
)


def parse(path: str, lines: Sequence[str]) -> RawGraph:
    """Parse TORO lines and apply the EQUIV merges.

    Merge rule: vertices joined by EQUIV lines (transitively) become one vertex, the one that
    appears first in the file (its VERTEX2 line, or its first edge when the file has no vertices);
    it keeps its own pose. The others disappear, edges touching them are redirected to the
    survivor, and an edge that becomes a self-loop is dropped (counted in
    ``raw.dropped_self_loops``). ``EQUIV a b`` with an id that appears nowhere is an error.
    """
    raw = parse_tagged_lines(path, lines, SYNTAX)
    if not raw.extra:
        return raw
    # First appearance decides which vertex of a merged group survives.
    rank: dict[int, int] = {}
    for v in raw.vertex_ids or [v for ij in raw.edge_ids for v in ij]:
        rank.setdefault(v, len(rank))
    parent: dict[int, int] = {}

    def root(v: int) -> int:
        while v in parent:
            v = parent[v]
        return v

    for line, tokens in raw.extra:
        if len(tokens) != 3:
            raise input_error(
                path,
                line,
                f"EQUIV needs 2 fields after the tag (a b), got {len(tokens) - 1}",
                "fix the line or delete it",
            )
        a, b = (parse_int(path, line, token, "vertex id") for token in tokens[1:])
        for v in (a, b):
            if v not in rank:
                raise input_error(
                    path,
                    line,
                    f"EQUIV names vertex {v}, which has no VERTEX2 line and no edge",
                    "fix the id or delete the line",
                )
        ra, rb = root(a), root(b)
        if ra != rb:
            keep, drop = (ra, rb) if rank[ra] < rank[rb] else (rb, ra)
            parent[drop] = keep
    merged = {v: root(v) for v in parent}
    kept_rows = [k for k, v in enumerate(raw.vertex_ids) if v not in merged]
    raw.vertex_ids = [raw.vertex_ids[k] for k in kept_rows]
    raw.vertex_lines = [raw.vertex_lines[k] for k in kept_rows]
    raw.poses = [raw.poses[k] for k in kept_rows]
    edges = [
        ((merged.get(i, i), merged.get(j, j)), line, values)
        for (i, j), line, values in zip(raw.edge_ids, raw.edge_lines, raw.edge_values, strict=True)
    ]
    kept = [e for e in edges if e[0][0] != e[0][1]]
    raw.edge_ids = [e[0] for e in kept]
    raw.edge_lines = [e[1] for e in kept]
    raw.edge_values = [e[2] for e in kept]
    raw.merged_vertices = len(merged)
    raw.dropped_self_loops = len(edges) - len(kept)
    return raw


def format_text(
    vertex_ids: NDArray[np.int64],
    poses: NDArray[np.float64],
    edge_ids: NDArray[np.int64],
    measurements: NDArray[np.float64],
    information: NDArray[np.float64],
) -> str:
    """TORO text (no EQUIV lines: a graph in memory has its equivalences already merged)."""
    return format_graph(SYNTAX, vertex_ids, poses, edge_ids, measurements, information)
