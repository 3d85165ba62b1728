//! Assembly of the normal equations at a linearization point: each factor's `J^T J` and
//! `J^T r` blocks are accumulated straight into the slots of the `SparsityPattern` (with a
//! fixed-size path for the relative-pose edges), robust factors' rows reweighted, and the rows
//! of wide factors stored as the low-rank term U instead. Also the cost alone (trial points)
//! and the quadratic form `v^T H v`.

use super::pattern::{block_of, SparsityPattern, NO_BLOCK};
use super::robust::{robust_cost, Kernel};
use crate::factors::Factor;
use crate::values::{Key, Values};

impl SparsityPattern {
    /// Accumulates `H = J^T J` and `g = J^T r` at `values`; returns the cost: chi2 `|r|^2`, or
    /// with robust kernels (`kernels[fi]`, empty for none) `sum rho(|r|^2)`, the rows of a robust
    /// factor scaled by `sqrt(rho')` (see `robust`). The rows of wide factors go to `g` and to U,
    /// not to the sparse `h`.
    pub fn linearize(
        &mut self,
        factors: &[Box<dyn Factor>],
        values: &Values,
        kernels: &[Option<Kernel>],
    ) -> f64 {
        self.h.fill(0.0);
        self.g.fill(0.0);
        let mut r = vec![0.0; self.max_residual];
        let mut jac = vec![0.0; self.max_jac];
        let mut chi2 = 0.0;
        for (fi, f) in factors.iter().enumerate() {
            let d = f.residual_dim();
            let keys = f.keys();
            f.linearize(values, &mut r[..d], &mut jac);
            let s = r[..d].iter().map(|v| v * v).sum::<f64>();
            match kernels.get(fi).copied().flatten() {
                None => chi2 += s,
                Some(k) => {
                    chi2 += k.rho(s);
                    let sw = k.weight(s).sqrt();
                    let cols: usize = keys.iter().map(|k| k.dim()).sum();
                    r[..d].iter_mut().for_each(|v| *v *= sw);
                    jac[..d * cols].iter_mut().for_each(|v| *v *= sw);
                }
            }
            if let Some(wi) = self.wide.wide_index(fi) {
                self.store_wide(wi, keys, &r[..d], &jac);
                continue;
            }
            let mut slot = self.factor_slots[fi];
            if d == 3 && keys.len() == 2 && keys[0].dim() == 3 && keys[1].dim() == 3 {
                // The pose-graph hot path (every relative-pose edge), with fixed sizes.
                let b0 = block_of(&self.pose_block, &self.line_block, keys[0]);
                let b1 = block_of(&self.pose_block, &self.line_block, keys[1]);
                self.accumulate_pose_pair(&jac[..18], &r[..3], b0, b1, slot);
                continue;
            }
            let mut off_p = 0;
            for (p, &kp) in keys.iter().enumerate() {
                let dp = kp.dim();
                let bp = block_of(&self.pose_block, &self.line_block, kp);
                if bp != NO_BLOCK {
                    let jp = &jac[off_p..off_p + d * dp];
                    let gp = self.block_offset[bp];
                    for a in 0..dp {
                        let mut s = 0.0;
                        for row in 0..d {
                            s += jp[row * dp + a] * r[row];
                        }
                        self.g[gp + a] += s;
                    }
                    let mut off_q = off_p;
                    for &kq in &keys[p..] {
                        let dq = kq.dim();
                        let bq = block_of(&self.pose_block, &self.line_block, kq);
                        if bq != NO_BLOCK {
                            let jq = &jac[off_q..off_q + d * dq];
                            if bp == bq {
                                // Diagonal block: column k holds rows 0..=k.
                                for k in 0..dp {
                                    let base = self.slots[slot + k];
                                    for i in 0..=k {
                                        let mut s = 0.0;
                                        for row in 0..d {
                                            s += jp[row * dp + i] * jp[row * dp + k];
                                        }
                                        self.h[base + i] += s;
                                    }
                                }
                                slot += dp;
                            } else {
                                // Off-diagonal: rows from the lower-numbered block.
                                let (jr, dr, jc, dc) = if bp < bq {
                                    (jp, dp, jq, dq)
                                } else {
                                    (jq, dq, jp, dp)
                                };
                                for k in 0..dc {
                                    let base = self.slots[slot + k];
                                    for i in 0..dr {
                                        let mut s = 0.0;
                                        for row in 0..d {
                                            s += jr[row * dr + i] * jc[row * dc + k];
                                        }
                                        self.h[base + i] += s;
                                    }
                                }
                                slot += dc;
                            }
                        }
                        off_q += d * dq;
                    }
                }
                off_p += d * dp;
            }
        }
        self.wide.update_diagonal();
        chi2
    }

    /// Whether a trial point can be linearized ahead (`linearize_ahead`): not with wide factors,
    /// whose rows (`U`) are not kept twice.
    pub fn can_look_ahead(&self) -> bool {
        self.wide.rank() == 0
    }

