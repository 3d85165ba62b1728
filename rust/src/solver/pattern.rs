//! The structure of the normal equations `H = J^T J`: the block sparsity pattern, the
//! fill-reducing ordering, and the symbolic Cholesky analysis. Computed once per graph structure,
//! then reused by every linearization (`assembly` accumulates the Hessian straight into this
//! pattern, block by block) and every numeric factorization (`linear_solve`).
//!
//! Layout: variables become blocks (3 for a pose, 2 for a line; fixed variables get none),
//! ordered by an approximate-minimum-degree ordering of the BLOCK graph; `H` is stored as the
//! upper triangle in compressed sparse columns in that order, so the factorization needs no
//! permutation of its own.
//!
//! Wide factors (`Factor::is_wide`: a human relation over the centroids of hundreds of poses)
//! would make `H` dense over all their variables. Their rows stay out of the pattern (`h` is
//! `H_s`, H without them) and join every solve as the low-rank term of `woodbury`.

use faer::dyn_stack::{MemBuffer, StackReq};
use faer::sparse::linalg::cholesky::{
    factorize_symbolic_cholesky, CholeskySymbolicParams, SymbolicCholesky, SymbolicCholeskyRaw,
    SymmetricOrdering,
};
use faer::sparse::linalg::SupernodalThreshold;
use faer::sparse::SymbolicSparseColMatRef;
use faer::{Par, Side, Spec};

use super::factor::Cholesky;
use super::ordering::block_amd;
use super::supernodal::SupernodalWork;
use super::woodbury::LowRank;
use crate::error::{HitlError, Result};
use crate::factors::Factor;
use crate::values::{Key, Values};

pub(super) const NO_BLOCK: usize = usize::MAX;
/// Scalar size from which the supernodal Cholesky kernel is always used.
const SUPERNODAL_MIN_DIM: usize = 3000;

pub struct SparsityPattern {
    /// Block of each pose / line (NO_BLOCK when fixed); blocks are in elimination order.
    pub(super) pose_block: Vec<usize>,
    pub(super) line_block: Vec<usize>,
    /// Scalar offset and size of each block.
    pub(super) block_offset: Vec<usize>,
    pub(super) block_dim: Vec<usize>,
    /// The key each block stands for.
    pub(super) block_key: Vec<Key>,
    pub(super) n: usize,
    pub(super) col_ptr: Vec<usize>,
    pub(super) row_idx: Vec<usize>,
    /// Per factor, the start of its slots in `slots`; one slot per (key pair, column).
    pub(super) factor_slots: Vec<usize>,
    pub(super) slots: Vec<usize>,
    pub(super) symbolic: SymbolicCholesky<usize>,
    /// Undamped `H` values (upper CSC), gradient `J^T r`, and the upper triangle of
    /// `H + mu D` (filled only where it is used: the simplicial kernel and Woodbury's refinement).
    pub(crate) h: Vec<f64>,
    pub(crate) g: Vec<f64>,
    pub(super) damped: Vec<f64>,
    /// `H`, `g` at a trial point (`linearize_ahead`), until it is accepted or another is tried.
    pub(super) h_ahead: Vec<f64>,
    pub(super) g_ahead: Vec<f64>,
    pub(super) l_values: Vec<f64>,
    /// Whether the factor's layout lets every solve use `Cholesky`'s plain loops (always so for
    /// the unpermuted analysis below; checked once rather than trusted).
    pub(super) plain_solves: bool,
    pub(super) supernodal_work: SupernodalWork,
    pub(super) mem: MemBuffer,
    pub(super) max_residual: usize,
    pub(super) max_jac: usize,
    /// The rows of wide factors: `H = h + U U^T`.
    pub(super) wide: LowRank,
    /// The lower triangle the supernodal factorization reads, built at the first factorization
    /// (solves that converge at their start never need it) from the block pattern kept here:
    /// `(block column pointers, block rows)`, None for the simplicial kernel.
    pub(super) lower: LowerTriangle,
    lower_blocks: Option<(Vec<usize>, Vec<usize>)>,
}

/// The lower triangle of `H`'s upper CSC, for faer's supernodal Cholesky, which reads the
/// lower triangle and would otherwise transpose the upper one (structure and values) at every
/// factorization: here the structure is built once and each factorization gathers the values.
#[derive(Default)]
pub(super) struct LowerTriangle {
    col_ptr: Vec<usize>,
    row_idx: Vec<usize>,
    /// Position in the upper CSC of each lower entry (32 bits: half the memory of an index;
    /// patterns with more entries go without a lower triangle).
    source: Vec<u32>,
    values: Vec<f64>,
}

