"""Type stubs for the compiled core (checked by ``python -m mypy.stubtest hitl_slam._core``)."""

from collections.abc import Callable
from typing import Any, final

import numpy as np
from numpy.typing import NDArray

__all__ = [
    "CorrectionEngine",
    "EmFit",
    "Graph",
    "IterationRecord",
    "MapScans",
    "Snap",
    "SolveReport",
    "__version__",
    "backpropagate",
    "em_fit",
    "em_fit_scans",
    "explicit_transform",
    "inconsistency",
    "line_fit",
    "match_consecutive",
    "run_slam",
    "segment_candidates",
    "wrap_angle",
]

__version__: str

def wrap_angle(a: float) -> float:
    """Wraps an angle to (-pi, pi]."""

def explicit_transform(
    mode: str, p_a: NDArray[np.float64], p_b: NDArray[np.float64]
) -> NDArray[np.float64]:
    """The rigid transform (x, y, theta) bringing segment p_b into the mode's relation with p_a."""

def backpropagate(
    poses: NDArray[np.float64],
    original: NDArray[np.float64],
    start: int,
    end: int,
    rot_var: NDArray[np.float64],
    trans_var: NDArray[np.float64],
) -> NDArray[np.float64]:
    """COP-SLAM back-propagation: the chain from poses[start] made to meet poses[end]."""

def match_consecutive(
    points: NDArray[np.float64],
    offsets: NDArray[np.int64],
    guesses: NDArray[np.float64],
    *,
    search_deg: float = 45.0,
    min_overlap: float = 0.25,
) -> tuple[NDArray[np.bool_], NDArray[np.float64], NDArray[np.float64], NDArray[np.float64]]:
    """Scan k+1 matched against scan k from guesses[k]: (ok, poses, covariances, overlap); ok
    where at least ``min_overlap`` of scan k+1's points (and 25) pair with scan k's lines."""

def run_slam(
    points: NDArray[np.float64],
    offsets: NDArray[np.int64],
    odometry: NDArray[np.float64],
    *,
    progress: Callable[[int], object] | None = None,
    keyframe_distance: float = 0.2,
    keyframe_angle_deg: float = 10.0,
    max_range: float = 20.0,
    loop_min_score: float = 0.55,
    dcs: float = 10.0,
) -> dict[str, Any]:
    """The scan-matching front end over a log: a dict of named arrays (poses, steps, keyframes,
    step_information, loop_pairs, loop_measurements, loop_information, loop_scores,
    loop_weights, loop_set_aside, doubtful, doubt) and the number of submaps."""

@final
class IterationRecord:
    """One trial step of a solve."""

    @property
    def iteration(self) -> int: ...
    @property
    def chi2(self) -> float: ...
    @property
    def damping(self) -> float: ...
    @property
    def step_norm(self) -> float: ...
    @property
    def accepted(self) -> bool: ...
    @property
    def elapsed_s(self) -> float: ...

@final
class SolveReport:
    """What a solve did. ``termination`` is ``function_tolerance``, ``gradient_tolerance`` or
    ``step_tolerance`` (converged; ``termination_detail`` names the test and its numbers), or
    ``max_iterations``, ``stalled``, ``non_finite`` (not converged). ``*_cost`` is the objective
    (chi2, or the robust cost with kernels), ``*_chi2`` plain chi2; ``weights`` is each factor's
    robust weight at the solution (1 without a kernel)."""

    @property
    def iterations(self) -> int: ...
    @property
    def linear_solves(self) -> int: ...
    @property
    def chord_steps(self) -> int: ...
    @property
    def initial_cost(self) -> float: ...
    @property
    def final_cost(self) -> float: ...
    @property
    def initial_chi2(self) -> float: ...
    @property
    def final_chi2(self) -> float: ...
    @property
    def termination(self) -> str: ...
    @property
    def termination_detail(self) -> str: ...
    @property
    def converged(self) -> bool: ...
    @property
    def weights(self) -> NDArray[np.float64]: ...
    @property
    def time_s(self) -> float: ...
    @property
    def time_symbolic_s(self) -> float: ...
    @property
    def time_linearize_s(self) -> float: ...
    @property
    def time_factorize_s(self) -> float: ...
    @property
    def symbolic_computed(self) -> bool: ...
    @property
    def nnz_hessian(self) -> int: ...
    @property
    def nnz_factor(self) -> int: ...
    @property
    def history(self) -> list[IterationRecord]: ...

