//! Python binding of the front end (`crate::frontend`): scan-to-scan matching along a chain,
//! with the GIL released.

use numpy::ndarray::{Array1, Array2, Array3};
use numpy::{IntoPyArray, PyArray1, PyArray2, PyArray3, PyReadonlyArray1, PyReadonlyArray2};
use pyo3::prelude::*;

use super::{flat_rows, guarded, input_err, to_py};
use crate::frontend::{match_chain, IcpParams};

/// Matches every scan `k + 1` against scan `k` (robot-frame `points` `(P, 2)`, `offsets`
/// `(N + 1,)`) from `guesses[k]` `(N - 1, 3)` (the odometry's `x_k^-1 x_(k+1)`), trying
/// rotations within `search_deg` of each guess. A match is `ok` when at least `min_overlap` of
/// scan `k + 1`'s points (and 25) pair with lines of scan `k`. Returns `(ok (N - 1,) bool,
/// poses (N - 1, 3), covariances (N - 1, 3, 3), overlap (N - 1,))`.
#[pyfunction]
#[pyo3(signature = (points, offsets, guesses, *, search_deg = 45.0, min_overlap = 0.25))]
#[allow(clippy::type_complexity)]
fn match_consecutive<'py>(
    py: Python<'py>,
    points: PyReadonlyArray2<'py, f64>,
    offsets: PyReadonlyArray1<'py, i64>,
    guesses: PyReadonlyArray2<'py, f64>,
    search_deg: f64,
    min_overlap: f64,
) -> PyResult<(
    Bound<'py, PyArray1<bool>>,
    Bound<'py, PyArray2<f64>>,
    Bound<'py, PyArray3<f64>>,
    Bound<'py, PyArray1<f64>>,
)> {
    if !(search_deg.is_finite() && (0.0..=180.0).contains(&search_deg)) {
        return Err(to_py(py, input_err("search_deg must be within 0..180")));
    }
    if !(min_overlap.is_finite() && (0.0..=1.0).contains(&min_overlap)) {
        return Err(to_py(py, input_err("min_overlap must be within 0..1")));
    }
    let params = IcpParams {
        search: search_deg.to_radians(),
        min_overlap,
        ..IcpParams::default()
    };
    let (points, offsets, guesses) = (points.as_array(), offsets.as_array(), guesses.as_array());
    let matches = py
        .detach(|| {
            guarded(|| {
                let pts = flat_rows(points, 2, "points")?;
                let pts: Vec<[f64; 2]> = pts.chunks_exact(2).map(|c| [c[0], c[1]]).collect();
                let g = flat_rows(guesses, 3, "guesses")?;
                let g: Vec<[f64; 3]> = g.chunks_exact(3).map(|c| [c[0], c[1], c[2]]).collect();
                let off = offsets
                    .iter()
                    .map(|&o| usize::try_from(o).map_err(|_| input_err("offsets must be >= 0")))
                    .collect::<Result<Vec<usize>, _>>()?;
                if !pts.iter().flatten().all(|v| v.is_finite()) {
                    return Err(input_err("points must be finite"));
                }
                match_chain(&pts, &off, &g, &params)
            })
        })
        .map_err(|e| to_py(py, e))?;
    let m = matches.len();
    let ok = Array1::from_iter(matches.iter().map(|x| x.ok));
    let poses = Array2::from_shape_fn((m, 3), |(i, j)| matches[i].pose[j]);
    let cov = Array3::from_shape_fn((m, 3, 3), |(i, j, k)| matches[i].covariance[j][k]);
    let overlap = Array1::from_iter(matches.iter().map(|x| x.overlap));
    Ok((
        ok.into_pyarray(py),
        poses.into_pyarray(py),
        cov.into_pyarray(py),
        overlap.into_pyarray(py),
    ))
}

pub(super) fn register(m: &Bound<'_, PyModule>) -> PyResult<()> {
    m.add_function(wrap_pyfunction!(match_consecutive, m)?)?;
    Ok(())
}
