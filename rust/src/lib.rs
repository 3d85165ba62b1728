//! # hitl-slam core
//!
//! The numerical engine of Human-in-the-Loop SLAM (Nashed and Biswas, AAAI 2018): SE(2) poses,
//! relative-pose and prior factors with analytic Jacobians, and a sparse Levenberg-Marquardt
//! solver on faer whose symbolic Cholesky analysis is computed once per graph structure.
//!
//! The problem, in one formula: over poses `x_i` (and later line parameters),
//!
//! `min sum_(i,j) |U_ij Log(z_ij^-1 x_i^-1 x_j)|^2 (+ human correction terms)`, pose `x_0` fixed.
//!
//! Module map: [`se2`] (pose math), [`geometry`] (lines: TLS fit, distances), [`values`] (variables), [`factors`] (residuals),
//! [`graph`] (the factor graph and its gauge), [`init`] (initial guesses: spanning tree,
//! chordal relaxation), [`solver`] (sparsity pattern, assembly, linear solves, LM/GN/dogleg, marginals),
//! [`correction`] (explicit correction and back-propagation), [`frontend`] (scan matching),
//! `python` (the only place that knows about Python; behind the `python` feature).
//!
//! ```
//! use hitl_slam::{graph::FactorGraph, se2::Pose2, solver::{optimize, SolverParams}, values::Values};
//! let info = [[100.0, 0.0, 0.0], [0.0, 100.0, 0.0], [0.0, 0.0, 400.0]];
//! // A square loop of four unit moves with a loop closure back to the start.
//! let edges = [(0, 1), (1, 2), (2, 3), (3, 0)];
//! let z = [[1.0, 0.0, 1.5707963267948966]; 4];
//! let mut graph = FactorGraph::from_edges(4, &edges, &z, &[info; 4], 0).unwrap();
//! let mut values = Values::from_poses(vec![
//!     Pose2::new(0.0, 0.0, 0.0), Pose2::new(1.1, 0.1, 1.5), Pose2::new(0.9, 1.2, 3.0), Pose2::new(-0.1, 0.9, -1.6),
//! ]);
//! let report = optimize(&mut graph, &mut values, &SolverParams::default()).unwrap();
//! assert!(report.final_chi2 < 1e-12);
//! assert!((values.poses[2].x - 1.0).abs() < 1e-6 && (values.poses[2].y - 1.0).abs() < 1e-6);
//! ```

// Index loops read like the formulas they implement (3x3 blocks, CSC columns).
#![allow(clippy::needless_range_loop)]

pub mod correction;
pub mod error;
pub mod factors;
pub mod frontend;
pub mod geometry;
pub mod graph;
pub mod init;
pub mod interpret;
pub mod metric;
pub mod se2;
pub mod solver;
pub mod values;

#[cfg(feature = "python")]
mod python;

/// The extension's allocator. A correction's solves allocate and free buffers of a few MB each
/// iteration (factor values, workspaces); with glibc's malloc those go to mmap and come back
/// zeroed by page faults, and two solves on two threads then queue on the process's memory map
/// (measured: the colocation guard's two parallel solves slower than one after the other).
/// mimalloc keeps freed pages per thread for re-use.
#[cfg(feature = "python")]
#[global_allocator]
static GLOBAL: mimalloc::MiMalloc = mimalloc::MiMalloc;

pub use error::{HitlError, Result};
