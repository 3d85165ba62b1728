//! Initial guesses for a 2D pose graph, as g2o/TORO and GTSAM compute them before optimizing.
//!
//! - [`InitMethod::Given`]: the caller's poses, unchanged.
//! - [`InitMethod::Tree`]: measurements composed along a spanning tree rooted at the anchor,
//!   preferring odometry edges (`tree`).
//! - [`InitMethod::Chordal`]: chordal relaxation, rotations first and then positions, each a
//!   sparse linear least-squares problem solved by sparse Cholesky (`chordal`, `linear`).
//!
//! Both computed guesses take O(n + m) memory and (for SLAM-like sparse graphs) near-linear time,
//! and keep the anchor's given pose exactly.

mod chordal;
mod linear;
mod tree;

use crate::error::{input, HitlError, Result};
use crate::se2::Pose2;

/// How to compute the initial guess.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum InitMethod {
    /// The given poses, unchanged.
    Given,
    /// Compose measurements along a spanning tree from the anchor (odometry first).
    Tree,
    /// Chordal relaxation: rotations, then positions, by linear least squares.
    Chordal,
}

impl InitMethod {
    /// `"given"`, `"tree"` or `"chordal"` (ASCII case ignored).
    pub fn parse(s: &str) -> Result<Self> {
        for m in [Self::Given, Self::Tree, Self::Chordal] {
            if s.trim().eq_ignore_ascii_case(m.name()) {
                return Ok(m);
            }
        }
        input(format!(
            "unknown initialization method {s:?}; choose one of \"given\", \"tree\" or \"chordal\""
        ))
    }

    pub fn name(self) -> &'static str {
        match self {
            Self::Given => "given",
            Self::Tree => "tree",
            Self::Chordal => "chordal",
        }
    }
}

/// An initial guess for the poses of a pose graph.
///
/// Edges are `(i, j)` pose indices, measurements `z_ij = x_i^-1 x_j`, information 3x3 in
/// `(x, y, theta)` order (symmetric positive definite). The anchor keeps its given pose. Every
/// other pose must be connected to the anchor through the edges (else an Input error names them).
/// `Given` returns `poses` unchanged without looking at the rest; `Tree` ignores the information
/// matrices (but checks their count).
pub fn initialize(
    method: InitMethod,
    poses: &[Pose2],
    edges: &[(usize, usize)],
    measurements: &[Pose2],
    information: &[[[f64; 3]; 3]],
    anchor: usize,
) -> Result<Vec<Pose2>> {
    if method == InitMethod::Given {
        return Ok(poses.to_vec());
    }
    validate(poses, edges, measurements, information, anchor)?;
    match method {
        InitMethod::Given => Ok(poses.to_vec()),
        InitMethod::Tree => tree::tree(poses, edges, measurements, anchor),
        InitMethod::Chordal => chordal::chordal(poses, edges, measurements, information, anchor),
    }
}

/// Shapes, indices and finiteness shared by both computed guesses.
fn validate(
    poses: &[Pose2],
    edges: &[(usize, usize)],
    measurements: &[Pose2],
    information: &[[[f64; 3]; 3]],
    anchor: usize,
) -> Result<()> {
    let n = poses.len();
    if n == 0 {
        return input("the graph has no poses; give at least one vertex");
    }
    if anchor >= n {
        return input(format!(
            "the anchor is pose {anchor}, which does not exist (the graph has {n} poses); pick an anchor in 0..{n}"
        ));
    }
    let a = poses[anchor];
    if !(a.x.is_finite() && a.y.is_finite() && a.theta.is_finite()) {
        return input(format!(
            "the anchor pose {anchor} is {a:?}; give it a finite pose"
        ));
    }
    if edges.len() != measurements.len() || edges.len() != information.len() {
        return input(format!(
            "edges, measurements and information must have the same length (got {}, {} and {})",
            edges.len(),
            measurements.len(),
            information.len()
        ));
    }
    for (k, (&(i, j), z)) in edges.iter().zip(measurements).enumerate() {
        if i >= n || j >= n {
            return input(format!(
                "edge {k} ({i} -> {j}) refers to a pose that does not exist (the graph has {n} poses)"
            ));
        }
        if i == j {
            return input(format!(
                "edge {k} ({i} -> {j}) joins pose {i} to itself; remove it"
            ));
        }
        if !(z.x.is_finite() && z.y.is_finite() && z.theta.is_finite()) {
            return input(format!(
                "edge {k} ({i} -> {j}) has a non-finite measurement {z:?}; use finite numbers"
            ));
        }
    }
    Ok(())
}

