//! The sparse symmetric positive-definite solve behind both steps of the chordal relaxation.
//!
//! Unknowns are 2-vectors, one per pose except the anchor, whose value is known and moves to the
//! right-hand side. Edge `(i, j)` contributes the weighted linear residual
//! `e = x_j - M x_i - c` with a symmetric positive (semi-)definite 2x2 weight `W`, i.e. the cost
//! `e^T W e`. Its normal-equation blocks
//!
//! `H_ii += M^T W M`, `H_jj += W`, `H_ij += -M^T W`, `b_i += -M^T W c`, `b_j += W c`
//!
//! are assembled into the upper triangle of `H` in compressed sparse columns, with the blocks in an
//! approximate-minimum-degree order of the pose graph (so the factorization needs no permutation
//! of its own), and `H x = b` is solved (for the correction to a starting point) by a sparse
//! Cholesky factorization plus one step of iterative refinement. The pattern, the ordering and the symbolic analysis depend only on the
//! graph, so the rotation and the position step share them ([`BlockSystem::new`] once,
//! [`BlockSystem::solve`] twice). Everything is linear in the size of the graph for the sparse
//! graphs SLAM produces.

use faer::dyn_stack::{MemBuffer, MemStack, StackReq};
use faer::linalg::cholesky::llt::factor::LltRegularization;
use faer::sparse::linalg::cholesky::{
    factorize_symbolic_cholesky, CholeskySymbolicParams, SymbolicCholesky, SymmetricOrdering,
};
use faer::sparse::{SparseColMatRef, SymbolicSparseColMatRef};
use faer::{Conj, MatMut, Par, Side, Spec};

use crate::error::{HitlError, Result};
use crate::solver::{block_amd, sym_upper_mul_add};

const NONE: usize = usize::MAX;

/// A row-major 2x2 matrix.
pub(super) type Mat2 = [[f64; 2]; 2];

pub(super) const IDENTITY: Mat2 = [[1.0, 0.0], [0.0, 1.0]];

/// One edge's linear residual `x_j - m x_i - c`, weighted by `w` (symmetric).
#[derive(Clone, Copy, Debug)]
pub(super) struct EdgeTerm {
    pub m: Mat2,
    pub c: [f64; 2],
    pub w: Mat2,
}

#[inline]
pub(super) fn mat_mul(a: &Mat2, b: &Mat2) -> Mat2 {
    [
        [
            a[0][0] * b[0][0] + a[0][1] * b[1][0],
            a[0][0] * b[0][1] + a[0][1] * b[1][1],
        ],
        [
            a[1][0] * b[0][0] + a[1][1] * b[1][0],
            a[1][0] * b[0][1] + a[1][1] * b[1][1],
        ],
    ]
}

#[inline]
pub(super) fn mat_vec(a: &Mat2, v: [f64; 2]) -> [f64; 2] {
    [
        a[0][0] * v[0] + a[0][1] * v[1],
        a[1][0] * v[0] + a[1][1] * v[1],
    ]
}

#[inline]
pub(super) fn transpose(a: &Mat2) -> Mat2 {
    [[a[0][0], a[1][0]], [a[0][1], a[1][1]]]
}

/// The normal equations of a pose graph with 2-vector unknowns: pattern, ordering and symbolic
/// Cholesky analysis, reusable for any edge terms on the same edges.
pub(super) struct BlockSystem {
    /// Block (position in elimination order) of each pose; NONE for the anchor.
    block: Vec<usize>,
    /// Upper triangle of H, scalar CSC. Block column c is scalar columns 2c and 2c + 1; each holds
    /// the block rows r < c (sorted, two scalar rows each), then its part of the diagonal block.
    col_ptr: Vec<usize>,
    row_idx: Vec<usize>,
    /// Per edge, the index of its off-diagonal block among the block rows of its column (NONE
    /// when the edge touches the anchor, which has no block).
    edge_pos: Vec<usize>,
    symbolic: SymbolicCholesky<usize>,
    mem: MemBuffer,
}

