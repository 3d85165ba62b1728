//! The block sparsity of the normal equations `H = J^T J`, the fill-reducing ordering, and the
//! symbolic Cholesky analysis: computed once per graph structure, then reused by every
//! linearization (the Hessian is accumulated straight into this pattern, block by block) and
//! every numeric factorization.
//!
//! Layout: variables become blocks (3 for a pose, 2 for a line; fixed variables get none),
//! ordered by an approximate-minimum-degree ordering of the BLOCK graph; `H` is stored as the
//! upper triangle in compressed sparse columns in that order, so the factorization needs no
//! permutation of its own.
//!
//! Wide factors (`Factor::is_wide`: a human relation over the centroids of hundreds of poses)
//! would make `H` dense over all their variables. Their rows stay out of the pattern (`h` is
//! `H_s`, H without them) and join every solve as the low-rank term of `woodbury`.

use faer::dyn_stack::{MemBuffer, MemStack, StackReq};
use faer::linalg::cholesky::llt::factor::LltRegularization;
use faer::sparse::linalg::cholesky::{
    factorize_symbolic_cholesky, CholeskySymbolicParams, LltRef, SymbolicCholesky,
    SymmetricOrdering,
};
use faer::sparse::linalg::SupernodalThreshold;
use faer::sparse::{SparseColMatRef, SymbolicSparseColMatRef};
use faer::{Conj, MatMut, Par, Side, Spec};
use std::collections::HashMap;

use super::ordering::block_amd;
use super::robust::{robust_cost, Kernel};
use super::woodbury::{Cholesky, LowRank};
use crate::error::{HitlError, Result};
use crate::factors::Factor;
use crate::values::{Key, Values};

const NO_BLOCK: usize = usize::MAX;
/// Scalar size from which the supernodal Cholesky kernel is always used.
const SUPERNODAL_MIN_DIM: usize = 3000;

/// `(rows, cols, values, gradient, keys)`: the upper triangle of H and J^T r in natural order.
pub type NaturalSystem = (Vec<usize>, Vec<usize>, Vec<f64>, Vec<f64>, Vec<Key>);

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

/// `A^-1 x` in place for the columns of `x` (n rows each), through A's numeric factor.
fn solve_in_place(llt: LltRef<'_, usize, f64>, mem: &mut MemBuffer, x: &mut [f64], n: usize) {
    let rhs = MatMut::from_column_major_slice_mut(x, n, x.len() / n);
    llt.solve_in_place_with_conj(Conj::No, rhs, Par::Seq, MemStack::new(mem));
}

pub struct SparsityPattern {
    /// Block of each pose / line (NO_BLOCK when fixed); blocks are in elimination order.
    pose_block: Vec<usize>,
    line_block: Vec<usize>,
    /// Scalar offset and size of each block.
    block_offset: Vec<usize>,
    block_dim: Vec<usize>,
    /// The key each block stands for.
    block_key: Vec<Key>,
    n: usize,
    col_ptr: Vec<usize>,
    row_idx: Vec<usize>,
    /// Per factor, the start of its slots in `slots`; one slot per (key pair, column).
    factor_slots: Vec<usize>,
    slots: Vec<usize>,
    symbolic: SymbolicCholesky<usize>,
    /// Undamped `H` values (upper CSC), gradient `J^T r`, and scratch for the damped copy.
    pub(crate) h: Vec<f64>,
    pub(crate) g: Vec<f64>,
    damped: Vec<f64>,
    l_values: Vec<f64>,
    mem: MemBuffer,
    max_residual: usize,
    max_jac: usize,
    /// The rows of wide factors: `H = h + U U^T`.
    wide: LowRank,
}

fn block_of(pose_block: &[usize], line_block: &[usize], key: Key) -> usize {
    match key {
        Key::Pose(i) => pose_block[i],
        Key::Line(i) => line_block[i],
    }
}

