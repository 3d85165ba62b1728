//! The Python boundary, and the only module that knows about Python: `hitl_slam._core`.
//!
//! Arrays come in as read-only numpy views and results go out as numpy arrays that take over
//! Rust's buffers (no copies). Solves run with the GIL released. Every error maps once to the
//! package's exception classes (defined in `hitl_slam/errors.py`), and a panic is caught here
//! and reported as an internal error instead of reaching the user as `PanicException`.

mod engine;
mod frontend;
mod interpret;
mod metric;

use std::panic::{catch_unwind, AssertUnwindSafe};

use numpy::ndarray::{Array1, Array2, Array3};
use numpy::{
    IntoPyArray, PyArray1, PyArray2, PyArray3, PyReadonlyArray1, PyReadonlyArray2, PyReadonlyArray3,
};
use pyo3::exceptions::PyRuntimeError;
use pyo3::prelude::*;
use pyo3::types::PyType;

use crate::correction::{
    backpropagate as backpropagate_chain, explicit_transform as explicit_rigid, CorrectionSpec,
    HumanWeights,
};
use crate::error::HitlError;
use crate::factors::{BetweenFactor, FactorClass, PriorFactor, RelationMode};
use crate::graph::FactorGraph;
use crate::init::InitMethod;
use crate::se2::Pose2;
use crate::solver::{
    self, IterationRecord, Kernel, Method, RobustKernels, SolveReport, SolverParams,
};
use crate::values::{Key, Line2, Values};

fn exception(py: Python<'_>, name: &str, msg: String) -> PyErr {
    let class = py
        .import("hitl_slam.errors")
        .and_then(|m| m.getattr(name))
        .and_then(|c| c.cast_into::<PyType>().map_err(PyErr::from));
    match class {
        Ok(cls) => PyErr::from_type(cls, msg),
        Err(_) => PyRuntimeError::new_err(msg),
    }
}

pub(super) fn to_py(py: Python<'_>, e: HitlError) -> PyErr {
    match e {
        HitlError::Input(m) => exception(py, "InputError", m),
        HitlError::Solver(m) => exception(py, "SolverError", m),
        HitlError::Rejected(m) => exception(py, "CorrectionRejected", m),
    }
}

/// Runs `f`, turning a panic into an error that says it is a bug.
pub(super) fn guarded<T>(f: impl FnOnce() -> Result<T, HitlError>) -> Result<T, HitlError> {
    match catch_unwind(AssertUnwindSafe(f)) {
        Ok(r) => r,
        Err(payload) => {
            let what = payload
                .downcast_ref::<&str>()
                .map(|s| s.to_string())
                .or_else(|| payload.downcast_ref::<String>().cloned())
                .unwrap_or_else(|| "unknown panic".into());
            Err(HitlError::Solver(format!(
                "internal error in the hitl-slam core ({what}); nothing was changed; please report this with the input"
            )))
        }
    }
}

/// A read-only `(n, cols)` view as one row-major slice: borrowed when the array is C-contiguous
/// (no copy), copied otherwise.
pub(super) fn flat_rows<'a>(
    a: numpy::ndarray::ArrayView2<'a, f64>,
    cols: usize,
    what: &str,
) -> Result<std::borrow::Cow<'a, [f64]>, HitlError> {
    if a.ncols() != cols {
        return Err(input_err(format!(
            "{what} must have shape (n, {cols}), got {:?}",
            a.shape()
        )));
    }
    Ok(match a.to_slice() {
        Some(s) => std::borrow::Cow::Borrowed(s),
        None => std::borrow::Cow::Owned(a.iter().copied().collect()),
    })
}

pub(super) fn input_err(msg: impl Into<String>) -> HitlError {
    HitlError::Input(msg.into())
}

