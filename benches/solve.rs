//! Criterion benchmarks of full solves on the public pose graphs (M3500, City10000) from their
//! own initial guesses, and of one linearize + factorize step. Needs ../shared/datasets; a graph
//! that is missing is skipped with a message. Run: `cargo bench`.

use std::path::{Path, PathBuf};

use criterion::{criterion_group, criterion_main, Criterion};
use hitl_slam::graph::FactorGraph;
use hitl_slam::se2::Pose2;
use hitl_slam::solver::{optimize, SolverParams};
use hitl_slam::values::Values;

/// A minimal g2o (VERTEX_SE2 / EDGE_SE2) reader for the benchmark only; the product's readers,
/// with full error reporting, are in the Python package.
pub fn load_g2o(path: &Path) -> Option<(FactorGraph, Values)> {
    let text = std::fs::read_to_string(path).ok()?;
    let mut ids = std::collections::HashMap::new();
    let mut poses = Vec::new();
    let (mut edges, mut zs, mut infos) = (Vec::new(), Vec::new(), Vec::new());
    for line in text.lines() {
        let f: Vec<&str> = line.split_whitespace().collect();
        let num = |k: usize| f[k].parse::<f64>().ok();
        match f.first() {
            Some(&"VERTEX_SE2") => {
                ids.insert(f[1].to_string(), poses.len());
                poses.push(Pose2::new(num(2)?, num(3)?, num(4)?));
            }
            Some(&"EDGE_SE2") => {
                edges.push((*ids.get(f[1])?, *ids.get(f[2])?));
                zs.push([num(3)?, num(4)?, num(5)?]);
                let (a, b, c, d, e, g) = (num(6)?, num(7)?, num(8)?, num(9)?, num(10)?, num(11)?);
                infos.push([[a, b, c], [b, d, e], [c, e, g]]);
            }
            _ => {}
        }
    }
    let graph = FactorGraph::from_edges(poses.len(), &edges, &zs, &infos, 0).ok()?;
    Some((graph, Values::from_poses(poses)))
}

fn dataset(name: &str) -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR"))
        .join("../shared/datasets/pose_graphs")
        .join(name)
}

fn bench_solves(c: &mut Criterion) {
    let mut group = c.benchmark_group("solve");
    group.sample_size(10);
    for name in ["M3500_carlone.g2o", "city10000.g2o"] {
        let Some((mut graph, initial)) = load_g2o(&dataset(name)) else {
            eprintln!("skipping {name}: ../shared/datasets/pose_graphs/{name} not found");
            continue;
        };
        let params = SolverParams::default();
        group.bench_function(format!("lm_from_initial_guess/{name}"), |b| {
            b.iter(|| {
                let mut v = initial.clone();
                optimize(&mut graph, &mut v, &params)
                    .map(|r| r.final_chi2)
                    .unwrap_or(f64::NAN)
            })
        });
        let one = SolverParams {
            max_iterations: 1,
            ..SolverParams::default()
        };
        group.bench_function(format!("one_iteration/{name}"), |b| {
            b.iter(|| {
                let mut v = initial.clone();
                optimize(&mut graph, &mut v, &one)
                    .map(|r| r.final_chi2)
                    .unwrap_or(f64::NAN)
            })
        });
    }
    group.finish();
}

criterion_group!(benches, bench_solves);
criterion_main!(benches);
