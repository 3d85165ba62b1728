"""A map with observations: poses, the laser points each pose saw (robot frame), and the ORIGINAL
relative-pose factors between poses. Corrections move poses; the observations and factors never
change, so every solve starts from what the robot actually measured (docs/ALGORITHM.md §1).
"""

from __future__ import annotations

import base64
import enum
import html
import io
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from numpy.typing import NDArray

from hitl_slam.config import DEFAULT, Config
from hitl_slam.errors import InputError, MissingExtra
from hitl_slam.extras import install_hint
from hitl_slam.geometry import chain_steps, to_world
from hitl_slam.graph import PoseGraph

__all__ = ["InformationSource", "Map", "motion_model_information"]

_REPR_MAX_POINTS = 20_000
"""At most this many observations are drawn in a notebook's picture of a map (a random subset,
the same every time), so showing a big map stays under a second (Freiburg 079, 1.7 M points:
about 0.5 s)."""
_REPR_SIZE = (6.4, 4.8)  # inches, at _REPR_DPI: a 640 x 480 PNG
_REPR_DPI = 100.0


class InformationSource(enum.IntEnum):
    """Where an edge's information matrix came from."""

    INPUT = 0  # the input's own (usable, SPD) covariance or information
    MOTION_MODEL = 1  # docs/ALGORITHM.md §1.3 motion model, the input had none usable


def motion_model_information(
    measurements: NDArray[np.float64], config: Config = DEFAULT
) -> NDArray[np.float64]:
    """(M, 3, 3) information from the §1.3 motion model for relative poses (M, 3)."""
    dt = np.hypot(measurements[:, 0], measurements[:, 1])
    dth = np.abs(measurements[:, 2])
    sigma_t = np.maximum(config.sigma_t0, config.k_t * dt)
    sigma_th = np.maximum(config.sigma_theta0, config.k_theta * dth + config.k_theta_t * dt)
    info = np.zeros((measurements.shape[0], 3, 3))
    info[:, 0, 0] = info[:, 1, 1] = 1.0 / sigma_t**2
    info[:, 2, 2] = 1.0 / sigma_th**2
    return info


