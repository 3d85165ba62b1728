"""How well each correction in effect holds on the current map: the angle and offset between
lines refit (total least squares) to its S_a and S_b as the current poses place them. A measure
of the points, so it is refit here on purpose; what the page draws are the solved lines
(:mod:`hitl_slam.web.drawing`).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import Any

import numpy as np
from numpy.typing import NDArray

from hitl_slam.corrections import Interpretation, Mode
from hitl_slam.geometry import fit_line
from hitl_slam.map import Map

__all__ = ["relation_residuals"]


def relation_residuals(
    map: Map, poses: NDArray[np.float64], active: Sequence[tuple[int, Interpretation]]
) -> list[dict[str, Any]]:
    """For each (history index, interpretation) in effect, the Relation document: the angle
    between the refit lines [deg] (from 90 for perpendicular) and, for collinear and
    colocation, the offset [m] between them."""
    out = []
    for index, h in active:
        a = map.observed_points(h.s_a, poses)
        b = map.observed_points(h.s_b, poses)
        phi_a, rho_a = fit_line(a)
        phi_b, _ = fit_line(b)
        # Lines have no direction: fold the angle between normals into [0, 90] degrees.
        diff = abs((phi_b - phi_a + math.pi / 2) % math.pi - math.pi / 2)
        angle = math.degrees(diff)
        if h.mode is Mode.PERPENDICULAR:
            angle = abs(90.0 - angle)
        centre_a, centre_b = a.mean(axis=0), b.mean(axis=0)
        offset: float | None = None
        if h.mode is Mode.COLLINEAR:
            normal = np.array([math.cos(phi_a), math.sin(phi_a)])
            offset = abs(float(normal @ centre_b) - rho_a)
        elif h.mode is Mode.COLOCATION:
            offset = float(np.hypot(*(centre_b - centre_a)))
        out.append({"index": index, "mode": h.mode.value, "angle_deg": angle, "offset_m": offset})
    return out
