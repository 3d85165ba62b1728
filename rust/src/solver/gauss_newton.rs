//! Gauss-Newton: the undamped step, always taken. Fast where the linearization is good; it can
//! diverge far from the solution (then `non_finite`) and has no remedy for rank deficiency
//! (then `stalled`).

use super::problem::{norm, Outcome, Problem};
use super::report::Termination;
use crate::error::Result;
use crate::values::Values;

pub(super) fn run(p: &mut Problem<'_>, values: &mut Values, mut cost: f64) -> Result<Outcome> {
    let mut delta = vec![0.0; p.dim()];
    loop {
        if let Some(done) = p.converged_at_point(cost) {
            return Ok(done);
        }
        if p.iterations >= p.params.max_iterations {
            return Ok(max_iterations(p, cost));
        }
        if !p.solve(0.0, &mut delta)? {
            return Ok(Outcome::new(
                Termination::Stalled,
                format!(
                    "the normal equations are not positive definite at iteration {}; \
                     use method 'lm' or 'dogleg', or check that every pose is constrained",
                    p.iterations + 1
                ),
                cost,
            ));
        }
        let step_norm = norm(&delta);
        let mut next = values.clone();
        p.pattern.retract(&mut next, &delta);
        let new_cost = p.linearize(&next);
        if !new_cost.is_finite() {
            p.record(new_cost, 0.0, step_norm, false);
            return Ok(Outcome::new(
                Termination::NonFinite,
                format!(
                    "Gauss-Newton diverged at iteration {} (non-finite cost); the last finite \
                     estimate is returned; use method 'lm', or --init chordal",
                    p.iterations + 1
                ),
                cost,
            ));
        }
        *values = next;
        p.iterations += 1;
        p.record(new_cost, 0.0, step_norm, true);
        let old = cost;
        cost = new_cost;
        if let Some(done) = p.converged_after_step(old, new_cost, step_norm, values) {
            return Ok(done);
        }
    }
}

pub(super) fn max_iterations(p: &Problem<'_>, cost: f64) -> Outcome {
    Outcome::new(
        Termination::MaxIterations,
        format!(
            "{} iterations without meeting a tolerance; raise max_iterations or try another --init",
            p.params.max_iterations
        ),
        cost,
    )
}
