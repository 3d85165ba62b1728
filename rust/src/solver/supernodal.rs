//! Numeric supernodal Cholesky `A = L L^T` on faer's symbolic analysis (left-looking, as
//! CHOLMOD's): each supernode gathers its columns of A, subtracts the updates of the supernodes
//! below it in the elimination tree, and factors its panel in place. The layout of `L` is faer's
//! (`col_ptr_for_val`, each supernode a column-major panel), so faer's and `Cholesky`'s solves
//! read it as they read faer's own factor.
//!
//! Why not faer's `factorize_supernodal_numeric_llt`: on pose graphs a supernode is a few 3 x 3
//! blocks wide and each update is a product of a few dozen rows by 3 to 15 columns; faer
//! dispatches each to its general matrix product and dense Cholesky, whose set-up then costs as
//! much as the arithmetic. The loops below are written for these sizes.

use faer::sparse::linalg::cholesky::supernodal::SymbolicSupernodalCholesky;

use super::factor::forward_panel;

const NONE: usize = usize::MAX;

/// Work arrays of [`factorize`], kept across factorizations.
#[derive(Default)]
pub(super) struct SupernodalWork {
    /// Per row: its position in the current supernode's panel, or NONE.
    local: Vec<usize>,
    /// Per supernode: the first descendant waiting to update it (linked through `next`).
    head: Vec<usize>,
    next: Vec<usize>,
    /// Per supernode: the position (in its panel's rows) of its next row not yet used to update.
    pos: Vec<usize>,
    /// Per row: the supernode holding it.
    owner: Vec<usize>,
    /// One update's product, and the four columns' coefficients being multiplied.
    column: Vec<f64>,
    coefficients: Vec<[f64; 4]>,
    /// Recorded by the first complete factorization and read by the later ones (the structure
    /// does not change): each entry of A's position in its supernode's panel (NONE_32 for an
    /// entry above the diagonal), and each update's rows' positions in its target panel, in
    /// the order the updates are made.
    entry_pos: Vec<u32>,
    targets: Vec<u32>,
    recorded: bool,
}

const NONE_32: u32 = u32::MAX;

/// A supernode's panel of L: `nrows x ncols`, column-major.
#[derive(Clone, Copy)]
struct Panel<'a> {
    vals: &'a [f64],
    nrows: usize,
    ncols: usize,
}

/// `out[j m + i] = sum_c L_d[p0 + i, c] L_d[p0 + j, c]` for the `m` rows of d's panel from
/// `p0` on and its first `nj` of them (`out` is `m x nj`, column-major; entries with `i < j`
/// are computed too, and not used). Four columns of the product at a time, and for them eight
/// rows (then four, then one) held in registers across d's columns: each value of L_d loaded
/// feeds four products.
#[inline(always)]
fn update_product<const FMA: bool>(
    d: Panel<'_>,
    p0: usize,
    m: usize,
    nj: usize,
    out: &mut [f64],
    bt: &mut Vec<[f64; 4]>,
) {
    let mut j = 0;
    while j < nj {
        let q = (nj - j).min(4);
        // The four columns' coefficients, one row per column of L_d.
        bt.clear();
        bt.extend((0..d.ncols).map(|c| {
            let base = c * d.nrows + p0 + j;
            let mut b = [0.0f64; 4];
            for (k, bk) in b.iter_mut().enumerate().take(q) {
                *bk = d.vals[base + k];
            }
            b
        }));
        let mut i = j;
        while i + 8 <= m {
            store_rows(&row_block::<8, FMA>(d, bt, p0 + i), out, m, i, j, q);
            i += 8;
        }
        if i + 4 <= m {
            store_rows(&row_block::<4, FMA>(d, bt, p0 + i), out, m, i, j, q);
            i += 4;
        }
        for i in i..m {
            store_rows(&row_block::<1, FMA>(d, bt, p0 + i), out, m, i, j, q);
        }
        j += q;
    }
}

