//! Powell's dogleg in a trust region (Madsen, Nielsen and Tingleff 2004, section 3.3; GTSAM's
//! `DoglegOptimizer`, Ceres' `DOGLEG`). One factorization per linearization: the Gauss-Newton
//! step `h_gn = -H^-1 g` and the Cauchy step `h_sd = -(g.g / g^T H g) g` are combined for each
//! radius tried, so a rejected step costs one cost evaluation, not a factorization.
//!
//! Radius update: gain ratio > 0.75 -> `max(radius, 3 |h|)`; < 0.25 -> halved (also on a
//! rejected step). The first radius is the first Gauss-Newton step's length unless given.

use super::gauss_newton::max_iterations;
use super::problem::{norm, pose_scale, Outcome, Problem};
use super::report::Termination;
use crate::error::Result;
use crate::values::Values;

#[derive(Clone, Copy, PartialEq, Eq)]
enum Kind {
    GaussNewton,
    SteepestDescent,
    Dogleg,
}

pub(super) fn run(p: &mut Problem<'_>, values: &mut Values, mut cost: f64) -> Result<Outcome> {
    let params = p.params;
    let n = p.dim();
    let mut h_gn = vec![0.0; n];
    let mut h = vec![0.0; n];
    let mut trial = values.clone();
    let mut radius = params.trust_radius_initial;
    'outer: loop {
        if let Some(done) = p.converged_at_point(cost) {
            return Ok(done);
        }
        if p.iterations >= params.max_iterations {
            return Ok(max_iterations(p, cost));
        }
        // The Gauss-Newton step; a rank-deficient H gets LM's smallest damping.
        if !p.solve(0.0, &mut h_gn)? && !p.solve(params.lambda_initial, &mut h_gn)? {
            return Ok(Outcome::new(
                Termination::Stalled,
                "the normal equations are not positive definite even with damping; \
                 check that every pose is constrained",
                cost,
            ));
        }
        let gn_norm = norm(&h_gn);
        let g = p.pattern.g.clone();
        let g_norm = norm(&g);
        let g_h_g = p.pattern.hessian_quadratic(&g);
        // Length of the Cauchy step along -g (infinite when H has no curvature along g).
        let sd_len = if g_h_g > 0.0 {
            g_norm * g_norm / g_h_g * g_norm
        } else {
            f64::INFINITY
        };
        if radius <= 0.0 {
            radius = gn_norm.max(f64::MIN_POSITIVE);
        }
        let mut watchdog_used = params.watchdog_steps == 0;
        loop {
            let kind = if gn_norm <= radius {
                h.copy_from_slice(&h_gn);
                Kind::GaussNewton
            } else if sd_len >= radius {
                let s = radius / g_norm;
                h.iter_mut().zip(&g).for_each(|(hi, gi)| *hi = -s * gi);
                Kind::SteepestDescent
            } else {
                // h = a + beta (b - a), |h| = radius, a the Cauchy step, b the GN step.
                let s = sd_len / g_norm;
                let a: Vec<f64> = g.iter().map(|gi| -s * gi).collect();
                let ba: Vec<f64> = h_gn.iter().zip(&a).map(|(b, a)| b - a).collect();
                let (aa, ab, bb) = (
                    a.iter().map(|v| v * v).sum::<f64>(),
                    a.iter().zip(&ba).map(|(x, y)| x * y).sum::<f64>(),
                    ba.iter().map(|v| v * v).sum::<f64>(),
                );
                let c = aa - radius * radius;
                let beta = if bb > 0.0 {
                    (-ab + (ab * ab - bb * c).max(0.0).sqrt()) / bb
                } else {
                    0.0
                };
                for k in 0..n {
                    h[k] = a[k] + beta * ba[k];
                }
                Kind::Dogleg
            };
            let step_norm = norm(&h);
            // Decrease predicted by |r + J h|^2: -2 g.h - h^T H h.
            let h_h_h = p.pattern.hessian_quadratic(&h);
            let predicted = -2.0 * p.gradient_dot(&h) - h_h_h;
            let (new_cost, gain) = p.try_step(values, &h, &mut trial, cost, predicted, false);
            if let Some(rho) = gain {
                if rho > 0.75 {
                    radius = radius.max(3.0 * step_norm);
                } else if rho < 0.25 {
                    radius *= 0.5;
                }
                std::mem::swap(values, &mut trial);
                p.iterations += 1;
                p.record(new_cost, radius, step_norm, true);
                let old = cost;
                cost = new_cost;
                if kind == Kind::GaussNewton {
                    if let Some(done) = p.converged_after_step(old, cost, step_norm, values) {
                        return Ok(done);
                    }
                }
                cost = p.linearize(values);
                continue 'outer;
            }
            if kind == Kind::GaussNewton {
                if let Some(done) = p.converged_by_model(predicted, cost) {
                    p.record(new_cost, radius, step_norm, false);
                    return Ok(done);
                }
            }
            p.record(new_cost, radius, step_norm, false);
            if kind == Kind::GaussNewton && !watchdog_used {
                watchdog_used = true;
                if let Some((x, _)) = p.watchdog(values, cost)? {
                    *values = x;
                    cost = p.linearize(values);
                    continue 'outer;
                }
                cost = p.linearize(values);
            }
            radius = radius.min(step_norm) * 0.5;
            let scale = pose_scale(values);
            if radius <= params.step_tolerance.max(1e-15) * (scale + 1.0) {
                return Ok(Outcome::new(
                    Termination::Stalled,
                    format!(
                        "the trust region shrank to {radius:.3e} without a step that decreases the cost {cost:.6e}"
                    ),
                    cost,
                ));
            }
        }
    }
}
