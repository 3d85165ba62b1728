"""How good is a map: the paper's inconsistency metric (docs/ALGORITHM.md §6), trajectory error
against ground truth (ATE), the relative-pose error against benchmark relations (Kuemmerle et al.
2009), and the Table 1 feature errors (angles between walls, spacing between parallel walls).
"""

from __future__ import annotations

import enum
import math
from collections.abc import Iterable, Sequence
from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray

from hitl_slam import _core
from hitl_slam.config import DEFAULT, Config
from hitl_slam.errors import InputError
from hitl_slam.geometry import between, fit_line, line_angle, rotate, wrap
from hitl_slam.io.relations import Relations, nearest_scans
from hitl_slam.map import Map

__all__ = [
    "FeaturePair",
    "Inconsistency",
    "PairError",
    "PairKind",
    "RelationsError",
    "ate",
    "feature_pair_errors",
    "inconsistency",
    "relations_error",
    "table1",
]

FloatArray = NDArray[np.float64]


# --- inconsistency --------------------------------------------------------------------------


@dataclass(frozen=True, eq=False)
class Inconsistency:
    """The inconsistency metric of a map under some poses (docs/ALGORITHM.md §6.1).

    Attributes:
        total_m2: ``I = res^2 sum_c (F_c O_c - B_c)`` [m^2]: summed over ordered pairs of scans
            (i, j), i != j, the area scan i sees free and scan j sees occupied.
        heat: ``(H, W)`` float64, per cell ``F_c O_c - B_c`` (the number of such ordered pairs);
            row 0 is the BOTTOM of the map (``y = origin[1]``), column 0 the left.
        origin: world ``(x, y)`` [m] of the lower-left corner of cell ``[0, 0]``.
        resolution: cell side [m].
    """

    total_m2: float
    heat: FloatArray
    origin: FloatArray
    resolution: float

    @property
    def extent(self) -> tuple[float, float, float, float]:
        """``(left, right, bottom, top)`` in world metres, as matplotlib's ``imshow`` wants."""
        height, width = self.heat.shape
        x0, y0 = float(self.origin[0]), float(self.origin[1])
        return (x0, x0 + width * self.resolution, y0, y0 + height * self.resolution)


def inconsistency(
    map: Map,
    poses: ArrayLike | None = None,
    config: Config = DEFAULT,
    *,
    pairwise: bool = False,
    like: Inconsistency | None = None,
    threads: int = 0,
) -> Inconsistency:
    """The inconsistency of ``map`` under ``poses`` (default: the map's own).

    Free space of a scan: the cells crossed (exact grid traversal) by the ray from the sensor (the
    pose's position) to each hit; occupied: the hit cells; each cell counts once per scan. The
    three robustness rules of §6.2 apply, set by ``config``: a beam's free space stops
    ``metric_surface_cells`` cells short of its surface measured across it (at least
    ``metric_min_stop`` m along the beam); beams meeting their surface at under
    ``metric_grazing_deg`` degrees carve none; the surface's tangent at a hit comes from the
    nearer neighbouring hit of the same scan (points are beams in their stored order; a hit
    with no distinct neighbour is taken head on).

    The grid has ``config.grid_resolution`` cells covering the data with an origin that is a
    multiple of the resolution, or the grid of ``like`` (to compare two maps cell by cell; data
    outside it is ignored). ``pairwise=True`` uses the direct quadratic definition (small maps
    only), which equals the default counter form exactly. ``threads``: 0 for all cores, 1 for one.

    Raises:
        InputError: bad poses, a non-positive resolution, a grid over 1e8 cells, or bad rules.
    """
    p = map.checked_poses(poses)
    if not (isinstance(threads, int) and threads >= 0):
        raise InputError(f"threads must be an integer >= 0 (0: all cores), got {threads!r}")
    resolution = config.grid_resolution if like is None else like.resolution
    origin = None if like is None else np.ascontiguousarray(like.origin, dtype=np.float64)
    shape = None if like is None else (int(like.heat.shape[0]), int(like.heat.shape[1]))
    total, heat, corner = _core.inconsistency(
        p,
        map.points,
        map.offsets,
        resolution=resolution,
        surface_cells=config.metric_surface_cells,
        min_stop=config.metric_min_stop,
        grazing_deg=config.metric_grazing_deg,
        pairwise=pairwise,
        heat_map=True,
        origin=origin,
        shape=shape,
        threads=threads,
    )
    assert heat is not None  # asked for
    return Inconsistency(total_m2=total, heat=heat, origin=corner, resolution=resolution)