pub(super) fn read_poses(poses: &PyReadonlyArray2<'_, f64>) -> Result<Vec<Pose2>, HitlError> {
    let a = poses.as_array();
    if a.ncols() != 3 {
        return Err(input_err(format!(
            "poses must have shape (N, 3), got {:?}",
            a.shape()
        )));
    }
    let mut out = Vec::with_capacity(a.nrows());
    for (i, row) in a.rows().into_iter().enumerate() {
        let (x, y, t) = (row[0], row[1], row[2]);
        if !(x.is_finite() && y.is_finite() && t.is_finite()) {
            return Err(input_err(format!(
                "pose row {i} is not finite ({x}, {y}, {t}); give finite values"
            )));
        }
        out.push(Pose2::new(x, y, t));
    }
    Ok(out)
}

pub(super) fn poses_out<'py>(py: Python<'py>, values: &Values) -> Bound<'py, PyArray2<f64>> {
    let flat: Vec<f64> = values.poses.iter().flat_map(|p| p.to_array()).collect();
    // Shape (N, 3) always matches the buffer length, so this cannot fail.
    let n = values.poses.len();
    Array2::from_shape_vec((n, 3), flat)
        .unwrap_or_else(|_| Array2::zeros((n, 3)))
        .into_pyarray(py)
}

/// The solver settings of the solves over poses and lines (`Graph.optimize_with_lines`,
/// `CorrectionEngine.solve`): the given ones, the rest at their defaults.
pub(super) fn line_solve_params(
    method: &str,
    max_iterations: usize,
    relative_tolerance: f64,
    absolute_tolerance: f64,
    lambda_initial: f64,
    robust: Option<&[(String, String)]>,
    watchdog_steps: usize,
) -> Result<SolverParams, HitlError> {
    Ok(SolverParams {
        method: parse_method(method)?,
        max_iterations,
        relative_tolerance,
        absolute_tolerance,
        lambda_initial,
        robust: parse_robust(robust.unwrap_or(&[]))?,
        watchdog_steps,
        ..SolverParams::default()
    })
}

/// A solve's answer for Python: poses `(N, 3)`, lines `(L, 2)` rows `(phi, rho)`, the report.
#[allow(clippy::type_complexity)]
pub(super) fn solved_out<'py>(
    py: Python<'py>,
    values: &Values,
    report: SolveReport,
) -> (
    Bound<'py, PyArray2<f64>>,
    Bound<'py, PyArray2<f64>>,
    PySolveReport,
) {
    let flat: Vec<f64> = values.lines.iter().flat_map(|v| [v.phi, v.rho]).collect();
    let nl = values.lines.len();
    // Shape (L, 2) always matches the buffer length, so this cannot fail.
    let lines = Array2::from_shape_vec((nl, 2), flat).unwrap_or_else(|_| Array2::zeros((nl, 2)));
    (
        poses_out(py, values),
        lines.into_pyarray(py),
        PySolveReport::new(py, report),
    )
}

fn read_info(m: numpy::ndarray::ArrayView2<'_, f64>) -> [[f64; 3]; 3] {
    [
        [m[(0, 0)], m[(0, 1)], m[(0, 2)]],
        [m[(1, 0)], m[(1, 1)], m[(1, 2)]],
        [m[(2, 0)], m[(2, 1)], m[(2, 2)]],
    ]
}

/// A `(3,)` measurement and its `(3, 3)` information, checked for shape.
fn read_measurement(
    z: numpy::ndarray::ArrayView1<'_, f64>,
    info: numpy::ndarray::ArrayView2<'_, f64>,
) -> Result<(Pose2, [[f64; 3]; 3]), HitlError> {
    if z.len() != 3 || info.shape() != [3, 3] {
        return Err(input_err(
            "measurement must have shape (3,) and information (3, 3)",
        ));
    }
    Ok((Pose2::new(z[0], z[1], z[2]), read_info(info)))
}

