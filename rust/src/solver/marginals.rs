//! Marginal covariances of selected variables: blocks of `H^-1` at a solution, from the same
//! sparse Cholesky factorization the solver uses (one triangular solve pair per column; with
//! wide factors, a refined Woodbury solve per column, see `woodbury`).
//! In the solver's chart, so a pose's covariance is in its own body frame, as GTSAM's `Marginals`.

use crate::error::{HitlError, Result};
use crate::graph::FactorGraph;
use crate::values::{Key, Values};

/// Covariance blocks (row-major `dim x dim`) of `keys` at `values`. A fixed variable has a zero
/// covariance.
pub fn marginal_covariances(
    graph: &mut FactorGraph,
    values: &Values,
    keys: &[Key],
) -> Result<Vec<Vec<f64>>> {
    graph.check_values(values)?;
    for &k in keys {
        if !values.contains(k) {
            return Err(HitlError::Input(format!(
                "{k:?} does not exist; marginals need existing variables"
            )));
        }
    }
    let (factors, pattern) = graph.parts()?;
    pattern.linearize(factors, values, &[]);
    let n = pattern.dim();
    let mut offsets = Vec::new();
    for &k in keys {
        if let Some(o) = pattern.offset_of(k) {
            offsets.push((k, o));
        }
    }
    let total: usize = offsets.iter().map(|(k, _)| k.dim()).sum();
    let mut cols = vec![0.0; n * total];
    let mut c = 0;
    for &(k, o) in &offsets {
        for a in 0..k.dim() {
            cols[c * n + o + a] = 1.0;
            c += 1;
        }
    }
    pattern.solve_undamped_columns(&mut cols, total)?;
    let mut out = Vec::with_capacity(keys.len());
    let mut c = 0;
    let mut it = offsets.iter().peekable();
    for &k in keys {
        let d = k.dim();
        match it.peek() {
            Some(&&(kk, o)) if kk == k => {
                let mut block = vec![0.0; d * d];
                for b in 0..d {
                    for a in 0..d {
                        block[a * d + b] = cols[(c + b) * n + o + a];
                    }
                }
                // Symmetrize: the two triangles agree to rounding.
                for a in 0..d {
                    for b in 0..a {
                        let m = 0.5 * (block[a * d + b] + block[b * d + a]);
                        block[a * d + b] = m;
                        block[b * d + a] = m;
                    }
                }
                out.push(block);
                c += d;
                it.next();
            }
            _ => out.push(vec![0.0; d * d]),
        }
    }
    Ok(out)
}
