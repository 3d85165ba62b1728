//! The rows of wide factors (`Factor::is_wide`) as a low-rank term of the normal equations,
//! `H = H_s + U U^T` with one column `u_k` of U per wide residual row, solved with the Woodbury
//! identity on top of the sparse Cholesky factor `L L^T = A = H_s + mu D`:
//!
//! `(A + U U^T)^-1 = L^-T (I + W W^T)^-1 L^-1 = L^-T (I - W S^-1 W^T) L^-1`,
//! `W = L^-1 U` (n x r), `S = I + W^T W` (r x r).
//!
//! A relation over the centroids of hundreds of poses then costs r sparse forward solves per
//! factorization and O(n r) per solve, instead of a dense block (and its fill) in the factor.
//! The columns of U are sparse, so each forward solve for W visits only the supernodes its
//! right-hand side reaches (on Freiburg 079 with 16 corrections, 5% of the factor per relation).

use rayon::prelude::*;

use super::factor::Cholesky;
use crate::error::{HitlError, Result};

/// Marks "not wide" in `LowRank::of_factor`.
const NOT_WIDE: usize = usize::MAX;
/// Refinement stops at this componentwise backward error (rounding level: refined solves end
/// at 2..4 eps, and a step from there gains nothing), or after this many steps.
const REFINE_BACKWARD_ERROR: f64 = 16.0 * f64::EPSILON;
const MAX_REFINEMENTS: usize = 4;

/// One wide factor's share of U: its free variables' scalar indices `idx[idx..idx + len]` and
/// its `rows x len` whitened Jacobian (row-major) at `val[val..]`.
#[derive(Clone, Copy, Debug)]
struct WideFactor {
    idx: usize,
    len: usize,
    rows: usize,
    val: usize,
}

/// U, its diagonal contribution, and the Woodbury workspace. Empty (rank 0, nothing allocated)
/// when no factor is wide, so pure pose graphs pay nothing for it.
#[derive(Default)]
pub(super) struct LowRank {
    /// Per factor, its index in `factors`, or NOT_WIDE; empty when no factor is wide.
    of_factor: Vec<usize>,
    factors: Vec<WideFactor>,
    idx: Vec<usize>,
    val: Vec<f64>,
    /// r: the number of wide rows, the rank of the update.
    rank: usize,
    /// diag(U U^T): Marquardt damping scales by the diagonal of the FULL H.
    diag: Vec<f64>,
    /// n x r, column-major: `W = L^-1 U`.
    w: Vec<f64>,
    /// Per wide factor, the row ranges where its columns of W can be non-zero.
    reach: Vec<Vec<(usize, usize)>>,
    /// r x r, column-major: `S = I + W^T W`, then its lower Cholesky factor.
    cap: Vec<f64>,
    /// Length r: `W^T L^-1 b`, then `S^-1 W^T L^-1 b`.
    t: Vec<f64>,
    /// Length n each: the right-hand side, and for refinement the residual, `|H| |x|` and the
    /// correction.
    b: Vec<f64>,
    res: Vec<f64>,
    mag: Vec<f64>,
    corr: Vec<f64>,
}

impl LowRank {
    /// Registers factor `fi` (of `num_factors`) as wide, with `rows` residual rows over the
    /// scalar unknowns `idx` (solver order).
    pub fn push(
        &mut self,
        fi: usize,
        num_factors: usize,
        idx: impl Iterator<Item = usize>,
        rows: usize,
    ) {
        if self.of_factor.is_empty() {
            self.of_factor = vec![NOT_WIDE; num_factors];
        }
        let start = self.idx.len();
        self.idx.extend(idx);
        let len = self.idx.len() - start;
        self.of_factor[fi] = self.factors.len();
        self.factors.push(WideFactor {
            idx: start,
            len,
            rows,
            val: self.val.len(),
        });
        self.val.resize(self.val.len() + rows * len, 0.0);
        self.rank += rows;
    }

