//! The linear solves on an assembled system: the numeric Cholesky factorization on the pattern's
//! cached symbolic analysis, the damped solve `(H + mu D) delta = -g` of every iteration, and
//! the undamped solves for columns of `H^-1` (marginals). With wide factors the sparse factor is
//! of `A = H_s (+ mu D)` alone, and the low-rank term `U U^T` joins every solve by the Woodbury
//! identity (`woodbury`), refined against `A`.

use faer::dyn_stack::{MemBuffer, MemStack};
use faer::linalg::cholesky::llt::factor::LltRegularization;
use faer::sparse::linalg::cholesky::{LltRef, SymbolicCholesky, SymbolicCholeskyRaw};
use faer::sparse::{SparseColMatRef, SymbolicSparseColMatRef};
use faer::{Conj, MatMut, Par, Side, Spec};

use super::factor::Cholesky;
use super::pattern::SparsityPattern;
use super::supernodal;
use super::woodbury::LowRank;
use crate::error::{HitlError, Result};

/// `y = A x` and `z = |A| |x|` (for the backward error of a refinement step) for a symmetric A
/// stored as its upper triangle in CSC.
fn mul_sym_upper(
    col_ptr: &[usize],
    row_idx: &[usize],
    vals: &[f64],
    x: &[f64],
    y: &mut [f64],
    z: &mut [f64],
) {
    y.fill(0.0);
    z.fill(0.0);
    for c in 0..x.len() {
        for k in col_ptr[c]..col_ptr[c + 1] {
            let r = row_idx[k];
            y[r] += vals[k] * x[c];
            z[r] += (vals[k] * x[c]).abs();
            if r != c {
                y[c] += vals[k] * x[r];
                z[c] += (vals[k] * x[r]).abs();
            }
        }
    }
}

/// `y += alpha A x` for a symmetric A stored as its upper triangle in CSC.
pub(crate) fn sym_upper_mul_add(
    col_ptr: &[usize],
    row_idx: &[usize],
    vals: &[f64],
    alpha: f64,
    x: &[f64],
    y: &mut [f64],
) {
    for c in 0..x.len() {
        let xc = alpha * x[c];
        let mut acc = 0.0;
        for k in col_ptr[c]..col_ptr[c + 1] {
            let r = row_idx[k];
            y[r] += vals[k] * xc;
            if r != c {
                acc += vals[k] * x[r];
            }
        }
        y[c] += alpha * acc;
    }
}

/// What an inexact step on a previous factor achieved: `-g.d`, the damping term
/// `mu d^T D d`, and the decrease the linear model predicts, `-2 g.d - d^T H d`.
pub(super) struct ChordStep {
    pub gd: f64,
    pub damping: f64,
    pub predicted: f64,
}

/// Work vectors of [`SparsityPattern::chord_step`], kept across iterations.
#[derive(Default)]
pub(super) struct ChordWork {
    r: Vec<f64>,
    z: Vec<f64>,
    p: Vec<f64>,
    q: Vec<f64>,
    ax: Vec<f64>,
    /// `mu D`, the damping's diagonal.
    damp: Vec<f64>,
}

/// `A^-1 x` in place for the columns of `x` (n rows each), through A's numeric factor: column
/// by column with `Cholesky`'s plain loops where the factor's layout allows (`plain`), else
/// with faer's solve.
fn solve_in_place(
    symbolic: &SymbolicCholesky<usize>,
    l_values: &[f64],
    plain: bool,
    mem: &mut MemBuffer,
    x: &mut [f64],
    n: usize,
) {
    if plain {
        let l = Cholesky { symbolic, l_values };
        for col in x.chunks_mut(n) {
            l.solve(col);
        }
    } else {
        let llt = LltRef::new(symbolic, l_values);
        let rhs = MatMut::from_column_major_slice_mut(x, n, x.len() / n);
        llt.solve_in_place_with_conj(Conj::No, rhs, Par::Seq, MemStack::new(mem));
    }
}