impl PyGraph {
    /// The factor graph of `edges` (validated; errors name the edge).
    pub(super) fn build(
        py: Python<'_>,
        num_poses: usize,
        edges: PyReadonlyArray2<'_, i64>,
        measurements: PyReadonlyArray2<'_, f64>,
        information: PyReadonlyArray3<'_, f64>,
        anchor: usize,
    ) -> PyResult<FactorGraph> {
        let (e, z, info) = (
            edges.as_array(),
            measurements.as_array(),
            information.as_array(),
        );
        let m = e.nrows();
        let build = || -> Result<FactorGraph, HitlError> {
            if e.ncols() != 2 {
                return Err(input_err(format!(
                    "edges must have shape (M, 2), got {:?}",
                    e.shape()
                )));
            }
            if z.shape() != [m, 3] {
                return Err(input_err(format!(
                    "measurements must have shape ({m}, 3), got {:?}",
                    z.shape()
                )));
            }
            if info.shape() != [m, 3, 3] {
                return Err(input_err(format!(
                    "information must have shape ({m}, 3, 3), got {:?}",
                    info.shape()
                )));
            }
            let mut pairs = Vec::with_capacity(m);
            for (k, row) in e.rows().into_iter().enumerate() {
                let (i, j) = (row[0], row[1]);
                if i < 0 || j < 0 {
                    return Err(input_err(format!(
                        "edge {k} has a negative pose index ({i}, {j})"
                    )));
                }
                pairs.push((i as usize, j as usize));
            }
            let zs: Vec<[f64; 3]> = z.rows().into_iter().map(|r| [r[0], r[1], r[2]]).collect();
            let infos: Vec<[[f64; 3]; 3]> = info.outer_iter().map(read_info).collect();
            FactorGraph::from_edges(num_poses, &pairs, &zs, &infos, anchor)
        };
        guarded(build).map_err(|e| to_py(py, e))
    }
}

/// A pose graph held by the core, with its cached symbolic analysis.
#[pyclass(module = "hitl_slam._core", name = "Graph")]
pub struct PyGraph {
    inner: FactorGraph,
}

#[pymethods]
impl PyGraph {
    #[new]
    #[pyo3(signature = (num_poses, edges, measurements, information, anchor = 0))]
    fn new(
        py: Python<'_>,
        num_poses: usize,
        edges: PyReadonlyArray2<'_, i64>,
        measurements: PyReadonlyArray2<'_, f64>,
        information: PyReadonlyArray3<'_, f64>,
        anchor: usize,
    ) -> PyResult<Self> {
        Self::build(py, num_poses, edges, measurements, information, anchor)
            .map(|inner| Self { inner })
    }

    /// Number of poses.
    #[getter]
    fn num_poses(&self) -> usize {
        self.inner.num_poses()
    }

    /// Number of factors (edges and priors).
    #[getter]
    fn num_factors(&self) -> usize {
        self.inner.num_factors()
    }

    /// How many symbolic analyses have been computed (one per structure change).
    #[getter]
    fn analyses(&self) -> usize {
        self.inner.analyses()
    }

    /// Adds a relative-pose factor (the next solve redoes the symbolic analysis).
    fn add_between(
        &mut self,
        py: Python<'_>,
        i: usize,
        j: usize,
        measurement: PyReadonlyArray1<'_, f64>,
        information: PyReadonlyArray2<'_, f64>,
    ) -> PyResult<()> {
        let (z, info) = (measurement.as_array(), information.as_array());
        let graph = &mut self.inner;
        guarded(|| {
            let (z, info) = read_measurement(z, info)?;
            let f = BetweenFactor::new(i, j, z, &info)
                .map_err(|e| input_err(format!("edge {i} -> {j}: {e}")))?;
            graph.add_between(f)
        })
        .map_err(|e| to_py(py, e))
    }

    /// Adds a prior on pose `i`.
    fn add_prior(
        &mut self,
        py: Python<'_>,
        i: usize,
        measurement: PyReadonlyArray1<'_, f64>,
        information: PyReadonlyArray2<'_, f64>,
    ) -> PyResult<()> {
        let (z, info) = (measurement.as_array(), information.as_array());
        let graph = &mut self.inner;
        guarded(|| {
            let (z, info) = read_measurement(z, info)?;
            let f = PriorFactor::new(i, z, &info)?;
            graph.add_prior(f)
        })
        .map_err(|e| to_py(py, e))
    }