_Correction = tuple[
    str, NDArray[np.int64], NDArray[np.float64], NDArray[np.int64], NDArray[np.float64]
]

@final
class CorrectionEngine:
    """The map's relative-pose factors, held once, and joint solves with human corrections."""

    def __new__(
        cls,
        num_poses: int,
        edges: NDArray[np.int64],
        measurements: NDArray[np.float64],
        information: NDArray[np.float64],
        anchor: int = 0,
        *,
        chain: tuple[
            NDArray[np.float64], NDArray[np.float64], NDArray[np.int64], NDArray[np.float64]
        ]
        | None = None,
    ) -> CorrectionEngine: ...
    @property
    def num_poses(self) -> int: ...
    @property
    def analyses(self) -> int: ...
    def apply(
        self,
        scans: MapScans,
        poses: NDArray[np.float64],
        a: NDArray[np.float64],
        b: NDArray[np.float64],
        mode: str,
        active: list[tuple[str, NDArray[np.int64], NDArray[np.int64]]],
        config: Any,
        *,
        sigma_h: float,
        robust: list[tuple[str, str]] | None = None,
        consistency_z: float = 0.0,
    ) -> tuple[
        _Interpretation,
        NDArray[np.float64],
        NDArray[np.float64],
        NDArray[np.float64],
        SolveReport,
        float,
        float,
    ]: ...
    def _consistency_guard(
        self,
        scans: MapScans,
        poses: NDArray[np.float64],
        a: NDArray[np.float64],
        b: NDArray[np.float64],
        mode: str,
        h: tuple[
            str,
            NDArray[np.float64],
            NDArray[np.float64],
            NDArray[np.int64],
            NDArray[np.int64],
            NDArray[np.int64],
            NDArray[np.int64],
        ],
        new_poses: NDArray[np.float64],
        active: list[tuple[str, NDArray[np.int64], NDArray[np.int64]]],
        config: Any,
        *,
        sigma_h: float,
        robust: list[tuple[str, str]] | None = None,
        consistency_z: float,
    ) -> tuple[_Interpretation, NDArray[np.float64]] | None: ...
    def explicit_and_backpropagate(
        self,
        poses: NDArray[np.float64],
        mode: str,
        line_a: NDArray[np.float64],
        line_b: NDArray[np.float64],
        x_a: NDArray[np.int64],
        x_b: NDArray[np.int64],
    ) -> tuple[NDArray[np.float64], NDArray[np.float64]]: ...
    def chain_variances(
        self, poses: NDArray[np.float64]
    ) -> tuple[NDArray[np.float64], NDArray[np.float64]]: ...
    def clear_cache(self) -> None: ...
    def base_chi2(self, poses: NDArray[np.float64]) -> float: ...
    def solve(
        self,
        poses: NDArray[np.float64],
        corrections: list[_Correction],
        *,
        sigma_f: float,
        k1: float,
        k2: float,
        average_points: bool = False,
        method: str = "lm",
        max_iterations: int = 100,
        relative_tolerance: float = 1e-6,
        absolute_tolerance: float = 1e-6,
        lambda_initial: float = 1e-5,
        robust: list[tuple[str, str]] | None = None,
        watchdog_steps: int = 3,
    ) -> tuple[NDArray[np.float64], NDArray[np.float64], SolveReport]: ...