/// Entry of the damping matrix D for a diagonal entry `h_kk` of the full H: `h_kk` clamped to
/// `[1e-6, 1e32]` (`diagonal`, Marquardt's scaling) or 1.
#[inline]
fn damping_weight(h_kk: f64, diagonal: bool) -> f64 {
    if diagonal {
        h_kk.clamp(1e-6, 1e32)
    } else {
        1.0
    }
}

/// Diagonal entry k of the full `H = H_s + U U^T`, from the upper CSC of `H_s` (`h`, `col_ptr`:
/// the diagonal closes each column) and the wide rows.
#[inline]
fn hessian_diagonal(h: &[f64], col_ptr: &[usize], wide: &LowRank, k: usize) -> f64 {
    h[col_ptr[k + 1] - 1] + wide.diagonal(k)
}

impl SparsityPattern {
    /// Diagonal entry k of the full `H = H_s + U U^T`.
    #[inline]
    fn hessian_diagonal(&self, k: usize) -> f64 {
        hessian_diagonal(&self.h, &self.col_ptr, &self.wide, k)
    }

    /// Entry k of the damping matrix D: `diag(H)` clamped to `[1e-6, 1e32]` (`diagonal`,
    /// Marquardt's scaling) or 1.
    #[inline]
    fn damping_weight(&self, k: usize, diagonal: bool) -> f64 {
        damping_weight(self.hessian_diagonal(k), diagonal)
    }

    /// Solves `(H + mu D) delta = -g` where `D = diag(H)` clamped to `[d_min, d_max]`
    /// (`diagonal = true`, Marquardt's scaling) or the identity. `mu = 0` is Gauss-Newton.
    /// Returns `Ok(false)` when the damped matrix is not numerically positive definite.
    /// With wide factors, `H = H_s + U U^T` and the sparse factor is of `A = H_s + mu D` alone
    /// (Woodbury, see the module docs); the solution is that of the full system either way.
    pub fn solve_damped(&mut self, mu: f64, diagonal: bool, delta: &mut [f64]) -> Result<bool> {
        if self.wide.rank() > 0 || !self.uses_lower() {
            // The upper triangle of H_s + mu D: what the simplicial kernel factorizes, and what
            // the Woodbury refinement multiplies by. (The supernodal kernel's lower triangle is
            // gathered from H_s and damped in `factorize`.)
            self.damped.resize(self.h.len(), 0.0);
            self.damped.copy_from_slice(&self.h);
            if mu > 0.0 {
                for k in 0..self.n {
                    let d = self.damping_weight(k, diagonal);
                    let p = self.col_ptr[k + 1] - 1;
                    self.damped[p] += mu * d;
                }
            }
        }
        for (x, g) in delta.iter_mut().zip(&self.g) {
            *x = -g;
        }
        let n = self.n;
        // The supernodal factorization solves forward as it goes where the plain loops then
        // finish the solve (not with wide factors: Woodbury needs -g as it is).
        let forward_in_factorization = self.wide.rank() == 0 && self.plain_solves;
        let rhs = forward_in_factorization.then_some(&mut *delta);
        let Some(forwarded) = self.factorize(Some((mu, diagonal)), rhs) else {
            return Ok(false);
        };
        if forwarded {
            Cholesky {
                symbolic: &self.symbolic,
                l_values: &self.l_values,
            }
            .backward(delta);
        } else if self.wide.rank() == 0 {
            solve_in_place(
                &self.symbolic,
                &self.l_values,
                self.plain_solves,
                &mut self.mem,
                delta,
                n,
            );
        } else {
            let l = Cholesky {
                symbolic: &self.symbolic,
                l_values: &self.l_values,
            };
            if !self.wide.prepare(l)? {
                return Ok(false);
            }
            let (col_ptr, row_idx, damped) = (&self.col_ptr, &self.row_idx, &self.damped);
            let a_times = |x: &[f64], y: &mut [f64], z: &mut [f64]| {
                mul_sym_upper(col_ptr, row_idx, damped, x, y, z)
            };
            self.wide.solve_refined(l, a_times, delta);
        }
        Ok(delta.iter().all(|v| v.is_finite()))
    }