fn internal(what: &str) -> HitlError {
    HitlError::Solver(format!(
        "internal error in the initial-guess solver ({what}); please report it"
    ))
}

impl BlockSystem {
    /// Analyzes the graph of `num_poses` poses (at least 2; `anchor` fixed) and `edges`, whose
    /// indices the caller has checked (in range, no self-loops). Duplicate edges are fine.
    pub fn new(num_poses: usize, anchor: usize, edges: &[(usize, usize)]) -> Result<Self> {
        if num_poses < 2 || anchor >= num_poses {
            return Err(internal("needs at least one free pose"));
        }
        let nb = num_poses - 1;
        let free = |v: usize| if v < anchor { v } else { v - 1 };

        // 1. Block adjacency (both directions, no diagonal), CSR in natural order, deduplicated.
        let mut adj_ptr = vec![0usize; nb + 1];
        for &(i, j) in edges {
            if i != anchor && j != anchor && i != j {
                adj_ptr[free(i) + 1] += 1;
                adj_ptr[free(j) + 1] += 1;
            }
        }
        for a in 0..nb {
            adj_ptr[a + 1] += adj_ptr[a];
        }
        let mut fill = adj_ptr.clone();
        let mut adj_idx = vec![0usize; adj_ptr[nb]];
        for &(i, j) in edges {
            if i != anchor && j != anchor && i != j {
                let (a, b) = (free(i), free(j));
                adj_idx[fill[a]] = b;
                fill[a] += 1;
                adj_idx[fill[b]] = a;
                fill[b] += 1;
            }
        }
        drop(fill);
        let mut out = 0;
        for a in 0..nb {
            let (s, e) = (adj_ptr[a], adj_ptr[a + 1]);
            adj_idx[s..e].sort_unstable();
            adj_ptr[a] = out;
            let mut last = NONE;
            for t in s..e {
                let v = adj_idx[t];
                if v != last {
                    adj_idx[out] = v;
                    out += 1;
                    last = v;
                }
            }
        }
        adj_ptr[nb] = out;
        adj_idx.truncate(out);

        // 2. Fill-reducing order of the blocks.
        let (fwd, inv) = block_amd(nb, &adj_ptr, &adj_idx)?;

        // 3. The upper block pattern in that order, then the scalar CSC.
        let mut block = vec![NONE; num_poses];
        for (v, b) in block.iter_mut().enumerate() {
            if v != anchor {
                *b = inv[free(v)];
            }
        }
        let mut upper_ptr = Vec::with_capacity(nb + 1);
        let mut upper_idx = Vec::with_capacity(adj_idx.len() / 2);
        upper_ptr.push(0usize);
        for c in 0..nb {
            let old = fwd[c];
            let begin = upper_idx.len();
            upper_idx.extend(
                adj_idx[adj_ptr[old]..adj_ptr[old + 1]]
                    .iter()
                    .map(|&o| inv[o])
                    .filter(|&r| r < c),
            );
            upper_idx[begin..].sort_unstable();
            upper_ptr.push(upper_idx.len());
        }
        drop((adj_ptr, adj_idx, fwd, inv));
        let dim = 2 * nb;
        let mut col_ptr = Vec::with_capacity(dim + 1);
        let mut row_idx = Vec::with_capacity(4 * upper_idx.len() + 3 * nb);
        col_ptr.push(0usize);
        for c in 0..nb {
            for k in 0..2 {
                for &r in &upper_idx[upper_ptr[c]..upper_ptr[c + 1]] {
                    row_idx.push(2 * r);
                    row_idx.push(2 * r + 1);
                }
                row_idx.extend(2 * c..=2 * c + k);
                col_ptr.push(row_idx.len());
            }
        }

        // 4. Where each edge's off-diagonal block lives.
        let mut edge_pos = Vec::with_capacity(edges.len());
        for &(i, j) in edges {
            let (bi, bj) = (block[i], block[j]);
            if bi == NONE || bj == NONE || bi == bj {
                edge_pos.push(NONE);
                continue;
            }
            let (r, c) = (bi.min(bj), bi.max(bj));
            let pos = upper_idx[upper_ptr[c]..upper_ptr[c + 1]]
                .binary_search(&r)
                .map_err(|_| internal("edge block missing from the pattern"))?;
            edge_pos.push(pos);
        }
        drop((upper_ptr, upper_idx));

        // 5. Symbolic analysis of the already-ordered pattern.
        let sym = SymbolicSparseColMatRef::new_checked(dim, dim, &col_ptr, None, &row_idx);
        let symbolic = factorize_symbolic_cholesky(
            sym,
            Side::Upper,
            SymmetricOrdering::Identity,
            CholeskySymbolicParams::default(),
        )
        .map_err(|e| HitlError::Solver(format!("symbolic Cholesky analysis failed: {e:?}")))?;
        let req = StackReq::any_of(&[
            symbolic.factorize_numeric_llt_scratch::<f64>(Par::Seq, Spec::default()),
            symbolic.solve_in_place_scratch::<f64>(1, Par::Seq),
        ]);
        let mem = MemBuffer::try_new(req).map_err(|_| {
            HitlError::Solver("out of memory for the initial-guess Cholesky workspace".into())
        })?;
        Ok(Self {
            block,
            col_ptr,
            row_idx,
            edge_pos,
            symbolic,
            mem,
        })
    }