# --- trajectory error -----------------------------------------------------------------------


def _positions(a: ArrayLike, name: str) -> FloatArray:
    out = np.asarray(a, dtype=np.float64)
    if out.ndim != 2 or out.shape[1] not in (2, 3) or out.shape[0] == 0:
        raise InputError(f"{name} must have shape (N, 2) or (N, 3) with N >= 1, got {out.shape}")
    if not np.all(np.isfinite(out)):
        raise InputError(f"{name} contains NaN or inf; pass finite poses")
    return out[:, :2]


def ate(estimate: ArrayLike, truth: ArrayLike, *, align: bool = True) -> float:
    """Absolute trajectory error [m]: the RMSE of the positions, ``sqrt(mean |p_i - q_i|^2)``.

    With ``align`` the estimate is first moved by the rigid 2D transform (rotation and
    translation, no scale) that minimizes that RMSE (Kabsch/Umeyama, closed form in 2D); without
    it the positions are compared as they are. Rows are ``(x, y)`` or ``(x, y, theta)`` (theta is
    ignored); row i of both is the same pose.
    """
    p, q = _positions(estimate, "estimate"), _positions(truth, "truth")
    if p.shape != q.shape:
        raise InputError(f"estimate and truth differ in length: {len(p)} vs {len(q)} poses")
    if align:
        pc, qc = p - p.mean(axis=0), q - q.mean(axis=0)
        # The best rotation in 2D: the angle of sum(conj(p) q) over the centred points.
        angle = math.atan2(
            float(np.sum(pc[:, 0] * qc[:, 1] - pc[:, 1] * qc[:, 0])),
            float(np.sum(pc[:, 0] * qc[:, 0] + pc[:, 1] * qc[:, 1])),
        )
        p = rotate(angle, pc)
        q = qc
    return float(np.sqrt(np.mean(np.sum((p - q) ** 2, axis=1))))


# --- relations (Kuemmerle et al. 2009) ------------------------------------------------------


@dataclass(frozen=True, eq=False)
class RelationsError:
    """Errors of the estimated relative poses against benchmark relations.

    Attributes:
        translation: ``(K,)`` per-relation translational error [m], matched relations only.
        rotation_deg: ``(K,)`` per-relation rotational error [deg].
        pairs: ``(K, 2)`` int64 pose indices of each relation's two scans.
        rows: ``(K,)`` int64 index of each scored relation in the relations given (None: all,
            in order).
        skipped: how many relations were skipped: a timestamp with no scan within
            ``tolerance`` (a cut log, dropped scans).
        tolerance: [s] how far from a relation's timestamp its scan could be.
    """

    translation: FloatArray
    rotation_deg: FloatArray
    pairs: NDArray[np.int64]
    rows: NDArray[np.int64] | None = None
    skipped: int = 0
    tolerance: float = 1e-3

    @property
    def count(self) -> int:
        """The relations matched (and scored)."""
        return int(self.translation.shape[0])

    @property
    def matched(self) -> int:
        """The relations matched to two scans (:attr:`count`)."""
        return self.count

    @property
    def translation_mean(self) -> float:
        return float(np.mean(self.translation))

    @property
    def translation_std(self) -> float:
        """Population standard deviation (ddof 0)."""
        return float(np.std(self.translation))

    @property
    def translation_max(self) -> float:
        return float(np.max(self.translation))

    @property
    def rotation_mean_deg(self) -> float:
        return float(np.mean(self.rotation_deg))

    @property
    def rotation_std_deg(self) -> float:
        """Population standard deviation (ddof 0)."""
        return float(np.std(self.rotation_deg))

    @property
    def rotation_max_deg(self) -> float:
        return float(np.max(self.rotation_deg))


