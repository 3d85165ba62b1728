//! Python binding of the front end (`crate::frontend`): scan-to-scan matching along a chain,
//! and the whole front end over a log (`run_slam`), with the GIL released.

use numpy::ndarray::{Array1, Array2, Array3};
use numpy::{IntoPyArray, PyArray1, PyArray2, PyArray3, PyReadonlyArray1, PyReadonlyArray2};
use pyo3::prelude::*;
use pyo3::types::PyDict;

use super::{flat_rows, guarded, input_err, read_poses, to_py};
use crate::frontend::slam::{run, LoopStatus, SlamParams};
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

/// Runs the scan-matching front end (`crate::frontend::slam`) over a log: robot-frame `points`
/// `(P, 2)` by scan (`offsets` `(N + 1,)`) and the odometry `(N, 3)`. `progress(done)` (a
/// callable, optional) is called every 500 scans. The GIL is released except for those calls.
/// Returns a dict: `poses` `(N, 3)`, `steps` `(N,)` uint8 (0 ICP from the prediction, 1 the
/// correlative search, 2 ambiguous, 3 failed: the odometry kept), `keyframes`
/// `(K,)` scan indices, `step_information` `(N, 3, 3)`, loop closures `loop_pairs` `(L, 2)`
/// scan indices with `loop_measurements` `(L, 3)`, `loop_information` `(L, 3, 3)`,
/// `loop_scores`, `loop_weights` (the final robust weight; 0 when set aside) and
/// `loop_set_aside` (set aside by the group test),
/// `doubtful` `(D, 2)` scan ranges (inclusive) with `doubt` `(D,)` uint8 (0 unmatched, 1
/// contradicted by the final solve), and `submaps`.
#[pyfunction]
#[pyo3(signature = (
    points, offsets, odometry, *, progress = None, keyframe_distance = 0.2,
    keyframe_angle_deg = 10.0, max_range = 20.0, loop_min_score = 0.55, dcs = 10.0
))]
#[allow(clippy::too_many_arguments)]
fn run_slam<'py>(
    py: Python<'py>,
    points: PyReadonlyArray2<'py, f64>,
    offsets: PyReadonlyArray1<'py, i64>,
    odometry: PyReadonlyArray2<'py, f64>,
    progress: Option<Py<PyAny>>,
    keyframe_distance: f64,
    keyframe_angle_deg: f64,
    max_range: f64,
    loop_min_score: f64,
    dcs: f64,
) -> PyResult<Bound<'py, PyDict>> {
    let params = SlamParams {
        keyframe_distance,
        keyframe_angle: keyframe_angle_deg.to_radians(),
        max_range,
        loop_min_score,
        dcs,
        ..SlamParams::default()
    };
    let odometry = read_poses(&odometry).map_err(|e| to_py(py, e))?;
    let (points, offsets) = (points.as_array(), offsets.as_array());
    let read = || {
        let pts = flat_rows(points, 2, "points")?;
        let off = offsets
            .iter()
            .map(|&o| usize::try_from(o).map_err(|_| input_err("offsets must be >= 0")))
            .collect::<Result<Vec<usize>, _>>()?;
        if off.first() != Some(&0)
            || off.last() != Some(&(pts.len() / 2))
            || off.windows(2).any(|w| w[0] > w[1])
        {
            return Err(input_err(
                "offsets must rise from 0 to the number of points",
            ));
        }
        Ok(off
            .windows(2)
            .map(|w| {
                pts[2 * w[0]..2 * w[1]]
                    .chunks_exact(2)
                    .map(|c| [c[0], c[1]])
                    .collect::<Vec<_>>()
            })
            .collect::<Vec<_>>())
    };
    let scans = guarded(read).map_err(|e| to_py(py, e))?;
    let out = py
        .detach(|| {
            guarded(|| {
                let mut report = |done: usize| {
                    if let Some(cb) = &progress {
                        // A failing callback only loses the progress display.
                        Python::attach(|py| {
                            let _ = cb.call1(py, (done,));
                        });
                    }
                };
                run(&scans, &odometry, &params, &mut report)
            })
        })
        .map_err(|e| to_py(py, e))?;
    let n = out.poses.len();
    let l = out.loops.len();
    let d = out.doubtful.len();
    let poses = Array2::from_shape_fn((n, 3), |(i, j)| out.poses[i].to_array()[j]);
    let steps = Array1::from_iter(out.steps.iter().map(|&s| s as u8));
    let keyframes = Array1::from_iter(out.keyframes.iter().map(|&k| k as i64));
    let step = Array3::from_shape_fn((n, 3, 3), |(i, a, b)| out.step_information[i][a][b]);
    let pairs = Array2::from_shape_fn((l, 2), |(i, j)| {
        let c = &out.loops[i];
        out.keyframes[if j == 0 { c.from } else { c.to }] as i64
    });
    let z = Array2::from_shape_fn((l, 3), |(i, j)| out.loops[i].measurement.to_array()[j]);
    let info = Array3::from_shape_fn((l, 3, 3), |(i, a, b)| out.loops[i].information[a][b]);
    let scores = Array1::from_iter(out.loops.iter().map(|c| c.score));
    let weights = Array1::from_iter(out.loops.iter().map(|c| c.weight));
    let set_aside = Array1::from_iter(
        out.loops
            .iter()
            .map(|c| c.status == LoopStatus::Inconsistent),
    );
    let doubtful = Array2::from_shape_fn((d, 2), |(i, j)| {
        let s = &out.doubtful[i];
        (if j == 0 { s.first } else { s.last }) as i64
    });
    let doubt = Array1::from_iter(out.doubtful.iter().map(|s| s.why as u8));
    let dict = PyDict::new(py);
    dict.set_item("poses", poses.into_pyarray(py))?;
    dict.set_item("steps", steps.into_pyarray(py))?;
    dict.set_item(
        "overlap",
        Array1::from_vec(out.overlap.clone()).into_pyarray(py),
    )?;
    dict.set_item("keyframes", keyframes.into_pyarray(py))?;
    dict.set_item("step_information", step.into_pyarray(py))?;
    dict.set_item("loop_pairs", pairs.into_pyarray(py))?;
    dict.set_item("loop_measurements", z.into_pyarray(py))?;
    dict.set_item("loop_information", info.into_pyarray(py))?;
    dict.set_item("loop_scores", scores.into_pyarray(py))?;
    dict.set_item("loop_weights", weights.into_pyarray(py))?;
    dict.set_item("loop_set_aside", set_aside.into_pyarray(py))?;
    dict.set_item("doubtful", doubtful.into_pyarray(py))?;
    dict.set_item("doubt", doubt.into_pyarray(py))?;
    dict.set_item("submaps", out.submaps)?;
    Ok(dict)
}

pub(super) fn register(m: &Bound<'_, PyModule>) -> PyResult<()> {
    m.add_function(wrap_pyfunction!(match_consecutive, m)?)?;
    m.add_function(wrap_pyfunction!(run_slam, m)?)?;
    Ok(())
}
