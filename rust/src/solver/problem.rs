//! What every algorithm shares: the linearized problem (factors, pattern, kernels), its
//! bookkeeping (history, timers, iteration count), the convergence tests, and the watchdog.
//!
//! Convergence is claimed only by a test that means what it says. The function and step tests
//! are applied to undamped steps only (Gauss-Newton, dogleg's Gauss-Newton step, or an LM step
//! whose damping term is at most half of its predicted decrease): a damped step can be short and
//! gain little far from any minimum, which is not convergence but a trust region at work.

use std::time::Instant;

use super::linear_solve::{ChordStep, ChordWork};
use super::params::SolverParams;
use super::pattern::SparsityPattern;
use super::report::{IterationRecord, Termination};
use super::robust::Kernel;
use crate::error::Result;
use crate::factors::Factor;
use crate::values::Values;

/// An LM step counts as undamped when the damping term `lambda d^T D d` is at most this share
/// of `-g.d = d^T H d + lambda d^T D d`.
pub(super) const UNDAMPED_SHARE: f64 = 0.5;

/// The forcing term of the chord step's inexact-Newton test, `|A d + g| <= eta |g|` (Ceres'
/// default `eta` for its truncated Newton solvers is 0.1).
pub(super) const CHORD_ETA: f64 = 0.1;

/// At most this many conjugate-gradient iterations on the held factor (each a triangular solve
/// pair and a product with H, a small fraction of a factorization) before factorizing anew.
pub(super) const CHORD_MAX_ITERATIONS: usize = 4;

/// How an algorithm ended: the reason, what it says, and the final cost.
pub(super) struct Outcome {
    pub termination: Termination,
    pub detail: String,
    pub cost: f64,
}

impl Outcome {
    pub fn new(termination: Termination, detail: impl Into<String>, cost: f64) -> Self {
        Self {
            termination,
            detail: detail.into(),
            cost,
        }
    }
}

pub(super) struct Problem<'a> {
    pub factors: &'a [Box<dyn Factor>],
    pub pattern: &'a mut SparsityPattern,
    /// Per factor, its robust kernel; empty when none has one.
    pub kernels: Vec<Option<Kernel>>,
    pub params: &'a SolverParams,
    pub start: Instant,
    pub time_linearize: f64,
    pub time_factorize: f64,
    pub linear_solves: usize,
    pub iterations: usize,
    pub history: Vec<IterationRecord>,
    /// Whether the pattern holds a numeric factor from a successful solve (any linearization).
    factor_held: bool,
    /// Steps taken on a previous factor (`chord`) instead of a new factorization.
    pub chord_steps: usize,
    chord_work: ChordWork,
}

impl<'a> Problem<'a> {
    pub fn new(
        factors: &'a [Box<dyn Factor>],
        pattern: &'a mut SparsityPattern,
        params: &'a SolverParams,
        start: Instant,
    ) -> Self {
        Self {
            factors,
            pattern,
            kernels: params.robust.per_factor(factors),
            params,
            start,
            time_linearize: 0.0,
            time_factorize: 0.0,
            linear_solves: 0,
            iterations: 0,
            history: Vec::new(),
            factor_held: false,
            chord_steps: 0,
            chord_work: ChordWork::default(),
        }
    }

    pub fn dim(&self) -> usize {
        self.pattern.dim()
    }

    /// Builds `H`, `g` at `values`; returns the cost there.
    pub fn linearize(&mut self, values: &Values) -> f64 {
        let t = Instant::now();
        let c = self.pattern.linearize(self.factors, values, &self.kernels);
        self.time_linearize += t.elapsed().as_secs_f64();
        c
    }

    /// Builds `H`, `g` at the trial point `values` into the look-ahead pair (see
    /// `SparsityPattern::linearize_ahead`); returns the cost there.
    fn linearize_ahead(&mut self, values: &Values) -> f64 {
        let t = Instant::now();
        let c = self
            .pattern
            .linearize_ahead(self.factors, values, &self.kernels);
        self.time_linearize += t.elapsed().as_secs_f64();
        c
    }

