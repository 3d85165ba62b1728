"""Type stubs for the compiled core (checked by ``python -m mypy.stubtest hitl_slam._core``)."""

from typing import final

import numpy as np
from numpy.typing import NDArray

__all__ = [
    "Graph",
    "IterationRecord",
    "SolveReport",
    "__version__",
    "backpropagate",
    "explicit_transform",
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
    """What a solve did. ``termination`` is one of ``relative_decrease``, ``absolute_decrease``,
    ``error_tolerance``, ``gradient``, ``step_size`` (converged) or ``lambda_limit``,
    ``max_iterations`` (not converged)."""

    @property
    def iterations(self) -> int: ...
    @property
    def linear_solves(self) -> int: ...
    @property
    def initial_chi2(self) -> float: ...
    @property
    def final_chi2(self) -> float: ...
    @property
    def termination(self) -> str: ...
    @property
    def converged(self) -> bool: ...
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