impl SparsityPattern {
    pub fn new(
        num_poses: usize,
        num_lines: usize,
        fixed: &[Key],
        factors: &[Box<dyn Factor>],
    ) -> Result<Self> {
        // 1. Free variables, in natural order (poses, then lines).
        let mut natural_pose = vec![NO_BLOCK; num_poses];
        let mut natural_line = vec![NO_BLOCK; num_lines];
        let mut keys: Vec<Key> = Vec::with_capacity(num_poses + num_lines);
        for i in 0..num_poses {
            if !fixed.contains(&Key::Pose(i)) {
                natural_pose[i] = keys.len();
                keys.push(Key::Pose(i));
            }
        }
        for i in 0..num_lines {
            if !fixed.contains(&Key::Line(i)) {
                natural_line[i] = keys.len();
                keys.push(Key::Line(i));
            }
        }
        let nb = keys.len();
        if nb == 0 {
            return Err(HitlError::Input(
                "every variable is fixed; there is nothing to optimize".into(),
            ));
        }

        // 2. Block adjacency (both directions, no diagonal) as CSR: through the block -> factor
        //    incidence, with a marker per block instead of a global sort (human corrections add
        //    factors over dozens of poses, whose pair lists would dominate).
        let mut factor_blocks: Vec<Vec<usize>> = factors
            .iter()
            .map(|f| {
                f.keys()
                    .iter()
                    .map(|&k| block_of(&natural_pose, &natural_line, k))
                    .filter(|&b| b != NO_BLOCK)
                    .collect()
            })
            .collect();
        // Wide factors add no couplings to the pattern (see the module docs). Only when each of
        // their variables also occurs in a sparse factor, though: a variable seen by wide factors
        // alone would have an empty diagonal in H_s, and H_s + mu D could be singular (always,
        // for Gauss-Newton) even where H is not; such a factor stays in the sparse part.
        let mut covered = vec![false; nb];
        for (f, bs) in factors.iter().zip(&factor_blocks) {
            if !f.is_wide() {
                for &b in bs {
                    covered[b] = true;
                }
            }
        }
        let is_wide: Vec<bool> = factors
            .iter()
            .zip(&factor_blocks)
            .map(|(f, bs)| f.is_wide() && !bs.is_empty() && bs.iter().all(|&b| covered[b]))
            .collect();
        for (bs, &w) in factor_blocks.iter_mut().zip(&is_wide) {
            if w {
                bs.clear();
            }
        }
        let mut inc_ptr = vec![0usize; nb + 1];
        for bs in &factor_blocks {
            for &b in bs {
                inc_ptr[b + 1] += 1;
            }
        }
        for b in 0..nb {
            inc_ptr[b + 1] += inc_ptr[b];
        }
        let mut fill = inc_ptr.clone();
        let mut inc_idx = vec![0usize; inc_ptr[nb]];
        for (fi, bs) in factor_blocks.iter().enumerate() {
            for &b in bs {
                inc_idx[fill[b]] = fi;
                fill[b] += 1;
            }
        }
        let mut mark = vec![NO_BLOCK; nb];
        let mut adj_ptr = Vec::with_capacity(nb + 1);
        let mut adj_idx = Vec::new();
        adj_ptr.push(0usize);
        for a in 0..nb {
            mark[a] = a;
            let begin = adj_idx.len();
            for &fi in &inc_idx[inc_ptr[a]..inc_ptr[a + 1]] {
                for &b in &factor_blocks[fi] {
                    if mark[b] != a {
                        mark[b] = a;
                        adj_idx.push(b);
                    }
                }
            }
            adj_idx[begin..].sort_unstable();
            adj_ptr.push(adj_idx.len());
        }
        let (perm_fwd, _) = block_amd(nb, &adj_ptr, &adj_idx)?;
        let mut perm_inv = vec![0usize; nb];
        for (new, &old) in perm_fwd.iter().enumerate() {
            perm_inv[old] = new;
        }

        // 3. Blocks in elimination order.
        let mut pose_block = vec![NO_BLOCK; num_poses];
        let mut line_block = vec![NO_BLOCK; num_lines];
        let mut block_key = Vec::with_capacity(nb);
        let mut block_dim = Vec::with_capacity(nb);
        let mut block_offset = Vec::with_capacity(nb);
        let mut n = 0;
        for &old in &perm_fwd {
            let key = keys[old];
            match key {
                Key::Pose(i) => pose_block[i] = block_key.len(),
                Key::Line(i) => line_block[i] = block_key.len(),
            }
            block_key.push(key);
            block_dim.push(key.dim());
            block_offset.push(n);
            n += key.dim();
        }

        // 4. Upper-triangular scalar CSC: block column C holds block rows R < C (sorted), then
        //    the upper triangle of its own diagonal block. Every scalar column of C has the same
        //    block rows, so `row_start[C][x]` (offset of the x-th block row within a column) is
        //    shared by all of them.
        let mut upper_ptr = vec![0usize; nb + 1];
        let mut upper_idx: Vec<usize> = Vec::with_capacity(adj_idx.len() / 2);
        {
            let mut rows: Vec<usize> = Vec::new();
            for c in 0..nb {
                let old = perm_fwd[c];
                rows.clear();
                rows.extend(
                    adj_idx[adj_ptr[old]..adj_ptr[old + 1]]
                        .iter()
                        .map(|&o| perm_inv[o])
                        .filter(|&r| r < c),
                );
                rows.sort_unstable();
                upper_idx.extend_from_slice(&rows);
                upper_ptr[c + 1] = upper_idx.len();
            }
        }
        let mut col_ptr = Vec::with_capacity(n + 1);
        let mut row_idx = Vec::new();
        col_ptr.push(0);
        for c in 0..nb {
            for k in 0..block_dim[c] {
                for &r in &upper_idx[upper_ptr[c]..upper_ptr[c + 1]] {
                    row_idx.extend(block_offset[r]..block_offset[r] + block_dim[r]);
                }
                row_idx.extend(block_offset[c]..=block_offset[c] + k);
                col_ptr.push(row_idx.len());
            }
        }

        // 5. Slots: where each factor's Hessian blocks land.
        let block_slot = |r: usize, c: usize, k: usize| -> Result<usize> {
            let col = block_offset[c] + k;
            if r == c {
                return Ok(col_ptr[col + 1] - (k + 1));
            }
            let rows = &upper_idx[upper_ptr[c]..upper_ptr[c + 1]];
            let x = rows.binary_search(&r).map_err(|_| {
                HitlError::Solver(format!(
                    "internal: block ({r}, {c}) missing from the pattern"
                ))
            })?;
            let before: usize = rows[..x].iter().map(|&b| block_dim[b]).sum();
            Ok(col_ptr[col] + before)
        };
        let mut factor_slots = Vec::with_capacity(factors.len() + 1);
        let mut slots = Vec::new();
        let mut max_residual = 0;
        let mut max_jac = 0;
        let mut wide = LowRank::default();
        for (fi, f) in factors.iter().enumerate() {
            factor_slots.push(slots.len());
            let fk = f.keys();
            max_residual = max_residual.max(f.residual_dim());
            max_jac = max_jac.max(f.residual_dim() * fk.iter().map(|k| k.dim()).sum::<usize>());
            if is_wide[fi] {
                // No slots: its rows go to U, over its free variables in key order.
                let idx = fk
                    .iter()
                    .map(|&k| block_of(&pose_block, &line_block, k))
                    .filter(|&b| b != NO_BLOCK)
                    .flat_map(|b| block_offset[b]..block_offset[b] + block_dim[b]);
                wide.push(fi, factors.len(), idx, f.residual_dim());
                continue;
            }
            for (p, &kp) in fk.iter().enumerate() {
                let bp = block_of(&pose_block, &line_block, kp);
                if bp == NO_BLOCK {
                    continue;
                }
                for &kq in &fk[p..] {
                    let bq = block_of(&pose_block, &line_block, kq);
                    if bq == NO_BLOCK {
                        continue;
                    }
                    let (r, c) = if bp <= bq { (bp, bq) } else { (bq, bp) };
                    for k in 0..block_dim[c] {
                        slots.push(block_slot(r, c, k)?);
                    }
                }
            }
        }
        factor_slots.push(slots.len());

        // 6. Symbolic analysis, on the already-ordered pattern.
        let sym = SymbolicSparseColMatRef::new_checked(n, n, &col_ptr, None, &row_idx);
        let symbolic = factorize_symbolic_cholesky(
            sym,
            Side::Upper,
            SymmetricOrdering::Identity,
            CholeskySymbolicParams {
                // faer's flop-ratio heuristic picks the simplicial kernel for M3500-like graphs,
                // but the supernodal one factorizes them ~15% faster (measured); tiny problems
                // keep the heuristic.
                supernodal_flop_ratio_threshold: if n >= SUPERNODAL_MIN_DIM {
                    SupernodalThreshold::FORCE_SUPERNODAL
                } else {
                    SupernodalThreshold::AUTO
                },
                ..Default::default()
            },
        )
        .map_err(|e| HitlError::Solver(format!("symbolic Cholesky analysis failed: {e:?}")))?;
        wide.allocate(n);
        if wide.rank() > 0 && symbolic.perm().is_some() {
            // The Woodbury forward solves work on L in the pattern's own order.
            return Err(HitlError::Solver(
                "internal: the Cholesky analysis permuted an ordered pattern".into(),
            ));
        }
        let req = StackReq::any_of(&[
            symbolic.factorize_numeric_llt_scratch::<f64>(Par::Seq, Spec::default()),
            symbolic.solve_in_place_scratch::<f64>(3, Par::Seq),
        ]);
        let mem = MemBuffer::try_new(req)
            .map_err(|_| HitlError::Solver("out of memory for the Cholesky workspace".into()))?;
        let nnz = row_idx.len();
        let l_len = symbolic.len_val();
        Ok(Self {
            pose_block,
            line_block,
            block_offset,
            block_dim,
            block_key,
            n,
            col_ptr,
            row_idx,
            factor_slots,
            slots,
            symbolic,
            h: vec![0.0; nnz],
            g: vec![0.0; n],
            damped: vec![0.0; nnz],
            l_values: vec![0.0; l_len],
            mem,
            max_residual,
            max_jac,
            wide,
        })
    }

