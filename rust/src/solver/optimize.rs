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