    /// A step on the factor still held from the previous numeric factorization (of the system
    /// at an earlier linearization) instead of a new one: conjugate gradients on
    /// `(H + mu D) delta = -g` preconditioned by that factor (its first iterate is the chord,
    /// or simplified Newton, step). Kept only when it is an inexact Newton step in the sense of
    /// Dembo, Eisenstat and Steihaug (1982), the test Ceres applies to its iterative solvers:
    /// `|(H + mu D) delta + g| <= eta |g|`, reached within `max_iterations`. Near a minimum,
    /// where a step barely moves the linearization, this saves a factorization for the price of
    /// a few triangular solve pairs and products with H. `None` (delta unspecified) when the
    /// test is not met, or with wide factors (Woodbury). Call only after a successful
    /// factorization on this pattern.
    pub(super) fn chord_step(
        &mut self,
        mu: f64,
        diagonal: bool,
        eta: f64,
        max_iterations: usize,
        delta: &mut [f64],
        work: &mut ChordWork,
    ) -> Option<ChordStep> {
        if self.wide.rank() != 0 {
            return None;
        }
        let n = self.n;
        let ChordWork {
            r,
            z,
            p,
            q,
            ax,
            damp,
        } = work;
        for v in [&mut *r, &mut *z, &mut *p, &mut *q, &mut *ax, &mut *damp] {
            v.clear();
            v.resize(n, 0.0);
        }
        for (k, d) in damp.iter_mut().enumerate() {
            *d = mu * self.damping_weight(k, diagonal);
        }
        let dot = |a: &[f64], b: &[f64]| a.iter().zip(b).map(|(x, y)| x * y).sum::<f64>();
        delta.fill(0.0);
        for (rk, g) in r.iter_mut().zip(&self.g) {
            *rk = -g;
        }
        let g2 = dot(r, r);
        let limit = eta * eta * g2;
        let (symbolic, l_values, plain) = (&self.symbolic, &self.l_values[..], self.plain_solves);
        z.copy_from_slice(r);
        solve_in_place(symbolic, l_values, plain, &mut self.mem, z, n);
        p.copy_from_slice(z);
        let mut rz = dot(r, z);
        let mut met = false;
        for it in 0..max_iterations {
            q.fill(0.0);
            sym_upper_mul_add(&self.col_ptr, &self.row_idx, &self.h, 1.0, p, q);
            for (k, d) in damp.iter().enumerate() {
                q[k] += d * p[k];
            }
            let pq = dot(p, q);
            if !(pq > 0.0 && rz.is_finite()) {
                return None;
            }
            let alpha = rz / pq;
            for k in 0..n {
                delta[k] += alpha * p[k];
                ax[k] += alpha * q[k];
                r[k] -= alpha * q[k];
            }
            let res2 = dot(r, r);
            if !res2.is_finite() || (it == 0 && res2 > g2) {
                return None;
            }
            if res2 <= limit {
                met = true;
                break;
            }
            if it + 1 == max_iterations {
                break;
            }
            z.copy_from_slice(r);
            solve_in_place(symbolic, l_values, plain, &mut self.mem, z, n);
            let rz_next = dot(r, z);
            let beta = rz_next / rz;
            rz = rz_next;
            for k in 0..n {
                p[k] = z[k] + beta * p[k];
            }
        }
        if !met {
            return None;
        }
        // (H + mu D) delta = ax, so d^T H d = d.ax - mu d^T D d.
        let damping: f64 = damp.iter().zip(&*delta).map(|(d, x)| d * x * x).sum();
        let dhd = dot(delta, ax) - damping;
        let gd = -dot(&self.g, delta);
        (dhd > 0.0).then_some(ChordStep {
            gd,
            damping,
            predicted: 2.0 * gd - dhd,
        })
    }

