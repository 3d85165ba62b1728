//! The correction engine: the map's own relative-pose factors held once, with the human
//! corrections of a session solved jointly on top of them (docs/ALGORITHM.md §4.3), re-using the
//! symbolic analysis of every structure it has solved recently.
//!
//! A session applies, undoes and redoes corrections; each step solves "the base graph plus the
//! active corrections". Building a fresh graph per step (as the first pipeline did) redoes the
//! block adjacency, the ordering and faer's symbolic Cholesky every time, although undo/redo
//! and the guards' second solve of the same drawing return to structures seen a moment ago. The
//! engine keeps the base factors, rebuilds only the human part, and keeps the last
//! [`PATTERN_CACHE`] sparsity patterns keyed by the human part's structure.

use super::apply::Chain;
use crate::error::{input, HitlError, Result};
use crate::factors::{CentroidShare, Factor, PointsToLineFactor, RelationFactor, RelationMode};
use crate::graph::FactorGraph;
use crate::se2::Pose2;
use crate::solver::{optimize, SolveReport, SolverParams, SparsityPattern};
use crate::values::{Key, Line2, Values};

/// Below this robust weight a relation counts as yielding to contradicting evidence (as
/// `hitl_slam.solve.downweighted`).
pub const YIELDED: f64 = 0.5;

/// How many sparsity patterns (one per structure of the human part) are kept.
pub const PATTERN_CACHE: usize = 6;

/// One pose's observations of one feature, in the robot frame.
pub type PoseObservations = (usize, Vec<[f64; 2]>);

/// A human correction as the joint solve needs it: the relation and, per segment, the
/// observations grouped by observing pose (ascending pose, point order kept).
#[derive(Clone, Debug)]
pub struct CorrectionSpec {
    pub mode: RelationMode,
    pub a: Vec<PoseObservations>,
    pub b: Vec<PoseObservations>,
}

/// The weights of the human factors (`Config.sigma_f`, `k1`, `k2`, `average_points`).
#[derive(Clone, Copy, Debug)]
pub struct HumanWeights {
    pub sigma_f: f64,
    pub k1: f64,
    pub k2: f64,
    pub average_points: bool,
}

impl HumanWeights {
    pub fn validate(&self) -> Result<()> {
        if !(self.sigma_f.is_finite() && self.sigma_f > 0.0) {
            return input(format!("sigma_f must be positive, got {}", self.sigma_f));
        }
        for (name, k) in [("k1", self.k1), ("k2", self.k2)] {
            if !(k.is_finite() && k >= 0.0) {
                return input(format!("{name} must be a finite number >= 0, got {k}"));
            }
        }
        Ok(())
    }

    /// The weight of each point of a segment of `count` points in all.
    fn point_weight(&self, count: usize) -> f64 {
        if self.average_points {
            1.0 / (self.sigma_f * (count as f64).sqrt())
        } else {
            1.0 / self.sigma_f
        }
    }
}

impl CorrectionSpec {
    /// Checks the observation sets against a graph of `num_poses` poses.
    pub fn validate(&self, num_poses: usize) -> Result<()> {
        for (name, set) in [("a", &self.a), ("b", &self.b)] {
            if set.is_empty() || set.iter().any(|(_, pts)| pts.is_empty()) {
                return input(format!("segment {name} has no observations"));
            }
            if let Some((i, _)) = set.iter().find(|(i, _)| *i >= num_poses) {
                return input(format!(
                    "{name}: pose index {i} is out of range (0..{num_poses})"
                ));
            }
            if set.windows(2).any(|w| w[0].0 >= w[1].0) {
                return input(format!(
                    "{name}: observations must be grouped by ascending pose"
                ));
            }
            let finite = set
                .iter()
                .flat_map(|(_, pts)| pts.iter())
                .all(|p| p[0].is_finite() && p[1].is_finite());
            if !finite {
                return input(format!("{name}: an observation is not finite"));
            }
        }
        if self
            .a
            .iter()
            .any(|(i, _)| self.b.binary_search_by_key(i, |(j, _)| *j).is_ok())
        {
            return input("a pose observes both features; remove it from one set");
        }
        Ok(())
    }