    /// chi2 = sum of squared whitened residuals at `poses`.
    fn chi2(&self, py: Python<'_>, poses: PyReadonlyArray2<'_, f64>) -> PyResult<f64> {
        let graph = &self.inner;
        guarded(|| {
            let values = Values::from_poses(read_poses(&poses)?);
            graph.check_values(&values)?;
            Ok(graph.chi2(&values))
        })
        .map_err(|e| to_py(py, e))
    }

    /// Optimizes from `poses`; returns the optimized poses and a report. The GIL is released
    /// while solving.
    #[pyo3(signature = (
        poses, *, method = "lm", max_iterations = 100, relative_tolerance = 1e-6,
        absolute_tolerance = 1e-6, error_tolerance = 0.0, gradient_tolerance = 1e-12,
        step_tolerance = 1e-12, lambda_initial = 1e-5, lambda_max = 1e16, diagonal_damping = false,
        watchdog_steps = 3, trust_radius_initial = 0.0, robust = None, init = "given"
    ))]
    #[allow(clippy::too_many_arguments)]
    fn optimize<'py>(
        &mut self,
        py: Python<'py>,
        poses: PyReadonlyArray2<'py, f64>,
        method: &str,
        max_iterations: usize,
        relative_tolerance: f64,
        absolute_tolerance: f64,
        error_tolerance: f64,
        gradient_tolerance: f64,
        step_tolerance: f64,
        lambda_initial: f64,
        lambda_max: f64,
        diagonal_damping: bool,
        watchdog_steps: usize,
        trust_radius_initial: f64,
        robust: Option<Vec<(String, String)>>,
        init: &str,
    ) -> PyResult<(Bound<'py, PyArray2<f64>>, PySolveReport)> {
        let params = (|| -> Result<SolverParams, HitlError> {
            Ok(SolverParams {
                method: Method::parse(method)?,
                max_iterations,
                relative_tolerance,
                absolute_tolerance,
                error_tolerance,
                gradient_tolerance,
                step_tolerance,
                lambda_initial,
                lambda_max,
                diagonal_damping,
                watchdog_steps,
                trust_radius_initial,
                robust: parse_robust(robust.as_deref().unwrap_or(&[]))?,
            })
        })()
        .map_err(|e| to_py(py, e))?;
        let init = InitMethod::parse(init).map_err(|e| to_py(py, e))?;
        let mut values = Values::from_poses(read_poses(&poses).map_err(|e| to_py(py, e))?);
        drop(poses);
        if init != InitMethod::Given {
            let graph = &self.inner;
            let initial = py
                .detach(|| guarded(|| graph.initial_guess(init, &values.poses)))
                .map_err(|e| to_py(py, e))?;
            values.poses = initial;
        }
        let graph = &mut self.inner;
        let result = py.detach(|| guarded(|| solver::optimize(graph, &mut values, &params)));
        let report = result.map_err(|e| to_py(py, e))?;
        Ok((poses_out(py, &values), PySolveReport::new(py, report)))
    }

    /// Marginal covariances `(K, 3, 3)` of the poses `indices` at `poses` (in each pose's body
    /// frame, as GTSAM's `Marginals`); the anchored pose has a zero covariance.
    fn marginals<'py>(
        &mut self,
        py: Python<'py>,
        poses: PyReadonlyArray2<'py, f64>,
        indices: PyReadonlyArray1<'py, i64>,
    ) -> PyResult<Bound<'py, PyArray3<f64>>> {
        let values = Values::from_poses(read_poses(&poses).map_err(|e| to_py(py, e))?);
        let n = values.poses.len();
        let mut keys = Vec::new();
        for &i in indices.as_array().iter() {
            if i < 0 || i as usize >= n {
                return Err(to_py(
                    py,
                    input_err(format!("pose index {i} is out of range (0..{n})")),
                ));
            }
            keys.push(Key::Pose(i as usize));
        }
        let graph = &mut self.inner;
        let blocks = py
            .detach(|| guarded(|| solver::marginal_covariances(graph, &values, &keys)))
            .map_err(|e| to_py(py, e))?;
        let flat: Vec<f64> = blocks.into_iter().flatten().collect();
        let k = keys.len();
        let arr =
            Array3::from_shape_vec((k, 3, 3), flat).unwrap_or_else(|_| Array3::zeros((k, 3, 3)));
        Ok(arr.into_pyarray(py))
    }

    /// The Gauss-Newton system at `poses`, for cross-checks: `(rows, cols, values, gradient,
    /// pose_indices)` where (rows, cols, values) is the upper triangle of `H = J^T J` in the
    /// natural order of the free poses `pose_indices`, and `gradient = J^T r`.
    #[allow(clippy::type_complexity)]
    fn linear_system<'py>(
        &mut self,
        py: Python<'py>,
        poses: PyReadonlyArray2<'py, f64>,
    ) -> PyResult<(
        Bound<'py, PyArray1<i64>>,
        Bound<'py, PyArray1<i64>>,
        Bound<'py, PyArray1<f64>>,
        Bound<'py, PyArray1<f64>>,
        Bound<'py, PyArray1<i64>>,
    )> {
        let values = Values::from_poses(read_poses(&poses).map_err(|e| to_py(py, e))?);
        let graph = &mut self.inner;
        let (r, c, v, g, keys) = guarded(|| {
            graph.check_values(&values)?;
            let (factors, pattern) = graph.parts()?;
            pattern.linearize(factors, &values, &[]);
            Ok(pattern.upper_triplets_natural())
        })
        .map_err(|e| to_py(py, e))?;
        let as_i64 =
            |v: Vec<usize>| Array1::from_vec(v.into_iter().map(|x| x as i64).collect::<Vec<i64>>());
        let pose_idx: Vec<usize> = keys
            .into_iter()
            .filter_map(|k| match k {
                Key::Pose(i) => Some(i),
                Key::Line(_) => None,
            })
            .collect();
        Ok((
            as_i64(r).into_pyarray(py),
            as_i64(c).into_pyarray(py),
            Array1::from_vec(v).into_pyarray(py),
            Array1::from_vec(g).into_pyarray(py),
            as_i64(pose_idx).into_pyarray(py),
        ))
    }

    /// Number of line variables (two per human correction).
    #[getter]
    fn num_lines(&self) -> usize {
        self.inner.num_lines()
    }

    /// Adds one human correction (docs/ALGORITHM.md §4.3): two line variables, the point-to-line
    /// factors R_a / R_b (one block per observing pose) and the relation R_p. `*_poses[k]` is the
    /// pose that observed robot-frame point `*_points[k]`. Returns the two line indices.
    #[pyo3(signature = (mode, a_poses, a_points, b_poses, b_points, *, sigma_f, k1, k2, average_points = false))]
    #[allow(clippy::too_many_arguments)]
    fn add_correction(
        &mut self,
        py: Python<'_>,
        mode: &str,
        a_poses: PyReadonlyArray1<'_, i64>,
        a_points: PyReadonlyArray2<'_, f64>,
        b_poses: PyReadonlyArray1<'_, i64>,
        b_points: PyReadonlyArray2<'_, f64>,
        sigma_f: f64,
        k1: f64,
        k2: f64,
        average_points: bool,
    ) -> PyResult<(usize, usize)> {
        let (ap, aq, bp, bq) = (
            a_poses.as_array(),
            a_points.as_array(),
            b_poses.as_array(),
            b_points.as_array(),
        );
        let graph = &mut self.inner;
        guarded(|| {
            let n = graph.num_poses();
            let spec = CorrectionSpec {
                mode: RelationMode::parse(mode)?,
                a: group_by_pose(ap, aq, n, "a")?,
                b: group_by_pose(bp, bq, n, "b")?,
            };
            spec.validate(n)?;
            let weights = HumanWeights {
                sigma_f,
                k1,
                k2,
                average_points,
            };
            weights.validate()?;
            // Build every factor first so that a bad input adds nothing.
            let la = graph.num_lines();
            let factors = spec.factors(la, &weights)?;
            graph.add_line();
            let lb = graph.add_line();
            for f in factors {
                graph.add_factor(f)?;
            }
            Ok((la, lb))
        })
        .map_err(|e| to_py(py, e))
    }

    /// As `optimize`, over poses and line variables: returns (poses, lines, report). `lines`
    /// is `(L, 2)` rows `(phi, rho)`.
    #[pyo3(signature = (
        poses, lines, *, method = "lm", max_iterations = 100, relative_tolerance = 1e-6,
        absolute_tolerance = 1e-6, lambda_initial = 1e-5, robust = None, watchdog_steps = 3
    ))]
    #[allow(clippy::too_many_arguments, clippy::type_complexity)]
    fn optimize_with_lines<'py>(
        &mut self,
        py: Python<'py>,
        poses: PyReadonlyArray2<'py, f64>,
        lines: PyReadonlyArray2<'py, f64>,
        method: &str,
        max_iterations: usize,
        relative_tolerance: f64,
        absolute_tolerance: f64,
        lambda_initial: f64,
        robust: Option<Vec<(String, String)>>,
        watchdog_steps: usize,
    ) -> PyResult<(
        Bound<'py, PyArray2<f64>>,
        Bound<'py, PyArray2<f64>>,
        PySolveReport,
    )> {
        let params = line_solve_params(
            method,
            max_iterations,
            relative_tolerance,
            absolute_tolerance,
            lambda_initial,
            robust.as_deref(),
            watchdog_steps,
        )
        .map_err(|e| to_py(py, e))?;
        let l = lines.as_array();
        if l.ncols() != 2 {
            return Err(to_py(
                py,
                input_err(format!("lines must have shape (L, 2), got {:?}", l.shape())),
            ));
        }
        let line_values: Vec<Line2> = l
            .rows()
            .into_iter()
            .map(|r| Line2 {
                phi: r[0],
                rho: r[1],
            })
            .collect();
        if line_values
            .iter()
            .any(|v| !(v.phi.is_finite() && v.rho.is_finite()))
        {
            return Err(to_py(py, input_err("line values must be finite")));
        }
        let mut values = Values {
            poses: read_poses(&poses).map_err(|e| to_py(py, e))?,
            lines: line_values,
        };
        let graph = &mut self.inner;
        let report = py
            .detach(|| guarded(|| solver::optimize(graph, &mut values, &params)))
            .map_err(|e| to_py(py, e))?;
        Ok(solved_out(py, &values, report))
    }

    fn __repr__(&self) -> String {
        format!(
            "Graph(num_poses={}, num_lines={}, num_factors={})",
            self.inner.num_poses(),
            self.inner.num_lines(),
            self.inner.num_factors()
        )
    }
}