_Interpretation = tuple[
    str,
    NDArray[np.float64],
    NDArray[np.float64],
    NDArray[np.int64],
    NDArray[np.int64],
    NDArray[np.int64],
    NDArray[np.int64],
    bool,
    tuple[int, int],
    tuple[float, float],
    list[str],
]

@final
class MapScans:
    """A map's scans held once for interpretation."""

    def __new__(cls, points: NDArray[np.float64], offsets: NDArray[np.int64]) -> MapScans: ...
    @property
    def num_poses(self) -> int: ...
    def interpret(
        self,
        poses: NDArray[np.float64],
        a: NDArray[np.float64],
        b: NDArray[np.float64],
        mode: str,
        config: Any,
        *,
        sigma_h: float,
        visit_gap: int | None = None,
        nearest_visits: bool = False,
    ) -> _Interpretation: ...

@final
class Graph:
    """A pose graph held by the core, with its cached symbolic analysis."""

    def __new__(
        cls,
        num_poses: int,
        edges: NDArray[np.int64],
        measurements: NDArray[np.float64],
        information: NDArray[np.float64],
        anchor: int = 0,
    ) -> Graph: ...
    @property
    def num_poses(self) -> int: ...
    @property
    def num_factors(self) -> int: ...
    @property
    def analyses(self) -> int: ...
    @property
    def num_lines(self) -> int: ...
    def add_correction(
        self,
        mode: str,
        a_poses: NDArray[np.int64],
        a_points: NDArray[np.float64],
        b_poses: NDArray[np.int64],
        b_points: NDArray[np.float64],
        *,
        sigma_f: float,
        k1: float,
        k2: float,
        average_points: bool = False,
    ) -> tuple[int, int]: ...
    def optimize_with_lines(
        self,
        poses: NDArray[np.float64],
        lines: NDArray[np.float64],
        *,
        method: str = "lm",
        max_iterations: int = 100,
        relative_tolerance: float = 1e-6,
        absolute_tolerance: float = 1e-6,
        lambda_initial: float = 1e-5,
        robust: list[tuple[str, str]] | None = None,
        watchdog_steps: int = 3,
    ) -> tuple[NDArray[np.float64], NDArray[np.float64], SolveReport]: ...
    def add_between(
        self, i: int, j: int, measurement: NDArray[np.float64], information: NDArray[np.float64]
    ) -> None: ...
    def add_prior(
        self, i: int, measurement: NDArray[np.float64], information: NDArray[np.float64]
    ) -> None: ...
    def chi2(self, poses: NDArray[np.float64]) -> float: ...
    def optimize(
        self,
        poses: NDArray[np.float64],
        *,
        method: str = "lm",
        max_iterations: int = 100,
        relative_tolerance: float = 1e-6,
        absolute_tolerance: float = 1e-6,
        error_tolerance: float = 0.0,
        gradient_tolerance: float = 1e-12,
        step_tolerance: float = 1e-12,
        lambda_initial: float = 1e-5,
        lambda_max: float = 1e16,
        diagonal_damping: bool = False,
        watchdog_steps: int = 3,
        trust_radius_initial: float = 0.0,
        robust: list[tuple[str, str]] | None = None,
        init: str = "given",
    ) -> tuple[NDArray[np.float64], SolveReport]: ...
    def marginals(
        self, poses: NDArray[np.float64], indices: NDArray[np.int64]
    ) -> NDArray[np.float64]: ...
    def linear_system(
        self, poses: NDArray[np.float64]
    ) -> tuple[
        NDArray[np.int64],
        NDArray[np.int64],
        NDArray[np.float64],
        NDArray[np.float64],
        NDArray[np.int64],
    ]: ...

