"""The g2o 2D pose-graph format: ``VERTEX_SE2 id x y th`` and ``EDGE_SE2 i j dx dy dth`` plus the
upper triangle of the information matrix, row-major (``I11 I12 I13 I22 I23 I33``).

``FIX id ...`` names the anchor (the first id of the first FIX line); other tags are skipped.
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
    name="g2o",
    vertex_tag="VERTEX_SE2",
    edge_tag="EDGE_SE2",
    info_fields=("I11", "I12", "I13", "I22", "I23", "I33"),
    info_index=((0, 0), (0, 1), (0, 2), (1, 1), (1, 2), (2, 2)),
    extra_tags=frozenset({"FIX"}),
)


def parse(path: str, lines: Sequence[str]) -> RawGraph:
    """Parse g2o lines; ``raw.anchor`` is the first vertex a FIX line names, if any.

    The solver holds exactly one pose fixed, so further FIX'd vertices are counted under
    ``skipped["FIX"]`` (and so reported) rather than honoured.
    """
    raw = parse_tagged_lines(path, lines, SYNTAX)
    for line, tokens in raw.extra:
        if len(tokens) < 2:
            raise input_error(
                path, line, "FIX needs at least one vertex id", "write 'FIX id' or delete the line"
            )
        ids = [parse_int(path, line, token, "vertex id") for token in tokens[1:]]
        if raw.anchor is None:
            raw.anchor = (ids[0], line)
            ids = ids[1:]
        if ids:
            raw.skipped["FIX"] = raw.skipped.get("FIX", 0) + len(ids)
            raw.skipped_first_line.setdefault("FIX", line)
    return raw


def format_text(
    vertex_ids: NDArray[np.int64],
    poses: NDArray[np.float64],
    edge_ids: NDArray[np.int64],
    measurements: NDArray[np.float64],
    information: NDArray[np.float64],
    anchor: int,
) -> str:
    """g2o text; a ``FIX`` line records the anchor when it is not the first vertex."""
    fix = [f"FIX {int(vertex_ids[anchor])}"] if anchor != 0 else []
    return format_graph(SYNTAX, vertex_ids, poses, edge_ids, measurements, information, fix)