/// One trial step of a solve.
#[pyclass(module = "hitl_slam._core", name = "IterationRecord", frozen, get_all)]
#[derive(Clone)]
pub struct PyIterationRecord {
    iteration: usize,
    chi2: f64,
    damping: f64,
    step_norm: f64,
    accepted: bool,
    elapsed_s: f64,
}

#[pymethods]
impl PyIterationRecord {
    fn __repr__(&self) -> String {
        format!(
            "IterationRecord(iteration={}, chi2={}, damping={}, step_norm={}, accepted={}, elapsed_s={})",
            self.iteration,
            self.chi2,
            self.damping,
            self.step_norm,
            if self.accepted { "True" } else { "False" },
            self.elapsed_s
        )
    }
}

impl From<&IterationRecord> for PyIterationRecord {
    fn from(r: &IterationRecord) -> Self {
        Self {
            iteration: r.iteration,
            chi2: r.chi2,
            damping: r.lambda,
            step_norm: r.step_norm,
            accepted: r.accepted,
            elapsed_s: r.elapsed,
        }
    }
}

/// What a solve did: iterations, chi2 before and after, why it stopped, where the time went.
#[pyclass(module = "hitl_slam._core", name = "SolveReport", frozen, get_all)]
pub struct PySolveReport {
    iterations: usize,
    linear_solves: usize,
    chord_steps: usize,
    initial_cost: f64,
    final_cost: f64,
    initial_chi2: f64,
    final_chi2: f64,
    termination: String,
    termination_detail: String,
    converged: bool,
    weights: Py<PyArray1<f64>>,
    time_s: f64,
    time_symbolic_s: f64,
    time_linearize_s: f64,
    time_factorize_s: f64,
    symbolic_computed: bool,
    nnz_hessian: usize,
    nnz_factor: usize,
    history: Vec<PyIterationRecord>,
}

