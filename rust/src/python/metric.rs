//! Python binding of the inconsistency metric (`crate::metric`): the map's arrays are read in
//! place when C-contiguous, the count runs with the GIL released, on rayon's global pool or on a
//! local pool of `threads` threads, and the heat map comes back as an `(H, W)` float64 array.

use std::borrow::Cow;

use numpy::ndarray::{Array1, Array2, ArrayView1};
use numpy::{IntoPyArray, PyArray1, PyArray2, PyReadonlyArray1, PyReadonlyArray2};
use pyo3::prelude::*;

use super::{flat_rows, guarded, input_err, to_py};
use crate::error::HitlError;
use crate::metric::{self, Grid, MetricParams, Scans};

/// More threads than this is surely a mistake (and would only cost memory).
const MAX_THREADS: usize = 1024;

fn vector<T: Copy>(a: ArrayView1<'_, T>) -> Cow<'_, [T]> {
    match a.to_slice() {
        Some(s) => Cow::Borrowed(s),
        None => Cow::Owned(a.iter().copied().collect()),
    }
}

/// The inconsistency metric (docs/ALGORITHM.md §6) of the map `poses` `(N, 3)`, robot-frame
/// `points` `(P, 2)` in beam order, `offsets` `(N + 1,)`. Returns `(total_m2, heat, origin)`:
/// `heat` is the `(H, W)` per-cell `F O - B` (row 0 at the origin's y) or None, `origin` the world
/// `(x, y)` of the grid's lower-left corner. The grid covers the data (origin a multiple of the
/// resolution) unless `origin` and `shape` `(H, W)` are given.
#[pyfunction]
#[pyo3(signature = (
    poses, points, offsets, *, resolution, surface_cells, min_stop, grazing_deg,
    pairwise = false, heat_map = true, origin = None, shape = None, threads = 0
))]
#[allow(clippy::too_many_arguments, clippy::type_complexity)]
fn inconsistency<'py>(
    py: Python<'py>,
    poses: PyReadonlyArray2<'py, f64>,
    points: PyReadonlyArray2<'py, f64>,
    offsets: PyReadonlyArray1<'py, i64>,
    resolution: f64,
    surface_cells: f64,
    min_stop: f64,
    grazing_deg: f64,
    pairwise: bool,
    heat_map: bool,
    origin: Option<PyReadonlyArray1<'py, f64>>,
    shape: Option<(usize, usize)>,
    threads: usize,
) -> PyResult<(
    f64,
    Option<Bound<'py, PyArray2<f64>>>,
    Bound<'py, PyArray1<f64>>,
)> {
    let params = MetricParams {
        surface_cells,
        min_stop,
        grazing_deg,
    };
    let (poses, points, offsets) = (poses.as_array(), points.as_array(), offsets.as_array());
    let origin: Option<Vec<f64>> = origin.map(|o| o.as_array().iter().copied().collect());
    let result = py.detach(|| {
        guarded(|| {
            let poses = flat_rows(poses, 3, "poses")?;
            let points = flat_rows(points, 2, "points")?;
            let offsets = vector(offsets);
            let scans = Scans::new(&poses, &points, &offsets)?;
            let grid = match (origin.as_deref(), shape) {
                (None, None) => scans.covering_grid(resolution)?,
                (Some(&[x, y]), Some((height, width))) => {
                    Grid::new([x, y], resolution, width, height)?
                }
                (Some(_), Some(_)) => {
                    return Err(input_err(
                        "origin must have shape (2,): the (x, y) of a corner",
                    ))
                }
                _ => return Err(input_err("give both origin and shape, or neither")),
            };
            let run = || {
                if pairwise {
                    metric::inconsistency_pairwise(&scans, &grid, &params, heat_map)
                } else {
                    metric::inconsistency(&scans, &grid, &params, heat_map)
                }
            };
            match threads {
                0 => run(),
                t if t > MAX_THREADS => Err(input_err(format!(
                    "threads must be from 0 (rayon's default) to {MAX_THREADS}, got {t}"
                ))),
                t => rayon::ThreadPoolBuilder::new()
                    .num_threads(t)
                    .build()
                    .map_err(|e| HitlError::Solver(format!("could not start {t} threads: {e}")))?
                    .install(run),
            }
        })
    });
    let r = result.map_err(|e| to_py(py, e))?;
    let (height, width) = (r.grid.height, r.grid.width);
    let heat = match r.heat {
        Some(h) => {
            let values: Vec<f64> = h.into_iter().map(|v| v as f64).collect();
            // (height, width) always matches the grid's cell count.
            Some(
                Array2::from_shape_vec((height, width), values)
                    .unwrap_or_else(|_| Array2::zeros((height, width)))
                    .into_pyarray(py),
            )
        }
        None => None,
    };
    let origin = Array1::from_vec(r.grid.origin.to_vec()).into_pyarray(py);
    Ok((r.total_m2, heat, origin))
}

pub(crate) fn register(m: &Bound<'_, PyModule>) -> PyResult<()> {
    m.add_function(wrap_pyfunction!(inconsistency, m)?)?;
    Ok(())
}