    /// How many factors [`Self::factors`] makes: one per observing pose and segment, then the
    /// relation (the last).
    pub fn num_factors(&self) -> usize {
        self.a.len() + self.b.len() + 1
    }

    /// The factors of this correction (docs/ALGORITHM.md §4.3) over lines `la` and `la + 1`: one
    /// point-to-line factor per observing pose and segment, then the relation R_p (every point
    /// counts alike in its centroid).
    pub fn factors(&self, la: usize, w: &HumanWeights) -> Result<Vec<Box<dyn Factor>>> {
        let lb = la + 1;
        let count = |set: &[PoseObservations]| set.iter().map(|(_, p)| p.len()).sum::<usize>();
        let (na, nb) = (count(&self.a), count(&self.b));
        let mut factors: Vec<Box<dyn Factor>> = Vec::with_capacity(self.num_factors());
        let mut shares = Vec::with_capacity(self.a.len() + self.b.len());
        for (set, total, is_a) in [(&self.a, na, true), (&self.b, nb, false)] {
            for (i, pts) in set {
                let share = pts
                    .iter()
                    .fold(CentroidShare::default(), |s, p| CentroidShare {
                        count: s.count + 1.0,
                        sum: [s.sum[0] + p[0], s.sum[1] + p[1]],
                    });
                shares.push(if is_a {
                    (*i, share, CentroidShare::default())
                } else {
                    (*i, CentroidShare::default(), share)
                });
                let line = if is_a { la } else { lb };
                factors.push(Box::new(PointsToLineFactor::new(
                    *i,
                    line,
                    pts.clone(),
                    w.point_weight(total),
                )?));
            }
        }
        factors.push(Box::new(RelationFactor::new(
            self.mode, la, lb, shares, w.k1, w.k2,
        )?));
        Ok(factors)
    }
}

/// The total-least-squares line `(phi, rho)` through the world points of `set` at `poses`
/// (`n = (cos phi, sin phi)` the normal, `n . p = rho` on the line): the joint solve's start
/// for a correction's line.
pub fn fit_line_at(poses: &[Pose2], set: &[PoseObservations]) -> Result<Line2> {
    let mut world = Vec::new();
    for (i, pts) in set {
        let x = poses
            .get(*i)
            .ok_or_else(|| HitlError::Input(format!("pose {i} does not exist")))?;
        world.extend(pts.iter().map(|p| x.transform_point(*p)));
    }
    crate::geometry::fit_line(&world)
        .ok_or_else(|| HitlError::Input("a line needs at least one observation".into()))
}

/// The map's relative-pose factors, held once, and the joint solve with human corrections.
/// The human part's structure: each factor's keys and rows.
type Structure = Vec<(Vec<Key>, usize)>;

#[derive(Debug)]
pub struct CorrectionEngine {
    graph: FactorGraph,
    base_factors: usize,
    /// Recently used patterns, most recent last, keyed by the human part's structure.
    patterns: Vec<(Structure, SparsityPattern)>,
    analyses: usize,
    /// The map's chain, for back-propagation (`apply`, `explicit_and_backpropagate`).
    chain: Option<Chain>,
    /// A second engine over the same factors, so that `apply` can solve a drawing's two
    /// readings (the colocation guard's colocation and collinear) at once, one per core.
    pub(super) twin: Option<Box<CorrectionEngine>>,
}

impl CorrectionEngine {
    /// An engine over `base` (the map's relative-pose factors; it must hold no line variable).
    pub fn new(base: FactorGraph) -> Result<Self> {
        if base.num_lines() != 0 {
            return input("the base graph of a correction engine must have no line variables");
        }
        let base_factors = base.num_factors();
        Ok(Self {
            graph: base,
            base_factors,
            patterns: Vec::new(),
            analyses: 0,
            chain: None,
            twin: None,
        })
    }