impl PySolveReport {
    pub(super) fn new(py: Python<'_>, r: SolveReport) -> Self {
        Self {
            iterations: r.iterations,
            linear_solves: r.linear_solves,
            chord_steps: r.chord_steps,
            initial_cost: r.initial_cost,
            final_cost: r.final_cost,
            initial_chi2: r.initial_chi2,
            final_chi2: r.final_chi2,
            termination: r.termination.name().to_string(),
            termination_detail: r.termination_detail,
            converged: r.termination.converged(),
            weights: Array1::from_vec(r.weights).into_pyarray(py).unbind(),
            time_s: r.time,
            time_symbolic_s: r.time_symbolic,
            time_linearize_s: r.time_linearize,
            time_factorize_s: r.time_factorize,
            symbolic_computed: r.symbolic_computed,
            nnz_hessian: r.nnz_hessian,
            nnz_factor: r.nnz_factor,
            history: r.history.iter().map(PyIterationRecord::from).collect(),
        }
    }
}

#[pymethods]
impl PySolveReport {
    fn __repr__(&self) -> String {
        format!(
            "SolveReport(iterations={}, initial_chi2={}, final_chi2={}, termination={:?}, time_s={:.6})",
            self.iterations, self.initial_chi2, self.final_chi2, self.termination, self.time_s
        )
    }
}

