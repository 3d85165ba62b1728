//! `_core.CorrectionEngine`: the map's relative-pose factors held once, joint solves with human
//! corrections on top, re-using recent symbolic analyses (see `correction::engine`).

use numpy::{PyArray2, PyReadonlyArray1, PyReadonlyArray2, PyReadonlyArray3};
use pyo3::prelude::*;

use super::{
    group_by_pose, guarded, input_err, line_solve_params, read_poses, solved_out, to_py, PyGraph,
    PySolveReport,
};
use crate::correction::{CorrectionEngine, CorrectionSpec, HumanWeights};
use crate::error::HitlError;
use crate::factors::RelationMode;
use crate::solver::SolverParams;

/// One correction as Python passes it: mode, then per segment the observing pose of each
/// robot-frame point and the points.
type PyCorrection<'py> = (
    String,
    PyReadonlyArray1<'py, i64>,
    PyReadonlyArray2<'py, f64>,
    PyReadonlyArray1<'py, i64>,
    PyReadonlyArray2<'py, f64>,
);

/// The map's own relative-pose factors, held once per map, and the joint solve of poses and
/// the lines of any list of human corrections on top of them (docs/ALGORITHM.md §4.3).
#[pyclass(module = "hitl_slam._core", name = "CorrectionEngine")]
pub struct PyCorrectionEngine {
    inner: CorrectionEngine,
}

#[pymethods]
impl PyCorrectionEngine {
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
        let graph = PyGraph::build(py, num_poses, edges, measurements, information, anchor)?;
        guarded(|| CorrectionEngine::new(graph))
            .map(|inner| Self { inner })
            .map_err(|e| to_py(py, e))
    }

    /// Number of poses.
    #[getter]
    fn num_poses(&self) -> usize {
        self.inner.num_poses()
    }

    /// How many symbolic analyses the engine has computed (structures it had not kept).
    #[getter]
    fn analyses(&self) -> usize {
        self.inner.analyses()
    }

    /// Forgets the kept symbolic analyses (memory; or to time a structure never seen).
    fn clear_cache(&mut self) {
        self.inner.clear_cache();
    }

    /// chi2 of the map's relative-pose factors alone (the robot's measurements) at `poses`.
    fn base_chi2(&self, py: Python<'_>, poses: PyReadonlyArray2<'_, f64>) -> PyResult<f64> {
        let engine = &self.inner;
        guarded(|| engine.base_chi2(&read_poses(&poses)?)).map_err(|e| to_py(py, e))
    }

    /// Solves poses and the lines of `corrections` jointly from `poses`. Each correction is
    /// `(mode, a_poses, a_points, b_poses, b_points)`: `*_poses[k]` observed robot-frame point
    /// `*_points[k]`. Lines start at the TLS fit of their observations at `poses`. Returns
    /// `(poses, lines (2K, 2) rows (phi, rho), report)`. The GIL is released while solving.
    #[pyo3(signature = (
        poses, corrections, *, sigma_f, k1, k2, average_points = false, method = "lm",
        max_iterations = 100, relative_tolerance = 1e-6, absolute_tolerance = 1e-6,
        lambda_initial = 1e-5, robust = None, watchdog_steps = 3
    ))]
    #[allow(clippy::too_many_arguments, clippy::type_complexity)]
    fn solve<'py>(
        &mut self,
        py: Python<'py>,
        poses: PyReadonlyArray2<'py, f64>,
        corrections: Vec<PyCorrection<'py>>,
        sigma_f: f64,
        k1: f64,
        k2: f64,
        average_points: bool,
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
        let n = self.inner.num_poses();
        let read = || -> Result<(SolverParams, Vec<CorrectionSpec>), HitlError> {
            let params = line_solve_params(
                method,
                max_iterations,
                relative_tolerance,
                absolute_tolerance,
                lambda_initial,
                robust.as_deref(),
                watchdog_steps,
            )?;
            let mut specs = Vec::with_capacity(corrections.len());
            for (k, (mode, ap, aq, bp, bq)) in corrections.iter().enumerate() {
                let label = |e: HitlError| input_err(format!("correction {k}: {e}"));
                specs.push(CorrectionSpec {
                    mode: RelationMode::parse(mode).map_err(label)?,
                    a: group_by_pose(ap.as_array(), aq.as_array(), n, "a").map_err(label)?,
                    b: group_by_pose(bp.as_array(), bq.as_array(), n, "b").map_err(label)?,
                });
            }
            Ok((params, specs))
        };
        let (params, specs) = guarded(read).map_err(|e| to_py(py, e))?;
        drop(corrections);
        let start = read_poses(&poses).map_err(|e| to_py(py, e))?;
        drop(poses);
        let weights = HumanWeights {
            sigma_f,
            k1,
            k2,
            average_points,
        };
        let engine = &mut self.inner;
        let (values, report) = py
            .detach(|| guarded(|| engine.solve(start, &specs, &weights, &params)))
            .map_err(|e| to_py(py, e))?;
        Ok(solved_out(py, &values, report))
    }

    fn __repr__(&self) -> String {
        format!(
            "CorrectionEngine(num_poses={}, analyses={})",
            self.inner.num_poses(),
            self.inner.analyses()
        )
    }
}

pub(super) fn register(m: &Bound<'_, PyModule>) -> PyResult<()> {
    m.add_class::<PyCorrectionEngine>()
}