    /// Number of scalar unknowns.
    pub fn dim(&self) -> usize {
        self.n
    }

    /// Non-zeros of the upper triangle of H and of the Cholesky factor.
    pub fn nnz(&self) -> (usize, usize) {
        (self.row_idx.len(), self.symbolic.len_val())
    }

    pub fn block_keys(&self) -> &[Key] {
        &self.block_key
    }

    /// Scalar offset of a variable in the solver's ordering, or None when it is fixed.
    pub fn offset_of(&self, key: Key) -> Option<usize> {
        let b = block_of(&self.pose_block, &self.line_block, key);
        (b != NO_BLOCK).then(|| self.block_offset[b])
    }

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
    /// built in `new`: (0,0) diagonal, (0,1) off-diagonal, (1,1) diagonal, skipping fixed ones.
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

    /// Diagonal entry k of the full `H = H_s + U U^T`.
    #[inline]
    fn hessian_diagonal(&self, k: usize) -> f64 {
        self.h[self.col_ptr[k + 1] - 1] + self.wide.diagonal(k)
    }

    /// Solves `(H + mu D) delta = -g` where `D = diag(H)` clamped to `[d_min, d_max]`
    /// (`diagonal = true`, Marquardt's scaling) or the identity. `mu = 0` is Gauss-Newton.
    /// Returns `Ok(false)` when the damped matrix is not numerically positive definite.
    /// With wide factors, `H = H_s + U U^T` and the sparse factor is of `A = H_s + mu D` alone
    /// (Woodbury, see the module docs); the solution is that of the full system either way.
    pub fn solve_damped(&mut self, mu: f64, diagonal: bool, delta: &mut [f64]) -> Result<bool> {
        self.damped.copy_from_slice(&self.h);
        if mu > 0.0 {
            for k in 0..self.n {
                let d = if diagonal {
                    self.hessian_diagonal(k).clamp(1e-6, 1e32)
                } else {
                    1.0
                };
                let p = self.col_ptr[k + 1] - 1;
                self.damped[p] += mu * d;
            }
        }
        for (x, g) in delta.iter_mut().zip(&self.g) {
            *x = -g;
        }
        let n = self.n;
        if !self.factorize(true) {
            return Ok(false);
        }
        let llt = LltRef::new(&self.symbolic, &self.l_values);
        if self.wide.rank() == 0 {
            solve_in_place(llt, &mut self.mem, delta, n);
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

    /// Numeric Cholesky of the damped (`damped`) or the undamped sparse part into `l_values`,
    /// on the cached symbolic analysis; false when it is not positive definite.
    fn factorize(&mut self, damped: bool) -> bool {
        let n = self.n;
        let sym = SymbolicSparseColMatRef::new_checked(n, n, &self.col_ptr, None, &self.row_idx);
        let values = if damped { &self.damped } else { &self.h };
        self.symbolic
            .factorize_numeric_llt::<f64>(
                &mut self.l_values,
                SparseColMatRef::new(sym, values),
                Side::Upper,
                LltRegularization::default(),
                Par::Seq,
                MemStack::new(&mut self.mem),
                Spec::default(),
            )
            .is_ok()
    }

    /// `d^T D d` for the damping matrix D of [`Self::solve_damped`].
    pub fn damping_quadratic(&self, delta: &[f64], diagonal: bool) -> f64 {
        delta
            .iter()
            .enumerate()
            .map(|(k, d)| {
                let dk = if diagonal {
                    self.hessian_diagonal(k).clamp(1e-6, 1e32)
                } else {
                    1.0
                };
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
        if !self.factorize(false) {
            return Err(singular());
        }
        if self.wide.rank() == 0 {
            let llt = LltRef::new(&self.symbolic, &self.l_values);
            // The workspace was sized for 3 right-hand sides; solve in chunks of 3.
            for chunk in cols.chunks_mut(3 * n) {
                solve_in_place(llt, &mut self.mem, chunk, n);
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

    /// Applies `delta` (solver ordering) to `values` through each variable's chart.
    pub fn retract(&self, values: &mut Values, delta: &[f64]) {
        for (b, &key) in self.block_key.iter().enumerate() {
            let o = self.block_offset[b];
            values.retract(key, &delta[o..o + self.block_dim[b]]);
        }
    }

    /// The upper triangle of the full H (wide factors' U U^T included) as (row, col, value)
    /// triplets in the NATURAL variable order (poses by index, then lines; fixed ones skipped),
    /// for cross-checks against SciPy.
    pub fn upper_triplets_natural(&self) -> NaturalSystem {
        let mut natural: Vec<(Key, usize)> = self
            .block_key
            .iter()
            .enumerate()
            .map(|(b, &k)| (k, b))
            .collect();
        natural.sort_unstable_by_key(|&(k, _)| k);
        let mut new_offset = vec![0usize; self.block_key.len()];
        let mut o = 0;
        for &(_, b) in &natural {
            new_offset[b] = o;
            o += self.block_dim[b];
        }
        let mut scalar_map = vec![0usize; self.n];
        for b in 0..self.block_key.len() {
            for k in 0..self.block_dim[b] {
                scalar_map[self.block_offset[b] + k] = new_offset[b] + k;
            }
        }
        // The wide factors' U U^T, in natural indices, merged into the sparse entries below so
        // that the triplets are the true H with no duplicates.
        let mut dense: HashMap<(usize, usize), f64> = HashMap::new();
        for (ix, v) in self.wide.rows() {
            for (&i, &ui) in ix.iter().zip(v) {
                for (&j, &uj) in ix.iter().zip(v) {
                    let (a, b) = (scalar_map[i], scalar_map[j]);
                    if a <= b {
                        *dense.entry((a, b)).or_insert(0.0) += ui * uj;
                    }
                }
            }
        }
        let (mut rows, mut cols, mut vals) = (Vec::new(), Vec::new(), Vec::new());
        for c in 0..self.n {
            for p in self.col_ptr[c]..self.col_ptr[c + 1] {
                let (a, b) = (scalar_map[self.row_idx[p]], scalar_map[c]);
                let (a, b) = (a.min(b), a.max(b));
                rows.push(a);
                cols.push(b);
                vals.push(self.h[p] + dense.remove(&(a, b)).unwrap_or(0.0));
            }
        }
        let mut rest: Vec<((usize, usize), f64)> = dense.into_iter().collect();
        rest.sort_unstable_by_key(|&(rc, _)| rc);
        for ((a, b), v) in rest {
            rows.push(a);
            cols.push(b);
            vals.push(v);
        }
        let mut g = vec![0.0; self.n];
        for (k, &m) in scalar_map.iter().enumerate() {
            g[m] = self.g[k];
        }
        (
            rows,
            cols,
            vals,
            g,
            natural.into_iter().map(|(k, _)| k).collect(),
        )
    }
}

impl std::fmt::Debug for SparsityPattern {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("SparsityPattern")
            .field("dim", &self.n)
            .field("nnz_hessian", &self.row_idx.len())
            .field("nnz_factor", &self.symbolic.len_val())
            .field("wide_rows", &self.wide.rank())
            .finish_non_exhaustive()
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::factors::{
        BetweenFactor, CentroidShare, PointsToLineFactor, RelationFactor, RelationMode,
    };
    use crate::graph::FactorGraph;
    use crate::se2::Pose2;
    use crate::values::Line2;
    use faer::sparse::linalg::cholesky::SymbolicCholeskyRaw;
    use std::f64::consts::FRAC_PI_2;

    /// A ring with chords: enough fill-in for a supernodal factorization.
    fn ring(n: usize) -> (FactorGraph, Values) {
        let mut edges = Vec::new();
        for i in 0..n {
            edges.push((i, (i + 1) % n));
            edges.push((i, (i + 7) % n));
            edges.push((i, (i * 13 + 5) % n));
        }
        edges.retain(|&(a, b)| a != b);
        let info = [[50.0, 2.0, 1.0], [2.0, 40.0, -1.0], [1.0, -1.0, 300.0]];
        let zs: Vec<[f64; 3]> = edges
            .iter()
            .map(|&(a, b)| [0.1 * (b as f64 - a as f64), 0.05 * a as f64 % 1.0, 0.3])
            .collect();
        let g = FactorGraph::from_edges(n, &edges, &zs, &vec![info; edges.len()], 0).unwrap();
        let poses = (0..n)
            .map(|i| Pose2::new(i as f64 * 0.3, (i as f64).sin(), 0.1 * i as f64))
            .collect();
        (g, Values::from_poses(poses))
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

    #[test]
    fn damped_solve_solves_the_system() {
        for &n in &[5usize, 60, 400] {
            let (mut g, values) = ring(n);
            let (factors, p) = g.parts().unwrap();
            p.linearize(factors, &values, &[]);
            for &(mu, diag) in &[(0.0, false), (1e-3, true), (10.0, false)] {
                let mut delta = vec![0.0; p.n];
                assert!(p.solve_damped(mu, diag, &mut delta).unwrap());
                let hd = mul_upper(p, &p.damped, &delta);
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

    // --- wide factors ---------------------------------------------------------------------------

    /// The same factor, but never wide: the reference the Woodbury path must reproduce.
    #[derive(Debug)]
    struct Narrow(RelationFactor);

    impl Factor for Narrow {
        fn keys(&self) -> &[Key] {
            self.0.keys()
        }
        fn is_wide(&self) -> bool {
            false
        }
        fn residual_dim(&self) -> usize {
            self.0.residual_dim()
        }
        fn residual(&self, values: &Values, r: &mut [f64]) {
            self.0.residual(values, r)
        }
        fn linearize(&self, values: &Values, r: &mut [f64], jacobians: &mut [f64]) {
            self.0.linearize(values, r, jacobians)
        }
    }

    #[derive(Clone, Copy, PartialEq)]
    enum Relations {
        None,
        Wide,
        Narrow,
    }

    /// A corridor of `n` poses seen twice: poses 1..=6 and the last 6 observe the wall y = 2
    /// (a colocation), poses 7..=10 and 40..=43 the wall x = 30 (a collinear), each through
    /// R_a / R_b factors and one relation over all those poses (12 and 10 keys: wide). The
    /// estimate is perturbed, so every factor has a residual. With `lonely`, the colocation
    /// also lists pose `n`, which no other factor touches.
    fn corrected(n: usize, relations: Relations, lonely: bool) -> (FactorGraph, Values) {
        let total = if lonely { n + 1 } else { n };
        let mut g = FactorGraph::new(total, Some(0)).unwrap();
        let info = [[100.0, 0.0, 0.0], [0.0, 100.0, 0.0], [0.0, 0.0, 1000.0]];
        let truth: Vec<Pose2> = (0..total)
            .map(|i| Pose2::new(0.5 * i as f64, 0.0, 0.0))
            .collect();
        for i in 0..n - 1 {
            let z = truth[i].between(truth[i + 1]);
            g.add_between(BetweenFactor::new(i, i + 1, z, &info).unwrap())
                .unwrap();
        }
        let walls = [
            (
                Line2 {
                    phi: FRAC_PI_2,
                    rho: 2.0,
                },
                RelationMode::Colocation,
            ),
            (
                Line2 {
                    phi: 0.0,
                    rho: 30.0,
                },
                RelationMode::Collinear,
            ),
        ];
        let mut groups = vec![
            ((1..=6).collect::<Vec<_>>(), (n - 6..n).collect::<Vec<_>>()),
            ((7..=10).collect(), (40..=43).collect()),
        ];
        if lonely {
            groups[0].1.push(n);
        }
        let mut lines = Vec::new();
        for ((wall, mode), (xa, xb)) in walls.iter().zip(&groups) {
            let la = g.add_line();
            let lb = g.add_line();
            lines.push(*wall);
            lines.push(Line2 {
                phi: wall.phi + 0.02,
                rho: wall.rho + 0.1,
            });
            let mut shares = Vec::new();
            for (set, line, is_a) in [(xa, la, true), (xb, lb, false)] {
                for &i in set {
                    // Points on the wall, in pose i's frame (true pose: no rotation).
                    let pts: Vec<[f64; 2]> = (0..5)
                        .map(|k| {
                            let s = k as f64 - 2.0;
                            let (wx, wy) = if wall.phi == 0.0 {
                                (wall.rho, s)
                            } else {
                                (truth[i].x + s, wall.rho)
                            };
                            [wx - truth[i].x, wy - truth[i].y]
                        })
                        .collect();
                    let sum = pts
                        .iter()
                        .fold([0.0, 0.0], |a, p| [a[0] + p[0], a[1] + p[1]]);
                    let share = CentroidShare { count: 5.0, sum };
                    shares.push(if is_a {
                        (i, share, CentroidShare::default())
                    } else {
                        (i, CentroidShare::default(), share)
                    });
                    if i < n {
                        let f = PointsToLineFactor::new(i, line, pts, 1.0 / 0.03).unwrap();
                        g.add_factor(Box::new(f)).unwrap();
                    }
                }
            }
            let f = RelationFactor::new(*mode, la, lb, shares, 1e6, 1e7).unwrap();
            match relations {
                Relations::None => {}
                Relations::Wide => g.add_factor(Box::new(f)).unwrap(),
                Relations::Narrow => g.add_factor(Box::new(Narrow(f))).unwrap(),
            }
        }
        let poses = truth
            .iter()
            .enumerate()
            .map(|(i, t)| {
                let drift = 0.01 * i as f64;
                Pose2::new(
                    t.x + drift,
                    t.y + 0.3 * drift,
                    t.theta + 0.1 * drift + 0.01 * (i as f64).sin(),
                )
            })
            .collect();
        (g, Values { poses, lines })
    }

    /// The full H (`H_s + U U^T`) as a dense symmetric matrix in solver order.
    fn dense_hessian(p: &SparsityPattern) -> nalgebra::DMatrix<f64> {
        let mut h = nalgebra::DMatrix::zeros(p.n, p.n);
        for c in 0..p.n {
            for k in p.col_ptr[c]..p.col_ptr[c + 1] {
                h[(p.row_idx[k], c)] = p.h[k];
                h[(c, p.row_idx[k])] = p.h[k];
            }
        }
        for (ix, v) in p.wide.rows() {
            for (&i, &ui) in ix.iter().zip(v) {
                for (&j, &uj) in ix.iter().zip(v) {
                    h[(i, j)] += ui * uj;
                }
            }
        }
        h
    }

    #[test]
    fn relations_over_many_poses_are_wide() {
        let (mut g, _) = corrected(60, Relations::Wide, false);
        let p = g.pattern().unwrap();
        // Colocation: 3 rows; collinear: 2.
        assert_eq!(p.wide.rank(), 5);
        let (mut g, _) = corrected(60, Relations::Narrow, false);
        assert_eq!(g.pattern().unwrap().wide.rank(), 0);
    }

    #[test]
    fn wide_hessian_and_gradient_match_numerical_jacobian() {
        let (mut g, values) = corrected(50, Relations::Wide, false);
        check_against_numerical_jacobian(&mut g, &values);
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
                let hd = mul_upper(pn, &pn.damped, d);
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
    fn wide_factors_add_no_fill() {
        let (mut none, _) = corrected(300, Relations::None, false);
        let (mut wide, _) = corrected(300, Relations::Wide, false);
        let (mut narrow, _) = corrected(300, Relations::Narrow, false);
        let (pn, pw) = (none.pattern().unwrap().nnz(), wide.pattern().unwrap().nnz());
        let pd = narrow.pattern().unwrap().nnz();
        // The pattern, the ordering and so the factor are those of the graph without relations.
        assert_eq!(pw, pn);
        assert!(pd.0 > pw.0 && pd.1 > pw.1, "dense {pd:?} vs wide {pw:?}");
        // And directly: no stored block couples two poses that share no sparse factor.
        let p = wide.pattern().unwrap();
        for c in 0..p.block_key.len() {
            let col = p.block_offset[c];
            for k in p.col_ptr[col]..p.col_ptr[col + 1] {
                let r = p.row_idx[k];
                let rb = p.block_offset.partition_point(|&o| o <= r) - 1;
                if let (Key::Pose(i), Key::Pose(j)) = (p.block_key[rb], p.block_key[c]) {
                    assert!(i.abs_diff(j) <= 1, "fill between poses {i} and {j}");
                }
            }
        }
    }

    #[test]
    fn a_key_seen_only_by_a_wide_factor_keeps_it_sparse() {
        let (mut g, values) = corrected(60, Relations::Wide, true);
        let (factors, p) = g.parts().unwrap();
        // The colocation lists pose 60, which nothing else touches: it stays in the sparse part
        // (its 3 rows are not in U); the collinear is still wide.
        assert_eq!(p.wide.rank(), 2);
        assert!(p.offset_of(Key::Pose(60)).is_some());
        p.linearize(factors, &values, &[]);
        let h = dense_hessian(p);
        let o = p.offset_of(Key::Pose(60)).unwrap();
        assert!(h[(o, o)] > 0.0 && h[(o + 2, o + 2)] > 0.0);
        // Pose 60 is under-determined (3 relation rows over it and everything else), so only a
        // damped system is regular; it must still be solved exactly.
        let mut delta = vec![0.0; p.n];
        assert!(p.solve_damped(1e-3, false, &mut delta).unwrap());
        let mut a = h.clone();
        for k in 0..p.n {
            a[(k, k)] += 1e-3;
        }
        let g_vec = nalgebra::DVector::from_column_slice(&p.g);
        let expect = a.cholesky().unwrap().solve(&(-&g_vec));
        let got = nalgebra::DVector::from_column_slice(&delta);
        assert!((&got - &expect).norm() <= 1e-9 * expect.norm());
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
    fn natural_triplets_include_the_wide_rows() {
        let (mut g, values) = corrected(60, Relations::Wide, false);
        let (factors, p) = g.parts().unwrap();
        p.linearize(factors, &values, &[]);
        let (rows, cols, vals, grad, keys) = p.upper_triplets_natural();
        let mut seen = std::collections::HashSet::new();
        let mut natural = nalgebra::DMatrix::zeros(p.n, p.n);
        for ((&r, &c), &v) in rows.iter().zip(&cols).zip(&vals) {
            assert!(
                r <= c && seen.insert((r, c)),
                "duplicate or lower entry ({r}, {c})"
            );
            natural[(r, c)] = v;
            natural[(c, r)] = v;
        }
        let full = dense_hessian(p);
        let mut nat_off = Vec::new();
        let mut o = 0;
        for &k in &keys {
            nat_off.push((k, o));
            o += k.dim();
        }
        for &(ka, na) in &nat_off {
            let sa = p.offset_of(ka).unwrap();
            assert_eq!(grad[na], p.g[sa]);
            for &(kb, nb) in &nat_off {
                let sb = p.offset_of(kb).unwrap();
                for a in 0..ka.dim() {
                    for b in 0..kb.dim() {
                        let (x, y) = (natural[(na + a, nb + b)], full[(sa + a, sb + b)]);
                        assert!((x - y).abs() <= 1e-12 * (1.0 + y.abs()), "{ka:?} {kb:?}");
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
