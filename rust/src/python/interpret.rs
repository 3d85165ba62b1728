//! Python bindings of the interpretation kernels (`crate::interpret`): EM over the candidates
//! of drawn segments, the candidate query itself, and the weighted line fit. Point arrays are
//! read in place when C-contiguous, and the work runs with the GIL released.

use std::borrow::Cow;

use numpy::ndarray::{Array1, Array2, ArrayView2, ArrayView3};
use numpy::{
    IntoPyArray, PyArray1, PyArray2, PyReadonlyArray1, PyReadonlyArray2, PyReadonlyArray3,
};
use pyo3::prelude::*;

use super::{flat_rows, guarded, input_err, to_py};
use crate::error::HitlError;
use crate::interpret::{self, EmFit, EmParams, LineFit, Points, Segment, Snap, SnapParams};

/// The rows of an `(n, cols)` array as one flat slice: borrowed when the array is
/// C-contiguous (the usual case), copied in logical order otherwise.
fn segment_of(a: ArrayView2<'_, f64>) -> Result<Segment, HitlError> {
    if a.shape() != [2, 2] {
        return Err(input_err(format!(
            "a segment must have shape (2, 2) (two [x, y] endpoints), got {:?}",
            a.shape()
        )));
    }
    Ok(Segment::new([a[(0, 0)], a[(0, 1)]], [a[(1, 0)], a[(1, 1)]]))
}

fn segments_of(a: ArrayView3<'_, f64>) -> Result<Vec<Segment>, HitlError> {
    if a.shape()[1..] != [2, 2] {
        return Err(input_err(format!(
            "segments must have shape (S, 2, 2), got {:?}",
            a.shape()
        )));
    }
    a.outer_iter().map(segment_of).collect()
}

fn extent_out(py: Python<'_>, line: &LineFit) -> Py<PyArray2<f64>> {
    let [p, q] = line.extent;
    // A (2, 2) shape always matches four numbers.
    Array2::from_shape_vec((2, 2), vec![p[0], p[1], q[0], q[1]])
        .unwrap_or_else(|_| Array2::zeros((2, 2)))
        .into_pyarray(py)
        .unbind()
}

/// EM's interpretation of one drawn segment (docs/ALGORITHM.md §3.3).
#[pyclass(module = "hitl_slam._core", name = "EmFit", frozen, get_all)]
pub struct PyEmFit {
    /// `(K,)` int64 indices of the points within the band of the drawn segment, ascending.
    candidates: Py<PyArray1<i64>>,
    /// `(K,)` final responsibilities; the observation set is `weights > 0.5`.
    weights: Py<PyArray1<f64>>,
    /// Fitted line `n . p = rho` with `n = (cos phi, sin phi)`, phi in (-pi/2, pi/2].
    phi: f64,
    rho: f64,
    /// `(2, 2)` endpoints of the line's extent (inliers' span, clipped to drawn + band).
    extent: Py<PyArray2<f64>>,
    iterations: usize,
    log_likelihood: f64,
    converged: bool,
    /// Final mixing weight pi.
    mixing: f64,
    num_inliers: usize,
    /// The line the drawn segment was snapped to before EM, or None (EM from the drawn line).
    snap: Option<Py<PySnap>>,
}

/// Where a drawn segment was snapped before EM (`em_fit_scans` with `search_band`).
#[pyclass(module = "hitl_slam._core", name = "Snap", frozen, get_all)]
pub struct PySnap {
    /// `(2, 2)` the drawn endpoints projected onto the chosen line, in the drawn order.
    segment: Py<PyArray2<f64>>,
    /// Distances the two endpoints moved (metres).
    moved: (f64, f64),
    /// Angle between the drawing and the line (radians).
    turn: f64,
    /// Observations within 1.5 sigma_em of the line.
    support: usize,
    score: f64,
    /// Best score of a line more than 3 sigma_em away (-inf when none): how clear the choice was.
    runner_up: f64,
}

impl PySnap {
    fn new(py: Python<'_>, s: &Snap) -> PyResult<Py<Self>> {
        let seg = Array2::from_shape_vec(
            (2, 2),
            vec![
                s.segment.a[0],
                s.segment.a[1],
                s.segment.b[0],
                s.segment.b[1],
            ],
        )
        .unwrap_or_else(|_| Array2::zeros((2, 2)))
        .into_pyarray(py)
        .unbind();
        Py::new(
            py,
            Self {
                segment: seg,
                moved: (s.moved[0], s.moved[1]),
                turn: s.turn,
                support: s.support,
                score: s.score,
                runner_up: s.runner_up,
            },
        )
    }
}