@dataclass(eq=False)
class Map:
    """A 2D laser map.

    Attributes:
        poses: ``(N, 3)`` current pose estimates ``t_world_robot`` (x, y, theta).
        points: ``(P, 2)`` every scan point in its robot's frame, pose by pose.
        offsets: ``(N + 1,)`` int64; pose i's points are ``points[offsets[i]:offsets[i + 1]]``.
        normals: ``(P, 2)`` unit normals in the robot frame (zero rows: none), or None.
        edges, measurements, information: the original relative-pose factors (as PoseGraph).
        information_source: ``(M,)`` int8 :class:`InformationSource` per edge.
        timestamps: ``(N,)`` seconds (e.g. CARMEN ipc time), or None.
        anchor: row of the pose held fixed.
        name: a human-readable name; source: the file read, if any.
    """

    poses: NDArray[np.float64]
    points: NDArray[np.float64]
    offsets: NDArray[np.int64]
    edges: NDArray[np.int64]
    measurements: NDArray[np.float64]
    information: NDArray[np.float64]
    information_source: NDArray[np.int8]
    normals: NDArray[np.float64] | None = None
    timestamps: NDArray[np.float64] | None = None
    anchor: int = 0
    name: str = "map"
    source: str | None = None
    metadata: dict[str, Any] = field(default_factory=dict)

    def __post_init__(self) -> None:
        self.poses = np.ascontiguousarray(self.poses, dtype=np.float64)
        self.points = np.ascontiguousarray(self.points, dtype=np.float64).reshape(-1, 2)
        self.offsets = np.ascontiguousarray(self.offsets, dtype=np.int64)
        n = self.poses.shape[0]
        if self.poses.ndim != 2 or self.poses.shape[1] != 3 or n == 0:
            raise InputError(f"poses must have shape (N, 3) with N >= 1, got {self.poses.shape}")
        if (
            self.offsets.shape != (n + 1,)
            or self.offsets[0] != 0
            or self.offsets[-1] != len(self.points)
        ):
            raise InputError("offsets must have N + 1 entries from 0 to the number of points")
        if np.any(np.diff(self.offsets) < 0):
            raise InputError("offsets must be non-decreasing")
        if self.normals is not None:
            self.normals = np.ascontiguousarray(self.normals, dtype=np.float64).reshape(-1, 2)
            if self.normals.shape != self.points.shape:
                raise InputError("normals must have one row per point")
        if self.timestamps is not None:
            self.timestamps = np.ascontiguousarray(self.timestamps, dtype=np.float64)
            if self.timestamps.shape != (n,):
                raise InputError("timestamps must have one entry per pose")
        self.edges = np.ascontiguousarray(self.edges, dtype=np.int64).reshape(-1, 2)
        m = self.edges.shape[0]
        self.measurements = np.ascontiguousarray(self.measurements, dtype=np.float64).reshape(m, 3)
        self.information = np.ascontiguousarray(self.information, dtype=np.float64).reshape(m, 3, 3)
        self.information_source = np.ascontiguousarray(
            self.information_source, dtype=np.int8
        ).reshape(m)
        if not 0 <= self.anchor < n:
            raise InputError(f"anchor {self.anchor} is not a pose index (0..{n - 1})")

    @property
    def num_poses(self) -> int:
        return int(self.poses.shape[0])

    @property
    def num_points(self) -> int:
        return int(self.points.shape[0])

    def summary(self) -> str:
        """One line: the name, how many poses and points, and the extent of the poses and points
        in the world frame under the current poses, e.g. ``room: 120 poses, 21,600 points,
        extent 6.5 m x 4.2 m``."""
        world = self.world_points()

        def span(k: int) -> float:
            # Column by column: numpy reduces a (P, 2) array along axis 0 about 30 times slower.
            low = min(self.poses[:, k].min(), world[:, k].min(initial=np.inf))
            high = max(self.poses[:, k].max(), world[:, k].max(initial=-np.inf))
            return float(high - low)

        width, height = span(0), span(1)
        return (
            f"{self.name}: {self.num_poses:,} poses, {self.num_points:,} points, "
            f"extent {width:.1f} m x {height:.1f} m"
        )

    def _repr_png_(self) -> bytes | None:
        """The map under its current poses as a PNG (observations, at most 20,000 of them, and
        pose arrows; :func:`hitl_slam.plot.plot_map`), shown by Jupyter/IPython. ``None`` (IPython's
        "no picture") when matplotlib, the ``[plot]`` extra, is not installed."""
        try:
            from hitl_slam.plot import plot_map
        except MissingExtra:
            return None
        figure = plot_map(
            self, self.poses, max_points=_REPR_MAX_POINTS, size=_REPR_SIZE, dpi=_REPR_DPI
        )
        buffer = io.BytesIO()
        figure.savefig(buffer, format="png", dpi=_REPR_DPI)
        return buffer.getvalue()

    def _repr_html_(self) -> str:
        """The picture of :meth:`_repr_png_` embedded in HTML above the :meth:`summary` line; only
        the summary (and how to get the picture) when matplotlib is not installed."""
        summary = html.escape(self.summary())
        png = self._repr_png_()
        if png is None:
            return (
                f"<div><code>{summary}</code><br><small>{html.escape(install_hint('plot'))} to "
                "see the map</small></div>"
            )
        data = base64.b64encode(png).decode("ascii")
        return (
            f'<div><img src="data:image/png;base64,{data}" alt="{summary}"><br>'
            f"<code>{summary}</code></div>"
        )

    def pose_of_point(self) -> NDArray[np.int64]:
        """``(P,)`` the pose index of every point."""
        return np.repeat(np.arange(self.num_poses, dtype=np.int64), np.diff(self.offsets))

    def checked_poses(self, poses: object = None) -> NDArray[np.float64]:
        """``poses`` (default: the map's) as a float64 ``(N, 3)`` array for this map, or a clear
        InputError when the shape is wrong or a value is not finite."""
        out = np.ascontiguousarray(self.poses if poses is None else poses, dtype=np.float64)
        if out.shape != (self.num_poses, 3):
            raise InputError(
                f"poses must have shape ({self.num_poses}, 3) for this map, got {out.shape}; "
                "pass one (x, y, theta) row per pose of the map"
            )
        if not np.all(np.isfinite(out)):
            raise InputError("poses contain NaN or inf; pass finite poses")
        return out

    def point_rows(self, rows: NDArray[np.int64]) -> NDArray[np.int64]:
        """The map rows (indices into :attr:`points`) of observations given as ``(K, 2)``
        (pose, point within that pose's scan) rows, as interpretations store them."""
        return np.asarray(self.offsets[rows[:, 0]] + rows[:, 1], dtype=np.int64)

    def observed_points(
        self, rows: NDArray[np.int64], poses: NDArray[np.float64] | None = None
    ) -> NDArray[np.float64]:
        """``(K, 2)`` the observations ``rows`` ((pose, point) rows) in the world frame under
        ``poses`` (default: the map's)."""
        owners = np.ascontiguousarray(rows[:, 0], dtype=np.int64)
        return to_world(
            self.poses if poses is None else poses, owners, self.points[self.point_rows(rows)]
        )

    def world_points(self, poses: NDArray[np.float64] | None = None) -> NDArray[np.float64]:
        """``(P, 2)`` every point in the world frame under ``poses`` (default: the map's)."""
        return to_world(self.poses if poses is None else poses, self.pose_of_point(), self.points)

    def pose_graph(self, poses: NDArray[np.float64] | None = None) -> PoseGraph:
        """The relative-pose factors as a :class:`PoseGraph` with ``poses`` as initial guess."""
        return PoseGraph(
            poses=self.poses if poses is None else poses,
            edges=self.edges,
            measurements=self.measurements,
            information=self.information,
            anchor=self.anchor,
            source=self.source,
        )

    @classmethod
    def from_poses_and_scans(
        cls,
        poses: NDArray[np.float64],
        scans: list[NDArray[np.float64]],
        *,
        covariances: NDArray[np.float64] | None = None,
        timestamps: NDArray[np.float64] | None = None,
        normals: list[NDArray[np.float64]] | None = None,
        config: Config = DEFAULT,
        name: str = "map",
        source: str | None = None,
    ) -> Map:
        """A map from absolute poses and robot-frame scans; the chain factors are built once from
        consecutive poses, ``z = x_i^-1 x_{i+1}`` (§1.2). ``covariances`` (N, 3, 3) are per-pose
        covariances; an edge uses the inverse of the sum of its two poses' covariances when that
        is SPD, otherwise the motion model, and says which in ``information_source``."""
        poses = np.ascontiguousarray(poses, dtype=np.float64)
        n = poses.shape[0]
        if len(scans) != n:
            raise InputError(f"{len(scans)} scans for {n} poses; give one scan per pose")
        counts = np.array([len(s) for s in scans], dtype=np.int64)
        offsets = np.concatenate([[0], np.cumsum(counts)]).astype(np.int64)
        points = (
            np.concatenate([np.asarray(s, dtype=np.float64).reshape(-1, 2) for s in scans])
            if n
            else np.zeros((0, 2))
        )
        nrm = None
        if normals is not None:
            nrm = np.concatenate([np.asarray(v, dtype=np.float64).reshape(-1, 2) for v in normals])
        z = chain_steps(poses)
        info = motion_model_information(z, config)
        source_kind = np.full(n - 1, InformationSource.MOTION_MODEL, dtype=np.int8)
        if covariances is not None:
            cov = np.asarray(covariances, dtype=np.float64).reshape(n, 3, 3)
            pair = cov[:-1] + cov[1:]
            for k in range(n - 1):
                sym = 0.5 * (pair[k] + pair[k].T)
                if np.all(np.isfinite(sym)) and np.all(np.linalg.eigvalsh(sym) > 1e-12):
                    info[k] = np.linalg.inv(sym)
                    source_kind[k] = InformationSource.INPUT
        edges = np.stack([np.arange(n - 1), np.arange(1, n)], axis=1).astype(np.int64)
        return cls(
            poses=poses,
            points=points,
            offsets=offsets,
            edges=edges,
            measurements=z,
            information=info,
            information_source=source_kind,
            normals=nrm,
            timestamps=timestamps,
            name=name,
            source=source,
        )
