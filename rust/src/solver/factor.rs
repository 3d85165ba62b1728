//! The numeric Cholesky factor `L` (`A = L L^T`) on faer's symbolic analysis, with plain-loop
//! triangular solves for one column at a time: the damped step of every iteration, the chord
//! step's conjugate gradients and the Woodbury columns (`woodbury`) all solve through it.

use faer::sparse::linalg::cholesky::supernodal::SymbolicSupernodalCholesky;
use faer::sparse::linalg::cholesky::{SymbolicCholesky, SymbolicCholeskyRaw};
use faer::sparse::linalg::triangular_solve::{
    solve_lower_triangular_in_place, solve_lower_triangular_transpose_in_place,
};
use faer::sparse::SparseColMatRef;
use faer::{Conj, MatMut, Par};

/// The numeric factor `L` of A (`A = L L^T`, no permutation: the pattern is analysed in its
/// own order), for the triangular solves of every iteration and those Woodbury needs. faer's
/// own supernodal solves pay a per-supernode setup (a temporary, a matrix-product dispatch)
/// that dominates on pose graphs, whose supernodes are a few 3 x 3 blocks, so single columns
/// go through the plain loops below (on City10000 they take a third of faer's time).
#[derive(Clone, Copy)]
pub(super) struct Cholesky<'a> {
    pub symbolic: &'a SymbolicCholesky<usize>,
    pub l_values: &'a [f64],
}

/// One supernode of L: first row, size, the rows below its diagonal block, and its values
/// (column-major, `size + pattern.len()` rows).
type Supernode<'a> = (usize, usize, &'a [usize], &'a [f64]);

impl<'a> Cholesky<'a> {
    /// Checks that the factor has the layout the loops below index into (no permutation, every
    /// supernode's values where its structure says): with it, they cannot go out of bounds.
    pub(super) fn layout_ok(&self) -> bool {
        if self.symbolic.perm().is_some() {
            return false;
        }
        match self.symbolic.raw() {
            SymbolicCholeskyRaw::Simplicial(_) => true,
            SymbolicCholeskyRaw::Supernodal(sn) => {
                let n = sn.nrows();
                (0..sn.n_supernodes()).all(|s| match self.supernode(sn, s) {
                    Some((s0, size, pattern, _)) => {
                        s0 + size <= n && pattern.iter().all(|&r| r >= s0 + size && r < n)
                    }
                    None => false,
                })
            }
        }
    }

