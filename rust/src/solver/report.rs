//! What a solve reports: iterations, chi2 before and after, why it stopped, where the time went.

use std::fmt;

/// Why the solver stopped. Only the three tolerance tests count as convergence, and each is
/// applied only where it means what it says (see `problem::Convergence`).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Termination {
    /// Function tolerance: an accepted, essentially undamped step changed the cost by less than
    /// the relative or absolute tolerance (or the cost fell below the error tolerance, or below
    /// what rounding can resolve).
    FunctionTolerance,
    /// Gradient tolerance: `max |J^T r|` fell below its tolerance.
    GradientTolerance,
    /// Step tolerance: an essentially undamped step became negligible relative to the estimate.
    StepTolerance,
    /// The iteration budget ran out before any tolerance test held.
    MaxIterations,
    /// No acceptable step: LM's damping reached its maximum, or dogleg's trust region shrank to
    /// nothing, without decreasing the cost.
    Stalled,
    /// The linearization or the cost stopped being finite (Gauss-Newton diverged, or the
    /// normal equations lost definiteness); the last finite estimate is returned.
    NonFinite,
}

impl Termination {
    pub fn name(self) -> &'static str {
        match self {
            Termination::FunctionTolerance => "function_tolerance",
            Termination::GradientTolerance => "gradient_tolerance",
            Termination::StepTolerance => "step_tolerance",
            Termination::MaxIterations => "max_iterations",
            Termination::Stalled => "stalled",
            Termination::NonFinite => "non_finite",
        }
    }

    /// Whether this counts as convergence.
    pub fn converged(self) -> bool {
        matches!(
            self,
            Termination::FunctionTolerance
                | Termination::GradientTolerance
                | Termination::StepTolerance
        )
    }
}

impl fmt::Display for Termination {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(self.name())
    }
}

/// One trial step.
#[derive(Clone, Debug, PartialEq)]
pub struct IterationRecord {
    pub iteration: usize,
    /// The cost (chi2, or the robust cost) after the step if accepted, of the rejected trial
    /// point otherwise.
    pub chi2: f64,
    /// Damping used (0 for Gauss-Newton; the trust-region radius for dogleg).
    pub lambda: f64,
    /// Euclidean norm of the step.
    pub step_norm: f64,
    pub accepted: bool,
    /// Seconds since the solve started.
    pub elapsed: f64,
}

#[derive(Clone, Debug, PartialEq)]
pub struct SolveReport {
    /// Accepted steps (Gauss-Newton: all steps).
    pub iterations: usize,
    /// Linear solves with a new factorization, accepted or not.
    pub linear_solves: usize,
    /// Accepted steps solved on the factor of an earlier linearization (Levenberg-Marquardt's
    /// chord step, conjugate gradients preconditioned by the held factor) instead of a new one.
    pub chord_steps: usize,
    /// The cost minimized: chi2 `sum |r|^2`, or with robust kernels `sum rho(|r|^2)`.
    pub initial_cost: f64,
    pub final_cost: f64,
    /// Plain chi2 `sum |r|^2` (equal to the costs without robust kernels).
    pub initial_chi2: f64,
    pub final_chi2: f64,
    pub termination: Termination,
    /// Which test stopped the solve and with what numbers, e.g.
    /// "relative decrease 3.1e-08 < 1e-06".
    pub termination_detail: String,
    /// Per factor, the robust weight `rho'(|r|^2)` at the solution (1 without a kernel).
    pub weights: Vec<f64>,
    /// Wall time of the whole solve, and its parts, in seconds.
    pub time: f64,
    pub time_symbolic: f64,
    pub time_linearize: f64,
    pub time_factorize: f64,
    /// Whether the symbolic analysis was computed by this solve (false: reused).
    pub symbolic_computed: bool,
    pub nnz_hessian: usize,
    pub nnz_factor: usize,
    pub history: Vec<IterationRecord>,
}