    /// Sizes the workspace for `n` unknowns once every wide factor is registered.
    pub fn allocate(&mut self, n: usize) {
        let r = self.rank;
        if r > 0 {
            self.diag = vec![0.0; n];
            self.w = vec![0.0; n * r];
            self.reach = vec![Vec::new(); self.factors.len()];
            self.cap = vec![0.0; r * r];
            self.t = vec![0.0; r];
            self.b = vec![0.0; n];
            self.res = vec![0.0; n];
            self.mag = vec![0.0; n];
            self.corr = vec![0.0; n];
        }
    }

    pub fn rank(&self) -> usize {
        self.rank
    }

    /// The wide index of factor `fi`, if it is wide.
    #[inline]
    pub fn wide_index(&self, fi: usize) -> Option<usize> {
        match self.of_factor.get(fi) {
            Some(&w) if w != NOT_WIDE => Some(w),
            _ => None,
        }
    }

    /// Entry (row, col) of wide factor `wi`'s Jacobian block, to be filled by `linearize`.
    #[inline]
    pub fn entry_mut(&mut self, wi: usize, row: usize, col: usize) -> &mut f64 {
        let f = self.factors[wi];
        &mut self.val[f.val + row * f.len + col]
    }

    /// Recomputes diag(U U^T) after `linearize` filled U.
    pub fn update_diagonal(&mut self) {
        if self.rank == 0 {
            return;
        }
        self.diag.fill(0.0);
        for (ix, v) in rows(&self.factors, &self.idx, &self.val) {
            for (&i, &u) in ix.iter().zip(v) {
                self.diag[i] += u * u;
            }
        }
    }

    /// Diagonal entry k of U U^T.
    #[inline]
    pub fn diagonal(&self, k: usize) -> f64 {
        if self.rank == 0 {
            0.0
        } else {
            self.diag[k]
        }
    }

    /// How many rows the forward solves for W visited, summed over the wide factors.
    #[cfg(test)]
    pub fn reached_rows(&self) -> usize {
        self.reach.iter().flatten().map(|(a, b)| b - a).sum()
    }

