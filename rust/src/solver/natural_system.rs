//! The assembled normal equations exported in the natural variable order (poses by index, then
//! lines; fixed ones skipped) instead of the solver's elimination order: the upper triangle of
//! the full H with the wide factors' `U U^T` merged in, and `J^T r`, for cross-checks against
//! SciPy.

use std::collections::HashMap;

use super::pattern::SparsityPattern;
use crate::values::Key;

/// `(rows, cols, values, gradient, keys)`: the upper triangle of H and J^T r in natural order.
pub type NaturalSystem = (Vec<usize>, Vec<usize>, Vec<f64>, Vec<f64>, Vec<Key>);

impl SparsityPattern {
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

#[cfg(test)]
mod tests {
    use crate::solver::test_problems::{corrected, dense_hessian, Relations};

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
}
