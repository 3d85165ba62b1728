//! A factor graph over poses (and, later, lines): the factors, which variables are held fixed
//! (the gauge), and the cached sparsity analysis that every solve of the same structure reuses.

use crate::error::{input, HitlError, Result};
use crate::factors::{BetweenFactor, Factor, PriorFactor};
use crate::init::{initialize, InitMethod};
use crate::se2::Pose2;
use crate::solver::SparsityPattern;
use crate::values::{Key, Values};

/// The problem structure: variables, factors, gauge. Values live outside (a [`Values`]), so one
/// graph can be solved from many initial guesses while its symbolic analysis is kept.
#[derive(Debug)]
pub struct FactorGraph {
    num_poses: usize,
    num_lines: usize,
    fixed: Vec<Key>,
    factors: Vec<Box<dyn Factor>>,
    anchors: Vec<bool>,
    pattern: Option<SparsityPattern>,
    analyses: usize,
}

impl FactorGraph {
    /// An empty graph over `num_poses` poses with pose `anchor` held fixed.
    pub fn new(num_poses: usize, anchor: Option<usize>) -> Result<Self> {
        if num_poses == 0 {
            return input("the graph has no poses; give at least one vertex");
        }
        let fixed = match anchor {
            Some(a) if a >= num_poses => {
                return input(format!(
                    "anchor pose {a} does not exist (the graph has {num_poses} poses)"
                ))
            }
            Some(a) => vec![Key::Pose(a)],
            None => Vec::new(),
        };
        Ok(Self {
            num_poses,
            num_lines: 0,
            fixed,
            factors: Vec::new(),
            anchors: Vec::new(),
            pattern: None,
            analyses: 0,
        })
    }

    /// A pose graph from relative-pose edges (the common case), validated and checked to be
    /// fully anchored.
    pub fn from_edges(
        num_poses: usize,
        edges: &[(usize, usize)],
        measurements: &[[f64; 3]],
        information: &[[[f64; 3]; 3]],
        anchor: usize,
    ) -> Result<Self> {
        let mut g = Self::new(num_poses, Some(anchor))?;
        if edges.len() != measurements.len() || edges.len() != information.len() {
            return input("edges, measurements and information must have the same length");
        }
        g.factors.reserve(edges.len());
        for (k, ((&(i, j), z), info)) in edges.iter().zip(measurements).zip(information).enumerate()
        {
            if i >= num_poses || j >= num_poses {
                return input(format!(
                    "edge {k} ({i} -> {j}) refers to a pose that does not exist (the graph has {num_poses} poses)"
                ));
            }
            let f = BetweenFactor::new(i, j, Pose2::new(z[0], z[1], z[2]), info)
                .map_err(|e| HitlError::Input(format!("edge {k} ({i} -> {j}): {e}")))?;
            g.push(Box::new(f), false);
        }
        g.check_anchored()?;
        Ok(g)
    }

    fn push(&mut self, f: Box<dyn Factor>, anchors: bool) {
        self.factors.push(f);
        self.anchors.push(anchors);
        self.pattern = None;
    }

    /// Adds a relative-pose factor; the next solve redoes the symbolic analysis.
    pub fn add_between(&mut self, f: BetweenFactor) -> Result<()> {
        // (Construction errors of `f` are the caller's to label.)
        let (i, j) = f.indices();
        if i >= self.num_poses || j >= self.num_poses {
            return input(format!(
                "edge {i} -> {j} refers to a pose that does not exist"
            ));
        }
        self.push(Box::new(f), false);
        Ok(())
    }

    /// Adds a prior; a prior anchors its pose's connected component.
    pub fn add_prior(&mut self, f: PriorFactor) -> Result<()> {
        if f.index() >= self.num_poses {
            return input(format!("prior on pose {} which does not exist", f.index()));
        }
        self.push(Box::new(f), true);
        Ok(())
    }

    /// Adds any factor (human corrections use this). Its keys must exist and be distinct.
    pub fn add_factor(&mut self, f: Box<dyn Factor>) -> Result<()> {
        let keys = f.keys();
        for (n, &k) in keys.iter().enumerate() {
            let ok = match k {
                Key::Pose(i) => i < self.num_poses,
                Key::Line(i) => i < self.num_lines,
            };
            if !ok {
                return input(format!("factor refers to {k:?}, which does not exist"));
            }
            if keys[..n].contains(&k) {
                return input(format!("factor lists {k:?} twice"));
            }
        }
        self.push(f, false);
        Ok(())
    }

    /// Drops every factor after the first `num_factors` and every line variable (the correction
    /// engine's reset to its base graph); the next solve needs a pattern again.
    pub(crate) fn truncate(&mut self, num_factors: usize) {
        self.factors.truncate(num_factors);
        self.anchors.truncate(num_factors);
        self.num_lines = 0;
        self.pattern = None;
    }

    /// Installs a sparsity pattern computed earlier for exactly this structure (same variables
    /// and the same factor keys in the same order; the caller keys its cache by them).
    pub(crate) fn set_pattern(&mut self, pattern: SparsityPattern) {
        self.pattern = Some(pattern);
    }

    /// Takes the current sparsity pattern out (for a cache), leaving none.
    pub(crate) fn take_pattern(&mut self) -> Option<SparsityPattern> {
        self.pattern.take()
    }

    /// Adds a line variable, returning its index.
    pub fn add_line(&mut self) -> usize {
        self.num_lines += 1;
        self.pattern = None;
        self.num_lines - 1
    }

    pub fn num_poses(&self) -> usize {
        self.num_poses
    }