pub(super) fn parse_method(method: &str) -> Result<Method, HitlError> {
    Method::parse(method)
}

/// `[(class, kernel)]` pairs such as `("loop", "dcs:1")` into a kernel per factor class.
pub(super) fn parse_robust(pairs: &[(String, String)]) -> Result<RobustKernels, HitlError> {
    let mut kernels = RobustKernels::none();
    for (class, spec) in pairs {
        let class = FactorClass::parse(class)?;
        if kernels.get(class).is_some() {
            return Err(input_err(format!(
                "two robust kernels for the {} edges; give one per class",
                class.name()
            )));
        }
        kernels.set(class, Some(Kernel::parse(spec)?));
    }
    Ok(kernels)
}

/// Groups `(pose, point)` rows by pose (sorted by pose, stable in point order).
#[allow(clippy::type_complexity)]
pub(super) fn group_by_pose(
    poses: numpy::ndarray::ArrayView1<'_, i64>,
    points: numpy::ndarray::ArrayView2<'_, f64>,
    n: usize,
    name: &str,
) -> Result<Vec<(usize, Vec<[f64; 2]>)>, HitlError> {
    if points.ncols() != 2 || points.nrows() != poses.len() || poses.is_empty() {
        return Err(input_err(format!(
            "{name}: need one (x, y) point per pose index, and at least one; got {} poses and points of shape {:?}",
            poses.len(),
            points.shape()
        )));
    }
    let mut rows: Vec<(usize, [f64; 2])> = Vec::with_capacity(poses.len());
    for (k, &i) in poses.iter().enumerate() {
        if i < 0 || i as usize >= n {
            return Err(input_err(format!(
                "{name}: pose index {i} is out of range (0..{n})"
            )));
        }
        rows.push((i as usize, [points[(k, 0)], points[(k, 1)]]));
    }
    rows.sort_by_key(|r| r.0);
    let mut out: Vec<(usize, Vec<[f64; 2]>)> = Vec::new();
    for (i, p) in rows {
        match out.last_mut() {
            Some((j, v)) if *j == i => v.push(p),
            _ => out.push((i, vec![p])),
        }
    }
    Ok(out)
}