    /// Numeric Cholesky of the sparse part `H_s + mu D` (`damping = Some((mu, diagonal))`, with
    /// `damped` filled for the upper triangle) or of `H_s` (`None`) into `l_values`, on the
    /// cached symbolic analysis; None when it is not positive definite. With `rhs`, the
    /// supernodal kernel also applies `L^-1` to it as it goes: `Some(true)` says it did (the
    /// simplicial kernel leaves `rhs` as it is and says `Some(false)`).
    fn factorize(&mut self, damping: Option<(f64, bool)>, rhs: Option<&mut [f64]>) -> Option<bool> {
        let n = self.n;
        self.ensure_lower();
        let (col_ptr, row_idx, values, side) = if !self.uses_lower() {
            let values = if damping.is_some() {
                &self.damped[..]
            } else {
                &self.h[..]
            };
            (&self.col_ptr[..], &self.row_idx[..], values, Side::Upper)
        } else {
            let (h, upper_ptr, wide) = (&self.h, &self.col_ptr, &self.wide);
            let weight = |k: usize, diagonal: bool| {
                damping_weight(hessian_diagonal(h, upper_ptr, wide, k), diagonal)
            };
            let (col_ptr, row_idx, values) = self.lower.gather(h, damping, weight);
            (col_ptr, row_idx, values, Side::Lower)
        };
        if let (Side::Lower, SymbolicCholeskyRaw::Supernodal(sn)) = (side, self.symbolic.raw()) {
            let forwarded = rhs.is_some();
            return supernodal::factorize(
                sn,
                col_ptr,
                row_idx,
                values,
                &mut self.l_values,
                &mut self.supernodal_work,
                rhs,
            )
            .then_some(forwarded);
        }
        let sym = SymbolicSparseColMatRef::new_checked(n, n, col_ptr, None, row_idx);
        self.symbolic
            .factorize_numeric_llt::<f64>(
                &mut self.l_values,
                SparseColMatRef::new(sym, values),
                side,
                LltRegularization::default(),
                Par::Seq,
                MemStack::new(&mut self.mem),
                Spec::default(),
            )
            .is_ok()
            .then_some(false)
    }

    /// `d^T D d` for the damping matrix D of [`Self::solve_damped`].
    pub fn damping_quadratic(&self, delta: &[f64], diagonal: bool) -> f64 {
        delta
            .iter()
            .enumerate()
            .map(|(k, d)| {
                let dk = self.damping_weight(k, diagonal);
                dk * d * d
            })
            .sum()
    }

