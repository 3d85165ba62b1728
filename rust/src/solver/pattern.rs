//! The block sparsity of the normal equations `H = J^T J`, the fill-reducing ordering, and the
//! symbolic Cholesky analysis: computed once per graph structure, then reused by every
//! linearization (the Hessian is accumulated straight into this pattern, block by block) and
//! every numeric factorization.
//!
//! Layout: variables become blocks (3 for a pose, 2 for a line; fixed variables get none),
//! ordered by an approximate-minimum-degree ordering of the BLOCK graph; `H` is stored as the
//! upper triangle in compressed sparse columns in that order, so the factorization needs no
//! permutation of its own.

use faer::dyn_stack::{MemBuffer, MemStack, StackReq};
use faer::linalg::cholesky::llt::factor::LltRegularization;
use faer::sparse::linalg::cholesky::{
    factorize_symbolic_cholesky, CholeskySymbolicParams, SymbolicCholesky, SymmetricOrdering,
};
use faer::sparse::linalg::{amd, SupernodalThreshold};
use faer::sparse::{SparseColMatRef, SymbolicSparseColMatRef};
use faer::{Conj, MatMut, Par, Side, Spec};

use crate::error::{HitlError, Result};
use crate::factors::Factor;
use crate::values::{Key, Values};

const NO_BLOCK: usize = usize::MAX;
/// Scalar size from which the supernodal Cholesky kernel is always used.
const SUPERNODAL_MIN_DIM: usize = 3000;