    fn supernode(
        &self,
        sn: &'a SymbolicSupernodalCholesky<usize>,
        s: usize,
    ) -> Option<Supernode<'a>> {
        let s0 = *sn.supernode_begin().get(s)?;
        let size = sn.supernode_end().get(s)?.checked_sub(s0)?;
        let pattern = sn.supernode(s).pattern();
        let ptr = sn.col_ptr_for_val();
        let vals = self.l_values.get(*ptr.get(s)?..*ptr.get(s + 1)?)?;
        (vals.len() == (size + pattern.len()) * size).then_some((s0, size, pattern, vals))
    }

    /// `L^-1 x` in place for the `k` columns of `x` (n x k, column-major), calling `visit` with
    /// the row range of every supernode it works on. The supernodal path skips every supernode
    /// whose rows are still zero: a wide factor's columns touch a few hundred poses, and only
    /// their elimination-tree ancestors are visited.
    ///
    /// With `seeds` (the rows where the columns may be non-zero, and a workspace), supernodes
    /// are skipped by structure instead of by scanning their rows for non-zeros: `L^-1 b` can
    /// be non-zero only on the elimination-tree ancestors of `b`'s rows, and a supernode's
    /// parent is the one holding the smallest row of its pattern.
    pub(super) fn forward_cols(
        &self,
        x: &mut [f64],
        k: usize,
        seeds: Option<(&[usize], &mut Vec<bool>)>,
        mut visit: impl FnMut(usize, usize),
    ) {
        let n = self.symbolic.nrows();
        match self.symbolic.raw() {
            SymbolicCholeskyRaw::Simplicial(sm) => {
                // Small problems only (large ones are forced supernodal): faer's solve is fine.
                let l = SparseColMatRef::new(sm.factor(), self.l_values);
                let rhs = MatMut::from_column_major_slice_mut(x, n, k);
                solve_lower_triangular_in_place(l, Conj::No, rhs, Par::Seq);
                visit(0, n);
            }
            SymbolicCholeskyRaw::Supernodal(sn) => {
                let ns = sn.n_supernodes();
                let begin = sn.supernode_begin();
                // The supernode holding row `row` (supernodes are contiguous, in order).
                let owner = |row: usize| begin.partition_point(|&b| b <= row).saturating_sub(1);
                let mut seen = match seeds {
                    Some((rows, seen)) => {
                        seen.clear();
                        seen.resize(ns, false);
                        for &row in rows {
                            if row < n {
                                seen[owner(row)] = true;
                            }
                        }
                        Some(seen)
                    }
                    None => None,
                };
                let mut below = Vec::new();
                for s in 0..ns {
                    let Some((s0, size, pattern, vals)) = self.supernode(sn, s) else {
                        continue;
                    };
                    let s1 = s0 + size;
                    match seen.as_deref_mut() {
                        Some(seen) => {
                            if !seen[s] {
                                continue;
                            }
                            if let Some(&parent_row) = pattern.iter().min() {
                                seen[owner(parent_row)] = true;
                            }
                        }
                        None => {
                            if (0..k).all(|j| x[j * n + s0..j * n + s1].iter().all(|&v| v == 0.0)) {
                                continue;
                            }
                        }
                    }
                    visit(s0, s1);
                    for col in x.chunks_mut(n).take(k) {
                        forward_panel(vals, s0, size, pattern, col, &mut below);
                    }
                }
            }
        }
    }

    /// `x <- (L L^T)^-1 x = A^-1 x` for one dense column. Call only on a factor whose layout
    /// [`Self::layout_ok`] accepted.
    pub(super) fn solve(&self, x: &mut [f64]) {
        match self.symbolic.raw() {
            SymbolicCholeskyRaw::Simplicial(_) => self.forward(x),
            SymbolicCholeskyRaw::Supernodal(sn) => {
                let mut below = Vec::new();
                for s in 0..sn.n_supernodes() {
                    let Some((s0, size, pattern, vals)) = self.supernode(sn, s) else {
                        continue;
                    };
                    forward_panel(vals, s0, size, pattern, x, &mut below);
                }
            }
        }
        self.backward(x);
    }

    /// `x <- L^-1 x` for one column.
    pub(super) fn forward(&self, x: &mut [f64]) {
        self.forward_cols(x, 1, None, |_, _| {});
    }

    /// `x <- L^-T x` for one column.
    pub(super) fn backward(&self, x: &mut [f64]) {
        let n = self.symbolic.nrows();
        match self.symbolic.raw() {
            SymbolicCholeskyRaw::Simplicial(sm) => {
                let l = SparseColMatRef::new(sm.factor(), self.l_values);
                let rhs = MatMut::from_column_major_slice_mut(x, n, 1);
                solve_lower_triangular_transpose_in_place(l, Conj::No, rhs, Par::Seq);
            }
            SymbolicCholeskyRaw::Supernodal(sn) => {
                // x_s <- L_ss^-T (x_s - L_below^T x[pattern]), supernodes last to first; the
                // rows below are gathered once per supernode.
                let mut below_x = Vec::new();
                for s in (0..sn.n_supernodes()).rev() {
                    let Some((s0, size, pattern, vals)) = self.supernode(sn, s) else {
                        continue;
                    };
                    let nrows = size + pattern.len();
                    below_x.clear();
                    below_x.extend(pattern.iter().map(|&row| x[row]));
                    for c in 0..size {
                        x[s0 + c] -= dot(&vals[c * nrows + size..(c + 1) * nrows], &below_x);
                    }
                    for c in (0..size).rev() {
                        let lc = &vals[c * nrows..c * nrows + size];
                        let mut v = x[s0 + c];
                        for i in c + 1..size {
                            v -= lc[i] * x[s0 + i];
                        }
                        x[s0 + c] = v / lc[c];
                    }
                }
            }
        }
    }
}