    /// Linearizes at a trial point `values` into the look-ahead buffers and returns the cost
    /// there, leaving `H`, `g` of the current point as they are (a rejected trial costs nothing
    /// more); [`Self::accept_ahead`] makes the trial's current. Only where `can_look_ahead`.
    pub fn linearize_ahead(
        &mut self,
        factors: &[Box<dyn Factor>],
        values: &Values,
        kernels: &[Option<Kernel>],
    ) -> f64 {
        debug_assert!(self.can_look_ahead());
        self.h_ahead.resize(self.h.len(), 0.0);
        self.g_ahead.resize(self.g.len(), 0.0);
        // Linearize into the look-ahead pair, then swap the current one back in.
        self.accept_ahead();
        let cost = self.linearize(factors, values, kernels);
        self.accept_ahead();
        cost
    }

    /// The trial point last linearized ahead becomes the current linearization.
    pub fn accept_ahead(&mut self) {
        std::mem::swap(&mut self.h, &mut self.h_ahead);
        std::mem::swap(&mut self.g, &mut self.g_ahead);
    }

    /// The cost at `values` without linearizing (trial points): chi2, or `sum rho(|r|^2)`.
    pub fn cost(factors: &[Box<dyn Factor>], values: &Values, kernels: &[Option<Kernel>]) -> f64 {
        if kernels.is_empty() {
            return factors.iter().map(|f| f.chi2(values)).sum();
        }
        factors
            .iter()
            .zip(kernels)
            .map(|(f, &k)| robust_cost(k, f.chi2(values)))
            .sum()
    }

    /// `v^T H v` for the full `H = H_s + U U^T` at the last linearization (the dogleg's
    /// steepest-descent step length needs `g^T H g`).
    pub fn hessian_quadratic(&self, v: &[f64]) -> f64 {
        let mut q = 0.0;
        for c in 0..self.n {
            for k in self.col_ptr[c]..self.col_ptr[c + 1] {
                let r = self.row_idx[k];
                let t = self.h[k] * v[r] * v[c];
                q += if r == c { t } else { 2.0 * t };
            }
        }
        for (ix, u) in self.wide.rows() {
            let d: f64 = ix.iter().zip(u).map(|(&i, &x)| x * v[i]).sum();
            q += d * d;
        }
        q
    }

    /// A wide factor's share of `linearize`: `J^T r` into `g`, its Jacobian rows into U.
    fn store_wide(&mut self, wi: usize, keys: &[Key], r: &[f64], jac: &[f64]) {
        let d = r.len();
        let mut col = 0;
        let mut off = 0;
        for &k in keys {
            let dk = k.dim();
            let b = block_of(&self.pose_block, &self.line_block, k);
            if b != NO_BLOCK {
                let jk = &jac[off..off + d * dk];
                let o = self.block_offset[b];
                for a in 0..dk {
                    let mut s = 0.0;
                    for (row, &rv) in r.iter().enumerate() {
                        let u = jk[row * dk + a];
                        s += u * rv;
                        *self.wide.entry_mut(wi, row, col + a) = u;
                    }
                    self.g[o + a] += s;
                }
                col += dk;
            }
            off += d * dk;
        }
    }