#[pymethods]
impl PySnap {
    fn __repr__(&self) -> String {
        format!(
            "Snap(moved=({:.3}, {:.3}), turn={:.4}, support={}, score={:.2}, runner_up={:.2})",
            self.moved.0, self.moved.1, self.turn, self.support, self.score, self.runner_up
        )
    }
}

impl PyEmFit {
    fn new(py: Python<'_>, fit: EmFit) -> PyResult<Self> {
        let candidates: Vec<i64> = fit.candidates.iter().map(|&i| i as i64).collect();
        let snap = fit.snap.as_ref().map(|s| PySnap::new(py, s)).transpose()?;
        Ok(Self {
            candidates: Array1::from_vec(candidates).into_pyarray(py).unbind(),
            extent: extent_out(py, &fit.line),
            weights: Array1::from_vec(fit.weights).into_pyarray(py).unbind(),
            phi: fit.line.phi,
            rho: fit.line.rho,
            iterations: fit.iterations,
            log_likelihood: fit.log_likelihood,
            converged: fit.converged,
            mixing: fit.mixing,
            num_inliers: fit.num_inliers,
            snap,
        })
    }
}

#[pymethods]
impl PyEmFit {
    fn __repr__(&self) -> String {
        format!(
            "EmFit(phi={}, rho={}, num_inliers={}, iterations={}, converged={}, log_likelihood={}, mixing={})",
            self.phi,
            self.rho,
            self.num_inliers,
            self.iterations,
            if self.converged { "True" } else { "False" },
            self.log_likelihood,
            self.mixing
        )
    }
}

/// EM for each segment of `segments` `(S, 2, 2)` over `world_points` `(P, 2)`; one grid index
/// (cell = band) serves every segment. Returns one `EmFit` per segment.
#[pyfunction]
#[pyo3(signature = (
    world_points, segments, *, band, sigma_em, pi0, tol_m, tol_rad, tol_pi, max_iterations
))]
#[allow(clippy::too_many_arguments)]
fn em_fit(
    py: Python<'_>,
    world_points: PyReadonlyArray2<'_, f64>,
    segments: PyReadonlyArray3<'_, f64>,
    band: f64,
    sigma_em: f64,
    pi0: f64,
    tol_m: f64,
    tol_rad: f64,
    tol_pi: f64,
    max_iterations: usize,
) -> PyResult<Vec<PyEmFit>> {
    let params = EmParams {
        band,
        sigma: sigma_em,
        pi0,
        tol_m,
        tol_rad,
        tol_pi,
        max_iterations,
    };
    let (pts, segs) = (world_points.as_array(), segments.as_array());
    let fits = py
        .detach(|| {
            guarded(|| {
                let segs = segments_of(segs)?;
                let flat = flat_rows(pts, 2, "world_points")?;
                interpret::em_fit_segments(Points::new(&flat)?, &segs, &params)
            })
        })
        .map_err(|e| to_py(py, e))?;
    fits.into_iter().map(|f| PyEmFit::new(py, f)).collect()
}

/// `em_fit` on a map as stored: `poses` `(N, 3)`, robot-frame `points` `(P, 2)` and `offsets`
/// `(N + 1,)` (pose i owns rows `offsets[i]:offsets[i + 1]`). The world points are computed
/// here, in the same pass as their bounds, instead of in numpy (several times faster).
/// With `search_band` (metres), each segment is first snapped onto the best-scoring line of
/// observations within that distance (`closeness`: how far beside a wall a person draws,
/// `pointing`: each endpoint's noise, `min_support` points make a line) and EM starts there.
#[pyfunction]
#[pyo3(signature = (
    poses, points, offsets, segments, *, band, sigma_em, pi0, tol_m, tol_rad, tol_pi,
    max_iterations, search_band = None, closeness = 0.2, pointing = 0.1, min_support = 8
))]
#[allow(clippy::too_many_arguments)]
fn em_fit_scans(
    py: Python<'_>,
    poses: PyReadonlyArray2<'_, f64>,
    points: PyReadonlyArray2<'_, f64>,
    offsets: PyReadonlyArray1<'_, i64>,
    segments: PyReadonlyArray3<'_, f64>,
    band: f64,
    sigma_em: f64,
    pi0: f64,
    tol_m: f64,
    tol_rad: f64,
    tol_pi: f64,
    max_iterations: usize,
    search_band: Option<f64>,
    closeness: f64,
    pointing: f64,
    min_support: usize,
) -> PyResult<Vec<PyEmFit>> {
    let params = EmParams {
        band,
        sigma: sigma_em,
        pi0,
        tol_m,
        tol_rad,
        tol_pi,
        max_iterations,
    };
    let search = search_band.map(|search_band| SnapParams {
        search_band,
        sigma: sigma_em,
        closeness,
        pointing,
        min_support,
    });
    let (poses, pts, offsets, segs) = (
        poses.as_array(),
        points.as_array(),
        offsets.as_array(),
        segments.as_array(),
    );
    let fits = py
        .detach(|| {
            guarded(|| {
                let segs = segments_of(segs)?;
                let poses = flat_rows(poses, 3, "poses")?;
                let pts = flat_rows(pts, 2, "points")?;
                let offsets: Cow<'_, [i64]> = match offsets.to_slice() {
                    Some(s) => Cow::Borrowed(s),
                    None => Cow::Owned(offsets.iter().copied().collect()),
                };
                interpret::em_fit_scans(
                    &poses,
                    Points::new(&pts)?,
                    &offsets,
                    &segs,
                    &params,
                    search.as_ref(),
                )
            })
        })
        .map_err(|e| to_py(py, e))?;
    fits.into_iter().map(|f| PyEmFit::new(py, f)).collect()
}

