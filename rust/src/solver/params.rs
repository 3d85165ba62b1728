//! Solver settings: the algorithm, its tolerances, and the robust kernels.

use super::robust::RobustKernels;
use crate::error::{HitlError, Result};

/// Which algorithm.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Method {
    GaussNewton,
    LevenbergMarquardt,
    /// Powell's dogleg in a trust region (as GTSAM's `DoglegOptimizer` and Ceres' `DOGLEG`).
    Dogleg,
}

impl Method {
    pub fn parse(s: &str) -> Result<Self> {
        match s {
            "lm" => Ok(Method::LevenbergMarquardt),
            "gn" => Ok(Method::GaussNewton),
            "dogleg" => Ok(Method::Dogleg),
            other => Err(HitlError::Input(format!(
                "unknown method {other:?}; use \"lm\", \"gn\" or \"dogleg\""
            ))),
        }
    }

    pub fn name(self) -> &'static str {
        match self {
            Method::GaussNewton => "gn",
            Method::LevenbergMarquardt => "lm",
            Method::Dogleg => "dogleg",
        }
    }
}

/// Solver settings. Tolerances are on the cost (chi2 = `sum |r|^2`, or the robust cost), as
/// GTSAM's are on its error (chi2 / 2).
#[derive(Clone, Debug, PartialEq)]
pub struct SolverParams {
    pub method: Method,
    pub max_iterations: usize,
    /// Function tolerance: converged when an accepted (and not damping-dominated) step lowers
    /// the cost by less than this fraction of it, or by less than `absolute_tolerance`, or the
    /// cost falls below `error_tolerance`.
    pub relative_tolerance: f64,
    pub absolute_tolerance: f64,
    pub error_tolerance: f64,
    /// Gradient tolerance: converged when `max |J^T r| <= gradient_tolerance`.
    pub gradient_tolerance: f64,
    /// Step tolerance: converged when an undamped step is shorter than
    /// `step_tolerance * (|x| + step_tolerance)`.
    pub step_tolerance: f64,
    /// Initial LM damping (relative to diag(H) with `diagonal_damping`, absolute otherwise).
    pub lambda_initial: f64,
    /// LM gives up (`stalled`) when no step decreases the cost at this damping.
    pub lambda_max: f64,
    /// Damp with diag(H) (Marquardt) instead of the identity.
    pub diagonal_damping: bool,
    /// The watchdog (see `levenberg_marquardt`): how many Gauss-Newton steps LM and dogleg may
    /// look ahead from a rejected near-Gauss-Newton step (0: off).
    pub watchdog_steps: usize,
    /// Dogleg's initial trust-region radius; 0 means the length of the first Gauss-Newton step.
    pub trust_radius_initial: f64,
    /// Robust kernel per factor class.
    pub robust: RobustKernels,
}

impl Default for SolverParams {
    fn default() -> Self {
        Self {
            method: Method::LevenbergMarquardt,
            max_iterations: 100,
            relative_tolerance: 1e-6,
            absolute_tolerance: 1e-6,
            error_tolerance: 0.0,
            gradient_tolerance: 1e-12,
            step_tolerance: 1e-12,
            // As GTSAM's defaults: an almost-Gauss-Newton first step, identity damping. Marquardt's
            // diag(H) scaling took twice the iterations on M3500 (measured).
            lambda_initial: 1e-5,
            lambda_max: 1e16,
            diagonal_damping: false,
            watchdog_steps: 3,
            trust_radius_initial: 0.0,
            robust: RobustKernels::none(),
        }
    }
}

impl SolverParams {
    pub fn validate(&self) -> Result<()> {
        let finite_nonneg = |name: &str, v: f64| -> Result<()> {
            if v.is_finite() && v >= 0.0 {
                Ok(())
            } else {
                Err(HitlError::Input(format!(
                    "{name} must be a finite number >= 0, got {v}"
                )))
            }
        };
        finite_nonneg("relative_tolerance", self.relative_tolerance)?;
        finite_nonneg("absolute_tolerance", self.absolute_tolerance)?;
        finite_nonneg("error_tolerance", self.error_tolerance)?;
        finite_nonneg("gradient_tolerance", self.gradient_tolerance)?;
        finite_nonneg("step_tolerance", self.step_tolerance)?;
        finite_nonneg("trust_radius_initial", self.trust_radius_initial)?;
        if !(self.lambda_initial.is_finite() && self.lambda_initial > 0.0) {
            return Err(HitlError::Input(format!(
                "lambda_initial must be > 0, got {}",
                self.lambda_initial
            )));
        }
        if self.lambda_max.is_nan() || self.lambda_max <= self.lambda_initial {
            return Err(HitlError::Input(
                "lambda_max must exceed lambda_initial".into(),
            ));
        }
        if self.watchdog_steps > 20 {
            return Err(HitlError::Input(format!(
                "watchdog_steps must be at most 20, got {}",
                self.watchdog_steps
            )));
        }
        Ok(())
    }
}