pub(super) fn read_segment(
    s: numpy::ndarray::ArrayView2<'_, f64>,
    name: &str,
) -> Result<[[f64; 2]; 2], HitlError> {
    if s.shape() != [2, 2] {
        return Err(input_err(format!(
            "segment {name} must have shape (2, 2), got {:?}",
            s.shape()
        )));
    }
    Ok([[s[(0, 0)], s[(0, 1)]], [s[(1, 0)], s[(1, 1)]]])
}

/// The explicit correction's rigid transform `A = (x, y, theta)` (docs/ALGORITHM.md §4.1) that
/// brings segment `p_b` into the mode's relation with `p_a`; moved poses become `A * pose`.
#[pyfunction]
fn explicit_transform<'py>(
    py: Python<'py>,
    mode: &str,
    p_a: PyReadonlyArray2<'py, f64>,
    p_b: PyReadonlyArray2<'py, f64>,
) -> PyResult<Bound<'py, PyArray1<f64>>> {
    let (a, b) = (p_a.as_array(), p_b.as_array());
    let t = guarded(|| {
        let mode = RelationMode::parse(mode)?;
        explicit_rigid(mode, &read_segment(a, "a")?, &read_segment(b, "b")?)
    })
    .map_err(|e| to_py(py, e))?;
    Ok(Array1::from_vec(t.to_array().to_vec()).into_pyarray(py))
}

/// COP-SLAM back-propagation (docs/ALGORITHM.md §4.2): returns `poses` with `start+1 .. end-1`
/// rewritten so the chain from `poses[start]` meets `poses[end]` (already moved); `original`
/// are the poses before the move; `rot_var[k]`, `trans_var[k]` the variances of edge k -> k+1.
#[pyfunction]
fn backpropagate<'py>(
    py: Python<'py>,
    poses: PyReadonlyArray2<'py, f64>,
    original: PyReadonlyArray2<'py, f64>,
    start: usize,
    end: usize,
    rot_var: PyReadonlyArray1<'py, f64>,
    trans_var: PyReadonlyArray1<'py, f64>,
) -> PyResult<Bound<'py, PyArray2<f64>>> {
    let mut moved = Values::from_poses(read_poses(&poses).map_err(|e| to_py(py, e))?);
    let before = read_poses(&original).map_err(|e| to_py(py, e))?;
    let rv: Vec<f64> = rot_var.as_array().iter().copied().collect();
    let tv: Vec<f64> = trans_var.as_array().iter().copied().collect();
    guarded(|| backpropagate_chain(&mut moved.poses, &before, start, end, &rv, &tv).map(|_| ()))
        .map_err(|e| to_py(py, e))?;
    Ok(poses_out(py, &moved))
}

/// Wraps an angle to (-pi, pi].
#[pyfunction]
fn wrap_angle(a: f64) -> f64 {
    crate::se2::wrap_angle(a)
}

#[pymodule]
fn _core(m: &Bound<'_, PyModule>) -> PyResult<()> {
    m.add_class::<PyGraph>()?;
    m.add_class::<PySolveReport>()?;
    m.add_class::<PyIterationRecord>()?;
    m.add_function(wrap_pyfunction!(wrap_angle, m)?)?;
    m.add_function(wrap_pyfunction!(explicit_transform, m)?)?;
    m.add_function(wrap_pyfunction!(backpropagate, m)?)?;
    engine::register(m)?;
    interpret::register(m)?;
    metric::register(m)?;
    frontend::register(m)?;
    m.add("__version__", env!("CARGO_PKG_VERSION"))?;
    Ok(())
}