    /// Factorizes the undamped `H` and solves for `H^-1` columns of the given scalar offsets
    /// (marginal covariances). `cols` is `n x k` column-major, overwritten with the solutions.
    /// With wide factors, A is the undamped `H_s` and each column is a refined Woodbury solve.
    pub fn solve_undamped_columns(&mut self, cols: &mut [f64], k: usize) -> Result<()> {
        let n = self.n;
        let singular = || {
            HitlError::Solver(
                "the information matrix is singular at this solution; marginals are undefined (is every pose constrained?)".into(),
            )
        };
        if self.factorize(None, None).is_none() {
            return Err(singular());
        }
        if self.wide.rank() == 0 {
            // The workspace was sized for 3 right-hand sides; solve in chunks of 3.
            for chunk in cols.chunks_mut(3 * n) {
                solve_in_place(
                    &self.symbolic,
                    &self.l_values,
                    self.plain_solves,
                    &mut self.mem,
                    chunk,
                    n,
                );
            }
        } else {
            let l = Cholesky {
                symbolic: &self.symbolic,
                l_values: &self.l_values,
            };
            if !self.wide.prepare(l)? {
                return Err(singular());
            }
            let (col_ptr, row_idx, h) = (&self.col_ptr, &self.row_idx, &self.h);
            let a_times = |x: &[f64], y: &mut [f64], z: &mut [f64]| {
                mul_sym_upper(col_ptr, row_idx, h, x, y, z)
            };
            for col in cols.chunks_mut(n) {
                self.wide.solve_refined(l, a_times, col);
            }
        }
        debug_assert!(cols.len() == k * n);
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::solver::test_problems::{corrected, dense_hessian, ring, Relations};
    use crate::values::Key;
    use faer::sparse::linalg::cholesky::SymbolicCholeskyRaw;

    /// The upper triangle of `H_s + mu D`.
    fn damped_upper(p: &SparsityPattern, mu: f64, diagonal: bool) -> Vec<f64> {
        let mut v = p.h.clone();
        if mu > 0.0 {
            for k in 0..p.n {
                v[p.col_ptr[k + 1] - 1] += mu * p.damping_weight(k, diagonal);
            }
        }
        v
    }

    fn mul_upper(p: &SparsityPattern, vals: &[f64], x: &[f64]) -> Vec<f64> {
        let mut y = vec![0.0; p.n];
        for c in 0..p.n {
            for k in p.col_ptr[c]..p.col_ptr[c + 1] {
                let r = p.row_idx[k];
                y[r] += vals[k] * x[c];
                if r != c {
                    y[c] += vals[k] * x[r];
                }
            }
        }
        y
    }

    /// The chord step on a factor of a nearby linearization meets its inexact-Newton test
    /// (checked here with an independent product), and refuses when the factor is of a system
    /// far from the current one.
    #[test]
    fn chord_step_is_an_inexact_newton_step_or_nothing() {
        let (mut g, values) = ring(300);
        let (factors, p) = g.parts().unwrap();
        let mut work = ChordWork::default();
        let mut delta = vec![0.0; p.n];
        p.linearize(factors, &values, &[]);
        assert!(p.solve_damped(1e-4, true, &mut delta).unwrap());
        // Move a little along the step and relinearize: the held factor is of the old system.
        let mut near = values.clone();
        let small: Vec<f64> = delta.iter().map(|d| 1e-3 * d).collect();
        p.retract(&mut near, &small);
        p.linearize(factors, &near, &[]);
        for (mu, eta) in [(0.0, 0.1), (1e-4, 0.1), (1e-4, 1e-6)] {
            let step = p
                .chord_step(mu, true, eta, 8, &mut delta, &mut work)
                .expect("a nearby factor preconditions well");
            let mut r = p.g.clone();
            sym_upper_mul_add(&p.col_ptr, &p.row_idx, &p.h, 1.0, &delta, &mut r);
            let mut dd = 0.0;
            for k in 0..p.n {
                let d = mu * p.damping_weight(k, true);
                r[k] += d * delta[k];
                dd += d * delta[k] * delta[k];
            }
            let res = r.iter().map(|v| v * v).sum::<f64>().sqrt();
            let gn = p.g.iter().map(|v| v * v).sum::<f64>().sqrt();
            assert!(
                res <= eta * gn * (1.0 + 1e-9),
                "mu {mu}: {res} > {eta} x {gn}"
            );
            let gd = -p.g.iter().zip(&delta).map(|(a, b)| a * b).sum::<f64>();
            assert!((step.gd - gd).abs() <= 1e-9 * gd.abs());
            assert!((step.damping - dd).abs() <= 1e-9 * dd.max(1e-300));
            assert!(step.predicted > 0.0);
        }
        // A factor of a very different system (damped by 1e6) is no preconditioner within
        // two iterations for a tight test: no step.
        p.linearize(factors, &values, &[]);
        assert!(p.solve_damped(1e6, false, &mut delta).unwrap());
        assert!(p
            .chord_step(0.0, true, 1e-8, 2, &mut delta, &mut work)
            .is_none());
    }

    #[test]
    fn damped_solve_solves_the_system() {
        // Both kernels: the simplicial one on the upper triangle (5 poses), the supernodal one
        // on the lower (1100 poses: over SUPERNODAL_MIN_DIM unknowns).
        for &n in &[5usize, 60, 400, 1100] {
            let (mut g, values) = ring(n);
            let (factors, p) = g.parts().unwrap();
            let supernodal = matches!(p.symbolic.raw(), SymbolicCholeskyRaw::Supernodal(_));
            if n == 5 || n == 1100 {
                assert_eq!(supernodal, n == 1100, "n {n}");
            }
            assert_eq!(p.uses_lower(), supernodal, "n {n}");
            p.linearize(factors, &values, &[]);
            for &(mu, diag) in &[(0.0, false), (1e-3, true), (10.0, false)] {
                let mut delta = vec![0.0; p.n];
                assert!(p.solve_damped(mu, diag, &mut delta).unwrap());
                let hd = mul_upper(p, &damped_upper(p, mu, diag), &delta);
                let err = hd
                    .iter()
                    .zip(&p.g)
                    .map(|(a, b)| (a + b).abs())
                    .fold(0.0, f64::max);
                let scale = p.g.iter().map(|v| v.abs()).fold(0.0, f64::max);
                assert!(
                    err <= 1e-9 * scale,
                    "n {n} mu {mu}: residual {err} (scale {scale})"
                );
            }
        }
    }

    #[test]
    fn woodbury_solve_equals_a_dense_solve_of_the_full_system() {
        for n in [50usize, 300] {
            let (mut g, values) = corrected(n, Relations::Wide, false);
            let (factors, p) = g.parts().unwrap();
            p.linearize(factors, &values, &[]);
            assert_eq!(p.wide.rank(), 5);
            let h = dense_hessian(p);
            let g_vec = nalgebra::DVector::from_column_slice(&p.g);
            for &(mu, diag) in &[(0.0, false), (1e-5, false), (1e-3, true), (10.0, false)] {
                let mut delta = vec![0.0; p.n];
                assert!(p.solve_damped(mu, diag, &mut delta).unwrap());
                let mut a = h.clone();
                for k in 0..p.n {
                    a[(k, k)] += mu
                        * if diag {
                            h[(k, k)].clamp(1e-6, 1e32)
                        } else {
                            1.0
                        };
                }
                let expect = a.clone().cholesky().unwrap().solve(&(-&g_vec));
                let got = nalgebra::DVector::from_column_slice(&delta);
                let rel = (&got - &expect).norm() / expect.norm();
                assert!(
                    rel < 1e-9,
                    "n {n} mu {mu} diag {diag}: relative error {rel:e}"
                );
                // The LM gain ratio relies on (H + mu D) delta = -g holding exactly.
                let res = (&a * &got + &g_vec).amax() / g_vec.amax();
                assert!(res < 1e-9, "n {n} mu {mu}: residual {res:e}");
                let quad = p.damping_quadratic(&delta, diag);
                let expect_quad: f64 = (0..p.n)
                    .map(|k| {
                        let d = if diag {
                            h[(k, k)].clamp(1e-6, 1e32)
                        } else {
                            1.0
                        };
                        d * delta[k] * delta[k]
                    })
                    .sum();
                assert!((quad - expect_quad).abs() <= 1e-12 * expect_quad.abs());
            }
        }
    }

    #[test]
    fn woodbury_on_a_supernodal_factor_matches_the_sparse_solve() {
        // 1100 poses: over SUPERNODAL_MIN_DIM unknowns, so the reach-limited supernodal forward
        // solve runs; the dense-coupling graph is the exact reference.
        let (mut gw, values) = corrected(1100, Relations::Wide, false);
        let (mut gn, _) = corrected(1100, Relations::Narrow, false);
        let (fw, pw) = gw.parts().unwrap();
        let (fnarrow, pn) = gn.parts().unwrap();
        assert!(matches!(
            pw.symbolic.raw(),
            SymbolicCholeskyRaw::Supernodal(_)
        ));
        pw.linearize(fw, &values, &[]);
        pn.linearize(fnarrow, &values, &[]);
        for &(mu, diag) in &[(0.0, false), (1e-5, false), (1e-2, true)] {
            let mut dw = vec![0.0; pw.n];
            let mut dn = vec![0.0; pn.n];
            assert!(pw.solve_damped(mu, diag, &mut dw).unwrap());
            assert!(pn.solve_damped(mu, diag, &mut dn).unwrap());
            // Same unknowns, possibly in another order: compare variable by variable.
            let (mut err, mut norm) = (0.0f64, 0.0f64);
            for &key in pn.block_keys() {
                let (ow, on) = (pw.offset_of(key).unwrap(), pn.offset_of(key).unwrap());
                for a in 0..key.dim() {
                    err = err.max((dw[ow + a] - dn[on + a]).abs());
                    norm = norm.max(dn[on + a].abs());
                }
            }
            // Residuals of both in the narrow graph's exact system: the refinement must bring
            // the Woodbury solve to the rounding level of a direct one.
            let mut dwn = vec![0.0; pn.n];
            for &key in pn.block_keys() {
                let (ow, on) = (pw.offset_of(key).unwrap(), pn.offset_of(key).unwrap());
                dwn[on..on + key.dim()].copy_from_slice(&dw[ow..ow + key.dim()]);
            }
            let gmax = pn.g.iter().fold(0.0f64, |m, v| m.max(v.abs()));
            for (name, d) in [("wide", &dwn), ("narrow", &dn)] {
                let hd = mul_upper(pn, &damped_upper(pn, mu, diag), d);
                let res = hd
                    .iter()
                    .zip(&pn.g)
                    .map(|(a, b)| (a + b).abs())
                    .fold(0.0, f64::max);
                assert!(res <= 1e-13 * gmax, "{name} mu {mu}: residual {res:e}");
            }
            assert!(err <= 1e-9 * norm, "mu {mu}: {err:e} vs {norm:e}");
        }
        // The relations' columns reach only part of the factor.
        let reached = pw.wide.reached_rows();
        assert!(
            reached > 0 && reached < 5 * pw.n / 2,
            "{reached} of 5 x {}",
            pw.n
        );
    }

    #[test]
    fn marginals_with_wide_factors_equal_the_dense_inverse() {
        let (mut g, values) = corrected(80, Relations::Wide, false);
        let keys = [
            Key::Pose(3),
            Key::Pose(77),
            Key::Pose(41),
            Key::Line(0),
            Key::Line(3),
            Key::Pose(0),
        ];
        let cov = crate::solver::marginal_covariances(&mut g, &values, &keys).unwrap();
        let (factors, p) = g.parts().unwrap();
        p.linearize(factors, &values, &[]);
        let inv = dense_hessian(p).cholesky().unwrap().inverse();
        for (key, block) in keys.iter().zip(&cov) {
            let d = key.dim();
            match p.offset_of(*key) {
                None => assert!(block.iter().all(|&v| v == 0.0)),
                Some(o) => {
                    for a in 0..d {
                        for b in 0..d {
                            let e = inv[(o + a, o + b)];
                            let scale = inv[(o + a, o + a)].abs().max(inv[(o + b, o + b)].abs());
                            assert!(
                                (block[a * d + b] - e).abs() <= 1e-9 * scale,
                                "{key:?} ({a}, {b}): {} vs {e}",
                                block[a * d + b]
                            );
                        }
                    }
                }
            }
        }
    }

    #[test]
    fn solves_with_wide_factors_equal_the_sparse_ones() {
        use crate::solver::{optimize, Method, SolverParams};
        for method in [Method::LevenbergMarquardt, Method::GaussNewton] {
            for diagonal_damping in [false, true] {
                let params = SolverParams {
                    method,
                    diagonal_damping,
                    relative_tolerance: 1e-12,
                    absolute_tolerance: 1e-12,
                    ..SolverParams::default()
                };
                let (mut gw, mut vw) = corrected(120, Relations::Wide, false);
                let (mut gn, mut vn) = corrected(120, Relations::Narrow, false);
                let rw = optimize(&mut gw, &mut vw, &params).unwrap();
                let rn = optimize(&mut gn, &mut vn, &params).unwrap();
                assert!(rw.final_chi2 < 0.5 * rw.initial_chi2);
                assert!(
                    (rw.final_chi2 - rn.final_chi2).abs() <= 1e-9 * rn.final_chi2,
                    "{method:?}: chi2 {} vs {}",
                    rw.final_chi2,
                    rn.final_chi2
                );
                assert!(rw.nnz_factor < rn.nnz_factor);
                for (a, b) in vw.poses.iter().zip(&vn.poses) {
                    assert!((a.x - b.x).abs() < 1e-9 && (a.y - b.y).abs() < 1e-9);
                    assert!((a.theta - b.theta).abs() < 1e-9);
                }
                for (a, b) in vw.lines.iter().zip(&vn.lines) {
                    assert!((a.phi - b.phi).abs() < 1e-9 && (a.rho - b.rho).abs() < 1e-9);
                }
            }
        }
    }
}