/// Rows `row..row + R` of d's panel times the four columns' coefficients `bt`.
#[inline(always)]
fn row_block<const R: usize, const FMA: bool>(
    d: Panel<'_>,
    bt: &[[f64; 4]],
    row: usize,
) -> [[f64; R]; 4] {
    let mut acc = [[0.0f64; R]; 4];
    for (c, b) in bt.iter().enumerate() {
        let v: &[f64; R] = d.vals[c * d.nrows + row..][..R].try_into().unwrap();
        for (a, &bk) in acc.iter_mut().zip(b) {
            for r in 0..R {
                a[r] = madd::<FMA>(v[r], bk, a[r]);
            }
        }
    }
    acc
}

/// The first `q` of a row block's four columns into `out` (`m` rows per column) at row `i`,
/// column `j`.
#[inline(always)]
fn store_rows<const R: usize>(
    acc: &[[f64; R]; 4],
    out: &mut [f64],
    m: usize,
    i: usize,
    j: usize,
    q: usize,
) {
    for (k, a) in acc.iter().take(q).enumerate() {
        out[(j + k) * m + i..][..R].copy_from_slice(a);
    }
}

/// Numeric factorization of the lower triangle `(col_ptr, row_idx, values)` (CSC, sorted or
/// not, the pattern the symbolic analysis was computed for) into `l` (`sn.len_val()` entries).
/// False when a pivot is not positive (A is not numerically positive definite). With `rhs`,
/// also `rhs <- L^-1 rhs`, each supernode's share while its panel is still in cache (the
/// forward half of a solve, one pass over L fewer); `rhs` is unspecified when it returns false.
pub(super) fn factorize(
    sn: &SymbolicSupernodalCholesky<usize>,
    col_ptr: &[usize],
    row_idx: &[usize],
    values: &[f64],
    l: &mut [f64],
    w: &mut SupernodalWork,
    rhs: Option<&mut [f64]>,
) -> bool {
    // Compiled for the widest vector instructions the processor has (pulp's run-time
    // dispatch, as faer's own kernels): the loops below are written to be auto-vectorized.
    pulp::Arch::new().dispatch(Job {
        sn,
        col_ptr,
        row_idx,
        values,
        l,
        w,
        rhs,
    })
}

/// [`factorize`]'s arguments, for pulp's dispatch (a closure is not inlined into the function
/// compiled for the processor's instructions; `with_simd` is).
struct Job<'a> {
    sn: &'a SymbolicSupernodalCholesky<usize>,
    col_ptr: &'a [usize],
    row_idx: &'a [usize],
    values: &'a [f64],
    l: &'a mut [f64],
    w: &'a mut SupernodalWork,
    rhs: Option<&'a mut [f64]>,
}

impl pulp::WithSimd for Job<'_> {
    type Output = bool;

    #[inline(always)]
    fn with_simd<S: pulp::Simd>(self, _simd: S) -> bool {
        if fused_multiply_add() {
            factorize_on::<true>(self)
        } else {
            factorize_on::<false>(self)
        }
    }
}

/// Whether the processor has a fused multiply-add instruction (`f64::mul_add` is a library
/// call, and a slow one, where it has not).
fn fused_multiply_add() -> bool {
    #[cfg(target_arch = "x86_64")]
    {
        std::arch::is_x86_feature_detected!("fma")
    }
    #[cfg(target_arch = "aarch64")]
    {
        true
    }
    #[cfg(not(any(target_arch = "x86_64", target_arch = "aarch64")))]
    {
        false
    }
}

/// `a b + c`, fused (one rounding, one instruction) where `FMA`.
#[inline(always)]
fn madd<const FMA: bool>(a: f64, b: f64, c: f64) -> f64 {
    if FMA {
        a.mul_add(b, c)
    } else {
        a * b + c
    }
}