    pub fn num_lines(&self) -> usize {
        self.num_lines
    }

    pub fn num_factors(&self) -> usize {
        self.factors.len()
    }

    pub fn factors(&self) -> &[Box<dyn Factor>] {
        &self.factors
    }

    pub fn fixed(&self) -> &[Key] {
        &self.fixed
    }

    /// How many symbolic analyses this graph has computed (one per structure).
    pub fn analyses(&self) -> usize {
        self.analyses
    }

    /// Total chi2 `sum |r|^2` at `values`.
    pub fn chi2(&self, values: &Values) -> f64 {
        self.factors.iter().map(|f| f.chi2(values)).sum()
    }

    /// Checks that `values` fits this graph (sizes, finiteness).
    pub fn check_values(&self, values: &Values) -> Result<()> {
        if values.poses.len() != self.num_poses {
            return input(format!(
                "expected {} poses, got {}; pass one (x, y, theta) row per vertex",
                self.num_poses,
                values.poses.len()
            ));
        }
        if values.lines.len() != self.num_lines {
            return input(format!(
                "expected {} lines, got {}",
                self.num_lines,
                values.lines.len()
            ));
        }
        if let Some((i, p)) = values
            .poses
            .iter()
            .enumerate()
            .find(|(_, p)| !(p.x.is_finite() && p.y.is_finite() && p.theta.is_finite()))
        {
            return input(format!(
                "pose {i} is not finite ({}, {}, {}); give finite initial values",
                p.x, p.y, p.theta
            ));
        }
        Ok(())
    }

    /// An initial guess for the poses from the graph's relative-pose edges (`init`), starting
    /// from `poses` (the anchor keeps its pose there; `Given` returns `poses`).
    pub fn initial_guess(&self, method: InitMethod, poses: &[Pose2]) -> Result<Vec<Pose2>> {
        if poses.len() != self.num_poses {
            return input(format!(
                "expected {} poses, got {}",
                self.num_poses,
                poses.len()
            ));
        }
        let mut edges = Vec::new();
        let mut measurements = Vec::new();
        let mut information = Vec::new();
        for f in self.factors.iter().filter_map(|f| f.as_between()) {
            edges.push(f.indices());
            measurements.push(f.measured());
            information.push(f.information());
        }
        let anchor = match self.fixed.first() {
            Some(Key::Pose(a)) => *a,
            _ => 0,
        };
        initialize(method, poses, &edges, &measurements, &information, anchor)
    }

    /// Every variable must be connected to a fixed variable or a prior; otherwise the problem
    /// has a free gauge and the normal equations are singular.
    pub fn check_anchored(&self) -> Result<()> {
        let n = self.num_poses + self.num_lines;
        let id = |k: Key| match k {
            Key::Pose(i) => i,
            Key::Line(i) => self.num_poses + i,
        };
        let mut parent: Vec<usize> = (0..n).collect();
        fn find(parent: &mut [usize], mut a: usize) -> usize {
            while parent[a] != a {
                parent[a] = parent[parent[a]];
                a = parent[a];
            }
            a
        }
        for f in &self.factors {
            let keys = f.keys();
            if let Some(&k0) = keys.first() {
                let r0 = find(&mut parent, id(k0));
                for &k in &keys[1..] {
                    let r = find(&mut parent, id(k));
                    if r != r0 {
                        parent[r] = r0;
                    }
                }
            }
        }
        let mut anchored = vec![false; n];
        for &k in &self.fixed {
            let r = find(&mut parent, id(k));
            anchored[r] = true;
        }
        for (f, &a) in self.factors.iter().zip(&self.anchors) {
            if a {
                let r = find(&mut parent, id(f.keys()[0]));
                anchored[r] = true;
            }
        }
        let mut loose = Vec::new();
        for v in 0..n {
            let r = find(&mut parent, v);
            if !anchored[r] {
                loose.push(v);
            }
        }
        if loose.is_empty() {
            return Ok(());
        }
        let names: Vec<String> = loose
            .iter()
            .take(5)
            .map(|&v| {
                if v < self.num_poses {
                    format!("pose {v}")
                } else {
                    format!("line {}", v - self.num_poses)
                }
            })
            .collect();
        let anchor = match self.fixed.first() {
            Some(Key::Pose(a)) => format!("the anchored pose {a}"),
            _ => "any anchor or prior".to_string(),
        };
        input(format!(
            "{} variable(s) are not connected to {anchor} ({}{}); add edges linking them, or remove them",
            loose.len(),
            names.join(", "),
            if loose.len() > 5 { ", ..." } else { "" }
        ))
    }

    /// The sparsity pattern and symbolic factorization for the current structure, computed on
    /// first use after any structural change and reused afterwards.
    pub(crate) fn pattern(&mut self) -> Result<&mut SparsityPattern> {
        if self.pattern.is_none() {
            let p =
                SparsityPattern::new(self.num_poses, self.num_lines, &self.fixed, &self.factors)?;
            self.analyses += 1;
            self.pattern = Some(p);
        }
        self.pattern
            .as_mut()
            .ok_or_else(|| HitlError::Solver("internal: no sparsity pattern".into()))
    }

    /// Splits the borrow so the solver can read factors while writing into the pattern.
    pub(crate) fn parts(&mut self) -> Result<(&[Box<dyn Factor>], &mut SparsityPattern)> {
        self.pattern()?;
        match self.pattern.as_mut() {
            Some(p) => Ok((&self.factors, p)),
            None => Err(HitlError::Solver("internal: no sparsity pattern".into())),
        }
    }
}