@final
class Snap:
    """Where a drawn segment was snapped before EM: ``segment`` ``(2, 2)`` the drawn ends
    projected onto the chosen line, ``moved`` how far each end moved, ``turn`` the angle
    [rad], ``support`` the line's points, ``score`` and the best other line's ``runner_up``."""

    @property
    def segment(self) -> NDArray[np.float64]: ...
    @property
    def moved(self) -> tuple[float, float]: ...
    @property
    def turn(self) -> float: ...
    @property
    def support(self) -> int: ...
    @property
    def score(self) -> float: ...
    @property
    def runner_up(self) -> float: ...

@final
class EmFit:
    """EM's interpretation of one drawn segment (docs/ALGORITHM.md §3.3). The line is
    ``n . p = rho`` with ``n = (cos phi, sin phi)``, phi in (-pi/2, pi/2]; ``extent`` is its
    ``(2, 2)`` endpoints; the observation set is ``candidates[weights > 0.5]``."""

    @property
    def candidates(self) -> NDArray[np.int64]: ...
    @property
    def weights(self) -> NDArray[np.float64]: ...
    @property
    def phi(self) -> float: ...
    @property
    def rho(self) -> float: ...
    @property
    def extent(self) -> NDArray[np.float64]: ...
    @property
    def iterations(self) -> int: ...
    @property
    def log_likelihood(self) -> float: ...
    @property
    def converged(self) -> bool: ...
    @property
    def mixing(self) -> float: ...
    @property
    def snap(self) -> Snap | None: ...
    @property
    def num_inliers(self) -> int: ...

def em_fit(
    world_points: NDArray[np.float64],
    segments: NDArray[np.float64],
    *,
    band: float,
    sigma_em: float,
    pi0: float,
    tol_m: float,
    tol_rad: float,
    tol_pi: float,
    max_iterations: int,
) -> list[EmFit]:
    """EM for each segment ``(S, 2, 2)`` over ``world_points`` ``(P, 2)``, one index for all."""

def em_fit_scans(
    poses: NDArray[np.float64],
    points: NDArray[np.float64],
    offsets: NDArray[np.int64],
    segments: NDArray[np.float64],
    *,
    band: float,
    sigma_em: float,
    pi0: float,
    tol_m: float,
    tol_rad: float,
    tol_pi: float,
    max_iterations: int,
    search_band: float | None = None,
    closeness: float = 0.2,
    pointing: float = 0.1,
    min_support: int = 8,
) -> list[EmFit]:
    """``em_fit`` on robot-frame ``points`` of a map (pose i owns ``offsets[i]:offsets[i+1]``).
    With ``search_band`` [m], each segment is first snapped onto the best line of observations
    near it (support against ``closeness``, the sideways offset, and the turn allowed by
    ``pointing``, each end's noise) and EM starts there."""

def segment_candidates(
    world_points: NDArray[np.float64],
    segment: NDArray[np.float64],
    band: float,
    *,
    use_index: bool = True,
) -> NDArray[np.int64]:
    """Indices (ascending) of the points within ``band`` of the segment ``(2, 2)``."""

def line_fit(
    points: NDArray[np.float64],
    weights: NDArray[np.float64],
    segment: NDArray[np.float64],
    band: float,
) -> tuple[float, float, NDArray[np.float64]]:
    """Weighted TLS line ``(phi, rho, extent)`` of ``points`` ``(K, 2)``."""

def inconsistency(
    poses: NDArray[np.float64],
    points: NDArray[np.float64],
    offsets: NDArray[np.int64],
    *,
    resolution: float,
    surface_cells: float,
    min_stop: float,
    grazing_deg: float,
    pairwise: bool = False,
    heat_map: bool = True,
    origin: NDArray[np.float64] | None = None,
    shape: tuple[int, int] | None = None,
    threads: int = 0,
) -> tuple[float, NDArray[np.float64] | None, NDArray[np.float64]]:
    """The inconsistency metric (docs/ALGORITHM.md §6): ``(total_m2, heat (H, W) or None, origin)``;
    the grid covers the data unless ``origin`` and ``shape`` ``(H, W)`` are given; ``threads``
    0 uses rayon's pool, n a local pool of n threads."""
