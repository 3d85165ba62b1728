//! `_core.CorrectionEngine`: the map's relative-pose factors held once, joint solves with human
//! corrections on top, re-using recent symbolic analyses (see `correction::engine`).

use numpy::ndarray::{Array1, Array2};
use numpy::{
    IntoPyArray, PyArray1, PyArray2, PyReadonlyArray1, PyReadonlyArray2, PyReadonlyArray3,
};
use pyo3::prelude::*;

use super::{
    group_by_pose, guarded, input_err, line_solve_params, read_poses, read_segment, solved_out,
    to_py, PyGraph, PySolveReport,
};
use crate::correction::{
    interpret, Active, ApplyParams, Chain, ConsistencyMetric, CorrectionEngine, CorrectionSpec,
    Drawing, HumanWeights, InterpretParams, Interpretation, Row, Scans,
};
use crate::error::HitlError;
use crate::factors::RelationMode;
use crate::metric::MetricParams;
use crate::se2::Pose2;
use crate::solver::SolverParams;
use crate::values::Values;

/// An interpretation for Python: `(mode, line_a (2, 2), line_b (2, 2), s_a (K, 2), s_b (K, 2),
/// x_a, x_b, swapped, iterations (a, b), log_likelihood (a, b), notes)`.
type PyInterpretation<'py> = (
    &'static str,
    Bound<'py, PyArray2<f64>>,
    Bound<'py, PyArray2<f64>>,
    Bound<'py, PyArray2<i64>>,
    Bound<'py, PyArray2<i64>>,
    Bound<'py, PyArray1<i64>>,
    Bound<'py, PyArray1<i64>>,
    bool,
    (usize, usize),
    (f64, f64),
    Vec<String>,
);

fn mode_name(mode: RelationMode) -> &'static str {
    match mode {
        RelationMode::Colocation => "colocation",
        RelationMode::Collinear => "collinear",
        RelationMode::Perpendicular => "perpendicular",
        RelationMode::Parallel => "parallel",
    }
}

fn segment_out<'py>(py: Python<'py>, s: [[f64; 2]; 2]) -> Bound<'py, PyArray2<f64>> {
    Array2::from_shape_vec((2, 2), vec![s[0][0], s[0][1], s[1][0], s[1][1]])
        .unwrap_or_else(|_| Array2::zeros((2, 2)))
        .into_pyarray(py)
}

fn rows_out<'py>(py: Python<'py>, rows: &[Row]) -> Bound<'py, PyArray2<i64>> {
    let flat: Vec<i64> = rows.iter().flatten().copied().collect();
    Array2::from_shape_vec((rows.len(), 2), flat)
        .unwrap_or_else(|_| Array2::zeros((rows.len(), 2)))
        .into_pyarray(py)
}

fn interpretation_out<'py>(py: Python<'py>, h: Interpretation) -> PyInterpretation<'py> {
    (
        mode_name(h.mode),
        segment_out(py, h.line_a),
        segment_out(py, h.line_b),
        rows_out(py, &h.s_a),
        rows_out(py, &h.s_b),
        Array1::from_vec(h.x_a).into_pyarray(py),
        Array1::from_vec(h.x_b).into_pyarray(py),
        h.swapped,
        (h.iterations[0], h.iterations[1]),
        (h.log_likelihood[0], h.log_likelihood[1]),
        h.notes,
    )
}

fn read_rows(a: &PyReadonlyArray2<'_, i64>, what: &str) -> Result<Vec<Row>, HitlError> {
    let a = a.as_array();
    if a.ncols() != 2 {
        return Err(input_err(format!(
            "{what} must be (pose, point) rows of shape (K, 2), got {:?}",
            a.shape()
        )));
    }
    Ok(a.rows().into_iter().map(|r| [r[0], r[1]]).collect())
}