/// `(rows, cols, values, gradient, keys)`: the upper triangle of H and J^T r in natural order.
pub type NaturalSystem = (Vec<usize>, Vec<usize>, Vec<f64>, Vec<f64>, Vec<Key>);

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
        let factor_blocks: Vec<Vec<usize>> = factors
            .iter()
            .map(|f| {
                f.keys()
                    .iter()
                    .map(|&k| block_of(&natural_pose, &natural_line, k))
                    .filter(|&b| b != NO_BLOCK)
                    .collect()
            })
            .collect();
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
        let perm_fwd = block_amd(nb, &adj_ptr, &adj_idx)?;
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
        for f in factors {
            factor_slots.push(slots.len());
            let fk = f.keys();
            max_residual = max_residual.max(f.residual_dim());
            max_jac = max_jac.max(f.residual_dim() * fk.iter().map(|k| k.dim()).sum::<usize>());
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

    /// Accumulates `H = J^T J` and `g = J^T r` at `values`; returns chi2 `|r|^2`.
    pub fn linearize(&mut self, factors: &[Box<dyn Factor>], values: &Values) -> f64 {
        self.h.fill(0.0);
        self.g.fill(0.0);
        let mut r = vec![0.0; self.max_residual];
        let mut jac = vec![0.0; self.max_jac];
        let mut chi2 = 0.0;
        for (fi, f) in factors.iter().enumerate() {
            let d = f.residual_dim();
            let keys = f.keys();
            f.linearize(values, &mut r[..d], &mut jac);
            chi2 += r[..d].iter().map(|v| v * v).sum::<f64>();
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
        chi2
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

    /// Solves `(H + mu D) delta = -g` where `D = diag(H)` clamped to `[d_min, d_max]`
    /// (`diagonal = true`, Marquardt's scaling) or the identity. `mu = 0` is Gauss-Newton.
    /// Returns `Ok(false)` when the damped matrix is not numerically positive definite.
    pub fn solve_damped(&mut self, mu: f64, diagonal: bool, delta: &mut [f64]) -> Result<bool> {
        self.damped.copy_from_slice(&self.h);
        if mu > 0.0 {
            for k in 0..self.n {
                let p = self.col_ptr[k + 1] - 1;
                let d = if diagonal {
                    self.h[p].clamp(1e-6, 1e32)
                } else {
                    1.0
                };
                self.damped[p] += mu * d;
            }
        }
        for (x, g) in delta.iter_mut().zip(&self.g) {
            *x = -g;
        }
        let sym = SymbolicSparseColMatRef::new_checked(
            self.n,
            self.n,
            &self.col_ptr,
            None,
            &self.row_idx,
        );
        let a = SparseColMatRef::new(sym, &self.damped);
        let stack = MemStack::new(&mut self.mem);
        let llt = match self.symbolic.factorize_numeric_llt::<f64>(
            &mut self.l_values,
            a,
            Side::Upper,
            LltRegularization::default(),
            Par::Seq,
            stack,
            Spec::default(),
        ) {
            Ok(llt) => llt,
            Err(_) => return Ok(false),
        };
        let rhs = MatMut::from_column_major_slice_mut(delta, self.n, 1);
        llt.solve_in_place_with_conj(Conj::No, rhs, Par::Seq, MemStack::new(&mut self.mem));
        Ok(delta.iter().all(|v| v.is_finite()))
    }

    /// `d^T D d` for the damping matrix D of [`Self::solve_damped`].
    pub fn damping_quadratic(&self, delta: &[f64], diagonal: bool) -> f64 {
        delta
            .iter()
            .enumerate()
            .map(|(k, d)| {
                let dk = if diagonal {
                    self.h[self.col_ptr[k + 1] - 1].clamp(1e-6, 1e32)
                } else {
                    1.0
                };
                dk * d * d
            })
            .sum()
    }

    /// Factorizes the undamped `H` and solves for `H^-1` columns of the given scalar offsets
    /// (marginal covariances). `cols` is `n x k` column-major, overwritten with the solutions.
    pub fn solve_undamped_columns(&mut self, cols: &mut [f64], k: usize) -> Result<()> {
        let sym = SymbolicSparseColMatRef::new_checked(
            self.n,
            self.n,
            &self.col_ptr,
            None,
            &self.row_idx,
        );
        let a = SparseColMatRef::new(sym, &self.h);
        let llt = self
            .symbolic
            .factorize_numeric_llt::<f64>(
                &mut self.l_values,
                a,
                Side::Upper,
                LltRegularization::default(),
                Par::Seq,
                MemStack::new(&mut self.mem),
                Spec::default(),
            )
            .map_err(|_| {
                HitlError::Solver(
                    "the information matrix is singular at this solution; marginals are undefined (is every pose constrained?)".into(),
                )
            })?;
        // The workspace was sized for 3 right-hand sides; solve in chunks of 3.
        for chunk in cols.chunks_mut(3 * self.n) {
            let m = chunk.len() / self.n;
            let rhs = MatMut::from_column_major_slice_mut(chunk, self.n, m);
            llt.solve_in_place_with_conj(Conj::No, rhs, Par::Seq, MemStack::new(&mut self.mem));
        }
        debug_assert!(cols.len() == k * self.n);
        Ok(())
    }

    /// Applies `delta` (solver ordering) to `values` through each variable's chart.
    pub fn retract(&self, values: &mut Values, delta: &[f64]) {
        for (b, &key) in self.block_key.iter().enumerate() {
            let o = self.block_offset[b];
            values.retract(key, &delta[o..o + self.block_dim[b]]);
        }
    }

    /// The upper triangle of H as (row, col, value) triplets in the NATURAL variable order
    /// (poses by index, then lines; fixed ones skipped), for cross-checks against SciPy.
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
        let (mut rows, mut cols, mut vals) = (Vec::new(), Vec::new(), Vec::new());
        for c in 0..self.n {
            for p in self.col_ptr[c]..self.col_ptr[c + 1] {
                let (a, b) = (scalar_map[self.row_idx[p]], scalar_map[c]);
                rows.push(a.min(b));
                cols.push(a.max(b));
                vals.push(self.h[p]);
            }
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
            .finish_non_exhaustive()
    }
}

/// AMD on the block graph (given as symmetric CSR without diagonal); returns `perm_fwd`
/// (new position -> old block).
fn block_amd(nb: usize, adj_ptr: &[usize], adj_idx: &[usize]) -> Result<Vec<usize>> {
    let mut col_ptr = Vec::with_capacity(nb + 1);
    let mut row_idx = Vec::with_capacity(adj_idx.len() / 2 + nb);
    col_ptr.push(0usize);
    for c in 0..nb {
        // Upper triangle plus the diagonal; AMD works on the pattern of A + A^T.
        row_idx.extend(
            adj_idx[adj_ptr[c]..adj_ptr[c + 1]]
                .iter()
                .copied()
                .filter(|&r| r < c),
        );
        row_idx.push(c);
        col_ptr.push(row_idx.len());
    }
    let mut fwd = vec![0usize; nb];
    let mut inv = vec![0usize; nb];
    let sym = SymbolicSparseColMatRef::new_checked(nb, nb, &col_ptr, None, &row_idx);
    let req = amd::order_scratch::<usize>(nb, row_idx.len());
    let mut mem =
        MemBuffer::try_new(req).map_err(|_| HitlError::Solver("out of memory for AMD".into()))?;
    amd::order(
        &mut fwd,
        &mut inv,
        sym,
        amd::Control::default(),
        MemStack::new(&mut mem),
    )
    .map_err(|e| HitlError::Solver(format!("fill-reducing ordering failed: {e:?}")))?;
    Ok(fwd)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::graph::FactorGraph;
    use crate::se2::Pose2;

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
            p.linearize(factors, &values);
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

    #[test]
    fn hessian_and_gradient_match_numerical_jacobian() {
        let (mut g, values) = ring(30);
        let (factors, p) = g.parts().unwrap();
        p.linearize(factors, &values);
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
        let r0 = stack(&values);
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
        let mut dense = vec![vec![0.0; n]; n];
        for c in 0..n {
            for k in p.col_ptr[c]..p.col_ptr[c + 1] {
                dense[p.row_idx[k]][c] = p.h[k];
                dense[c][p.row_idx[k]] = p.h[k];
            }
        }
        for a in 0..n {
            let ga: f64 = (0..m).map(|row| jac[row][a] * r0[row]).sum();
            assert!(
                (ga - p.g[a]).abs() < 1e-5 * (1.0 + ga.abs()),
                "g[{a}]: {} vs {ga}",
                p.g[a]
            );
            for b in 0..n {
                let hab: f64 = (0..m).map(|row| jac[row][a] * jac[row][b]).sum();
                assert!(
                    (hab - dense[a][b]).abs() < 1e-5 * (1.0 + hab.abs()),
                    "H[{a}][{b}]: {} vs {hab}",
                    dense[a][b]
                );
            }
        }
    }
}
