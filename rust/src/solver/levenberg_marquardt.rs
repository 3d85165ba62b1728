//! Levenberg-Marquardt with Nielsen's damping update (Madsen, Nielsen and Tingleff, "Methods for
//! non-linear least squares problems", 2004): after an accepted step with gain ratio rho,
//! `lambda *= max(1/3, 1 - (2 rho - 1)^3)`; after a rejected one `lambda *= nu, nu *= 2`. The
//! damping therefore cannot run away while steps succeed, and when none does even at
//! `lambda_max` the solve ends as `stalled`, never as converged.
//!
//! A watchdog (`Problem::watchdog`) guards the first rejected near-Gauss-Newton step at each
//! linearization: from a wildly wrong initial guess the Gauss-Newton path can climb before it
//! descends, and plain LM would then crawl for hundreds of iterations.

use super::gauss_newton::max_iterations;
use super::problem::{norm, Outcome, Problem, UNDAMPED_SHARE};
use super::report::Termination;
use crate::error::Result;
use crate::values::Values;

pub(super) fn run(p: &mut Problem<'_>, values: &mut Values, mut cost: f64) -> Result<Outcome> {
    let params = p.params;
    let mut delta = vec![0.0; p.dim()];
    let mut trial = values.clone();
    let mut lambda = params.lambda_initial;
    let mut nu = 2.0;
    let mut chord_ready = false;
    // A trial is linearized as it is evaluated: most steps are accepted, and the linearization
    // then replaces the separate evaluation of the cost (the last, converging step pays one
    // linearization for nothing). Not with wide factors (see `can_look_ahead`).
    let ahead = p.pattern.can_look_ahead();
    'outer: loop {
        if let Some(done) = p.converged_at_point(cost) {
            return Ok(done);
        }
        if p.iterations >= params.max_iterations {
            return Ok(max_iterations(p, cost));
        }
        let mut watchdog_used = params.watchdog_steps == 0;
        let mut try_chord = chord_ready;
        loop {
            let chord = if std::mem::take(&mut try_chord) {
                p.chord(lambda, &mut delta)
            } else {
                None
            };
            let is_chord = chord.is_some();
            let ok = is_chord || p.solve(lambda, &mut delta)?;
            let step_norm = norm(&delta);
            let mut new_cost = f64::NAN;
            let mut undamped = false;
            if ok {
                let (gd, damping, predicted) = match chord {
                    Some(c) => (c.gd, c.damping, c.predicted),
                    None => {
                        // Decrease predicted by the linear model |r + J d|^2: -2 g.d - d^T H d,
                        // which with (H + lambda D) d = -g equals -g.d + lambda d^T D d (both
                        // terms >= 0).
                        let gd = -p.gradient_dot(&delta);
                        let damping =
                            lambda * p.pattern.damping_quadratic(&delta, params.diagonal_damping);
                        (gd, damping, gd + damping)
                    }
                };
                undamped = damping <= UNDAMPED_SHARE * gd;
                // A chord step is taken near the minimum, where it is usually the last: its
                // trial is evaluated without linearizing (linearized only if the solve goes on).
                let look_ahead = ahead && !is_chord;
                let (c, gain) = p.try_step(values, &delta, &mut trial, cost, predicted, look_ahead);
                new_cost = c;
                if let Some(rho) = gain {
                    lambda *= f64::max(1.0 / 3.0, 1.0 - (2.0 * rho - 1.0).powi(3));
                    lambda = lambda.max(1e-20);
                    nu = 2.0;
                    std::mem::swap(values, &mut trial);
                    p.iterations += 1;
                    p.chord_steps += usize::from(is_chord);
                    p.record(new_cost, lambda, step_norm, true);
                    let old = cost;
                    cost = new_cost;
                    chord_ready = undamped && chord_worth_trying(old, cost, rho);
                    if undamped {
                        if let Some(done) = p.converged_after_step(old, cost, step_norm, values) {
                            return Ok(done);
                        }
                    }
                    if look_ahead {
                        p.pattern.accept_ahead();
                    } else {
                        cost = p.linearize(values);
                    }
                    continue 'outer;
                }
                if is_chord {
                    // The previous factor's step failed; take the ordinary one at this damping.
                    continue;
                }
                if undamped {
                    if let Some(done) = p.converged_by_model(predicted, cost) {
                        p.record(new_cost, lambda, step_norm, false);
                        return Ok(done);
                    }
                }
            }
            p.record(new_cost, lambda, step_norm, false);
            if ok && undamped && !watchdog_used {
                watchdog_used = true;
                chord_ready = false;
                if let Some((x, _)) = p.watchdog(values, cost)? {
                    *values = x;
                    cost = p.linearize(values);
                    continue 'outer;
                }
                cost = p.linearize(values);
            }
            lambda *= nu;
            nu *= 2.0;
            if lambda > params.lambda_max {
                return Ok(Outcome::new(
                    Termination::Stalled,
                    format!(
                        "no step decreases the cost {cost:.6e}, even at damping {:.1e}",
                        params.lambda_max
                    ),
                    cost,
                ));
            }
        }
    }
}

/// Whether the last accepted step suggests the next linearization is close enough to the one
/// the factor was computed at for the chord step to pass its test.
fn chord_worth_trying(old: f64, new: f64, rho: f64) -> bool {
    (old - new) < 0.05 * old && (rho - 1.0).abs() < 0.01
}