/// Disjoint sets over pose indices (union by size, path halving).
struct UnionFind {
    parent: Vec<usize>,
    size: Vec<usize>,
}

impl UnionFind {
    pub fn new(n: usize) -> Self {
        Self {
            parent: (0..n).collect(),
            size: vec![1; n],
        }
    }

    pub fn find(&mut self, mut v: usize) -> usize {
        while self.parent[v] != v {
            let g = self.parent[self.parent[v]];
            self.parent[v] = g;
            v = g;
        }
        v
    }

    /// Merges the sets of `a` and `b`; false when they were already one.
    pub fn union(&mut self, a: usize, b: usize) -> bool {
        let (mut ra, mut rb) = (self.find(a), self.find(b));
        if ra == rb {
            return false;
        }
        if self.size[ra] < self.size[rb] {
            std::mem::swap(&mut ra, &mut rb);
        }
        self.parent[rb] = ra;
        self.size[ra] += self.size[rb];
        true
    }

    /// Ok when every element is in the anchor's set; else an Input error naming up to 5 others.
    pub fn check_reaches_all(&mut self, anchor: usize) -> Result<()> {
        let n = self.parent.len();
        let root = self.find(anchor);
        if self.size[root] == n {
            return Ok(());
        }
        let missing = n - self.size[root];
        let mut named = Vec::with_capacity(5);
        for v in 0..n {
            if named.len() == 5 {
                break;
            }
            if self.find(v) != root {
                named.push(v.to_string());
            }
        }
        let more = if missing > named.len() {
            format!(" (and {} more)", missing - named.len())
        } else {
            String::new()
        };
        Err(HitlError::Input(format!(
            "{missing} pose(s) are not connected to the anchor pose {anchor} by any chain of edges: {}{more}; add edges (odometry or loop closures) that reach them, or remove them from the graph",
            named.join(", ")
        )))
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::se2::wrap_angle;
    use rand::{Rng, SeedableRng};
    use std::f64::consts::{FRAC_PI_2, PI};

    type Graph = (
        Vec<Pose2>,
        Vec<(usize, usize)>,
        Vec<Pose2>,
        Vec<[[f64; 3]; 3]>,
    );

    fn gaussian(rng: &mut impl Rng) -> f64 {
        // Box-Muller.
        let u1: f64 = rng.random_range(f64::EPSILON..1.0);
        let u2: f64 = rng.random();
        (-2.0 * u1.ln()).sqrt() * (2.0 * PI * u2).cos()
    }

    fn max_error(a: &[Pose2], b: &[Pose2]) -> (f64, f64) {
        a.iter().zip(b).fold((0.0f64, 0.0f64), |(t, r), (p, q)| {
            (
                t.max((p.x - q.x).abs()).max((p.y - q.y).abs()),
                r.max(wrap_angle(p.theta - q.theta).abs()),
            )
        })
    }

    /// `sum_k r_k^T Omega_k r_k` with `r = Log(z^-1 x_i^-1 x_j)`.
    fn chi2(poses: &[Pose2], edges: &[(usize, usize)], z: &[Pose2], info: &[[[f64; 3]; 3]]) -> f64 {
        let mut total = 0.0;
        for ((&(i, j), zk), o) in edges.iter().zip(z).zip(info) {
            let r = zk.local(poses[i].between(poses[j]));
            for a in 0..3 {
                for b in 0..3 {
                    total += r[a] * o[a][b] * r[b];
                }
            }
        }
        total
    }

    /// Exact chain of `n` poses with random headings: (truth, edges, measurements, information).
    fn exact_chain(n: usize, seed: u64) -> Graph {
        let mut rng = rand::rngs::StdRng::seed_from_u64(seed);
        let mut truth = Vec::with_capacity(n);
        let mut x = Pose2::new(0.5, -0.2, rng.random_range(-PI..PI));
        for _ in 0..n {
            truth.push(x);
            let step = rng.random_range(0.2..1.5);
            let next_heading = rng.random_range(-PI..PI);
            let p = x.compose(Pose2::new(step, 0.0, 0.0));
            x = Pose2::new(p.x, p.y, next_heading);
        }
        let edges: Vec<(usize, usize)> = (0..n.saturating_sub(1)).map(|i| (i, i + 1)).collect();
        let z = edges
            .iter()
            .map(|&(i, j)| truth[i].between(truth[j]))
            .collect();
        let info = vec![[[100.0, 0.0, 0.0], [0.0, 100.0, 0.0], [0.0, 0.0, 400.0]]; edges.len()];
        (truth, edges, z, info)
    }

    fn perturb(truth: &[Pose2], anchor: usize, seed: u64) -> Vec<Pose2> {
        let mut rng = rand::rngs::StdRng::seed_from_u64(seed ^ 0xabcdef);
        truth
            .iter()
            .enumerate()
            .map(|(v, t)| {
                if v == anchor {
                    *t
                } else {
                    Pose2::new(
                        t.x + rng.random_range(-1.0..1.0),
                        t.y + rng.random_range(-1.0..1.0),
                        t.theta + rng.random_range(-3.0..3.0),
                    )
                }
            })
            .collect()
    }

    /// A Manhattan-like world: a random walk on a unit grid (headings multiples of pi/2, mostly
    /// straight), odometry between consecutive poses and loop closures to the latest earlier
    /// visit of the same cell, all with Gaussian noise (sigma_t, sigma_theta).
    fn manhattan(n: usize, seed: u64, sigma_t: f64, sigma_th: f64) -> Graph {
        let mut rng = rand::rngs::StdRng::seed_from_u64(seed);
        let size = 8i64;
        let (mut cx, mut cy, mut h) = (0i64, 0i64, 0i64);
        let mut truth = Vec::with_capacity(n);
        let mut last_visit = std::collections::HashMap::new();
        let mut edges = Vec::new();
        for v in 0..n {
            truth.push(Pose2::new(cx as f64, cy as f64, h as f64 * FRAC_PI_2));
            if v > 0 {
                edges.push((v - 1, v));
            }
            if let Some(&u) = last_visit.get(&(cx, cy)) {
                if u + 2 < v && rng.random::<f64>() < 0.7 {
                    // Some loop closures point backwards.
                    edges.push(if rng.random::<bool>() { (u, v) } else { (v, u) });
                }
            }
            last_visit.insert((cx, cy), v);
            // Next move: straight mostly, else turn; stay inside the grid.
            let turns = [0i64, 0, 0, 1, -1];
            let mut t = turns[rng.random_range(0..turns.len())];
            for attempt in 0..4 {
                let nh = (h + t).rem_euclid(4);
                let (dx, dy) = [(1, 0), (0, 1), (-1, 0), (0, -1)][nh as usize];
                if (0..size).contains(&(cx + dx)) && (0..size).contains(&(cy + dy)) {
                    h = nh;
                    cx += dx;
                    cy += dy;
                    break;
                }
                t = [1, -1, 2, 1][attempt];
            }
        }
        let z = edges
            .iter()
            .map(|&(i, j)| {
                let e = truth[i].between(truth[j]);
                Pose2::new(
                    e.x + sigma_t * gaussian(&mut rng),
                    e.y + sigma_t * gaussian(&mut rng),
                    e.theta + sigma_th * gaussian(&mut rng),
                )
            })
            .collect();
        let (it, ith) = (1.0 / (sigma_t * sigma_t), 1.0 / (sigma_th * sigma_th));
        let info = vec![[[it, 0.0, 0.0], [0.0, it, 0.0], [0.0, 0.0, ith]]; edges.len()];
        (truth, edges, z, info)
    }

    #[test]
    fn parse_and_name_round_trip() {
        for m in [InitMethod::Given, InitMethod::Tree, InitMethod::Chordal] {
            assert_eq!(InitMethod::parse(m.name()).unwrap(), m);
        }
        assert_eq!(InitMethod::parse("Chordal").unwrap(), InitMethod::Chordal);
        match InitMethod::parse("lago") {
            Err(HitlError::Input(m)) => {
                assert!(
                    m.contains("given") && m.contains("tree") && m.contains("chordal"),
                    "{m}"
                )
            }
            other => panic!("{other:?}"),
        }
    }

    #[test]
    fn exact_chain_is_reproduced_by_tree_and_chordal() {
        let (truth, edges, z, info) = exact_chain(2000, 1);
        let given = perturb(&truth, 0, 1);
        for method in [InitMethod::Tree, InitMethod::Chordal] {
            let got = initialize(method, &given, &edges, &z, &info, 0).unwrap();
            let (et, er) = max_error(&got, &truth);
            eprintln!("2000-pose exact chain, {method:?}: max error {et:.1e} m, {er:.1e} rad");
            assert!(et < 1e-9 && er < 1e-9, "{method:?}: {et:e} m, {er:e} rad");
            assert_eq!(got[0], given[0]);
        }
        let same = initialize(InitMethod::Given, &given, &edges, &z, &info, 0).unwrap();
        assert_eq!(same, given);
    }

    #[test]
    fn anchor_in_the_middle_with_reversed_edges_keeps_its_pose() {
        let (truth, edges, z, info) = exact_chain(300, 2);
        // Reverse every third edge (j < i) and invert its measurement.
        let (edges, z): (Vec<_>, Vec<_>) = edges
            .iter()
            .zip(&z)
            .enumerate()
            .map(|(k, (&(i, j), zk))| {
                if k % 3 == 0 {
                    ((j, i), zk.inverse())
                } else {
                    ((i, j), *zk)
                }
            })
            .unzip();
        let anchor = 137;
        let given = perturb(&truth, anchor, 2);
        for method in [InitMethod::Tree, InitMethod::Chordal] {
            let got = initialize(method, &given, &edges, &z, &info, anchor).unwrap();
            assert_eq!(got[anchor], given[anchor], "{method:?}");
            let (et, er) = max_error(&got, &truth);
            assert!(et < 1e-9 && er < 1e-9, "{method:?}: {et:e} m, {er:e} rad");
        }
        // An anchor whose given pose differs from the truth: the result is the truth moved
        // rigidly so that the anchor sits exactly where it was given.
        let mut moved = given.clone();
        moved[anchor] = Pose2::new(-3.0, 7.0, 2.5);
        let g = moved[anchor].compose(truth[anchor].inverse());
        for method in [InitMethod::Tree, InitMethod::Chordal] {
            let got = initialize(method, &moved, &edges, &z, &info, anchor).unwrap();
            assert_eq!(got[anchor], moved[anchor], "{method:?}");
            let expect: Vec<Pose2> = truth.iter().map(|t| g.compose(*t)).collect();
            let (et, er) = max_error(&got, &expect);
            assert!(et < 1e-9 && er < 1e-9, "{method:?}: {et:e} m, {er:e} rad");
        }
    }

    #[test]
    fn chordal_beats_tree_on_a_noisy_manhattan_grid() {
        let mut chordal_wins = 0;
        for seed in [11u64, 12, 13] {
            let (truth, edges, z, info) = manhattan(800, seed, 0.05, 0.02);
            let closures = edges.iter().filter(|(i, j)| i.abs_diff(*j) != 1).count();
            assert!(closures > 100, "seed {seed}: only {closures} loop closures");
            let given = perturb(&truth, 0, seed);
            let tree = initialize(InitMethod::Tree, &given, &edges, &z, &info, 0).unwrap();
            let chordal = initialize(InitMethod::Chordal, &given, &edges, &z, &info, 0).unwrap();
            let (c_tree, c_chordal, c_truth) = (
                chi2(&tree, &edges, &z, &info),
                chi2(&chordal, &edges, &z, &info),
                chi2(&truth, &edges, &z, &info),
            );
            let (tt, tr) = max_error(&tree, &truth);
            let (ct, cr) = max_error(&chordal, &truth);
            eprintln!(
                "seed {seed}: {} edges ({closures} closures); chi2 truth {c_truth:.0}, tree {c_tree:.0}, chordal {c_chordal:.0}; max error tree {tt:.3} m {tr:.3} rad, chordal {ct:.3} m {cr:.3} rad",
                edges.len()
            );
            for p in tree.iter().chain(&chordal) {
                assert!(p.x.is_finite() && p.y.is_finite() && p.theta.is_finite());
            }
            assert!(cr < 0.2, "seed {seed}: chordal rotation error {cr}");
            assert!(ct < 1.0, "seed {seed}: chordal position error {ct}");
            assert!(
                c_chordal < 20.0 * c_truth,
                "seed {seed}: chordal chi2 {c_chordal} vs truth {c_truth}"
            );
            if c_chordal < c_tree {
                chordal_wins += 1;
            }
        }
        assert!(
            chordal_wins >= 2,
            "chordal had the lower chi2 in {chordal_wins} of 3 seeds"
        );
    }

    #[test]
    fn disconnected_poses_are_an_input_error() {
        let (truth, mut edges, mut z, mut info) = exact_chain(20, 3);
        // Cut the chain after pose 11: poses 12..19 lose their link to the anchor.
        edges.remove(11);
        z.remove(11);
        info.remove(11);
        for method in [InitMethod::Tree, InitMethod::Chordal] {
            match initialize(method, &truth, &edges, &z, &info, 0) {
                Err(HitlError::Input(m)) => {
                    assert!(m.contains("12, 13, 14, 15, 16 (and 3 more)"), "{m}");
                    assert!(m.contains("anchor pose 0"), "{m}");
                }
                other => panic!("{method:?}: {other:?}"),
            }
        }
        // An isolated vertex with no edges at all, anchor elsewhere.
        let poses = vec![Pose2::IDENTITY; 3];
        for method in [InitMethod::Tree, InitMethod::Chordal] {
            let r = initialize(
                method,
                &poses,
                &[(0, 1)],
                &[Pose2::new(1.0, 0.0, 0.0)],
                &info[..1],
                1,
            );
            match r {
                Err(HitlError::Input(m)) => {
                    assert!(m.contains("1 pose(s)") && m.contains(": 2;"), "{m}")
                }
                other => panic!("{method:?}: {other:?}"),
            }
        }
    }

    #[test]
    fn malformed_input_is_an_input_error() {
        let poses = vec![Pose2::IDENTITY; 3];
        let z = [Pose2::new(1.0, 0.0, 0.0); 2];
        let info = [[[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]]; 2];
        let nan = Pose2 {
            x: f64::NAN,
            y: 0.0,
            theta: 0.0,
        };
        type Case = (Vec<(usize, usize)>, Vec<Pose2>, usize, &'static str);
        let cases: Vec<Case> = vec![
            (vec![(0, 1), (1, 3)], z.to_vec(), 0, "does not exist"),
            (vec![(0, 1), (1, 1)], z.to_vec(), 0, "itself"),
            (vec![(0, 1), (1, 2)], z.to_vec(), 3, "anchor"),
            (vec![(0, 1), (1, 2)], vec![z[0], nan], 0, "non-finite"),
            (vec![(0, 1)], z.to_vec(), 0, "same length"),
        ];
        for (edges, zs, anchor, what) in cases {
            for method in [InitMethod::Tree, InitMethod::Chordal] {
                match initialize(method, &poses, &edges, &zs, &info, anchor) {
                    Err(HitlError::Input(m)) => assert!(m.contains(what), "{what}: {m}"),
                    other => panic!("{what}: {other:?}"),
                }
            }
        }
        let bad_info = [info[0], [[1.0, 2.0, 0.0], [2.0, 1.0, 0.0], [0.0, 0.0, 1.0]]];
        let r = initialize(
            InitMethod::Chordal,
            &poses,
            &[(0, 1), (1, 2)],
            &z,
            &bad_info,
            0,
        );
        assert!(matches!(r, Err(HitlError::Input(m)) if m.contains("edge 1")));
        assert!(initialize(InitMethod::Tree, &[], &[], &[], &[], 0).is_err());
    }

    #[test]
    fn single_vertex_graph_returns_its_pose() {
        let p = [Pose2::new(1.0, 2.0, 3.0)];
        for method in [InitMethod::Given, InitMethod::Tree, InitMethod::Chordal] {
            assert_eq!(
                initialize(method, &p, &[], &[], &[], 0).unwrap(),
                p.to_vec()
            );
        }
    }

    #[test]
    fn duplicate_edges_and_two_poses() {
        // Two poses, two parallel edges with different measurements: chordal averages them by
        // information weight; the tree takes the first.
        let poses = [Pose2::new(0.0, 0.0, 0.0), Pose2::IDENTITY];
        let edges = [(0, 1), (1, 0)];
        let z = [
            Pose2::new(1.0, 0.0, 0.1),
            Pose2::new(1.2, 0.0, 0.1).inverse(),
        ];
        let info = [[[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]]; 2];
        let tree = initialize(InitMethod::Tree, &poses, &edges, &z, &info, 0).unwrap();
        assert_eq!(tree[1], poses[0].compose(z[0]));
        let chordal = initialize(InitMethod::Chordal, &poses, &edges, &z, &info, 0).unwrap();
        assert!((chordal[1].theta - 0.1).abs() < 1e-12, "{:?}", chordal[1]);
        assert!((chordal[1].x - 1.1).abs() < 1e-12, "{:?}", chordal[1]);
        assert!(chordal[1].y.abs() < 1e-12, "{:?}", chordal[1]);
    }

    /// Timing of a 1,000,000-pose chain (run with
    /// `cargo test --release --lib init -- --ignored --nocapture`).
    #[test]
    #[ignore]
    fn million_pose_chain_timing() {
        let n = 1_000_000;
        let (truth, edges, z, info) = exact_chain(n, 5);
        let given = vec![truth[0]; n];
        for method in [InitMethod::Tree, InitMethod::Chordal] {
            let start = std::time::Instant::now();
            let got = initialize(method, &given, &edges, &z, &info, 0).unwrap();
            let secs = start.elapsed().as_secs_f64();
            let (et, er) = max_error(&got, &truth);
            eprintln!(
                "{n}-pose chain, {method:?}: {secs:.3} s; max error {et:.2e} m, {er:.2e} rad"
            );
            assert!(et < 1e-4 && er < 1e-6);
        }
        if let Ok(status) = std::fs::read_to_string("/proc/self/status") {
            for line in status
                .lines()
                .filter(|l| l.starts_with("VmHWM") || l.starts_with("VmRSS"))
            {
                eprintln!("{line}");
            }
        }
    }
}