def relations_error(
    map: Map, poses: ArrayLike | None, relations: Relations, *, tolerance: float = 1e-3
) -> RelationsError:
    """The relative-pose error of ``poses`` (default: the map's) against ground-truth relations.

    Each relation ``(t1, t2, dx, dy, yaw)`` is matched to the scans nearest its two timestamps;
    a relation with a timestamp farther than ``tolerance`` s from every scan is skipped and
    counted (``skipped``: a log cut short; a larger tolerance scores a re-stamped log;
    :func:`~hitl_slam.io.relations.nearest_scans`). With the estimated
    poses ``x_1``, ``x_2`` of those scans, the estimated relation is ``x_1^-1 x_2``: translation
    ``t_est = R(theta_1)^T (p_2 - p_1)`` and rotation ``yaw_est = theta_2 - theta_1``. Following
    Kuemmerle et al. (2009), translations and rotations are compared separately:

    * translational error ``|t_est - (dx, dy)|`` [m] (Euclidean norm of the difference of the
      two relative translations, both in the frame of scan t1);
    * rotational error ``|wrap(yaw_est - yaw)|`` [deg], wrapped to [0, 180].

    These are absolute (not squared) errors; the result reports their mean, population standard
    deviation, maximum and count.

    Raises:
        InputError: bad poses, a map without timestamps, a bad tolerance, or no relation with
            both its scans within the tolerance.
    """
    p = map.checked_poses(poses)
    if map.timestamps is None:
        raise InputError(
            "the map has no timestamps to match relations to; load the map from the CARMEN "
            "log the relations were made for"
        )
    match = nearest_scans(relations, map.timestamps, tolerance)
    pairs, rows = match.pairs, match.rows
    est = between(p[pairs[:, 0]], p[pairs[:, 1]])
    truth = relations.relative[rows]
    translation = np.hypot(*(est[:, :2] - truth[:, :2]).T)
    rotation = np.degrees(np.abs(wrap(est[:, 2] - truth[:, 2])))
    return RelationsError(
        translation=np.ascontiguousarray(translation),
        rotation_deg=np.ascontiguousarray(rotation),
        pairs=pairs,
        rows=rows,
        skipped=int(match.skipped.size),
        tolerance=match.tolerance,
    )


# --- Table 1: angles between walls and spacing of parallel walls ----------------------------


class PairKind(enum.Enum):
    """What a feature pair measures."""

    PARALLEL = "parallel"
    """The angle between two walls known to be parallel [deg]; truth usually 0."""
    PERPENDICULAR = "perpendicular"
    """The angle between two walls known to be perpendicular [deg]; truth usually 90."""
    SPACING = "spacing"
    """The distance between two parallel walls [m] (a corridor's width, a room's size)."""

    @property
    def is_angle(self) -> bool:
        return self is not PairKind.SPACING


@dataclass(frozen=True)
class FeaturePair:
    """Two labelled walls and the true value of their relation (deg for angles, m for spacing)."""

    wall_a: int
    wall_b: int
    kind: PairKind
    truth: float


@dataclass(frozen=True)
class PairError:
    """One Table 1 sample: the measured value on the map and its absolute error (deg or m)."""

    pair: FeaturePair
    measured: float
    error: float


def _as_pair(item: FeaturePair | Sequence[object]) -> FeaturePair:
    if isinstance(item, FeaturePair):
        return item
    try:
        wall_a, wall_b, kind, truth = item
        pair = FeaturePair(
            int(wall_a),  # type: ignore[call-overload]
            int(wall_b),  # type: ignore[call-overload]
            PairKind(kind),
            float(truth),  # type: ignore[arg-type]
        )
    except (TypeError, ValueError) as exc:
        kinds = ", ".join(k.value for k in PairKind)
        raise InputError(
            f"a feature pair is (wall_a, wall_b, kind, truth) with kind one of {kinds}, "
            f"got {item!r}"
        ) from exc
    if not math.isfinite(pair.truth):
        raise InputError(f"feature pair {item!r}: the true value must be finite")
    return pair