fn attr<T>(config: &Bound<'_, PyAny>, name: &str) -> PyResult<T>
where
    T: for<'a, 'py> FromPyObject<'a, 'py>,
    for<'a, 'py> <T as FromPyObject<'a, 'py>>::Error: Into<PyErr>,
{
    config.getattr(name)?.extract::<T>().map_err(Into::into)
}

/// The interpretation constants from a `Config`, with `sigma_h` chosen by the caller.
fn interpret_params(
    config: &Bound<'_, PyAny>,
    sigma_h: f64,
    visit_gap: Option<usize>,
) -> PyResult<InterpretParams> {
    Ok(InterpretParams {
        sigma_h,
        candidate_band: attr(config, "candidate_band")?,
        search_band: attr(config, "search_band")?,
        drawing_sigma: attr(config, "drawing_sigma")?,
        sigma_em: attr(config, "sigma_em")?,
        clutter_weight: attr(config, "clutter_weight")?,
        em_tolerance_m: attr(config, "em_tolerance_m")?,
        em_tolerance_rad: attr(config, "em_tolerance_rad")?,
        em_max_iterations: attr(config, "em_max_iterations")?,
        min_points_per_pose: attr(config, "min_points_per_pose")?,
        visit_gap: match visit_gap {
            Some(g) => g,
            None => attr(config, "visit_gap")?,
        },
    })
}

type PyActive<'py> = (
    String,
    PyReadonlyArray2<'py, i64>,
    PyReadonlyArray2<'py, i64>,
);

fn read_active(active: &[PyActive<'_>]) -> Result<Vec<Active>, HitlError> {
    let mut specs = Vec::with_capacity(active.len());
    for (k, (m, sa, sb)) in active.iter().enumerate() {
        let label = |e: HitlError| input_err(format!("correction {k}: {e}"));
        specs.push(Active {
            mode: RelationMode::parse(m).map_err(label)?,
            s_a: read_rows(sa, "s_a").map_err(label)?,
            s_b: read_rows(sb, "s_b").map_err(label)?,
        });
    }
    Ok(specs)
}

/// A correction's constants from a `Config`, `sigma_h`, the robust kernels and the normal
/// quantile of the consistency guard.
fn apply_params(
    py: Python<'_>,
    config: &Bound<'_, PyAny>,
    sigma_h: f64,
    robust: Option<&[(String, String)]>,
    consistency_z: f64,
) -> PyResult<ApplyParams> {
    // The start is the explicit correction and its back-propagation: a trust region stays in
    // its basin. The watchdog's Gauss-Newton jumps (for starts off by radians) found other,
    // lower-cost basins here that fit the drawings worse (Freiburg 079 in the evaluation: mean
    // angle error 1.75 -> 2.75 deg with it).
    let solver = line_solve_params(
        "lm",
        attr(config, "max_iterations")?,
        attr(config, "relative_tolerance")?,
        attr(config, "absolute_tolerance")?,
        1e-5,
        robust,
        0,
    )
    .map_err(|e| to_py(py, e))?;
    Ok(ApplyParams {
        interpret: interpret_params(config, sigma_h, None)?,
        weights: HumanWeights {
            sigma_f: attr(config, "sigma_f")?,
            k1: attr(config, "k1")?,
            k2: attr(config, "k2")?,
            average_points: attr(config, "average_points")?,
        },
        solver,
        colocation_guard: attr(config, "colocation_guard")?,
        consistency_guard: attr(config, "consistency_guard")?,
        consistency_z,
        consistency_metric: if attr::<bool>(config, "colocation_consistency")? {
            Some(ConsistencyMetric {
                params: MetricParams {
                    surface_cells: attr(config, "metric_surface_cells")?,
                    min_stop: attr(config, "metric_min_stop")?,
                    grazing_deg: attr(config, "metric_grazing_deg")?,
                },
                resolution: attr(config, "grid_resolution")?,
            })
        } else {
            None
        },
        near_tie_reading: attr(config, "near_tie_reading")?,
    })
}

fn drawing(
    a: &PyReadonlyArray2<'_, f64>,
    b: &PyReadonlyArray2<'_, f64>,
    mode: &str,
) -> Result<Drawing, HitlError> {
    Ok(Drawing {
        a: read_segment(a.as_array(), "a")?,
        b: read_segment(b.as_array(), "b")?,
        mode: RelationMode::parse(mode)?,
    })
}

/// A map's scans, held once per map for interpretation: robot-frame points `(P, 2)` and
/// `offsets` `(N + 1,)` (pose i owns rows `offsets[i]..offsets[i + 1]`).
#[pyclass(module = "hitl_slam._core", name = "MapScans", frozen)]
pub struct PyMapScans {
    inner: Scans,
}

#[pymethods]
impl PyMapScans {
    #[new]
    fn new(
        py: Python<'_>,
        points: PyReadonlyArray2<'_, f64>,
        offsets: PyReadonlyArray1<'_, i64>,
    ) -> PyResult<Self> {
        let (p, o) = (points.as_array(), offsets.as_array());
        let read = || {
            if p.ncols() != 2 {
                return Err(input_err(format!(
                    "points must have shape (P, 2), got {:?}",
                    p.shape()
                )));
            }
            Scans::new(p.iter().copied().collect(), o.iter().copied().collect())
        };
        guarded(read)
            .map(|inner| Self { inner })
            .map_err(|e| to_py(py, e))
    }

    #[getter]
    fn num_poses(&self) -> usize {
        self.inner.num_poses()
    }

    /// What the drawing `(a, b, mode)` means on the map shown with `poses` (docs/ALGORITHM.md
    /// §3): see `hitl_slam.interpret.interpret`, which calls this. Raises CorrectionRejected
    /// with what to draw instead.
    #[pyo3(signature = (poses, a, b, mode, config, *, sigma_h, visit_gap = None, nearest_visits = false))]
    #[allow(clippy::too_many_arguments)]
    fn interpret<'py>(
        &self,
        py: Python<'py>,
        poses: PyReadonlyArray2<'py, f64>,
        a: PyReadonlyArray2<'py, f64>,
        b: PyReadonlyArray2<'py, f64>,
        mode: &str,
        config: &Bound<'py, PyAny>,
        sigma_h: f64,
        visit_gap: Option<usize>,
        nearest_visits: bool,
    ) -> PyResult<PyInterpretation<'py>> {
        let params = interpret_params(config, sigma_h, visit_gap)?;
        let read = || Ok((read_poses(&poses)?, drawing(&a, &b, mode)?));
        let (current, drawn) = guarded(read).map_err(|e| to_py(py, e))?;
        let scans = &self.inner;
        let h = py
            .detach(|| guarded(|| interpret(scans, &current, &drawn, &params, nearest_visits)))
            .map_err(|e| to_py(py, e))?;
        Ok(interpretation_out(py, h))
    }
}