    pub fn num_poses(&self) -> usize {
        self.graph.num_poses()
    }

    /// The map's relative-pose factors (its measured edges).
    pub fn num_base_factors(&self) -> usize {
        self.base_factors
    }

    /// Gives the engine its map's chain (back-propagation needs it).
    pub fn set_chain(&mut self, chain: Chain) -> Result<()> {
        chain.validate(self.num_poses())?;
        if let Some(twin) = self.twin.as_mut() {
            twin.set_chain(chain.clone())?;
        }
        self.chain = Some(chain);
        Ok(())
    }

    /// Gives the engine a twin over `base`, the same factors as its own (built again by the
    /// caller): `apply` then solves the colocation guard's two readings in parallel.
    pub fn set_twin(&mut self, base: FactorGraph) -> Result<()> {
        if base.num_factors() != self.base_factors || base.num_poses() != self.num_poses() {
            return input("the twin of a correction engine must hold the same factors");
        }
        let mut twin = CorrectionEngine::new(base)?;
        if let Some(chain) = &self.chain {
            twin.set_chain(chain.clone())?;
        }
        self.twin = Some(Box::new(twin));
        Ok(())
    }

    pub fn chain(&self) -> Option<&Chain> {
        self.chain.as_ref()
    }

    /// How many symbolic analyses this engine has computed (cache misses).
    pub fn analyses(&self) -> usize {
        self.analyses
    }

    /// Forgets the kept analyses (the next solve of any structure computes its own).
    pub fn clear_cache(&mut self) {
        self.patterns.clear();
        if let Some(twin) = self.twin.as_mut() {
            twin.clear_cache();
        }
    }

    /// chi2 of the map's own relative-pose factors at `poses` (the robot's measurements only).
    pub fn base_chi2(&self, poses: &[Pose2]) -> Result<f64> {
        let values = Values::from_poses(poses.to_vec());
        self.check_poses(&values)?;
        Ok(self.graph.factors()[..self.base_factors]
            .iter()
            .map(|f| f.chi2(&values))
            .sum())
    }

    fn check_poses(&self, values: &Values) -> Result<()> {
        if values.poses.len() != self.graph.num_poses() {
            return input(format!(
                "expected {} poses, got {}; pass one (x, y, theta) row per vertex",
                self.graph.num_poses(),
                values.poses.len()
            ));
        }
        if let Some(i) = values.poses.iter().position(|p| !p.is_finite()) {
            return input(format!("pose {i} is not finite; give finite poses"));
        }
        Ok(())
    }

    /// The robust weight of each correction's relation in `report`, a solve of `corrections`
    /// (each correction's factors follow the map's, its relation last; 1 without a kernel).
    pub fn relation_weights(
        &self,
        corrections: &[CorrectionSpec],
        report: &SolveReport,
    ) -> Vec<f64> {
        let mut at = self.num_base_factors();
        corrections
            .iter()
            .map(|c| {
                at += c.num_factors();
                report.weights.get(at - 1).copied().unwrap_or(1.0)
            })
            .collect()
    }

    /// Solves poses and the lines of `corrections` jointly from `poses`, over the base factors
    /// plus every correction's factors. Each correction's lines start at the TLS fit of its
    /// observations at `poses`. Returns the values (poses, then two lines per correction, in
    /// order) and the report. Nothing is kept of the corrections but the structure's analysis.
    pub fn solve(
        &mut self,
        poses: Vec<Pose2>,
        corrections: &[CorrectionSpec],
        weights: &HumanWeights,
        params: &SolverParams,
    ) -> Result<(Values, SolveReport)> {
        let (values, report, _) =
            self.solve_from_best(vec![poses], corrections, weights, params)?;
        Ok((values, report))
    }