impl LowerTriangle {
    /// The lower triangle of the pattern's upper CSC `col_ptr` (built from the block pattern:
    /// block column c holds the rows of the blocks `upper_idx[upper_ptr[c]..upper_ptr[c + 1]]`,
    /// then its own diagonal block's upper triangle). Written column by column in order, with
    /// each entry's upper position computed rather than searched.
    pub(super) fn of_blocks(
        block_offset: &[usize],
        block_dim: &[usize],
        upper_ptr: &[usize],
        upper_idx: &[usize],
        col_ptr: &[usize],
    ) -> Self {
        let nb = block_dim.len();
        let n = col_ptr.len() - 1;
        let nnz = col_ptr[n];
        // Block transpose: for block r, the blocks c > r whose column holds it, with the offset
        // of r's rows within c's columns.
        let (t_ptr, t_entry) = group_by_key(
            nb,
            (0..nb).flat_map(|c| {
                upper_idx[upper_ptr[c]..upper_ptr[c + 1]]
                    .iter()
                    .scan(0, move |before, &r| {
                        let entry = (r, (c, *before));
                        *before += block_dim[r];
                        Some(entry)
                    })
            }),
        );
        let mut lower_ptr = Vec::with_capacity(n + 1);
        let mut lower_idx = Vec::with_capacity(nnz);
        let mut source = Vec::with_capacity(nnz);
        lower_ptr.push(0);
        for r in 0..nb {
            let (off, dim) = (block_offset[r], block_dim[r]);
            for k in 0..dim {
                // The diagonal block: upper column off + i ends with rows off..=off + i.
                for i in k..dim {
                    lower_idx.push(off + i);
                    source.push((col_ptr[off + i + 1] - (i + 1) + k) as u32);
                }
                for &(c, before) in &t_entry[t_ptr[r]..t_ptr[r + 1]] {
                    let c_off = block_offset[c];
                    for i in 0..block_dim[c] {
                        lower_idx.push(c_off + i);
                        source.push((col_ptr[c_off + i] + before + k) as u32);
                    }
                }
                lower_ptr.push(lower_idx.len());
            }
        }
        Self {
            col_ptr: lower_ptr,
            row_idx: lower_idx,
            values: vec![0.0; nnz],
            source,
        }
    }

    /// The transpose of the upper CSC `(col_ptr, row_idx)` of an n x n matrix, entry by entry
    /// (the reference for [`Self::of_blocks`]).
    #[cfg(test)]
    pub(super) fn of_upper(n: usize, col_ptr: &[usize], row_idx: &[usize]) -> Self {
        let mut lower_ptr = vec![0usize; n + 1];
        for &r in row_idx {
            lower_ptr[r + 1] += 1;
        }
        for k in 0..n {
            lower_ptr[k + 1] += lower_ptr[k];
        }
        let mut next = lower_ptr.clone();
        let mut lower_idx = vec![0usize; row_idx.len()];
        let mut source = vec![0u32; row_idx.len()];
        for c in 0..n {
            for p in col_ptr[c]..col_ptr[c + 1] {
                let r = row_idx[p];
                lower_idx[next[r]] = c;
                source[next[r]] = p as u32;
                next[r] += 1;
            }
        }
        Self {
            col_ptr: lower_ptr,
            row_idx: lower_idx,
            values: vec![0.0; source.len()],
            source,
        }
    }

    pub(super) fn is_empty(&self) -> bool {
        self.source.is_empty()
    }

    /// The lower triangle (column pointers, row indices, values), its values gathered from
    /// the upper CSC's `upper`, plus `mu weight(k, diagonal)` on diagonal entry k with
    /// `damping = Some((mu, diagonal))`.
    pub(super) fn gather(
        &mut self,
        upper: &[f64],
        damping: Option<(f64, bool)>,
        weight: impl Fn(usize, bool) -> f64,
    ) -> (&[usize], &[usize], &[f64]) {
        for (v, &p) in self.values.iter_mut().zip(&self.source) {
            *v = upper[p as usize];
        }
        if let Some((mu, diagonal)) = damping.filter(|&(mu, _)| mu > 0.0) {
            // Rows are sorted within a column: the diagonal comes first.
            for k in 0..self.col_ptr.len() - 1 {
                self.values[self.col_ptr[k]] += mu * weight(k, diagonal);
            }
        }
        (&self.col_ptr, &self.row_idx, &self.values)
    }
}