/// One correction's answer for Python: the interpretation, poses `(N, 3)`, lines `(2K, 2)`,
/// the explicit transform `(3,)`, the solve's report, and the times (interpretation, total) [s].
type PyApplied<'py> = (
    PyInterpretation<'py>,
    Bound<'py, PyArray2<f64>>,
    Bound<'py, PyArray2<f64>>,
    Bound<'py, PyArray1<f64>>,
    PySolveReport,
    f64,
    f64,
);

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
    /// `chain`: `(rot, trans, steps, turns)` of the map's chain (`pipeline._chain_of`), which
    /// back-propagation needs (`apply`, `explicit_and_backpropagate`).
    #[new]
    #[pyo3(signature = (num_poses, edges, measurements, information, anchor = 0, *, chain = None))]
    #[allow(clippy::type_complexity)]
    fn new(
        py: Python<'_>,
        num_poses: usize,
        edges: PyReadonlyArray2<'_, i64>,
        measurements: PyReadonlyArray2<'_, f64>,
        information: PyReadonlyArray3<'_, f64>,
        anchor: usize,
        chain: Option<(
            PyReadonlyArray1<'_, f64>,
            PyReadonlyArray1<'_, f64>,
            PyReadonlyArray1<'_, i64>,
            PyReadonlyArray1<'_, f64>,
        )>,
    ) -> PyResult<Self> {
        let graph = PyGraph::build(
            py,
            num_poses,
            edges.clone(),
            measurements.clone(),
            information.clone(),
            anchor,
        )?;
        let twin = PyGraph::build(py, num_poses, edges, measurements, information, anchor)?;
        let build = || {
            let mut engine = CorrectionEngine::new(graph)?;
            engine.set_twin(twin)?;
            if let Some((rot, trans, steps, turns)) = &chain {
                let steps = steps
                    .as_array()
                    .iter()
                    .map(|&k| usize::try_from(k).map_err(|_| input_err("a chain step is negative")))
                    .collect::<Result<Vec<_>, _>>()?;
                engine.set_chain(Chain {
                    rot: rot.as_array().to_vec(),
                    trans: trans.as_array().to_vec(),
                    steps,
                    turns: turns.as_array().to_vec(),
                })?;
            }
            Ok(engine)
        };
        guarded(build)
            .map(|inner| Self { inner })
            .map_err(|e| to_py(py, e))
    }

    /// One correction end to end, in one call (docs/ALGORITHM.md §3, §4, §I.3, §I.6): interpret
    /// the drawing `(a, b, mode)` on `scans` shown with `poses`, the explicit correction and
    /// back-propagation, the joint solve with every correction of `active` (`(mode, s_a, s_b)`
    /// rows) plus the new one, and the guards. Returns `(interpretation, poses, lines,
    /// transform, report, time_interpret, time_total)`; raises CorrectionRejected. The GIL is
    /// released throughout.
    #[pyo3(signature = (
        scans, poses, a, b, mode, active, config, *, sigma_h, robust = None, consistency_z = 0.0
    ))]
    #[allow(clippy::too_many_arguments)]
    fn apply<'py>(
        &mut self,
        py: Python<'py>,
        scans: PyRef<'py, PyMapScans>,
        poses: PyReadonlyArray2<'py, f64>,
        a: PyReadonlyArray2<'py, f64>,
        b: PyReadonlyArray2<'py, f64>,
        mode: &str,
        active: Vec<PyActive<'py>>,
        config: &Bound<'py, PyAny>,
        sigma_h: f64,
        robust: Option<Vec<(String, String)>>,
        consistency_z: f64,
    ) -> PyResult<PyApplied<'py>> {
        let params = apply_params(py, config, sigma_h, robust.as_deref(), consistency_z)?;
        let read = || -> Result<_, HitlError> {
            Ok((
                read_active(&active)?,
                read_poses(&poses)?,
                drawing(&a, &b, mode)?,
            ))
        };
        let (specs, current, drawn) = guarded(read).map_err(|e| to_py(py, e))?;
        drop(active);
        let (engine, scans) = (&mut self.inner, &scans.inner);
        let out = py
            .detach(|| guarded(|| engine.apply(scans, &current, &drawn, &specs, &params)))
            .map_err(|e| to_py(py, e))?;
        let values = Values {
            poses: out.poses,
            lines: out.lines,
        };
        let (poses, lines, report) = solved_out(py, &values, out.report);
        Ok((
            interpretation_out(py, out.interpretation),
            poses,
            lines,
            Array1::from_vec(out.transform.to_array().to_vec()).into_pyarray(py),
            report,
            out.time_interpret,
            out.time_total,
        ))
    }

    /// The consistency guard alone (docs/ALGORITHM.md §I.6), for tests: `h` (an interpretation
    /// tuple as `MapScans.interpret` returns) solved to `new_poses`. None when the result is
    /// within the odometry's noise; otherwise the alternative interpretation and its poses, or
    /// CorrectionRejected with the figures.
    #[pyo3(name = "_consistency_guard", signature = (
        scans, poses, a, b, mode, h, new_poses, active, config, *, sigma_h, robust = None,
        consistency_z
    ))]
    #[allow(clippy::too_many_arguments, clippy::type_complexity)]
    fn consistency_guard<'py>(
        &mut self,
        py: Python<'py>,
        scans: PyRef<'py, PyMapScans>,
        poses: PyReadonlyArray2<'py, f64>,
        a: PyReadonlyArray2<'py, f64>,
        b: PyReadonlyArray2<'py, f64>,
        mode: &str,
        h: (
            String,
            PyReadonlyArray2<'py, f64>,
            PyReadonlyArray2<'py, f64>,
            PyReadonlyArray2<'py, i64>,
            PyReadonlyArray2<'py, i64>,
            PyReadonlyArray1<'py, i64>,
            PyReadonlyArray1<'py, i64>,
        ),
        new_poses: PyReadonlyArray2<'py, f64>,
        active: Vec<PyActive<'py>>,
        config: &Bound<'py, PyAny>,
        sigma_h: f64,
        robust: Option<Vec<(String, String)>>,
        consistency_z: f64,
    ) -> PyResult<Option<(PyInterpretation<'py>, Bound<'py, PyArray2<f64>>)>> {
        let params = apply_params(py, config, sigma_h, robust.as_deref(), consistency_z)?;
        let read = || -> Result<_, HitlError> {
            let interpretation = Interpretation {
                mode: RelationMode::parse(&h.0)?,
                line_a: read_segment(h.1.as_array(), "line_a")?,
                line_b: read_segment(h.2.as_array(), "line_b")?,
                s_a: read_rows(&h.3, "s_a")?,
                s_b: read_rows(&h.4, "s_b")?,
                x_a: h.5.as_array().to_vec(),
                x_b: h.6.as_array().to_vec(),
                swapped: false,
                iterations: [0, 0],
                log_likelihood: [0.0, 0.0],
                notes: Vec::new(),
                near_ties: [None, None],
            };
            Ok((
                read_active(&active)?,
                read_poses(&poses)?,
                drawing(&a, &b, mode)?,
                interpretation,
                read_poses(&new_poses)?,
            ))
        };
        let (specs, current, drawn, hh, solved) = guarded(read).map_err(|e| to_py(py, e))?;
        let (engine, scans) = (&mut self.inner, &scans.inner);
        let out = py
            .detach(|| {
                guarded(|| {
                    let before = engine.base_chi2(&current)?;
                    engine.guard_alternative(
                        scans, &current, &drawn, &hh, &solved, before, &specs, &params,
                    )
                })
            })
            .map_err(|e| to_py(py, e))?;
        Ok(out.map(|(alt, alt_solved)| {
            (
                interpretation_out(py, alt),
                super::poses_out(py, &Values::from_poses(alt_solved.poses)),
            )
        }))
    }

    #[allow(clippy::type_complexity)]
    /// docs/ALGORITHM.md §4.1 then §4.2 for an interpretation `(mode, line_a, line_b, x_a,
    /// x_b)`: the rigid move of every pose from `min(x_b)` on, and the chain from `max(x_a)`
    /// made to meet it. Returns `(poses, transform)`.
    #[allow(clippy::too_many_arguments)]
    fn explicit_and_backpropagate<'py>(
        &self,
        py: Python<'py>,
        poses: PyReadonlyArray2<'py, f64>,
        mode: &str,
        line_a: PyReadonlyArray2<'py, f64>,
        line_b: PyReadonlyArray2<'py, f64>,
        x_a: PyReadonlyArray1<'py, i64>,
        x_b: PyReadonlyArray1<'py, i64>,
    ) -> PyResult<(Bound<'py, PyArray2<f64>>, Bound<'py, PyArray1<f64>>)> {
        let engine = &self.inner;
        let run = || {
            let h = Interpretation {
                mode: RelationMode::parse(mode)?,
                line_a: read_segment(line_a.as_array(), "line_a")?,
                line_b: read_segment(line_b.as_array(), "line_b")?,
                s_a: Vec::new(),
                s_b: Vec::new(),
                x_a: x_a.as_array().to_vec(),
                x_b: x_b.as_array().to_vec(),
                swapped: false,
                iterations: [0, 0],
                log_likelihood: [0.0, 0.0],
                notes: Vec::new(),
                near_ties: [None, None],
            };
            engine.explicit_and_backpropagate(&read_poses(&poses)?, &h)
        };
        let (moved, transform): (Vec<Pose2>, Pose2) = guarded(run).map_err(|e| to_py(py, e))?;
        let values = Values::from_poses(moved);
        Ok((
            super::poses_out(py, &values),
            Array1::from_vec(transform.to_array().to_vec()).into_pyarray(py),
        ))
    }

    #[allow(clippy::type_complexity)]
    /// The chain's rotational and translational variance per step at `poses` (a step whose
    /// turn there differs from its edge's measurement is widened by the squared difference).
    fn chain_variances<'py>(
        &self,
        py: Python<'py>,
        poses: PyReadonlyArray2<'py, f64>,
    ) -> PyResult<(Bound<'py, PyArray1<f64>>, Bound<'py, PyArray1<f64>>)> {
        let engine = &self.inner;
        let run = || {
            let current = read_poses(&poses)?;
            if current.len() != engine.num_poses() {
                return Err(input_err(format!(
                    "expected {} poses, got {}",
                    engine.num_poses(),
                    current.len()
                )));
            }
            let chain = engine
                .chain()
                .ok_or_else(|| input_err("the engine was built without the map's chain"))?;
            Ok(chain.variances(&current))
        };
        let (rot, trans) = guarded(run).map_err(|e| to_py(py, e))?;
        Ok((rot.into_pyarray(py), trans.into_pyarray(py)))
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
        max_iterations = 100,
        relative_tolerance = 1e-6, absolute_tolerance = 1e-6,
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
    m.add_class::<PyCorrectionEngine>()?;
    m.add_class::<PyMapScans>()
}