    /// [`Self::solve`] from whichever of `starts` violates the factors least: the chi2 at face
    /// value (no robust kernel; each correction's lines the TLS fit of its observations there)
    /// of every start, then one solve from the lowest (the first of equals). Returns the
    /// solution, its report and the index of the start it began at (docs/ALGORITHM.md §4.5).
    pub fn solve_from_best(
        &mut self,
        starts: Vec<Vec<Pose2>>,
        corrections: &[CorrectionSpec],
        weights: &HumanWeights,
        params: &SolverParams,
    ) -> Result<(Values, SolveReport, usize)> {
        weights.validate()?;
        if starts.is_empty() {
            return input("a solve needs at least one start");
        }
        let mut starts: Vec<Values> = starts.into_iter().map(Values::from_poses).collect();
        for start in &starts {
            self.check_poses(start)?;
        }
        let n = self.graph.num_poses();
        // Every factor is built before the graph changes, so a bad correction changes nothing.
        let mut human: Vec<Box<dyn Factor>> = Vec::new();
        for (k, c) in corrections.iter().enumerate() {
            c.validate(n)
                .map_err(|e| HitlError::Input(format!("correction {k}: {e}")))?;
            human.extend(c.factors(2 * k, weights)?);
        }
        for start in &mut starts {
            let mut lines = Vec::with_capacity(2 * corrections.len());
            for c in corrections {
                lines.push(fit_line_at(&start.poses, &c.a)?);
                lines.push(fit_line_at(&start.poses, &c.b)?);
            }
            start.lines = lines;
        }
        // The structure: each factor's keys and rows (a colocation and a collinear statement on
        // the same observations share the keys but not the rows, and a wide factor's rows are
        // registered in the pattern).
        let key: Structure = human
            .iter()
            .map(|f| (f.keys().to_vec(), f.residual_dim()))
            .collect();
        self.graph.truncate(self.base_factors);
        for _ in 0..2 * corrections.len() {
            self.graph.add_line();
        }
        for f in human {
            self.graph.add_factor(f)?;
        }
        self.graph.check_anchored()?;
        match self.patterns.iter().position(|(k, _)| *k == key) {
            Some(hit) => {
                let (_, pattern) = self.patterns.remove(hit);
                self.graph.set_pattern(pattern);
            }
            None => self.analyses += 1,
        }
        let mut chosen = 0;
        if starts.len() > 1 {
            let mut best = f64::INFINITY;
            for (k, start) in starts.iter().enumerate() {
                let chi2 = self.graph.chi2(start);
                if chi2 < best {
                    (best, chosen) = (chi2, k);
                }
            }
        }
        let mut values = starts.swap_remove(chosen);
        let result = optimize(&mut self.graph, &mut values, params);
        if let Some(pattern) = self.graph.take_pattern() {
            if self.patterns.len() >= PATTERN_CACHE {
                self.patterns.remove(0);
            }
            self.patterns.push((key, pattern));
        }
        Ok((values, result?, chosen))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// What pose `i` sees of the bottom wall y = 0: five points about it, in its own frame.
    fn wall_seen_from(truth: &[Pose2], i: usize) -> PoseObservations {
        let x = truth[i];
        let pts: Vec<[f64; 2]> = (0..5)
            .map(|k| {
                x.inverse()
                    .transform_point([x.x - 0.4 + 0.2 * k as f64, 0.0])
            })
            .collect();
        (i, pts)
    }

    /// A square corridor walked twice: the second lap's poses are the first's, and each pose
    /// sees the bottom wall y = 0 (as robot-frame points).
    fn two_laps() -> (
        FactorGraph,
        Vec<Pose2>,
        Vec<PoseObservations>,
        Vec<PoseObservations>,
    ) {
        let n = 40;
        let truth: Vec<Pose2> = (0..n)
            .map(|i| Pose2::new(0.5 * (i % 20) as f64, 1.0, 0.0))
            .collect();
        let info = [[100.0, 0.0, 0.0], [0.0, 100.0, 0.0], [0.0, 0.0, 1000.0]];
        let edges: Vec<(usize, usize)> = (0..n - 1).map(|i| (i, i + 1)).collect();
        let z: Vec<[f64; 3]> = edges
            .iter()
            .map(|&(i, j)| truth[i].between(truth[j]).to_array())
            .collect();
        let graph = FactorGraph::from_edges(n, &edges, &z, &vec![info; n - 1], 0).unwrap();
        let a = (2..8).map(|i| wall_seen_from(&truth, i)).collect();
        let b = (22..28).map(|i| wall_seen_from(&truth, i)).collect();
        (graph, truth, a, b)
    }

    fn weights() -> HumanWeights {
        HumanWeights {
            sigma_f: 0.03,
            k1: 1e6,
            k2: 1e7,
            average_points: false,
        }
    }

    fn params() -> SolverParams {
        SolverParams {
            watchdog_steps: 0,
            ..SolverParams::default()
        }
    }

    #[test]
    fn repeated_structures_reuse_their_analysis_and_give_the_same_answer() {
        let (graph, truth, a, b) = two_laps();
        let mut engine = CorrectionEngine::new(graph).unwrap();
        let w = weights();
        let c = CorrectionSpec {
            mode: RelationMode::Colocation,
            a,
            b,
        };
        // Start off the truth: the second lap turned by 3 degrees.
        let mut start = truth.clone();
        for p in start.iter_mut().skip(20) {
            p.theta += 0.05;
        }
        let (v1, r1) = engine
            .solve(start.clone(), std::slice::from_ref(&c), &w, &params())
            .unwrap();
        assert_eq!(engine.analyses(), 1);
        let (_, r0) = engine.solve(start.clone(), &[], &w, &params()).unwrap();
        assert_eq!(engine.analyses(), 2);
        assert!(r0.final_chi2 < 1e-9);
        let (v2, r2) = engine
            .solve(start, std::slice::from_ref(&c), &w, &params())
            .unwrap();
        assert_eq!(
            engine.analyses(),
            2,
            "the first structure's analysis is re-used"
        );
        assert!(!r2.symbolic_computed);
        assert_eq!(r1.final_chi2.to_bits(), r2.final_chi2.to_bits());
        assert_eq!(v1.poses, v2.poses);
        assert_eq!(v1.lines.len(), 2);
        engine.clear_cache();
        let (_, r3) = engine
            .solve(truth, std::slice::from_ref(&c), &w, &params())
            .unwrap();
        assert!(r3.symbolic_computed);
        assert_eq!(engine.analyses(), 3);
        // The base factors' chi2 alone is what the map's measurements say of the result.
        let base = engine.base_chi2(&v2.poses).unwrap();
        assert!(base <= r2.final_chi2 + 1e-12);
    }

    /// A colocation and a collinear statement on the same observations share their factors'
    /// keys but not their rows: each gets its own analysis, and one solved after the other on
    /// one engine gives what a fresh engine gives (the cache once handed the second the first's
    /// pattern: a stale row of the wide factor, or an index past its end).
    #[test]
    fn the_same_observations_in_another_mode_get_their_own_pattern() {
        let (_, truth, _, _) = two_laps();
        // More poses on each side than WIDE_KEYS: the relation factor is wide.
        let seen = |i: usize| wall_seen_from(&truth, i);
        let spec = |mode| CorrectionSpec {
            mode,
            a: (1..13).map(seen).collect(),
            b: (21..33).map(seen).collect(),
        };
        assert!(spec(RelationMode::Collinear).a.len() > crate::factors::WIDE_KEYS);
        let mut start = truth.clone();
        for p in start.iter_mut().skip(20) {
            p.theta += 0.05;
            p.y += 0.1;
        }
        let w = weights();
        for (first, second) in [
            (RelationMode::Colocation, RelationMode::Collinear),
            (RelationMode::Collinear, RelationMode::Colocation),
        ] {
            let mut engine = CorrectionEngine::new(two_laps().0).unwrap();
            engine
                .solve(start.clone(), &[spec(first)], &w, &params())
                .unwrap();
            let (v, r) = engine
                .solve(start.clone(), &[spec(second)], &w, &params())
                .unwrap();
            assert_eq!(engine.analyses(), 2, "{second:?} after {first:?}");
            let mut fresh = CorrectionEngine::new(two_laps().0).unwrap();
            let (vf, rf) = fresh
                .solve(start.clone(), &[spec(second)], &w, &params())
                .unwrap();
            assert_eq!(r.final_chi2.to_bits(), rf.final_chi2.to_bits());
            assert_eq!(v.poses, vf.poses);
        }
    }

    /// Of two starts, the solve begins at the one the factors (the map's and the correction's,
    /// at face value) violate less, in either order, and answers exactly as a solve from that
    /// start alone; no start is an error.
    #[test]
    fn a_solve_starts_where_the_factors_are_least_violated() {
        let (graph, truth, a, b) = two_laps();
        let c = CorrectionSpec {
            mode: RelationMode::Colocation,
            a,
            b,
        };
        let turned = |by: f64| -> Vec<Pose2> {
            let mut p = truth.clone();
            for q in p.iter_mut().skip(20) {
                q.theta += by;
            }
            p
        };
        let (near, far) = (turned(0.01), turned(0.2));
        let (w, params) = (weights(), params());
        let mut alone = CorrectionEngine::new(two_laps().0).unwrap();
        let (v_near, r_near) = alone
            .solve(near.clone(), std::slice::from_ref(&c), &w, &params)
            .unwrap();
        let mut engine = CorrectionEngine::new(graph).unwrap();
        for (starts, expect) in [
            (vec![far.clone(), near.clone()], 1),
            (vec![near.clone(), far.clone()], 0),
        ] {
            let (v, r, chosen) = engine
                .solve_from_best(starts, std::slice::from_ref(&c), &w, &params)
                .unwrap();
            assert_eq!(chosen, expect);
            assert_eq!(r.initial_chi2.to_bits(), r_near.initial_chi2.to_bits());
            assert_eq!(r.final_chi2.to_bits(), r_near.final_chi2.to_bits());
            assert_eq!(v.poses, v_near.poses);
        }
        let err = engine
            .solve_from_best(Vec::new(), std::slice::from_ref(&c), &w, &params)
            .unwrap_err();
        assert!(err.to_string().contains("at least one start"), "{err}");
    }

    #[test]
    fn a_bad_correction_is_refused_and_changes_nothing() {
        let (graph, truth, a, _) = two_laps();
        let mut engine = CorrectionEngine::new(graph).unwrap();
        let w = weights();
        let bad = CorrectionSpec {
            mode: RelationMode::Collinear,
            a: a.clone(),
            b: vec![(99, vec![[0.0, 0.0]])],
        };
        let err = engine
            .solve(truth.clone(), &[bad], &w, &params())
            .unwrap_err();
        assert!(err.to_string().contains("out of range"), "{err}");
        let shared = CorrectionSpec {
            mode: RelationMode::Collinear,
            a: a.clone(),
            b: a,
        };
        assert!(engine
            .solve(truth.clone(), &[shared], &w, &params())
            .is_err());
        let (_, r) = engine.solve(truth, &[], &w, &params()).unwrap();
        assert!(r.final_chi2 < 1e-12);
    }

    #[test]
    fn each_point_weighs_one_over_sigma_f_or_its_rms_share() {
        // Every point is independent (the paper's R_a, R_b): 1 / sigma_f whatever the count,
        // or with `average_points` 1 / (sigma_f sqrt(count)).
        let mut w = weights();
        for count in [1usize, 10, 5000] {
            assert!((w.point_weight(count) - 1.0 / 0.03).abs() < 1e-12);
        }
        w.average_points = true;
        let rms = w.point_weight(100);
        assert!((rms - 1.0 / (0.03 * 10.0)).abs() < 1e-12, "{rms}");
        w.sigma_f = 0.0;
        assert!(w.validate().is_err());
    }
}