    /// The rows `(indices, values)` of U^T, one per wide residual row.
    pub fn rows(&self) -> impl Iterator<Item = (&[usize], &[f64])> + '_ {
        rows(&self.factors, &self.idx, &self.val)
    }

    /// With `L` the numeric factor of A: computes `W = L^-1 U`, `S = I + W^T W` and the Cholesky
    /// factor of S. `Ok(false)` when S is not numerically positive definite (nor, then,
    /// `A + U U^T`).
    pub fn prepare(&mut self, l: Cholesky<'_>) -> Result<bool> {
        if !l.layout_ok() {
            return Err(HitlError::Solver(
                "internal: the Cholesky factor does not have the expected layout".into(),
            ));
        }
        let n = l.symbolic.nrows();
        let r = self.rank;
        // Each wide factor's columns of W on their own, in parallel (the same arithmetic as one
        // after the other: the columns do not interact).
        let mut columns = Vec::with_capacity(self.factors.len());
        let mut rest = self.w.as_mut_slice();
        for f in &self.factors {
            let (w, tail) = rest.split_at_mut(f.rows * n);
            columns.push(w);
            rest = tail;
        }
        let (idx, val) = (&self.idx, &self.val);
        self.factors
            .par_iter()
            .zip(self.reach.par_iter_mut())
            .zip(columns.into_par_iter())
            .for_each_init(Vec::new, |seen, ((f, reach), w)| {
                // Only the last reach can be non-zero: clearing it is clearing W's columns.
                for col in w.chunks_mut(n) {
                    for &(a, b) in reach.iter() {
                        col[a..b].fill(0.0);
                    }
                }
                let ix = &idx[f.idx..f.idx + f.len];
                for row in 0..f.rows {
                    let v = &val[f.val + row * f.len..f.val + (row + 1) * f.len];
                    let col = &mut w[row * n..(row + 1) * n];
                    for (&i, &u) in ix.iter().zip(v) {
                        col[i] = u;
                    }
                }
                reach.clear();
                l.forward_cols(w, f.rows, Some((ix, seen)), |s0, s1| {
                    match reach.last_mut() {
                        Some(last) if last.1 == s0 => last.1 = s1,
                        _ => reach.push((s0, s1)),
                    }
                });
            });
        // S = I + W^T W: W's column k is zero outside the reach of its factor, so each entry
        // needs only the rows of one reach. Column k's entries from the diagonal down, one
        // column per task, then mirrored.
        let mut reach_of = Vec::with_capacity(r);
        for (f, reach) in self.factors.iter().zip(&self.reach) {
            reach_of.extend(std::iter::repeat_n(reach, f.rows));
        }
        let w = &self.w;
        self.cap
            .par_chunks_mut(r)
            .zip(reach_of.par_iter())
            .enumerate()
            .for_each(|(k, (col, reach))| {
                let wk = &w[k * n..(k + 1) * n];
                for (l, s) in col.iter_mut().enumerate().skip(k) {
                    *s = dot_over(reach, wk, &w[l * n..(l + 1) * n]);
                }
                col[k] += 1.0;
            });
        for k in 0..r {
            for l in k + 1..r {
                self.cap[l * r + k] = self.cap[k * r + l];
            }
        }
        Ok(dense_cholesky(&mut self.cap, r))
    }

    /// `x = (A + U U^T)^-1 b` after [`Self::prepare`]: `L^-T (I - W S^-1 W^T) L^-1 b`, one
    /// forward and one backward sparse solve around O(n r) work.
    fn apply(&mut self, l: Cholesky<'_>, b: &[f64], x: &mut [f64]) {
        let n = x.len();
        x.copy_from_slice(b);
        l.forward(x);
        let mut k = 0;
        for (f, reach) in self.factors.iter().zip(&self.reach) {
            for _ in 0..f.rows {
                self.t[k] = dot_over(reach, &self.w[k * n..(k + 1) * n], x);
                k += 1;
            }
        }
        dense_cholesky_solve(&self.cap, self.rank, &mut self.t);
        let mut k = 0;
        for (f, reach) in self.factors.iter().zip(&self.reach) {
            for _ in 0..f.rows {
                let (t, wk) = (self.t[k], &self.w[k * n..(k + 1) * n]);
                for &(a, b) in reach {
                    for (xi, wi) in x[a..b].iter_mut().zip(&wk[a..b]) {
                        *xi -= t * wi;
                    }
                }
                k += 1;
            }
        }
        l.backward(x);
    }

    /// `x <- (A + U U^T)^-1 x`, refined, after [`Self::prepare`]; `a_times(x, y, z)` writes
    /// `y = A x` and `z = |A| |x|`.
    ///
    /// K1 and K2 make S large (1e6 and more; more still where the chain to the anchor is long),
    /// and Woodbury then subtracts nearly equal vectors, losing about `log10 cond(S)` digits.
    /// Iterative refinement on the full system, with H applied as `A x + U (U^T x)`, wins them
    /// back, each step multiplying the error by about `eps cond(S)`. As LAPACK's `dporfs`, it
    /// stops when the componentwise backward error `max_i |b - H x|_i / (|H| |x| + |b|)_i` is
    /// at rounding level or no longer halves (measured: 1e-13..1e-10 after the plain solve, then
    /// one step on the campus and Freiburg maps; a 1100-pose chain needs two).
    pub fn solve_refined(
        &mut self,
        l: Cholesky<'_>,
        a_times: impl Fn(&[f64], &mut [f64], &mut [f64]),
        x: &mut [f64],
    ) {
        let mut rhs = std::mem::take(&mut self.b);
        let mut res = std::mem::take(&mut self.res);
        let mut mag = std::mem::take(&mut self.mag);
        let mut corr = std::mem::take(&mut self.corr);
        rhs.copy_from_slice(x);
        self.apply(l, &rhs, x);
        let mut last = f64::INFINITY;
        for _ in 0..MAX_REFINEMENTS {
            a_times(x, &mut res, &mut mag);
            for (ix, v) in rows(&self.factors, &self.idx, &self.val) {
                let (mut t, mut ta) = (0.0, 0.0);
                for (&i, &u) in ix.iter().zip(v) {
                    t += u * x[i];
                    ta += (u * x[i]).abs();
                }
                for (&i, &u) in ix.iter().zip(v) {
                    res[i] += t * u;
                    mag[i] += ta * u.abs();
                }
            }
            let mut berr = 0.0f64;
            for ((r, m), b) in res.iter_mut().zip(&mag).zip(&rhs) {
                *r = b - *r;
                let den = m + b.abs();
                if den > 0.0 {
                    berr = berr.max(r.abs() / den);
                } else if *r != 0.0 {
                    berr = f64::INFINITY;
                }
            }
            if !(berr > REFINE_BACKWARD_ERROR && berr <= 0.5 * last) {
                break;
            }
            last = berr;
            self.apply(l, &res, &mut corr);
            for (x, c) in x.iter_mut().zip(&corr) {
                *x += c;
            }
        }
        self.b = rhs;
        self.res = res;
        self.mag = mag;
        self.corr = corr;
    }
}

