//! Test problems shared by the tests of the pattern, the assembly, the linear solves and the
//! natural-order export: a ring with chords, a corrected corridor whose relations are wide (or
//! the same factors kept narrow), and the full H as a dense matrix.

use super::pattern::SparsityPattern;
use crate::factors::{
    BetweenFactor, CentroidShare, Factor, PointsToLineFactor, RelationFactor, RelationMode,
};
use crate::graph::FactorGraph;
use crate::se2::Pose2;
use crate::values::{Key, Line2, Values};
use std::f64::consts::FRAC_PI_2;

/// A ring with chords: enough fill-in for a supernodal factorization.
pub(super) fn ring(n: usize) -> (FactorGraph, Values) {
    let mut edges = Vec::new();
    for i in 0..n {
        edges.push((i, (i + 1) % n));
        edges.push((i, (i + 7) % n));
        edges.push((i, (i * 13 + 5) % n));
    }
    edges.retain(|&(a, b)| a != b);
    let info = [[50.0, 2.0, 1.0], [2.0, 40.0, -1.0], [1.0, -1.0, 300.0]];
    let zs: Vec<[f64; 3]> = edges
        .iter()
        .map(|&(a, b)| [0.1 * (b as f64 - a as f64), 0.05 * a as f64 % 1.0, 0.3])
        .collect();
    let g = FactorGraph::from_edges(n, &edges, &zs, &vec![info; edges.len()], 0).unwrap();
    let poses = (0..n)
        .map(|i| Pose2::new(i as f64 * 0.3, (i as f64).sin(), 0.1 * i as f64))
        .collect();
    (g, Values::from_poses(poses))
}

/// The same factor, but never wide: the reference the Woodbury path must reproduce.
#[derive(Debug)]
pub(super) struct Narrow(RelationFactor);

impl Factor for Narrow {
    fn keys(&self) -> &[Key] {
        self.0.keys()
    }
    fn is_wide(&self) -> bool {
        false
    }
    fn residual_dim(&self) -> usize {
        self.0.residual_dim()
    }
    fn residual(&self, values: &Values, r: &mut [f64]) {
        self.0.residual(values, r)
    }
    fn linearize(&self, values: &Values, r: &mut [f64], jacobians: &mut [f64]) {
        self.0.linearize(values, r, jacobians)
    }
}

#[derive(Clone, Copy, PartialEq)]
pub(super) enum Relations {
    None,
    Wide,
    Narrow,
}

/// A corridor of `n` poses seen twice: poses 1..=6 and the last 6 observe the wall y = 2
/// (a colocation), poses 7..=10 and 40..=43 the wall x = 30 (a collinear), each through
/// R_a / R_b factors and one relation over all those poses (12 and 10 keys: wide). The
/// estimate is perturbed, so every factor has a residual. With `lonely`, the colocation
/// also lists pose `n`, which no other factor touches.
pub(super) fn corrected(n: usize, relations: Relations, lonely: bool) -> (FactorGraph, Values) {
    let total = if lonely { n + 1 } else { n };
    let mut g = FactorGraph::new(total, Some(0)).unwrap();
    let info = [[100.0, 0.0, 0.0], [0.0, 100.0, 0.0], [0.0, 0.0, 1000.0]];
    let truth: Vec<Pose2> = (0..total)
        .map(|i| Pose2::new(0.5 * i as f64, 0.0, 0.0))
        .collect();
    for i in 0..n - 1 {
        let z = truth[i].between(truth[i + 1]);
        g.add_between(BetweenFactor::new(i, i + 1, z, &info).unwrap())
            .unwrap();
    }
    let walls = [
        (
            Line2 {
                phi: FRAC_PI_2,
                rho: 2.0,
            },
            RelationMode::Colocation,
        ),
        (
            Line2 {
                phi: 0.0,
                rho: 30.0,
            },
            RelationMode::Collinear,
        ),
    ];
    let mut groups = vec![
        ((1..=6).collect::<Vec<_>>(), (n - 6..n).collect::<Vec<_>>()),
        ((7..=10).collect(), (40..=43).collect()),
    ];
    if lonely {
        groups[0].1.push(n);
    }
    let mut lines = Vec::new();
    for ((wall, mode), (xa, xb)) in walls.iter().zip(&groups) {
        let la = g.add_line();
        let lb = g.add_line();
        lines.push(*wall);
        lines.push(Line2 {
            phi: wall.phi + 0.02,
            rho: wall.rho + 0.1,
        });
        let mut shares = Vec::new();
        for (set, line, is_a) in [(xa, la, true), (xb, lb, false)] {
            for &i in set {
                // Points on the wall, in pose i's frame (true pose: no rotation).
                let pts: Vec<[f64; 2]> = (0..5)
                    .map(|k| {
                        let s = k as f64 - 2.0;
                        let (wx, wy) = if wall.phi == 0.0 {
                            (wall.rho, s)
                        } else {
                            (truth[i].x + s, wall.rho)
                        };
                        [wx - truth[i].x, wy - truth[i].y]
                    })
                    .collect();
                let sum = pts
                    .iter()
                    .fold([0.0, 0.0], |a, p| [a[0] + p[0], a[1] + p[1]]);
                let share = CentroidShare { count: 5.0, sum };
                shares.push(if is_a {
                    (i, share, CentroidShare::default())
                } else {
                    (i, CentroidShare::default(), share)
                });
                if i < n {
                    let f = PointsToLineFactor::new(i, line, pts, 1.0 / 0.03).unwrap();
                    g.add_factor(Box::new(f)).unwrap();
                }
            }
        }
        let f = RelationFactor::new(*mode, la, lb, shares, 1e6, 1e7).unwrap();
        match relations {
            Relations::None => {}
            Relations::Wide => g.add_factor(Box::new(f)).unwrap(),
            Relations::Narrow => g.add_factor(Box::new(Narrow(f))).unwrap(),
        }
    }
    let poses = truth
        .iter()
        .enumerate()
        .map(|(i, t)| {
            let drift = 0.01 * i as f64;
            Pose2::new(
                t.x + drift,
                t.y + 0.3 * drift,
                t.theta + 0.1 * drift + 0.01 * (i as f64).sin(),
            )
        })
        .collect();
    (g, Values { poses, lines })
}

/// The full H (`H_s + U U^T`) as a dense symmetric matrix in solver order.
pub(super) fn dense_hessian(p: &SparsityPattern) -> nalgebra::DMatrix<f64> {
    let mut h = nalgebra::DMatrix::zeros(p.n, p.n);
    for c in 0..p.n {
        for k in p.col_ptr[c]..p.col_ptr[c + 1] {
            h[(p.row_idx[k], c)] = p.h[k];
            h[(c, p.row_idx[k])] = p.h[k];
        }
    }
    for (ix, v) in p.wide.rows() {
        for (&i, &ui) in ix.iter().zip(v) {
            for (&j, &uj) in ix.iter().zip(v) {
                h[(i, j)] += ui * uj;
            }
        }
    }
    h
}