    /// `accumulate` for a 3-row factor on two 3-dof blocks (either may be fixed). Slot order as
    /// built in `SparsityPattern::new`: (0,0) diagonal, (0,1) off-diagonal, (1,1) diagonal,
    /// skipping fixed ones.
    #[inline]
    fn accumulate_pose_pair(
        &mut self,
        jac: &[f64],
        r: &[f64],
        b0: usize,
        b1: usize,
        mut slot: usize,
    ) {
        let j0: &[f64; 9] = jac[..9].try_into().unwrap_or(&[0.0; 9]);
        let j1: &[f64; 9] = jac[9..18].try_into().unwrap_or(&[0.0; 9]);
        let r: [f64; 3] = [r[0], r[1], r[2]];
        let grad = |j: &[f64; 9]| -> [f64; 3] {
            let mut out = [0.0; 3];
            for (a, o) in out.iter_mut().enumerate() {
                *o = j[a] * r[0] + j[3 + a] * r[1] + j[6 + a] * r[2];
            }
            out
        };
        // (J_a^T J_b)[i][k] = sum_row J_a[row][i] J_b[row][k]
        let jtj = |ja: &[f64; 9], i: usize, jb: &[f64; 9], k: usize| -> f64 {
            ja[i] * jb[k] + ja[3 + i] * jb[3 + k] + ja[6 + i] * jb[6 + k]
        };
        if b0 != NO_BLOCK {
            let g0 = grad(j0);
            let o = self.block_offset[b0];
            for a in 0..3 {
                self.g[o + a] += g0[a];
            }
            for k in 0..3 {
                let base = self.slots[slot + k];
                for i in 0..=k {
                    self.h[base + i] += jtj(j0, i, j0, k);
                }
            }
            slot += 3;
            if b1 != NO_BLOCK {
                let (jr, jc) = if b0 < b1 { (j0, j1) } else { (j1, j0) };
                for k in 0..3 {
                    let base = self.slots[slot + k];
                    for i in 0..3 {
                        self.h[base + i] += jtj(jr, i, jc, k);
                    }
                }
                slot += 3;
            }
        }
        if b1 != NO_BLOCK {
            let g1 = grad(j1);
            let o = self.block_offset[b1];
            for a in 0..3 {
                self.g[o + a] += g1[a];
            }
            for k in 0..3 {
                let base = self.slots[slot + k];
                for i in 0..=k {
                    self.h[base + i] += jtj(j1, i, j1, k);
                }
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::graph::FactorGraph;
    use crate::solver::test_problems::{corrected, dense_hessian, ring, Relations};

    #[test]
    fn a_trial_linearized_ahead_leaves_the_current_linearization_until_accepted() {
        let (mut g, values) = ring(30);
        let mut trial = values.clone();
        for (k, q) in trial.poses.iter_mut().enumerate() {
            q.x += 0.01 * k as f64;
            q.theta -= 0.003 * k as f64;
        }
        let (factors, p) = g.parts().unwrap();
        assert!(p.can_look_ahead());
        let here = p.linearize(factors, &trial, &[]);
        let (h_trial, g_trial) = (p.h.clone(), p.g.clone());
        let cost = p.linearize(factors, &values, &[]);
        let (h_now, g_now) = (p.h.clone(), p.g.clone());
        // Rejected: nothing of the current linearization changes.
        assert_eq!(p.linearize_ahead(factors, &trial, &[]), here);
        assert_eq!((&p.h, &p.g), (&h_now, &g_now));
        assert_ne!(h_now, h_trial);
        // Accepted: the trial's is current, exactly as if linearized there.
        p.accept_ahead();
        assert_eq!((&p.h, &p.g), (&h_trial, &g_trial));
        assert!(cost != here);
        // Wide factors' rows are not kept twice.
        let (mut w, _) = corrected(60, Relations::Wide, false);
        assert!(!w.pattern().unwrap().can_look_ahead());
    }

    /// Checks the full `H = H_s + U U^T` and `g` against a central-difference Jacobian.
    fn check_against_numerical_jacobian(g: &mut FactorGraph, values: &Values) {
        let (factors, p) = g.parts().unwrap();
        p.linearize(factors, values, &[]);
        let n = p.n;
        let m: usize = factors.iter().map(|f| f.residual_dim()).sum();
        let stack = |v: &Values| {
            let mut out = Vec::with_capacity(m);
            for f in factors {
                let mut r = vec![0.0; f.residual_dim()];
                f.residual(v, &mut r);
                out.extend(r);
            }
            out
        };
        let r0 = stack(values);
        let h = 1e-6;
        let mut jac = vec![vec![0.0; n]; m];
        for (b, &key) in p.block_key.iter().enumerate() {
            for k in 0..key.dim() {
                let mut d = vec![0.0; key.dim()];
                d[k] = h;
                let mut plus = values.clone();
                plus.retract(key, &d);
                d[k] = -h;
                let mut minus = values.clone();
                minus.retract(key, &d);
                let (rp, rm) = (stack(&plus), stack(&minus));
                for row in 0..m {
                    jac[row][p.block_offset[b] + k] = (rp[row] - rm[row]) / (2.0 * h);
                }
            }
        }
        let dense = dense_hessian(p);
        for a in 0..n {
            let ga: f64 = (0..m).map(|row| jac[row][a] * r0[row]).sum();
            assert!(
                (ga - p.g[a]).abs() < 1e-5 * (1.0 + ga.abs()),
                "g[{a}]: {} vs {ga}",
                p.g[a]
            );
            for b in 0..n {
                let hab: f64 = (0..m).map(|row| jac[row][a] * jac[row][b]).sum();
                // Differencing residuals of size sqrt(K2) e leaves ~1e-8 in each Jacobian
                // entry, which the large diagonal entries (K1, K2 ~ 1e6..1e7) amplify.
                let tol = 1e-5 * (1.0 + hab.abs()) + 1e-6 * (dense[(a, a)] * dense[(b, b)]).sqrt();
                assert!(
                    (hab - dense[(a, b)]).abs() < tol,
                    "H[{a}][{b}]: {} vs {hab}",
                    dense[(a, b)]
                );
            }
        }
    }

    #[test]
    fn hessian_and_gradient_match_numerical_jacobian() {
        let (mut g, values) = ring(30);
        check_against_numerical_jacobian(&mut g, &values);
    }

    #[test]
    fn wide_hessian_and_gradient_match_numerical_jacobian() {
        let (mut g, values) = corrected(50, Relations::Wide, false);
        check_against_numerical_jacobian(&mut g, &values);
    }
}
