//! The fill-reducing ordering of a block graph (faer's approximate minimum degree).

use faer::dyn_stack::{MemBuffer, MemStack};
use faer::sparse::linalg::amd;
use faer::sparse::SymbolicSparseColMatRef;

use crate::error::{HitlError, Result};

/// AMD on a block graph (given as symmetric CSR without diagonal): `(fwd, inv)` with
/// `fwd[new] = old` and `inv[old] = new`. Used by the solver's pattern and by `init`.
pub(crate) fn block_amd(
    nb: usize,
    adj_ptr: &[usize],
    adj_idx: &[usize],
) -> Result<(Vec<usize>, Vec<usize>)> {
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
    Ok((fwd, inv))
}