#[inline(always)]
fn factorize_on<const FMA: bool>(job: Job<'_>) -> bool {
    let Job {
        sn,
        col_ptr,
        row_idx,
        values,
        l,
        w,
        mut rhs,
    } = job;
    let n = sn.nrows();
    let ns = sn.n_supernodes();
    let begin = sn.supernode_begin();
    let end = sn.supernode_end();
    let val_ptr = sn.col_ptr_for_val();
    assert_eq!(l.len(), sn.len_val());
    assert_eq!(col_ptr.len(), n + 1);
    let SupernodalWork {
        local,
        head,
        next,
        pos,
        owner,
        column,
        coefficients,
        entry_pos,
        targets,
        recorded,
    } = w;
    let mut below = Vec::new();
    let replay = *recorded;
    if !replay {
        local.clear();
        local.resize(n, NONE);
        entry_pos.clear();
        targets.clear();
        owner.clear();
        owner.resize(n, 0);
        for s in 0..ns {
            owner[begin[s]..end[s]].fill(s);
        }
    }
    head.clear();
    head.resize(ns, NONE);
    next.clear();
    next.resize(ns, NONE);
    pos.clear();
    pos.resize(ns, 0);
    let mut cursor = 0;
    for s in 0..ns {
        let (s0, s1) = (begin[s], end[s]);
        let size = s1 - s0;
        let pattern = sn.supernode(s).pattern();
        let nrows = size + pattern.len();
        if !replay {
            for (k, r) in (s0..s1).enumerate() {
                local[r] = k;
            }
            for (k, &r) in pattern.iter().enumerate() {
                local[r] = size + k;
            }
        }
        let (done, rest) = l.split_at_mut(val_ptr[s]);
        let panel = &mut rest[..val_ptr[s + 1] - val_ptr[s]];
        panel.fill(0.0);
        // 1. The columns of A.
        if replay {
            for k in col_ptr[s0]..col_ptr[s1] {
                let p = entry_pos[k];
                if p != NONE_32 {
                    panel[p as usize] += values[k];
                }
            }
        } else {
            for (c, j) in (s0..s1).enumerate() {
                for k in col_ptr[j]..col_ptr[j + 1] {
                    let i = row_idx[k];
                    let mut p = NONE_32;
                    if i >= j {
                        let at = c * nrows + local[i];
                        panel[at] += values[k];
                        p = at as u32;
                    }
                    entry_pos.push(p);
                }
            }
        }
        // 2. The updates of the descendants waiting for this supernode.
        let mut d = head[s];
        while d != NONE {
            let next_d = next[d];
            let (d0, d1) = (begin[d], end[d]);
            let dsize = d1 - d0;
            let dpat = sn.supernode(d).pattern();
            let dnrows = dsize + dpat.len();
            let dvals = &done[val_ptr[d]..val_ptr[d + 1]];
            // Rows of d's panel from p0 on: those in s (p0..p1), then the rest.
            let p0 = pos[d];
            let mut p1 = p0;
            while p1 < dnrows && dpat[p1 - dsize] < s1 {
                p1 += 1;
            }
            let m = dnrows - p0;
            if !replay {
                targets.extend(dpat[p0 - dsize..].iter().map(|&r| local[r] as u32));
            }
            let target = &targets[cursor..cursor + m];
            cursor += m;
            let nj = p1 - p0;
            column.resize(m * nj, 0.0);
            update_product::<FMA>(
                Panel {
                    vals: dvals,
                    nrows: dnrows,
                    ncols: dsize,
                },
                p0,
                m,
                nj,
                column,
                coefficients,
            );
            for j in 0..nj {
                // Column j of the update, subtracted from the panel's column of row p0 + j.
                let tj = target[j] as usize;
                let dest = &mut panel[tj * nrows..(tj + 1) * nrows];
                for (&t, &r) in column[j * m + j..(j + 1) * m].iter().zip(&target[j..]) {
                    dest[r as usize] -= t;
                }
            }
            // Link d to the supernode of its next row.
            pos[d] = p1;
            if p1 < dnrows {
                let o = owner[dpat[p1 - dsize]];
                next[d] = head[o];
                head[o] = d;
            }
            d = next_d;
        }
        // 3. The panel: Cholesky of its top, the rows below divided through; four columns at
        //    a time, each block first updated by the columns before it (the product of the
        //    updates above), then factored right-looking.
        let mut jb = 0;
        while jb < size {
            let q = (size - jb).min(4);
            let (left, right) = panel.split_at_mut(jb * nrows);
            if jb > 0 {
                let m = nrows - jb;
                column.resize(m * q, 0.0);
                let done = Panel {
                    vals: left,
                    nrows,
                    ncols: jb,
                };
                update_product::<FMA>(done, jb, m, q, column, coefficients);
                for k in 0..q {
                    let col = &mut right[k * nrows + jb..(k + 1) * nrows];
                    for (o, &t) in col[k..].iter_mut().zip(&column[k * m + k..(k + 1) * m]) {
                        *o -= t;
                    }
                }
            }
            for c in jb..jb + q {
                let (left, right) = panel.split_at_mut((c + 1) * nrows);
                let col = &mut left[c * nrows..];
                let p = col[c];
                if !(p > 0.0 && p.is_finite()) {
                    if !replay {
                        // Not recorded: the next factorization records from the start.
                        entry_pos.clear();
                        targets.clear();
                    }
                    return false;
                }
                let p = p.sqrt();
                col[c] = p;
                let inv = 1.0 / p;
                for v in &mut col[c + 1..] {
                    *v *= inv;
                }
                for (k, other) in right
                    .chunks_exact_mut(nrows)
                    .take(jb + q - c - 1)
                    .enumerate()
                {
                    let c2 = c + 1 + k;
                    let f = col[c2];
                    for (o, &v) in other[c2..].iter_mut().zip(&col[c2..]) {
                        *o -= v * f;
                    }
                }
            }
            jb += q;
        }
        if let Some(x) = rhs.as_deref_mut() {
            forward_panel(panel, s0, size, pattern, x, &mut below);
        }
        if !replay {
            for &r in pattern {
                local[r] = NONE;
            }
        }
        // Link s to the supernode of its first row below the panel.
        pos[s] = size;
        if let Some(&r) = pattern.first() {
            let o = owner[r];
            next[s] = head[o];
            head[o] = s;
        }
    }
    *recorded = true;
    true
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::graph::FactorGraph;
    use crate::se2::Pose2;
    use crate::values::Values;

    /// A `side x side` grid of poses joined to their right and lower neighbours: a pose graph's
    /// kind of fill (many small supernodes), cheap enough for debug builds.
    fn grid(side: usize) -> (FactorGraph, Values) {
        let at = |r: usize, c: usize| r * side + c;
        let mut edges = Vec::new();
        for r in 0..side {
            for c in 0..side {
                if c + 1 < side {
                    edges.push((at(r, c), at(r, c + 1)));
                }
                if r + 1 < side {
                    edges.push((at(r, c), at(r + 1, c)));
                }
            }
        }
        let info = [[50.0, 2.0, 1.0], [2.0, 40.0, -1.0], [1.0, -1.0, 300.0]];
        let zs: Vec<[f64; 3]> = edges
            .iter()
            .map(|&(a, b)| [1.0 + 0.01 * (a % 7) as f64, 0.02 * (b % 5) as f64, 0.05])
            .collect();
        let g =
            FactorGraph::from_edges(side * side, &edges, &zs, &vec![info; edges.len()], 0).unwrap();
        let poses = (0..side * side)
            .map(|k| Pose2::new((k % side) as f64, (k / side) as f64, 0.01 * k as f64))
            .collect();
        (g, Values::from_poses(poses))
    }
    use faer::dyn_stack::{MemBuffer, MemStack};
    use faer::linalg::cholesky::llt::factor::LltRegularization;
    use faer::sparse::linalg::cholesky::SymbolicCholeskyRaw;
    use faer::sparse::{SparseColMatRef, SymbolicSparseColMatRef};
    use faer::{Par, Side, Spec};

    /// The same factor as faer's numeric factorization, entry by entry, on supernodal factors
    /// of two grids and three dampings, replaying what an earlier factorization of the pattern
    /// (at another damping) recorded; a refusal where the matrix is indefinite, after which a
    /// fresh work records anew and factors right.
    #[test]
    fn the_factor_equals_faers() {
        for (n, mu) in [(33usize, 0.0), (33, 1e-3), (40, 1e-6)] {
            let (mut g, values) = grid(n);
            let (factors, p) = g.parts().unwrap();
            p.linearize(factors, &values, &[]);
            let mut delta = vec![0.0; p.n];
            assert!(p.solve_damped(1.0, true, &mut delta).unwrap());
            assert!(p.supernodal_work.recorded);
            assert!(p.solve_damped(mu, true, &mut delta).unwrap());
            let SymbolicCholeskyRaw::Supernodal(sn) = p.symbolic.raw() else {
                panic!("n {n}: not supernodal");
            };
            let ours = p.l_values.clone();
            let (h, upper_ptr, wide) = (&p.h, &p.col_ptr, &p.wide);
            let weight = |k: usize, diagonal: bool| {
                let d = h[upper_ptr[k + 1] - 1] + wide.diagonal(k);
                if diagonal {
                    d.clamp(1e-6, 1e32)
                } else {
                    1.0
                }
            };
            let (col_ptr, row_idx, vals) = p.lower.gather(h, Some((mu, true)), weight);
            let sym = SymbolicSparseColMatRef::new_checked(p.n, p.n, col_ptr, None, row_idx);
            let mut theirs = vec![0.0; sn.len_val()];
            let mut mem = MemBuffer::new(
                p.symbolic
                    .factorize_numeric_llt_scratch::<f64>(Par::Seq, Spec::default()),
            );
            p.symbolic
                .factorize_numeric_llt::<f64>(
                    &mut theirs,
                    SparseColMatRef::new(sym, vals),
                    Side::Lower,
                    LltRegularization::default(),
                    Par::Seq,
                    MemStack::new(&mut mem),
                    Spec::default(),
                )
                .unwrap();
            // Entry by entry over each panel's lower part (above the diagonal of its top block
            // faer leaves working values that no solve reads).
            let scale = theirs.iter().fold(0.0f64, |m, v| m.max(v.abs()));
            let mut worst = 0.0f64;
            for s in 0..sn.n_supernodes() {
                let size = sn.supernode_end()[s] - sn.supernode_begin()[s];
                let nrows = size + sn.supernode(s).pattern().len();
                let base = sn.col_ptr_for_val()[s];
                for c in 0..size {
                    for r in c..nrows {
                        let k = base + c * nrows + r;
                        worst = worst.max((ours[k] - theirs[k]).abs());
                    }
                }
            }
            assert!(
                worst <= 1e-12 * scale,
                "n {n} mu {mu}: {worst:e} (scale {scale:e})"
            );
            // An indefinite matrix: the first diagonal entry made negative.
            let mut bad = vals.to_vec();
            bad[0] = -1.0;
            let mut l = vec![0.0; sn.len_val()];
            let mut w = SupernodalWork::default();
            assert!(!factorize(sn, col_ptr, row_idx, &bad, &mut l, &mut w, None));
            assert!(!w.recorded);
            assert!(factorize(sn, col_ptr, row_idx, vals, &mut l, &mut w, None));
            assert!(w.recorded);
            assert!(!factorize(sn, col_ptr, row_idx, &bad, &mut l, &mut w, None));
            assert!(factorize(sn, col_ptr, row_idx, vals, &mut l, &mut w, None));
            assert_eq!(l, ours, "n {n} mu {mu}: refactored after a refusal");
        }
    }
}