    /// Minimizes `sum_k e_k^T W_k e_k` with `e_k = x_j - M_k x_i - c_k` for edge `k = (i, j)`
    /// (`term(k)` gives `M_k, c_k, W_k`), the anchor held at `start[anchor]`. Returns one 2-vector
    /// per pose. `edges` must be the ones given to `new`.
    ///
    /// The unknown is the correction `d = x - start`, whose residuals `d_j - M d_i + e_k(start)`
    /// are computed edge by edge: when `start` is close (a spanning-tree guess on consistent
    /// data), the result is as accurate as `start`'s residuals, not limited by the conditioning
    /// of `H` (which grows like the square of a chain's length).
    pub fn solve(
        &mut self,
        edges: &[(usize, usize)],
        start: &[[f64; 2]],
        term: impl Fn(usize) -> EdgeTerm,
    ) -> Result<Vec<[f64; 2]>> {
        if start.len() != self.block.len() {
            return Err(internal("start has the wrong length"));
        }
        if edges.len() != self.edge_pos.len() {
            return Err(internal("edge list changed between analysis and solve"));
        }
        let dim = self.col_ptr.len() - 1;
        let cp = &self.col_ptr;
        let mut h = vec![0.0; self.row_idx.len()];
        let mut rhs = vec![0.0; dim];
        // Upper triangle of a symmetric diagonal block of block column c.
        let add_diag = |h: &mut [f64], c: usize, b: &Mat2| {
            h[cp[2 * c + 1] - 1] += b[0][0];
            h[cp[2 * c + 2] - 2] += 0.5 * (b[0][1] + b[1][0]);
            h[cp[2 * c + 2] - 1] += b[1][1];
        };
        // Off-diagonal block (block row of index `pos` in block column c), entry (a, k) of b.
        let add_off = |h: &mut [f64], c: usize, pos: usize, b: &Mat2| {
            for k in 0..2 {
                let base = cp[2 * c + k] + 2 * pos;
                h[base] += b[0][k];
                h[base + 1] += b[1][k];
            }
        };
        for (k, &(i, j)) in edges.iter().enumerate() {
            let (bi, bj) = (self.block[i], self.block[j]);
            if i == j || (bi == NONE && bj == NONE) {
                continue;
            }
            let EdgeTerm { m, c, w } = term(k);
            // e_k(start + d) = d_j - M d_i - ce with ce = -e_k(start); the anchor's d is 0.
            let ms = mat_vec(&m, start[i]);
            let ce = [ms[0] + c[0] - start[j][0], ms[1] + c[1] - start[j][1]];
            let wc = mat_vec(&w, ce);
            if bj != NONE {
                add_diag(&mut h, bj, &w);
                rhs[2 * bj] += wc[0];
                rhs[2 * bj + 1] += wc[1];
            }
            if bi != NONE {
                let mt = transpose(&m);
                let mtw = mat_mul(&mt, &w);
                add_diag(&mut h, bi, &mat_mul(&mtw, &m));
                let g = mat_vec(&mt, wc);
                rhs[2 * bi] -= g[0];
                rhs[2 * bi + 1] -= g[1];
                if bj != NONE {
                    let pos = self.edge_pos[k];
                    if bi < bj {
                        // Rows of i, columns of j: -M^T W.
                        let b = [[-mtw[0][0], -mtw[0][1]], [-mtw[1][0], -mtw[1][1]]];
                        add_off(&mut h, bj, pos, &b);
                    } else {
                        // Rows of j, columns of i: -W M.
                        let wm = mat_mul(&w, &m);
                        let b = [[-wm[0][0], -wm[0][1]], [-wm[1][0], -wm[1][1]]];
                        add_off(&mut h, bi, pos, &b);
                    }
                }
            }
        }
        if !(h.iter().all(|v| v.is_finite()) && rhs.iter().all(|v| v.is_finite())) {
            return Err(HitlError::Input(
                "the initial-guess system has non-finite entries; check the poses, measurements and information matrices for huge or non-finite values".into(),
            ));
        }

        let sym = SymbolicSparseColMatRef::new_checked(dim, dim, cp, None, &self.row_idx);
        let a = SparseColMatRef::new(sym, &h);
        let mut l_values = vec![0.0; self.symbolic.len_val()];
        let llt = self
            .symbolic
            .factorize_numeric_llt::<f64>(
                &mut l_values,
                a,
                Side::Upper,
                LltRegularization::default(),
                Par::Seq,
                MemStack::new(&mut self.mem),
                Spec::default(),
            )
            .map_err(|_| {
                HitlError::Solver(
                    "the initial-guess system is not numerically positive definite; check that the information matrices are well scaled (no near-zero or huge entries)".into(),
                )
            })?;
        let mut x = rhs.clone();
        llt.solve_in_place_with_conj(
            Conj::No,
            MatMut::from_column_major_slice_mut(&mut x, dim, 1),
            Par::Seq,
            MemStack::new(&mut self.mem),
        );
        // One step of iterative refinement: long chains make H ill-conditioned (~ n^2).
        let mut r = rhs;
        sym_upper_mul_add(cp, &self.row_idx, &h, -1.0, &x, &mut r);
        llt.solve_in_place_with_conj(
            Conj::No,
            MatMut::from_column_major_slice_mut(&mut r, dim, 1),
            Par::Seq,
            MemStack::new(&mut self.mem),
        );
        for (xv, dv) in x.iter_mut().zip(&r) {
            *xv += dv;
        }
        if !x.iter().all(|v| v.is_finite()) {
            return Err(HitlError::Solver(
                "the initial-guess solve produced non-finite values; check that the information matrices are well scaled".into(),
            ));
        }
        Ok(self
            .block
            .iter()
            .zip(start)
            .map(|(&b, s)| {
                if b == NONE {
                    *s
                } else {
                    [s[0] + x[2 * b], s[1] + x[2 * b + 1]]
                }
            })
            .collect())
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use rand::{Rng, SeedableRng};

    fn random_spd(rng: &mut impl Rng) -> Mat2 {
        let a: Mat2 = [
            [rng.random_range(-1.0..1.0), rng.random_range(-1.0..1.0)],
            [rng.random_range(-1.0..1.0), rng.random_range(-1.0..1.0)],
        ];
        let mut w = mat_mul(&transpose(&a), &a);
        w[0][0] += 0.5;
        w[1][1] += 0.5;
        w
    }

    /// The sparse solve equals a dense least-squares solve of the same residuals, for random
    /// terms on a graph with duplicate edges, edges in both directions and edges at the anchor.
    #[test]
    fn sparse_solve_matches_dense_least_squares() {
        let mut rng = rand::rngs::StdRng::seed_from_u64(7);
        let n = 30;
        let anchor = 11;
        let mut edges: Vec<(usize, usize)> = (0..n - 1).map(|i| (i, i + 1)).collect();
        for _ in 0..40 {
            let i = rng.random_range(0..n);
            let j = rng.random_range(0..n);
            if i != j {
                edges.push((i, j));
            }
        }
        edges.push((3, 4));
        edges.push((anchor, 2));
        edges.push((20, anchor));
        let terms: Vec<EdgeTerm> = edges
            .iter()
            .map(|_| EdgeTerm {
                m: [
                    [rng.random_range(-1.0..1.0), rng.random_range(-1.0..1.0)],
                    [rng.random_range(-1.0..1.0), rng.random_range(-1.0..1.0)],
                ],
                c: [rng.random_range(-2.0..2.0), rng.random_range(-2.0..2.0)],
                w: random_spd(&mut rng),
            })
            .collect();
        let anchor_value = [0.3, -0.7];
        let mut sys = BlockSystem::new(n, anchor, &edges).unwrap();
        // Any start works (the problem is linear); only the anchor's entry is binding.
        let mut start: Vec<[f64; 2]> = (0..n)
            .map(|_| [rng.random_range(-5.0..5.0), rng.random_range(-5.0..5.0)])
            .collect();
        start[anchor] = anchor_value;
        let got = sys.solve(&edges, &start, |k| terms[k]).unwrap();
        assert_eq!(got[anchor], anchor_value);

        // Dense reference: the same normal equations over all 2n unknowns, with the anchor's
        // columns moved to the right-hand side and its rows replaced by x_anchor = value.
        let dim = 2 * n;
        let mut a_full = nalgebra::DMatrix::<f64>::zeros(dim, dim);
        let mut b_full = nalgebra::DVector::<f64>::zeros(dim);
        for (&(i, j), t) in edges.iter().zip(&terms) {
            let mut jac = nalgebra::DMatrix::<f64>::zeros(2, dim);
            for r in 0..2 {
                jac[(r, 2 * j + r)] += 1.0;
                for q in 0..2 {
                    jac[(r, 2 * i + q)] -= t.m[r][q];
                }
            }
            let w = nalgebra::DMatrix::from_row_slice(
                2,
                2,
                &[t.w[0][0], t.w[0][1], t.w[1][0], t.w[1][1]],
            );
            let mut c = nalgebra::DVector::from_column_slice(&t.c);
            for r in 0..2 {
                for q in 0..2 {
                    c[r] -= jac[(r, 2 * anchor + q)] * anchor_value[q];
                }
                jac[(r, 2 * anchor)] = 0.0;
                jac[(r, 2 * anchor + 1)] = 0.0;
            }
            a_full += jac.transpose() * &w * &jac;
            b_full += jac.transpose() * &w * c;
        }
        for r in 0..2 {
            a_full[(2 * anchor + r, 2 * anchor + r)] = 1.0;
            b_full[2 * anchor + r] = anchor_value[r];
        }
        let expect = a_full.cholesky().unwrap().solve(&b_full);
        for v in 0..n {
            for r in 0..2 {
                let e = expect[2 * v + r];
                assert!(
                    (got[v][r] - e).abs() < 1e-10 * (1.0 + e.abs()),
                    "pose {v}: {:?} vs {e}",
                    got[v]
                );
            }
        }
    }
}