def feature_pair_errors(
    map: Map,
    poses: ArrayLike | None,
    wall_of_point: ArrayLike,
    pairs: Iterable[FeaturePair | Sequence[object]],
) -> list[PairError]:
    """The paper's Table 1 quantities on ``map`` under ``poses`` (default: the map's).

    ``wall_of_point`` ``(P,)`` labels every point with the wall it hit (negative: none). A wall's
    line is the total-least-squares fit (:func:`hitl_slam.geometry.fit_line`) to all its points in
    the world frame, from every pose that saw it. For each pair ``(wall_a, wall_b, kind, truth)``:

    * ``parallel`` / ``perpendicular``: the measured value is the angle between the two
      (undirected) lines in [0, 90] degrees, and the error ``|angle - truth|`` [deg];
    * ``spacing``: the measured value is the distance between the two lines, the mean of the
      distance from wall b's centroid to line a and from wall a's centroid to line b (equal for
      exactly parallel lines), and the error ``|distance - truth|`` [m].

    Raises:
        InputError: bad poses or labels, an unknown kind, or a wall with fewer than two points.
    """
    p = map.checked_poses(poses)
    labels = np.asarray(wall_of_point).reshape(-1)
    if labels.shape != (map.num_points,) or not np.issubdtype(labels.dtype, np.integer):
        raise InputError(
            f"wall_of_point must be {map.num_points} integer labels (one per point), got "
            f"{labels.dtype} of shape {labels.shape}"
        )
    world = map.world_points(p)
    fits: dict[int, tuple[float, float, FloatArray]] = {}

    def line(wall: int) -> tuple[float, float, FloatArray]:
        if wall not in fits:
            pts = world[labels == wall]
            if len(pts) < 2:
                raise InputError(
                    f"wall {wall} has {len(pts)} labelled points; a line needs at least two"
                )
            phi, rho = fit_line(pts)
            fits[wall] = (phi, rho, pts.mean(axis=0))
        return fits[wall]

    out = []
    for item in pairs:
        pair = _as_pair(item)
        phi_a, rho_a, centre_a = line(pair.wall_a)
        phi_b, rho_b, centre_b = line(pair.wall_b)
        if pair.kind.is_angle:
            measured = math.degrees(line_angle(phi_a, phi_b))
        else:
            n_a = np.array([math.cos(phi_a), math.sin(phi_a)])
            n_b = np.array([math.cos(phi_b), math.sin(phi_b)])
            measured = 0.5 * (
                abs(float(n_a @ centre_b) - rho_a) + abs(float(n_b @ centre_a) - rho_b)
            )
        out.append(PairError(pair=pair, measured=measured, error=abs(measured - pair.truth)))
    return out


def _mean_or_dash(values: list[float], digits: int) -> str:
    return f"{np.mean(values):.{digits}f}" if values else "-"


def table1(
    errors_before: Sequence[PairError], errors_after: Sequence[PairError], *, name: str = "map"
) -> str:
    """The paper's Table 1 row for one map, as Markdown: the number of angle (A) and translation
    (T) samples, and the mean absolute error of each before (input) and after HitL-SLAM.

    Raises:
        InputError: the two lists are not the same pairs in the same order.
    """
    if [e.pair for e in errors_before] != [e.pair for e in errors_after]:
        raise InputError("errors_before and errors_after must measure the same pairs, in order")
    angles = [i for i, e in enumerate(errors_before) if e.pair.kind.is_angle]
    spacings = [i for i, e in enumerate(errors_before) if not e.pair.kind.is_angle]

    def means(errors: Sequence[PairError]) -> tuple[str, str]:
        return (
            _mean_or_dash([errors[i].error for i in angles], 2),
            _mean_or_dash([errors[i].error for i in spacings], 3),
        )

    a_in, t_in = means(errors_before)
    a_out, t_out = means(errors_after)
    return "\n".join(
        [
            "| Map | Samples A | Samples T | Input A (deg) | Input T (m) "
            "| HitL-SLAM A (deg) | HitL-SLAM T (m) |",
            "|---|---:|---:|---:|---:|---:|---:|",
            f"| {name} | {len(angles)} | {len(spacings)} | {a_in} | {t_in} | {a_out} | {t_out} |",
        ]
    )
