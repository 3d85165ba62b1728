//! What a solve reports: iterations, chi2 before and after, why it stopped, where the time went.

use std::fmt;

/// Why the solver stopped.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Termination {
    /// The relative decrease of chi2 fell below the relative tolerance.
    RelativeDecrease,
    /// The absolute decrease of chi2 fell below the absolute tolerance.
    AbsoluteDecrease,
    /// chi2 fell below the error tolerance (an exact fit).
    ErrorTolerance,
    /// The gradient vanished (`max |J^T r|` below its tolerance).
    Gradient,
    /// The step became negligible relative to the estimate.
    StepSize,
    /// Levenberg-Marquardt could not find a decreasing step even with a huge damping.
    LambdaLimit,
    /// The iteration budget ran out before convergence.
    MaxIterations,
}

impl Termination {
    pub fn name(self) -> &'static str {
        match self {
            Termination::RelativeDecrease => "relative_decrease",
            Termination::AbsoluteDecrease => "absolute_decrease",
            Termination::ErrorTolerance => "error_tolerance",
            Termination::Gradient => "gradient",
            Termination::StepSize => "step_size",
            Termination::LambdaLimit => "lambda_limit",
            Termination::MaxIterations => "max_iterations",
        }
    }

    /// Whether this counts as convergence.
    pub fn converged(self) -> bool {
        !matches!(self, Termination::MaxIterations | Termination::LambdaLimit)
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
    /// chi2 after the step if accepted, of the rejected trial point otherwise.
    pub chi2: f64,
    /// Damping used (0 for Gauss-Newton).
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
    /// Linear solves, accepted or not.
    pub linear_solves: usize,
    pub initial_chi2: f64,
    pub final_chi2: f64,
    pub termination: Termination,
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