/// One supernode's share of the forward solve `x <- L^-1 x`: `x_s <- L_ss^-1 x_s`, then
/// `x[pattern] -= L_below x_s`, the product summed column by column over contiguous values and
/// scattered once (no tests for zero rows: a dense right-hand side has none to skip). `vals` is
/// the supernode's panel (`size + pattern.len()` rows, column-major) for columns `s0..s0 +
/// size`; `below` is workspace. Called supernode after supernode, first to last, by
/// [`Cholesky::solve`] and by the factorization, which solves forward as it goes.
#[inline(always)]
pub(super) fn forward_panel(
    vals: &[f64],
    s0: usize,
    size: usize,
    pattern: &[usize],
    x: &mut [f64],
    below: &mut Vec<f64>,
) {
    let nrows = size + pattern.len();
    for c in 0..size {
        let diag = &vals[c * nrows..c * nrows + size];
        let v = x[s0 + c] / diag[c];
        x[s0 + c] = v;
        for (xi, &l) in x[s0 + c + 1..s0 + size].iter_mut().zip(&diag[c + 1..]) {
            *xi -= l * v;
        }
    }
    below.clear();
    below.resize(pattern.len(), 0.0);
    for c in 0..size {
        let v = x[s0 + c];
        for (b, &l) in below
            .iter_mut()
            .zip(&vals[c * nrows + size..(c + 1) * nrows])
        {
            *b += l * v;
        }
    }
    for (&row, &b) in pattern.iter().zip(below.iter()) {
        x[row] -= b;
    }
}

/// `a . b` with four partial sums (independent chains: the loop is not bound by the latency of
/// one addition after another).
fn dot(a: &[f64], b: &[f64]) -> f64 {
    let (a4, a_rest) = a.split_at(a.len() - a.len() % 4);
    let b4 = &b[..a4.len()];
    let mut s = [0.0f64; 4];
    for (x, y) in a4.chunks_exact(4).zip(b4.chunks_exact(4)) {
        for k in 0..4 {
            s[k] += x[k] * y[k];
        }
    }
    let mut tail = 0.0;
    for (x, y) in a_rest.iter().zip(&b[a4.len()..]) {
        tail += x * y;
    }
    (s[0] + s[1]) + (s[2] + s[3]) + tail
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::solver::test_problems::ring;
    use faer::dyn_stack::{MemBuffer, MemStack};
    use faer::sparse::linalg::cholesky::LltRef;

    /// The plain loops solve as faer's own supernodal solve does, on a supernodal factor.
    #[test]
    fn plain_solves_match_faers_supernodal_solve() {
        for n in [1100usize, 2000] {
            let (mut g, values) = ring(n);
            let (factors, p) = g.parts().unwrap();
            p.linearize(factors, &values, &[]);
            let mut delta = vec![0.0; p.n];
            assert!(p.solve_damped(1e-3, true, &mut delta).unwrap());
            assert!(matches!(
                p.symbolic.raw(),
                SymbolicCholeskyRaw::Supernodal(_)
            ));
            let l = Cholesky {
                symbolic: &p.symbolic,
                l_values: &p.l_values,
            };
            assert!(l.layout_ok());
            let b: Vec<f64> = (0..p.n)
                .map(|k| ((k * 37 % 101) as f64 - 50.0) * 0.1)
                .collect();
            let mut plain = b.clone();
            l.solve(&mut plain);
            let mut reference = b.clone();
            let llt = LltRef::new(&p.symbolic, &p.l_values);
            let mut mem = MemBuffer::new(p.symbolic.solve_in_place_scratch::<f64>(1, Par::Seq));
            llt.solve_in_place_with_conj(
                Conj::No,
                MatMut::from_column_major_slice_mut(&mut reference, p.n, 1),
                Par::Seq,
                MemStack::new(&mut mem),
            );
            let scale = reference.iter().fold(0.0f64, |m, v| m.max(v.abs()));
            for (a, b) in plain.iter().zip(&reference) {
                assert!((a - b).abs() <= 1e-10 * scale, "n {n}: {a} vs {b}");
            }
        }
    }
}