/// `(key, value)` entries grouped by key (`key < n`) in compressed form, by a counting sort:
/// key k's values are `values[ptr[k]..ptr[k + 1]]`, in the order the entries come.
fn group_by_key<T: Copy + Default>(
    n: usize,
    entries: impl Iterator<Item = (usize, T)> + Clone,
) -> (Vec<usize>, Vec<T>) {
    let mut ptr = vec![0usize; n + 1];
    for (k, _) in entries.clone() {
        ptr[k + 1] += 1;
    }
    for k in 0..n {
        ptr[k + 1] += ptr[k];
    }
    let mut next = ptr[..n].to_vec();
    let mut values = vec![T::default(); ptr[n]];
    for (k, v) in entries {
        values[next[k]] = v;
        next[k] += 1;
    }
    (ptr, values)
}

pub(super) fn block_of(pose_block: &[usize], line_block: &[usize], key: Key) -> usize {
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
        // The free blocks of each factor, flat (factor fi's are fb_idx[fb_ptr[fi]..fb_ptr[fi+1]]).
        let mut fb_ptr = Vec::with_capacity(factors.len() + 1);
        let mut fb_idx = Vec::with_capacity(2 * factors.len());
        fb_ptr.push(0usize);
        for f in factors {
            fb_idx.extend(
                f.keys()
                    .iter()
                    .map(|&k| block_of(&natural_pose, &natural_line, k))
                    .filter(|&b| b != NO_BLOCK),
            );
            fb_ptr.push(fb_idx.len());
        }
        let factor_blocks = |fi: usize| &fb_idx[fb_ptr[fi]..fb_ptr[fi + 1]];
        // Wide factors add no couplings to the pattern (see the module docs). Only when each of
        // their variables also occurs in a sparse factor, though: a variable seen by wide factors
        // alone would have an empty diagonal in H_s, and H_s + mu D could be singular (always,
        // for Gauss-Newton) even where H is not; such a factor stays in the sparse part.
        let mut covered = vec![false; nb];
        for (fi, f) in factors.iter().enumerate() {
            if !f.is_wide() {
                for &b in factor_blocks(fi) {
                    covered[b] = true;
                }
            }
        }
        let is_wide: Vec<bool> = factors
            .iter()
            .enumerate()
            .map(|(fi, f)| {
                let bs = factor_blocks(fi);
                f.is_wide() && !bs.is_empty() && bs.iter().all(|&b| covered[b])
            })
            .collect();
        // Block -> sparse factor incidence (wide factors left out).
        let (inc_ptr, inc_idx) = group_by_key(
            nb,
            (0..factors.len())
                .filter(|&fi| !is_wide[fi])
                .flat_map(|fi| factor_blocks(fi).iter().map(move |&b| (b, fi))),
        );
        let mut mark = vec![NO_BLOCK; nb];
        let mut adj_ptr = Vec::with_capacity(nb + 1);
        let mut adj_idx = Vec::new();
        adj_ptr.push(0usize);
        for a in 0..nb {
            mark[a] = a;
            let begin = adj_idx.len();
            for &fi in &inc_idx[inc_ptr[a]..inc_ptr[a + 1]] {
                for &b in factor_blocks(fi) {
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
        // Where column k of block c's rows from block r begin, for each k: one search per pair.
        let push_slots = |r: usize, c: usize, slots: &mut Vec<usize>| -> Result<()> {
            let dim = block_dim[c];
            let first = block_offset[c];
            if r == c {
                slots.extend((0..dim).map(|k| col_ptr[first + k + 1] - (k + 1)));
                return Ok(());
            }
            let rows = &upper_idx[upper_ptr[c]..upper_ptr[c + 1]];
            let x = rows.binary_search(&r).map_err(|_| {
                HitlError::Solver(format!(
                    "internal: block ({r}, {c}) missing from the pattern"
                ))
            })?;
            let before: usize = rows[..x].iter().map(|&b| block_dim[b]).sum();
            slots.extend((0..dim).map(|k| col_ptr[first + k] + before));
            Ok(())
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
                    push_slots(r, c, &mut slots)?;
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
        let l_values = vec![0.0; l_len];
        let plain_solves = Cholesky {
            symbolic: &symbolic,
            l_values: &l_values,
        }
        .layout_ok();
        let lower_blocks = (matches!(symbolic.raw(), SymbolicCholeskyRaw::Supernodal(_))
            && u32::try_from(nnz).is_ok())
        .then_some((upper_ptr, upper_idx));
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
            damped: Vec::new(),
            h_ahead: Vec::new(),
            g_ahead: Vec::new(),
            l_values,
            plain_solves,
            supernodal_work: SupernodalWork::default(),
            mem,
            max_residual,
            max_jac,
            wide,
            lower: LowerTriangle::default(),
            lower_blocks,
        })
    }

    /// Whether the factorization reads the lower triangle (the supernodal kernel).
    pub(super) fn uses_lower(&self) -> bool {
        self.lower_blocks.is_some()
    }

    /// Builds the lower triangle if the factorization reads one and it is not built yet.
    pub(super) fn ensure_lower(&mut self) {
        if let (true, Some((ptr, rows))) = (self.lower.is_empty(), &self.lower_blocks) {
            self.lower = LowerTriangle::of_blocks(
                &self.block_offset,
                &self.block_dim,
                ptr,
                rows,
                &self.col_ptr,
            );
        }
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

    /// Applies `delta` (solver ordering) to `values` through each variable's chart.
    pub fn retract(&self, values: &mut Values, delta: &[f64]) {
        for (b, &key) in self.block_key.iter().enumerate() {
            let o = self.block_offset[b];
            values.retract(key, &delta[o..o + self.block_dim[b]]);
        }
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
    #[test]
    fn the_lower_triangle_is_the_transpose_of_the_upper() {
        // Upper CSC of a 4 x 4 symmetric matrix with a few off-diagonal entries.
        let col_ptr = [0, 1, 3, 4, 7];
        let row_idx = [0, 0, 1, 2, 1, 2, 3];
        let upper = [1.0, 2.0, 3.0, 4.0, 5.0, 6.0, 7.0];
        let mut lower = super::LowerTriangle::of_upper(4, &col_ptr, &row_idx);
        let (lp, li, lv) = lower.gather(&upper, None, |_, _| 0.0);
        assert_eq!(lp, &[0, 2, 4, 6, 7]);
        assert_eq!(li, &[0, 1, 1, 3, 2, 3, 3]);
        assert_eq!(lv, &[1.0, 2.0, 3.0, 5.0, 4.0, 6.0, 7.0]);
        // Damping lands on the diagonal, weighted per column.
        let (_, _, lv) = lower.gather(&upper, Some((2.0, true)), |k, _| k as f64);
        assert_eq!(lv, &[1.0, 2.0, 5.0, 5.0, 8.0, 6.0, 13.0]);
    }

    use super::*;
    use crate::solver::test_problems::{corrected, dense_hessian, Relations};

    #[test]
    fn the_block_built_lower_triangle_equals_the_transposed_upper() {
        // Poses (3 x 3 blocks) and lines (2 x 2), sparse and wide factors.
        for (n, relations) in [(50, Relations::Narrow), (60, Relations::Wide)] {
            let (mut g, _) = corrected(n, relations, false);
            let p = g.pattern().unwrap();
            let nb = p.block_dim.len();
            assert!(p.block_dim.contains(&2) && p.block_dim.contains(&3));
            // The block pattern, recovered from the scalar one: the rows of each block's
            // first column that are not its own.
            let mut upper_ptr = vec![0usize];
            let mut upper_idx = Vec::new();
            for c in 0..nb {
                let col = p.block_offset[c];
                let mut last = NO_BLOCK;
                for &row in &p.row_idx[p.col_ptr[col]..p.col_ptr[col + 1]] {
                    let b = p.block_offset.partition_point(|&o| o <= row) - 1;
                    if b != c && b != last {
                        upper_idx.push(b);
                        last = b;
                    }
                }
                upper_ptr.push(upper_idx.len());
            }
            let upper: Vec<f64> = (0..p.row_idx.len()).map(|k| k as f64).collect();
            let mut fast = LowerTriangle::of_blocks(
                &p.block_offset,
                &p.block_dim,
                &upper_ptr,
                &upper_idx,
                &p.col_ptr,
            );
            let mut slow = LowerTriangle::of_upper(p.n, &p.col_ptr, &p.row_idx);
            let (a, b) = (
                fast.gather(&upper, None, |_, _| 0.0),
                slow.gather(&upper, None, |_, _| 0.0),
            );
            assert_eq!(a.0, b.0, "n {n}: column pointers");
            assert_eq!(a.1, b.1, "n {n}: row indices");
            assert_eq!(a.2, b.2, "n {n}: values");
        }
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
        let expect = a.clone().cholesky().unwrap().solve(&(-&g_vec));
        let got = nalgebra::DVector::from_column_slice(&delta);
        // The damped system is ill-conditioned (cond ~4e10), so "exactly" means a backward
        // error at rounding level; the two solves then agree to within cond x eps, not better
        // (a change of the linearization in the last ulp moved them 7e-11 -> 5e-9 apart).
        let backward = (&a * &got + &g_vec).norm() / (a.norm() * got.norm());
        assert!(backward <= 1e-15, "backward error {backward:e}");
        let sv = a.singular_values();
        let cond = sv.max() / sv.min();
        let rel = (&got - &expect).norm() / expect.norm();
        assert!(rel <= cond * f64::EPSILON, "{rel:e} vs cond {cond:e}");
    }
}