    /// The cost at `values` (no linearization).
    pub fn cost(&mut self, values: &Values) -> f64 {
        let t = Instant::now();
        let c = SparsityPattern::cost(self.factors, values, &self.kernels);
        self.time_linearize += t.elapsed().as_secs_f64();
        c
    }

    /// Solves `(H + lambda D) delta = -g`; false when not positive definite or not finite.
    pub fn solve(&mut self, lambda: f64, delta: &mut [f64]) -> Result<bool> {
        let t = Instant::now();
        let ok = self
            .pattern
            .solve_damped(lambda, self.params.diagonal_damping, delta)?;
        self.time_factorize += t.elapsed().as_secs_f64();
        self.linear_solves += 1;
        self.factor_held = ok;
        Ok(ok)
    }

    /// The chord step on the factor held from an earlier solve (see
    /// `SparsityPattern::chord_step`): `None` when there is none or the step is not an inexact
    /// Newton step with forcing term `CHORD_ETA`.
    pub fn chord(&mut self, lambda: f64, delta: &mut [f64]) -> Option<ChordStep> {
        if !self.factor_held {
            return None;
        }
        let t = Instant::now();
        let step = self.pattern.chord_step(
            lambda,
            self.params.diagonal_damping,
            CHORD_ETA,
            CHORD_MAX_ITERATIONS,
            delta,
            &mut self.chord_work,
        );
        self.time_factorize += t.elapsed().as_secs_f64();
        step
    }

    /// Evaluates the step `delta` from `values` into `trial`: the trial cost and, when it
    /// decreases the cost `cost`, the gain ratio against the model's `predicted` decrease. With
    /// `ahead` the trial is linearized as well (`SparsityPattern::linearize_ahead`), so that an
    /// accepted step needs no linearization of its own (`accept_ahead`).
    pub fn try_step(
        &mut self,
        values: &Values,
        delta: &[f64],
        trial: &mut Values,
        cost: f64,
        predicted: f64,
        ahead: bool,
    ) -> (f64, Option<f64>) {
        trial.clone_from(values);
        self.pattern.retract(trial, delta);
        let new_cost = if ahead {
            self.linearize_ahead(trial)
        } else {
            self.cost(trial)
        };
        let actual = cost - new_cost;
        if new_cost.is_finite() && actual > 0.0 {
            let rho = if predicted > 0.0 {
                actual / predicted
            } else {
                1.0
            };
            (new_cost, Some(rho))
        } else {
            (new_cost, None)
        }
    }

    pub fn max_gradient(&self) -> f64 {
        self.pattern.g.iter().fold(0.0f64, |m, v| m.max(v.abs()))
    }

    pub fn gradient_dot(&self, d: &[f64]) -> f64 {
        d.iter().zip(&self.pattern.g).map(|(a, b)| a * b).sum()
    }

    pub fn record(&mut self, chi2: f64, lambda: f64, step_norm: f64, accepted: bool) {
        self.history.push(IterationRecord {
            iteration: self.iterations + usize::from(!accepted),
            chi2,
            lambda,
            step_norm,
            accepted,
            elapsed: self.start.elapsed().as_secs_f64(),
        });
    }

    /// The tests that hold before any step: cost below the error tolerance, vanishing gradient.
    pub fn converged_at_point(&self, cost: f64) -> Option<Outcome> {
        let p = self.params;
        if cost <= p.error_tolerance {
            return Some(Outcome::new(
                Termination::FunctionTolerance,
                format!(
                    "cost {cost:.6e} <= error tolerance {:.1e}",
                    p.error_tolerance
                ),
                cost,
            ));
        }
        let g = self.max_gradient();
        if g <= p.gradient_tolerance {
            return Some(Outcome::new(
                Termination::GradientTolerance,
                format!(
                    "max |gradient| {g:.3e} <= gradient tolerance {:.1e}",
                    p.gradient_tolerance
                ),
                cost,
            ));
        }
        None
    }

