//! The solver's entry point: validates, sets up the problem on the graph's cached pattern,
//! runs the chosen algorithm and reports.

use std::time::Instant;

use super::params::{Method, SolverParams};
use super::pattern::SparsityPattern;
use super::problem::Problem;
use super::report::SolveReport;
use super::{dogleg, gauss_newton, levenberg_marquardt};
use crate::error::{HitlError, Result};
use crate::graph::FactorGraph;
use crate::values::Values;

/// Minimizes the graph's cost (chi2, or the robust cost with `params.robust`) starting from
/// `values` (updated in place).
pub fn optimize(
    graph: &mut FactorGraph,
    values: &mut Values,
    params: &SolverParams,
) -> Result<SolveReport> {
    params.validate()?;
    graph.check_values(values)?;
    let start = Instant::now();
    let analyses_before = graph.analyses();
    graph.pattern()?;
    let symbolic_computed = graph.analyses() != analyses_before;
    let time_symbolic = start.elapsed().as_secs_f64();
    let (factors, pattern) = graph.parts()?;
    let mut p = Problem::new(factors, pattern, params, start);

    let initial_cost = p.linearize(values);
    if !initial_cost.is_finite() {
        return Err(HitlError::Input(
            "the initial cost is not finite; check the initial guess and measurements".into(),
        ));
    }
    let plain = |p: &Problem<'_>, v: &Values, cost: f64| {
        if p.kernels.is_empty() {
            cost
        } else {
            SparsityPattern::cost(p.factors, v, &[])
        }
    };
    let initial_chi2 = plain(&p, values, initial_cost);
    let outcome = match params.method {
        Method::GaussNewton => gauss_newton::run(&mut p, values, initial_cost)?,
        Method::LevenbergMarquardt => levenberg_marquardt::run(&mut p, values, initial_cost)?,
        Method::Dogleg => dogleg::run(&mut p, values, initial_cost)?,
    };
    let final_chi2 = plain(&p, values, outcome.cost);
    let weights = if p.kernels.is_empty() {
        vec![1.0; p.factors.len()]
    } else {
        p.factors
            .iter()
            .zip(&p.kernels)
            .map(|(f, k)| k.map_or(1.0, |k| k.weight(f.chi2(values))))
            .collect()
    };
    let (nnz_hessian, nnz_factor) = p.pattern.nnz();
    Ok(SolveReport {
        iterations: p.iterations,
        linear_solves: p.linear_solves,
        chord_steps: p.chord_steps,
        initial_cost,
        final_cost: outcome.cost,
        initial_chi2,
        final_chi2,
        termination: outcome.termination,
        termination_detail: outcome.detail,
        weights,
        time: start.elapsed().as_secs_f64(),
        time_symbolic,
        time_linearize: p.time_linearize,
        time_factorize: p.time_factorize,
        symbolic_computed,
        nnz_hessian,
        nnz_factor,
        history: p.history,
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::factors::{BetweenFactor, Factor, FactorClass};
    use crate::se2::Pose2;
    use crate::solver::{Kernel, RobustKernels, Termination};
    use crate::values::Key;
    use rand::{Rng, SeedableRng};

    const INFO: [[f64; 3]; 3] = [[100.0, 0.0, 0.0], [0.0, 100.0, 0.0], [0.0, 0.0, 400.0]];

    /// A noisy loop of `n` poses around a circle with a few chords; returns graph and start.
    fn loop_graph(n: usize, seed: u64, jitter: f64) -> (FactorGraph, Values) {
        let mut rng = rand::rngs::StdRng::seed_from_u64(seed);
        let truth: Vec<Pose2> = (0..n)
            .map(|k| {
                let a = 2.0 * std::f64::consts::PI * k as f64 / n as f64;
                Pose2::new(
                    5.0 * a.cos(),
                    5.0 * a.sin(),
                    a + std::f64::consts::FRAC_PI_2,
                )
            })
            .collect();
        let mut edges = Vec::new();
        for k in 0..n {
            edges.push((k, (k + 1) % n));
        }
        for k in (0..n).step_by(5) {
            edges.push((k, (k + n / 2) % n));
        }
        let z: Vec<[f64; 3]> = edges
            .iter()
            .map(|&(i, j)| {
                let m = truth[i].between(truth[j]);
                [
                    m.x + rng.random_range(-0.02..0.02),
                    m.y + rng.random_range(-0.02..0.02),
                    m.theta + rng.random_range(-0.01..0.01),
                ]
            })
            .collect();
        let g = FactorGraph::from_edges(n, &edges, &z, &vec![INFO; edges.len()], 0).unwrap();
        let start: Vec<Pose2> = truth
            .iter()
            .enumerate()
            .map(|(k, p)| {
                if k == 0 || jitter == 0.0 {
                    *p
                } else {
                    Pose2::new(
                        p.x + rng.random_range(-jitter..jitter),
                        p.y + rng.random_range(-jitter..jitter),
                        p.theta + rng.random_range(-jitter..jitter) * 0.2,
                    )
                }
            })
            .collect();
        (g, Values::from_poses(start))
    }

    fn solve(g: &mut FactorGraph, v: &Values, params: SolverParams) -> (Values, SolveReport) {
        let mut v = v.clone();
        let r = optimize(g, &mut v, &params).unwrap();
        (v, r)
    }

    fn tight(method: Method) -> SolverParams {
        SolverParams {
            method,
            relative_tolerance: 1e-14,
            absolute_tolerance: 1e-14,
            ..SolverParams::default()
        }
    }

    /// Final chi2 equal to the reference's within 1e-9 relative.
    fn assert_same_minimum(r: &SolveReport, reference: &SolveReport, what: &str) {
        let rel = (r.final_chi2 - reference.final_chi2).abs() / reference.final_chi2;
        assert!(
            rel < 1e-9,
            "{what}: {} vs {}",
            r.final_chi2,
            reference.final_chi2
        );
    }

    #[test]
    fn gauss_newton_lm_and_dogleg_reach_the_same_minimum() {
        for seed in 0..4 {
            let (mut g, start) = loop_graph(40, seed, 0.3);
            let (_, gn) = solve(&mut g, &start, tight(Method::GaussNewton));
            for m in [Method::LevenbergMarquardt, Method::Dogleg] {
                let (_, r) = solve(&mut g, &start, tight(m));
                assert!(r.termination.converged(), "{m:?}: {}", r.termination_detail);
                assert_same_minimum(&r, &gn, &format!("{m:?} seed {seed}"));
            }
        }
    }

    /// Near the minimum Levenberg-Marquardt takes steps on the held factor (the chord step):
    /// fewer factorizations than iterations, and the same minimum as Gauss-Newton.
    #[test]
    fn lm_saves_factorizations_near_the_minimum_and_reaches_the_same_minimum() {
        let mut saved = 0;
        for seed in 0..6 {
            let (mut g, start) = loop_graph(200, seed, 0.05);
            let (_, gn) = solve(&mut g, &start, tight(Method::GaussNewton));
            let (_, lm) = solve(&mut g, &start, tight(Method::LevenbergMarquardt));
            assert!(lm.termination.converged(), "{}", lm.termination_detail);
            assert_same_minimum(&lm, &gn, &format!("seed {seed}"));
            assert_eq!(lm.linear_solves + lm.chord_steps, lm.history.len());
            saved += lm.chord_steps;
        }
        assert!(saved > 0, "no chord step was taken on any seed");
    }

    #[test]
    fn dogleg_records_its_radius_and_never_accepts_an_increase() {
        let (mut g, start) = loop_graph(60, 9, 1.0);
        let (_, r) = solve(&mut g, &start, tight(Method::Dogleg));
        let mut cost = r.initial_cost;
        for rec in r.history.iter().filter(|h| h.accepted) {
            assert!(rec.chi2 < cost, "accepted step increased the cost");
            assert!(rec.lambda > 0.0);
            cost = rec.chi2;
        }
    }

    #[test]
    fn hessian_quadratic_matches_the_assembled_matrix() {
        let (mut g, start) = loop_graph(30, 2, 0.1);
        let (factors, pattern) = g.parts().unwrap();
        pattern.linearize(factors, &start, &[]);
        let n = pattern.dim();
        let (rows, cols, vals, _, _) = pattern.upper_triplets_natural();
        // Same quadratic form in either order, so test with vectors in natural order mapped
        // through the offsets: simplest is a vector of ones (order-free) and a one-hot one.
        let ones = vec![1.0; n];
        let dense: f64 = rows
            .iter()
            .zip(&cols)
            .zip(&vals)
            .map(|((r, c), v)| if r == c { *v } else { 2.0 * v })
            .sum();
        let q = pattern.hessian_quadratic(&ones);
        assert!((q - dense).abs() <= 1e-9 * dense.abs());
    }

    #[test]
    fn robust_weights_scale_rows_by_the_kernel() {
        // One edge with a residual of chi2 s: H and g scale by rho'(s), the cost is rho(s).
        let z = Pose2::new(1.0, 0.0, 0.0);
        let f = BetweenFactor::new(0, 2, z, &INFO).unwrap();
        assert_eq!(f.class(), FactorClass::LoopClosure);
        let mut g = FactorGraph::new(3, Some(0)).unwrap();
        g.add_between(f).unwrap();
        g.add_between(BetweenFactor::new(0, 1, z, &INFO).unwrap())
            .unwrap();
        g.add_between(BetweenFactor::new(1, 2, z, &INFO).unwrap())
            .unwrap();
        let v = Values::from_poses(vec![
            Pose2::new(0.0, 0.0, 0.0),
            Pose2::new(1.0, 0.1, 0.0),
            Pose2::new(2.3, 0.0, 0.05),
        ]);
        let kernel = Kernel::Cauchy(0.7);
        let kernels = [Some(kernel), None, None];
        let (factors, pattern) = g.parts().unwrap();
        let plain_cost = pattern.linearize(factors, &v, &[]);
        let g0 = pattern.g.clone();
        let ones = vec![1.0; pattern.dim()];
        let q0 = pattern.hessian_quadratic(&ones);
        let cost = pattern.linearize(factors, &v, &kernels);
        let s = factors[0].chi2(&v);
        let expected = plain_cost - s + kernel.rho(s);
        assert!((cost - expected).abs() < 1e-12 * expected);
        let cost_only = SparsityPattern::cost(factors, &v, &kernels);
        assert!((cost_only - cost).abs() < 1e-12 * cost);
        // The robust edge's share of H (PSD) is scaled down by rho'(s) < 1, so the quadratic
        // form shrinks, and the gradient changes.
        assert!(kernel.weight(s) < 1.0);
        assert!(pattern.hessian_quadratic(&ones) < q0);
        assert!(pattern.g.iter().zip(&g0).any(|(a, b)| (a - b).abs() > 1e-9));
    }

    #[test]
    fn a_faulty_odometry_edge_is_isolated_by_a_kernel_on_odometry() {
        // A loop of 40 poses with chords; one odometry edge claims an extra 20-degree turn.
        let (g0, start) = loop_graph(40, 1, 0.0);
        let mut edges = Vec::new();
        let mut z = Vec::new();
        for f in g0.factors() {
            let b = f.as_between().unwrap();
            edges.push(b.indices());
            let m = b.measured();
            z.push([m.x, m.y, m.theta]);
        }
        z[7][2] += 20f64.to_radians();
        let mut g = FactorGraph::from_edges(40, &edges, &z, &vec![INFO; edges.len()], 0).unwrap();
        let params = SolverParams {
            robust: RobustKernels::none().with(FactorClass::Odometry, Kernel::Cauchy(1.0)),
            max_iterations: 300,
            ..SolverParams::default()
        };
        let (_, r) = solve(&mut g, &start, params);
        assert!(r.termination.converged(), "{}", r.termination_detail);
        assert!(r.weights[7] < 0.05, "faulty edge weight {}", r.weights[7]);
        let others: Vec<f64> = r
            .weights
            .iter()
            .copied()
            .enumerate()
            .filter(|(k, _)| *k != 7)
            .map(|(_, w)| w)
            .collect();
        assert!(others.iter().all(|&w| w > 0.3), "{others:?}");
    }

    /// A factor whose residual is NaN once pose 1 moves far from the origin: Gauss-Newton must
    /// end `non_finite` with the last finite estimate, LM must treat it as a rejected step.
    #[derive(Debug)]
    struct Cliff {
        keys: [Key; 1],
    }

    impl Factor for Cliff {
        fn keys(&self) -> &[Key] {
            &self.keys
        }
        fn residual_dim(&self) -> usize {
            1
        }
        fn residual(&self, values: &Values, r: &mut [f64]) {
            let x = values.poses[1].x;
            r[0] = if x.abs() > 2.0 { f64::NAN } else { x - 10.0 };
        }
        fn linearize(&self, values: &Values, r: &mut [f64], jac: &mut [f64]) {
            self.residual(values, r);
            let (c, s) = values.poses[1].cos_sin();
            // d x / d delta for x (+) delta = x * Exp(delta): (c, -s, 0).
            jac[..3].copy_from_slice(&[c, -s, 0.0]);
        }
    }

    #[test]
    fn divergence_is_reported_not_hidden() {
        let mut g = FactorGraph::new(2, Some(0)).unwrap();
        let z = Pose2::new(0.0, 0.0, 0.0);
        let weak = [[1e-3, 0.0, 0.0], [0.0, 1e-3, 0.0], [0.0, 0.0, 1e-3]];
        g.add_between(BetweenFactor::new(0, 1, z, &weak).unwrap())
            .unwrap();
        g.add_factor(Box::new(Cliff {
            keys: [Key::Pose(1)],
        }))
        .unwrap();
        let start = Values::from_poses(vec![Pose2::new(0.0, 0.0, 0.0); 2]);
        let (v, gn) = solve(
            &mut g,
            &start,
            SolverParams {
                method: Method::GaussNewton,
                ..SolverParams::default()
            },
        );
        assert_eq!(gn.termination, Termination::NonFinite);
        assert!(!gn.termination.converged());
        assert!(v.poses[1].x.is_finite() && v.poses[1].x.abs() <= 2.0);
        let (v, lm) = solve(&mut g, &start, SolverParams::default());
        assert!(v.poses[1].x.abs() <= 2.0);
        assert!(lm.final_cost <= lm.initial_cost);
        assert_ne!(lm.termination, Termination::NonFinite);
    }
}