/// `sum_i a_i b_i` over the row ranges of `reach`.
fn dot_over(reach: &[(usize, usize)], a: &[f64], b: &[f64]) -> f64 {
    reach
        .iter()
        .map(|&(lo, hi)| {
            a[lo..hi]
                .iter()
                .zip(&b[lo..hi])
                .map(|(x, y)| x * y)
                .sum::<f64>()
        })
        .sum()
}

/// The rows `(indices, values)` of U^T, one per wide residual row.
fn rows<'a>(
    factors: &'a [WideFactor],
    idx: &'a [usize],
    val: &'a [f64],
) -> impl Iterator<Item = (&'a [usize], &'a [f64])> + 'a {
    factors.iter().flat_map(move |f| {
        let ix = &idx[f.idx..f.idx + f.len];
        (0..f.rows).map(move |row| {
            let start = f.val + row * f.len;
            (ix, &val[start..start + f.len])
        })
    })
}

/// In-place lower Cholesky of an r x r column-major SPD matrix; false if a pivot is not
/// positive. r is the number of wide rows (a few per correction), so O(r^3) is nothing.
fn dense_cholesky(a: &mut [f64], r: usize) -> bool {
    for j in 0..r {
        let mut d = a[j * r + j];
        for k in 0..j {
            d -= a[k * r + j] * a[k * r + j];
        }
        if !(d > 0.0 && d.is_finite()) {
            return false;
        }
        let d = d.sqrt();
        a[j * r + j] = d;
        for i in j + 1..r {
            let mut s = a[j * r + i];
            for k in 0..j {
                s -= a[k * r + i] * a[k * r + j];
            }
            a[j * r + i] = s / d;
        }
    }
    true
}

/// Solves `L L^T x = b` in place with the factor of [`dense_cholesky`] (lower triangle used).
fn dense_cholesky_solve(l: &[f64], r: usize, b: &mut [f64]) {
    for i in 0..r {
        let mut s = b[i];
        for k in 0..i {
            s -= l[k * r + i] * b[k];
        }
        b[i] = s / l[i * r + i];
    }
    for i in (0..r).rev() {
        let mut s = b[i];
        for k in i + 1..r {
            s -= l[i * r + k] * b[k];
        }
        b[i] = s / l[i * r + i];
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn dense_cholesky_solves_and_rejects_indefinite() {
        // A = M M^T + I for a fixed M.
        let r = 4;
        let m = [
            1.0, 2.0, 0.5, -1.0, 0.3, 1.5, 2.0, 0.0, -0.7, 1.1, 0.4, 2.2, 0.9, -0.2, 1.3, 0.6,
        ];
        let mut a = vec![0.0; r * r];
        for i in 0..r {
            for j in 0..r {
                a[j * r + i] = (0..r).map(|k| m[k * r + i] * m[k * r + j]).sum::<f64>()
                    + if i == j { 1.0 } else { 0.0 };
            }
        }
        let x = [1.0, -2.0, 3.0, 0.5];
        let mut b: Vec<f64> = (0..r)
            .map(|i| (0..r).map(|j| a[j * r + i] * x[j]).sum())
            .collect();
        let mut l = a.clone();
        assert!(dense_cholesky(&mut l, r));
        dense_cholesky_solve(&l, r, &mut b);
        for (got, want) in b.iter().zip(x) {
            assert!((got - want).abs() < 1e-12);
        }
        let mut indefinite = vec![1.0, 2.0, 2.0, 1.0];
        assert!(!dense_cholesky(&mut indefinite, 2));
    }
}