    /// The function and step tests after an accepted undamped step from cost `old` to `new`.
    pub fn converged_after_step(
        &self,
        old: f64,
        new: f64,
        step_norm: f64,
        values: &Values,
    ) -> Option<Outcome> {
        // (A cost below the error tolerance is caught by `converged_at_point` next.)
        let p = self.params;
        let dec = (old - new).abs();
        if dec < p.absolute_tolerance {
            return Some(Outcome::new(
                Termination::FunctionTolerance,
                format!(
                    "absolute decrease {dec:.3e} < absolute tolerance {:.1e}",
                    p.absolute_tolerance
                ),
                new,
            ));
        }
        if old > 0.0 && dec / old < p.relative_tolerance {
            return Some(Outcome::new(
                Termination::FunctionTolerance,
                format!(
                    "relative decrease {:.3e} < relative tolerance {:.1e}",
                    dec / old,
                    p.relative_tolerance
                ),
                new,
            ));
        }
        let scale = pose_scale(values);
        if step_norm <= p.step_tolerance * (scale + p.step_tolerance) {
            return Some(Outcome::new(
                Termination::StepTolerance,
                format!(
                    "|step| {step_norm:.3e} <= step tolerance {:.1e} x |x| {scale:.3e}",
                    p.step_tolerance
                ),
                new,
            ));
        }
        None
    }

    /// After a rejected undamped step: when the undamped model itself predicts a decrease below
    /// the function tolerance (or below what rounding in the cost can resolve), there is nothing
    /// left to gain that the tolerance could see; the trial's failure is rounding noise.
    pub fn converged_by_model(&self, predicted: f64, cost: f64) -> Option<Outcome> {
        let p = self.params;
        let limit = (16.0 * f64::EPSILON * cost)
            .max(p.absolute_tolerance)
            .max(p.relative_tolerance * cost);
        (predicted <= limit).then(|| {
            Outcome::new(
                Termination::FunctionTolerance,
                format!(
                    "the undamped model predicts a decrease of {predicted:.3e} from cost {cost:.6e}, \
                     below the function tolerance"
                ),
                cost,
            )
        })
    }

    /// The watchdog (Chamberlain, Powell, Lemarechal and Pedersen, 1982): a rejected
    /// near-Gauss-Newton step does not prove that the Gauss-Newton path leads nowhere. Far from
    /// the solution (headings off by radians) the first Gauss-Newton step fixes the rotations
    /// while the translations, linearized about the wrong ones, overshoot: the cost rises
    /// enormously, a trust region shrinks to crawling steps, yet the next Gauss-Newton step lands
    /// near the minimum. From `values` (the current estimate, whose linearization the pattern
    /// holds) up to `watchdog_steps` pure Gauss-Newton steps are taken (LM's smallest damping if
    /// H is singular); the first point whose cost is below `target` (the current cost) is
    /// returned with its cost, and its steps count as iterations. Otherwise nothing changes but
    /// the pattern, which callers relinearize.
    pub fn watchdog(&mut self, values: &Values, target: f64) -> Result<Option<(Values, f64)>> {
        let steps = self.params.watchdog_steps;
        let mut x = values.clone();
        let mut delta = vec![0.0; self.dim()];
        let mut trail = Vec::new();
        let mut found = None;
        for k in 0..steps {
            if k > 0 && !self.linearize(&x).is_finite() {
                break;
            }
            let mut lambda = 0.0;
            if !self.solve(0.0, &mut delta)? {
                lambda = self.params.lambda_initial;
                if !self.solve(lambda, &mut delta)? {
                    break;
                }
            }
            self.pattern.retract(&mut x, &delta);
            let c = self.cost(&x);
            trail.push((c, lambda, norm(&delta)));
            if !c.is_finite() {
                break;
            }
            if c < target {
                found = Some(c);
                break;
            }
        }
        let accepted = found.is_some();
        for (c, lambda, s) in trail {
            if accepted {
                self.iterations += 1;
            }
            self.record(c, lambda, s, accepted);
        }
        Ok(found.map(|c| (x, c)))
    }
}

/// `|x|` over the poses, the scale of the step tolerance.
pub(super) fn pose_scale(values: &Values) -> f64 {
    values
        .poses
        .iter()
        .map(|q| q.x * q.x + q.y * q.y + q.theta * q.theta)
        .sum::<f64>()
        .sqrt()
}

pub(super) fn norm(v: &[f64]) -> f64 {
    v.iter().map(|x| x * x).sum::<f64>().sqrt()
}