/// `(K,)` int64 indices (ascending) of the `world_points` within distance `band` of `segment`
/// `(2, 2)` (distance to the segment, so the band wraps round each end). `use_index=False`
/// tests every point instead of using the grid: the reference the index is checked against.
#[pyfunction]
#[pyo3(signature = (world_points, segment, band, *, use_index = true))]
fn segment_candidates<'py>(
    py: Python<'py>,
    world_points: PyReadonlyArray2<'py, f64>,
    segment: PyReadonlyArray2<'py, f64>,
    band: f64,
    use_index: bool,
) -> PyResult<Bound<'py, PyArray1<i64>>> {
    let (pts, seg) = (world_points.as_array(), segment.as_array());
    let found = py
        .detach(|| {
            guarded(|| {
                let seg = segment_of(seg)?;
                let flat = flat_rows(pts, 2, "world_points")?;
                let points = Points::new(&flat)?;
                if use_index {
                    interpret::candidates(points, &seg, band)
                } else {
                    interpret::candidates_brute_force(points, &seg, band)
                }
            })
        })
        .map_err(|e| to_py(py, e))?;
    let out: Vec<i64> = found.into_iter().map(|i| i as i64).collect();
    Ok(Array1::from_vec(out).into_pyarray(py))
}

/// Weighted total least squares line of `points` `(K, 2)` with `weights` `(K,)`: returns
/// `(phi, rho, extent)`, the line `n . p = rho` with `n = (cos phi, sin phi)`, phi in
/// (-pi/2, pi/2], and the `(2, 2)` extent of the points with weight > 0.5 clipped to `segment`
/// plus `band` past each end (`segment` also gives the direction when the points have none).
#[pyfunction]
fn line_fit<'py>(
    py: Python<'py>,
    points: PyReadonlyArray2<'py, f64>,
    weights: PyReadonlyArray1<'py, f64>,
    segment: PyReadonlyArray2<'py, f64>,
    band: f64,
) -> PyResult<(f64, f64, Bound<'py, PyArray2<f64>>)> {
    let (pts, w, seg) = (points.as_array(), weights.as_array(), segment.as_array());
    let line = guarded(|| {
        let seg = segment_of(seg)?;
        let flat = flat_rows(pts, 2, "points")?;
        let w: Cow<'_, [f64]> = match w.to_slice() {
            Some(s) => Cow::Borrowed(s),
            None => Cow::Owned(w.iter().copied().collect()),
        };
        interpret::line_fit(Points::new(&flat)?, &w, &seg, band)
    })
    .map_err(|e| to_py(py, e))?;
    Ok((line.phi, line.rho, extent_out(py, &line).into_bound(py)))
}

pub(crate) fn register(m: &Bound<'_, PyModule>) -> PyResult<()> {
    m.add_class::<PyEmFit>()?;
    m.add_class::<PySnap>()?;
    m.add_function(wrap_pyfunction!(em_fit, m)?)?;
    m.add_function(wrap_pyfunction!(em_fit_scans, m)?)?;
    m.add_function(wrap_pyfunction!(segment_candidates, m)?)?;
    m.add_function(wrap_pyfunction!(line_fit, m)?)?;
    Ok(())
}
