//! One human correction end to end (the paper's Fig. 3, block 2), in one call: interpret the
//! drawing, move the later part of the map rigidly (explicit correction), close the gap along
//! the chain (back-propagation), solve poses and line parameters jointly with every active
//! correction, and the guards of docs/ALGORITHM.md §I.3 and §I.6 that keep a result the robot's
//! own measurements contradict from being applied silently.

use std::time::Instant;

use super::backpropagate;
use super::engine::{fit_line_at, CorrectionEngine, CorrectionSpec, HumanWeights, YIELDED};
use super::explicit::explicit_transform;
use super::interpretation::{interpret, span, Drawing, InterpretParams, Interpretation};
use super::scans::{Row, Scans};
use crate::error::{input, HitlError, Result};
use crate::factors::{FactorClass, RelationMode};
use crate::interpret::NEAR_TIE;
use crate::metric::{self, MetricParams};
use crate::se2::{wrap_angle, Pose2};
use crate::solver::{SolveReport, SolverParams};
use crate::values::{Line2, Values};

/// What back-propagation needs of a map's chain (`pipeline._chain_of`): per step `k -> k + 1`
/// the rotational and isotropic translational variance, and for the steps that have a chain
/// edge, the edge's measured turn.
#[derive(Clone, Debug)]
pub struct Chain {
    pub rot: Vec<f64>,
    pub trans: Vec<f64>,
    pub steps: Vec<usize>,
    pub turns: Vec<f64>,
}

impl Chain {
    pub fn validate(&self, num_poses: usize) -> Result<()> {
        let n = num_poses.saturating_sub(1);
        if self.rot.len() != n || self.trans.len() != n || self.steps.len() != self.turns.len() {
            return input(format!(
                "a chain of {num_poses} poses needs {n} variances of each kind and one turn per \
                 step with an edge"
            ));
        }
        if self.steps.iter().any(|&k| k >= n) {
            return input("a chain step is out of range");
        }
        Ok(())
    }

    /// The variances of each step; a step whose turn in `poses` differs from its edge's
    /// measurement has its rotational variance widened by the squared difference.
    pub fn variances(&self, poses: &[Pose2]) -> (Vec<f64>, Vec<f64>) {
        let mut rot = self.rot.clone();
        for (&k, &turn) in self.steps.iter().zip(&self.turns) {
            let shown = wrap_angle(poses[k + 1].theta - poses[k].theta);
            rot[k] += wrap_angle(shown - turn).powi(2);
        }
        (rot, self.trans.clone())
    }
}

/// Everything a correction depends on besides the map and the drawing (`Config`'s values).
#[derive(Clone, Debug)]
pub struct ApplyParams {
    pub interpret: InterpretParams,
    pub weights: HumanWeights,
    pub solver: SolverParams,
    /// chi2 units; 0 = off.
    pub colocation_guard: f64,
    /// A probability; 0 = off.
    pub consistency_guard: f64,
    /// The standard normal quantile of `consistency_guard`.
    pub consistency_z: f64,
    /// The inconsistency metric (docs/ALGORITHM.md §6) that chooses between a colocation and its
    /// collinear reading when the chi2 guard lets both stand (§I.13); None = chi2 alone.
    pub consistency_metric: Option<ConsistencyMetric>,
    /// Whether a reading that contradicts earlier corrections is tried again on the next line
    /// of a near-tie snap (`Config.near_tie_reading`, docs/ALGORITHM.md §I.18).
    pub near_tie_reading: bool,
}

/// How far around its passes a colocation's two readings are compared (§I.13): each pass
/// widened by twice its own number of poses on either side. The passes alone do not see a
/// shift along their wall (the lost-poses room's passes see one wall each); the whole map costs
/// a second per colocation on Freiburg 079's 4,791 scans.
pub const COLOCATION_CONSISTENCY_MARGIN: f64 = 2.0;

/// The inconsistency metric's rules and grid resolution, to compare two solutions of one map.
#[derive(Clone, Copy, Debug)]
pub struct ConsistencyMetric {
    pub params: MetricParams,
    pub resolution: f64,
}

/// The scans around a correction's passes, gathered once to score several solutions.
struct Around {
    poses: Vec<usize>,
    points: Vec<f64>,
    offsets: Vec<i64>,
}

impl ConsistencyMetric {
    /// The scans of each pass of `h` (`x_a`, `x_b`) widened by
    /// [`COLOCATION_CONSISTENCY_MARGIN`] times its length on either side.
    fn around(scans: &Scans, h: &Interpretation) -> Around {
        let n = scans.num_poses();
        let mut keep = vec![false; n];
        for pass in [&h.x_a, &h.x_b] {
            let (Some(&first), Some(&last)) = (pass.iter().min(), pass.iter().max()) else {
                continue;
            };
            let widen = (COLOCATION_CONSISTENCY_MARGIN * (last - first + 1) as f64).round() as i64;
            let lo = (first - widen).max(0) as usize;
            let hi = ((last + widen) as usize).min(n - 1);
            keep[lo..=hi].iter_mut().for_each(|k| *k = true);
        }
        let (all, off) = (scans.points(), scans.offsets());
        let poses: Vec<usize> = (0..n).filter(|&i| keep[i]).collect();
        let mut points = Vec::new();
        let mut offsets = Vec::with_capacity(poses.len() + 1);
        offsets.push(0i64);
        for &i in &poses {
            let (a, b) = (off[i] as usize, off[i + 1] as usize);
            points.extend_from_slice(&all[2 * a..2 * b]);
            offsets.push((points.len() / 2) as i64);
        }
        Around {
            poses,
            points,
            offsets,
        }
    }

    /// The inconsistency [m^2] of the scans `around` at `poses`, on the grid covering them.
    fn of(&self, around: &Around, poses: &[Pose2]) -> Result<f64> {
        let flat: Vec<f64> = around
            .poses
            .iter()
            .flat_map(|&i| [poses[i].x, poses[i].y, poses[i].theta])
            .collect();
        let at = metric::Scans::new(&flat, &around.points, &around.offsets)?;
        let grid = at.covering_grid(self.resolution)?;
        Ok(metric::inconsistency(&at, &grid, &self.params, false)?.total_m2)
    }
}

/// An earlier correction that stays active: its relation and observations.
#[derive(Clone, Debug)]
pub struct Active {
    pub mode: RelationMode,
    pub s_a: Vec<Row>,
    pub s_b: Vec<Row>,
}

/// The map after one correction, and how it got there.
#[derive(Clone, Debug)]
pub struct Applied {
    pub interpretation: Interpretation,
    pub poses: Vec<Pose2>,
    /// Two per active correction, in order, the new one last.
    pub lines: Vec<Line2>,
    pub transform: Pose2,
    pub report: SolveReport,
    pub time_interpret: f64,
    pub time_total: f64,
}

/// A joint solve's answer for one interpretation.
pub struct Solved {
    pub poses: Vec<Pose2>,
    pub lines: Vec<Line2>,
    pub transform: Pose2,
    pub report: SolveReport,
    /// The robust weight of each correction's relation at the solution (`active` in order,
    /// then the new one; 1 without a kernel on relations).
    pub relation_weights: Vec<f64>,
    /// Whether this solution was kept over the new correction's own because the earlier
    /// corrections it contradicts hold at a lower cost (`settle_contradiction`).
    pub contested: bool,
    /// Whether the solve began at the map as shown rather than at the explicit step.
    pub from_shown: bool,
}

/// The earlier relations (indices into `weights`, the active corrections' robust weights in
/// order, then the new one's) that yield now but held on the map as shown (`before`, empty when
/// every one held): the ones the new correction makes yield.
fn newly_yielded<'a>(weights: &'a [f64], before: &'a [f64]) -> impl Iterator<Item = usize> + 'a {
    let earlier = weights.split_last().map_or(&[][..], |(_, e)| e);
    earlier
        .iter()
        .enumerate()
        .filter(|(k, w)| **w < YIELDED && before.get(*k).is_none_or(|b| *b >= YIELDED))
        .map(|(k, _)| k)
}

/// Whether a solution contradicts earlier corrections: an earlier relation that held yields
/// ([`newly_yielded`]), or the new one yields to them (`contested`, as [`contradicted_note`]).
fn contradicts(weights: &[f64], before: &[f64], contested: bool) -> bool {
    let Some(new) = weights.last() else {
        return false;
    };
    newly_yielded(weights, before).next().is_some() || (contested && *new < YIELDED)
}

/// The note naming the relations that yield where corrections contradict one another
/// (docs/ALGORITHM.md §I.8): `weights` are the active corrections' relations in order, then the
/// new one's; `contested`: the new one yields to earlier corrections it contradicts (otherwise,
/// if it yields, it yields to the robot's measurements alone); `before`: the active ones' weights
/// on the map as shown, so that only relations this correction makes yield are named (one that
/// yielded already keeps yielding to whatever contradicted it). `None` when every relation holds.
fn contradicted_note(weights: &[f64], before: &[f64], contested: bool) -> Option<String> {
    let (new, earlier) = weights.split_last()?;
    let yielded: Vec<String> = newly_yielded(weights, before)
        .map(|k| format!("#{} (weight {:.2})", k + 1, earlier[k]))
        .collect();
    let mut parts = Vec::new();
    if !yielded.is_empty() {
        parts.push(format!(
            "earlier correction{} {} of the {} active yield{}: {} this one, and the robot's \
             measurements side with this one",
            if yielded.len() > 1 { "s" } else { "" },
            yielded.join(", "),
            earlier.len(),
            if yielded.len() > 1 { "" } else { "s" },
            if yielded.len() > 1 {
                "they contradict"
            } else {
                "it contradicts"
            },
        ));
    }
    if *new < YIELDED {
        parts.push(if contested {
            format!(
                "this correction holds only in part (weight {new:.2}): it contradicts earlier \
                 corrections, and the robot's measurements side with them; undo the one that is \
                 wrong"
            )
        } else {
            format!(
                "this correction holds only in part (weight {new:.2}): the robot's own \
                 measurements contradict it far beyond their noise; check that it selected the \
                 passes you meant"
            )
        });
    }
    (!parts.is_empty()).then(|| parts.join("; "))
}

/// The Wilson-Hilferty quantile of chi2 with `dof` degrees of freedom for the standard normal
/// quantile `z`.
pub fn chi2_limit(dof: usize, z: f64) -> f64 {
    let k = dof.max(1) as f64;
    k * (1.0 - 2.0 / (9.0 * k) + z * (2.0 / (9.0 * k)).sqrt()).powi(3)
}

impl CorrectionEngine {
    /// docs/ALGORITHM.md §4.1 then §4.2: the rigid move of every pose from `min(X_b)` on, and
    /// the chain from `max(X_a)` made to meet it. Returns (new poses, the transform).
    pub fn explicit_and_backpropagate(
        &self,
        poses: &[Pose2],
        h: &Interpretation,
    ) -> Result<(Vec<Pose2>, Pose2)> {
        let transform = explicit_transform(h.mode, &h.line_a, &h.line_b)?;
        let (Some(&first), Some(&last_a)) = (h.x_b.iter().min(), h.x_a.iter().max()) else {
            return input("an interpretation needs poses on both sides");
        };
        let (first, last_a) = (first as usize, last_a as usize);
        if first >= poses.len() {
            return input(format!("pose {first} is out of range"));
        }
        let mut moved = poses.to_vec();
        for p in &mut moved[first..] {
            *p = transform.compose(*p);
        }
        if first > last_a + 1 {
            let chain = self.chain().ok_or_else(|| {
                HitlError::Input("the engine was built without the map's chain".into())
            })?;
            let (rot, trans) = chain.variances(poses);
            backpropagate(&mut moved, poses, last_a, first, &rot, &trans)?;
        }
        Ok((moved, transform))
    }

    /// The joint solve of `active` plus `h`, from the explicit correction of `h` or from the
    /// map as shown, whichever violates the factors less (docs/ALGORITHM.md §4.5).
    fn correct(
        &mut self,
        scans: &Scans,
        current: &[Pose2],
        h: &Interpretation,
        active: &[Active],
        p: &ApplyParams,
    ) -> Result<Solved> {
        let (moved, transform) = self.explicit_and_backpropagate(current, h)?;
        self.solve_from(
            scans,
            vec![moved, current.to_vec()],
            transform,
            h,
            active,
            p,
        )
    }

    /// The joint solve of `active` plus `h` from the least violated of `starts` (the explicit
    /// step first, then the map as shown, if given); `transform` is recorded as the explicit
    /// correction's.
    fn solve_from(
        &mut self,
        scans: &Scans,
        starts: Vec<Vec<Pose2>>,
        transform: Pose2,
        h: &Interpretation,
        active: &[Active],
        p: &ApplyParams,
    ) -> Result<Solved> {
        let specs = specs_with(scans, active, h)?;
        let (values, report, chosen) =
            self.solve_from_best(starts, &specs, &p.weights, &p.solver)?;
        let relation_weights = self.relation_weights(&specs, &report);
        Ok(Solved {
            poses: values.poses,
            lines: values.lines,
            transform,
            report,
            relation_weights,
            contested: false,
            from_shown: chosen == 1,
        })
    }

    /// Which of two contradicting statements yields is decided by the robot's measurements and
    /// the number of statements on each side, not by which came last (docs/ALGORITHM.md §I.8),
    /// nor by where the solve began (§4.5). Where `solved` began at the explicit step (the new
    /// statement held from the start) and an earlier relation yields, the same set is solved
    /// again from the map as shown, where the earlier statements hold; where it began at the map
    /// as shown and the new relation yields, again from the explicit step, whose solution is
    /// kept outright if no earlier relation yields in it. Otherwise the one of the lower robust
    /// cost is kept (the explicit one on a tie), the one from the map as shown marked contested
    /// (the new statement yields to earlier ones).
    fn settle_contradiction(
        &mut self,
        scans: &Scans,
        current: &[Pose2],
        h: &Interpretation,
        solved: Solved,
        active: &[Active],
        p: &ApplyParams,
    ) -> Result<Solved> {
        let earlier_yield = |s: &Solved| {
            let earlier = s.relation_weights.split_last().map_or(&[][..], |(_, e)| e);
            earlier.iter().any(|w| *w < YIELDED)
        };
        let new_yields = solved.relation_weights.last().is_some_and(|w| *w < YIELDED);
        let other_start = match solved.from_shown {
            true if new_yields && !active.is_empty() => {
                self.explicit_and_backpropagate(current, h)?.0
            }
            false if earlier_yield(&solved) => current.to_vec(),
            _ => return Ok(solved),
        };
        let other = self.solve_from(scans, vec![other_start], solved.transform, h, active, p)?;
        let (explicit, shown) = if solved.from_shown {
            if !earlier_yield(&other) {
                return Ok(other);
            }
            (other, solved)
        } else {
            (solved, other)
        };
        Ok(if shown.report.final_cost < explicit.report.final_cost {
            Solved {
                contested: true,
                ..shown
            }
        } else {
            explicit
        })
    }

    /// The robust weight of each active correction's relation on the map shown with `poses`
    /// (each line the TLS fit of its observations there, as a solve starts): which relations
    /// yield already, before the new correction. All 1 without a kernel on relations.
    fn relation_weights_at(
        &self,
        scans: &Scans,
        poses: &[Pose2],
        active: &[Active],
        p: &ApplyParams,
    ) -> Result<Vec<f64>> {
        let Some(kernel) = p.solver.robust.get(FactorClass::Relation) else {
            return Ok(vec![1.0; active.len()]);
        };
        let mut values = Values::from_poses(poses.to_vec());
        active
            .iter()
            .map(|c| {
                let c = spec(scans, c.mode, &c.s_a, &c.s_b)?;
                values.lines = vec![fit_line_at(poses, &c.a)?, fit_line_at(poses, &c.b)?];
                let factors = c.factors(0, &p.weights)?;
                let relation = factors.last().ok_or_else(|| {
                    HitlError::Solver("internal: a correction without a relation factor".into())
                })?;
                Ok(kernel.weight(relation.chi2(&values)))
            })
            .collect()
    }

    /// Interprets `drawing` on the map shown with `current`, corrects, and re-solves with every
    /// correction in `active` plus the new one. Refusals are [`HitlError::Rejected`]; nothing
    /// held by the engine but its cache of analyses changes either way.
    pub fn apply(
        &mut self,
        scans: &Scans,
        current: &[Pose2],
        drawing: &Drawing,
        active: &[Active],
        p: &ApplyParams,
    ) -> Result<Applied> {
        let t0 = Instant::now();
        if scans.num_poses() != self.num_poses() {
            return input(format!(
                "the scans are of {} poses, the engine's map of {}",
                scans.num_poses(),
                self.num_poses()
            ));
        }
        // The map's own chi2 as shown, for the consistency guard, on the other core meanwhile.
        let (h, before) = rayon::join(
            || interpret(scans, current, drawing, &p.interpret, false),
            || {
                if p.consistency_guard > 0.0 {
                    self.base_chi2(current)
                } else {
                    Ok(0.0)
                }
            },
        );
        let (h, before) = (h?, before?);
        let time_interpret = t0.elapsed().as_secs_f64();
        let (mut h, mut solved) =
            self.solve_reading(scans, current, drawing, h, before, active, p)?;
        // The weights on the map as shown matter only where an earlier relation yields now.
        let earlier = &solved.relation_weights[..active.len().min(solved.relation_weights.len())];
        let before_weights = if earlier.iter().any(|w| *w < YIELDED) {
            self.relation_weights_at(scans, current, active, p)?
        } else {
            Vec::new()
        };
        if p.near_tie_reading
            && contradicts(&solved.relation_weights, &before_weights, solved.contested)
        {
            if let Some((alt, alt_solved)) = self.near_tie_reading(
                scans,
                current,
                drawing,
                &h,
                &solved,
                before,
                &before_weights,
                active,
                p,
            )? {
                (h, solved) = (alt, alt_solved);
            }
        }
        if let Some(note) =
            contradicted_note(&solved.relation_weights, &before_weights, solved.contested)
        {
            h.notes.push(note);
        }
        Ok(Applied {
            interpretation: h,
            poses: solved.poses,
            lines: solved.lines,
            transform: solved.transform,
            report: solved.report,
            time_interpret,
            time_total: t0.elapsed().as_secs_f64(),
        })
    }

    /// One reading of a drawing (`h`, interpreted on the map shown with `current`) corrected
    /// and solved: the colocation guard (§I.3, §I.13), the contradiction
    /// settled (§I.8), and the consistency guard (§I.6). `before`: the chi2 of the map's own
    /// factors at `current`.
    #[allow(clippy::too_many_arguments)]
    fn solve_reading(
        &mut self,
        scans: &Scans,
        current: &[Pose2],
        drawing: &Drawing,
        mut h: Interpretation,
        before: f64,
        active: &[Active],
        p: &ApplyParams,
    ) -> Result<(Interpretation, Solved)> {
        let guarded = h.mode == RelationMode::Colocation && p.colocation_guard > 0.0;
        let mut alt = h.clone();
        alt.mode = RelationMode::Collinear;
        let (first, second) = if guarded {
            // The two readings at once, each on its own engine (one per core where there are
            // two): the same solves as one after the other.
            let mut twin = self.twin.take();
            let (first, second) = match twin.as_mut() {
                Some(t) => rayon::join(
                    || self.correct(scans, current, &h, active, p),
                    || Some(t.correct(scans, current, &alt, active, p)),
                ),
                None => (self.correct(scans, current, &h, active, p), None),
            };
            self.twin = twin;
            let second = match second {
                Some(s) => s,
                None => self.correct(scans, current, &alt, active, p),
            };
            (first, Some(second))
        } else {
            (self.correct(scans, current, &h, active, p), None)
        };
        let mut solved = first?;
        if let Some(alt_solved) = second {
            let alt_solved = alt_solved?;
            let cost = self.base_chi2(&solved.poses)?;
            let alt_cost = self.base_chi2(&alt_solved.poses)?;
            if cost - alt_cost > p.colocation_guard {
                alt.notes.push(format!(
                    "applied as collinear: the two passes' positions along the wall contradict \
                     the odometry (chi2 of the map's measurements {cost:.1} as colocation, \
                     {alt_cost:.1} as collinear; guard {})",
                    python_g(p.colocation_guard)
                ));
                h = alt;
                solved = alt_solved;
            } else if let Some(m) = &p.consistency_metric {
                // The chi2 cannot tell where the chain between the passes is loose; the scans
                // can: keep the reading under which they agree the better (§I.13).
                let around = ConsistencyMetric::around(scans, &h);
                let (first, second) = rayon::join(
                    || m.of(&around, &solved.poses),
                    || m.of(&around, &alt_solved.poses),
                );
                let (first, second) = (first?, second?);
                if second < first {
                    alt.notes.push(format!(
                        "applied as collinear: the map is more consistent with the two passes on \
                         one line than at one place ({first:.1} -> {second:.1} m^2), so their \
                         positions along the wall are left to the robot's measurements"
                    ));
                    h = alt;
                    solved = alt_solved;
                }
            }
        }
        solved = self.settle_contradiction(scans, current, &h, solved, active, p)?;
        if p.consistency_guard > 0.0 {
            (h, solved) =
                self.consistency_guard(scans, current, drawing, h, solved, before, active, p)?;
        }
        Ok((h, solved))
    }

    /// Where the reading kept contradicts earlier corrections (`solved`: some earlier relation
    /// that held on the map as shown, `before_weights`, yields now, or the new one yields to
    /// them) and a segment's snap was a near tie ([`Interpretation::near_ties`]), the drawing
    /// is read again with that segment on the other line of the tie (each alone, then both).
    /// The first reading that contradicts none of them and costs the robot's measurements (the
    /// chi2 of the map's own factors) less than the first is returned with a note; `None` keeps
    /// the first (docs/ALGORITHM.md §I.18). A person who drew between two lines of nearly equal
    /// weight meant the one consistent with what they said before, unless what they said before
    /// is what the measurements contradict.
    #[allow(clippy::too_many_arguments)]
    fn near_tie_reading(
        &mut self,
        scans: &Scans,
        current: &[Pose2],
        drawing: &Drawing,
        h: &Interpretation,
        solved: &Solved,
        before: f64,
        before_weights: &[f64],
        active: &[Active],
        p: &ApplyParams,
    ) -> Result<Option<(Interpretation, Solved)>> {
        let [tie_a, tie_b] = h.near_ties;
        let mut tries: Vec<Drawing> = Vec::new();
        if let Some(a) = tie_a {
            tries.push(Drawing { a, ..*drawing });
        }
        if let Some(b) = tie_b {
            tries.push(Drawing { b, ..*drawing });
        }
        if let (Some(a), Some(b)) = (tie_a, tie_b) {
            tries.push(Drawing { a, b, ..*drawing });
        }
        if tries.is_empty() {
            return Ok(None);
        }
        // What the alternatives are judged against, once: the weights of the map as shown (if
        // the first reading did not need them) and the first reading's cost to the odometry.
        let fresh;
        let weights = if before_weights.is_empty() && !active.is_empty() {
            fresh = self.relation_weights_at(scans, current, active, p)?;
            fresh.as_slice()
        } else {
            before_weights
        };
        let first = self.base_chi2(&solved.poses)?;
        for alt_drawing in tries {
            // A reading the engine refuses is no alternative; the first one stands.
            let alt = match interpret(scans, current, &alt_drawing, &p.interpret, false) {
                Ok(alt) => alt,
                Err(HitlError::Rejected(_)) => continue,
                Err(e) => return Err(e),
            };
            if alt.s_a == h.s_a && alt.s_b == h.s_b {
                continue;
            }
            let (mut alt, alt_solved) =
                match self.solve_reading(scans, current, &alt_drawing, alt, before, active, p) {
                    Ok(found) => found,
                    Err(HitlError::Rejected(_)) => continue,
                    Err(e) => return Err(e),
                };
            if contradicts(&alt_solved.relation_weights, weights, alt_solved.contested) {
                continue;
            }
            // Which of two contradicting statements is wrong, the new one or the earlier, the
            // robot's own measurements decide (as between a colocation and its collinear
            // reading, §I.3): the other reading is kept only where it costs them less.
            let second = self.base_chi2(&alt_solved.poses)?;
            if second.partial_cmp(&first) != Some(std::cmp::Ordering::Less) {
                continue;
            }
            let moved: Vec<String> = [('a', tie_a, alt_drawing.a), ('b', tie_b, alt_drawing.b)]
                .into_iter()
                .filter(|(_, tie, seg)| tie.is_some_and(|t| t == *seg))
                .map(|(name, _, _)| name.to_string())
                .collect();
            let mut why = Vec::new();
            let k = newly_yielded(&solved.relation_weights, before_weights).count();
            if k > 0 {
                why.push(format!(
                    "{k} earlier correction{} would yield",
                    if k > 1 { "s" } else { "" }
                ));
            }
            if solved.relation_weights.last().is_some_and(|w| *w < YIELDED) {
                why.push("it would hold only in part".to_string());
            }
            alt.notes.push(format!(
                "read on the next line: segment {} lay between two lines of nearly equal weight \
                 (scores within {NEAR_TIE}), and read on the nearer one this correction \
                 contradicted earlier ones ({}); on the next line it contradicts none and costs \
                 the robot's measurements less (chi2 {first:.1} -> {second:.1}), so that reading \
                 was kept",
                moved.join(" and "),
                why.join(", and ")
            ));
            return Ok(Some((alt, alt_solved)));
        }
        Ok(None)
    }

    /// The guard of docs/ALGORITHM.md §I.6 on a solved result (see [`Self::guard_alternative`]).
    #[allow(clippy::too_many_arguments)]
    fn consistency_guard(
        &mut self,
        scans: &Scans,
        current: &[Pose2],
        drawing: &Drawing,
        h: Interpretation,
        solved: Solved,
        before: f64,
        active: &[Active],
        p: &ApplyParams,
    ) -> Result<(Interpretation, Solved)> {
        match self.guard_alternative(
            scans,
            current,
            drawing,
            &h,
            &solved.poses,
            before,
            active,
            p,
        )? {
            None => Ok((h, solved)),
            Some((alt, alt_solved)) => Ok((alt, alt_solved)),
        }
    }

    /// The guard of docs/ALGORITHM.md §I.6: a result (`new_poses` for `h`) whose odometry chi2
    /// is beyond what the odometry's own noise allows (3 dof per edge; once the map is past
    /// that, a rise of more than the quantile's spread, z sqrt(2 dof)) is not applied silently.
    /// `None`: within the limit, apply it. Otherwise it is tried again with each segment's pass
    /// nearest its drawing; if that is within the limit, that interpretation (with a note) and
    /// its solution are returned, otherwise the correction is refused with the figures.
    /// `before`: the chi2 of the map's own factors at `current`.
    #[allow(clippy::too_many_arguments)]
    pub fn guard_alternative(
        &mut self,
        scans: &Scans,
        current: &[Pose2],
        drawing: &Drawing,
        h: &Interpretation,
        new_poses: &[Pose2],
        before: f64,
        active: &[Active],
        p: &ApplyParams,
    ) -> Result<Option<(Interpretation, Solved)>> {
        let dof = 3 * self.num_base_factors();
        let limit = chi2_limit(dof, p.consistency_z);
        let step = p.consistency_z * (2.0 * dof as f64).sqrt();
        let cost = self.base_chi2(new_poses)?;
        let allowed = limit.max(before + step);
        if cost <= allowed {
            return Ok(None);
        }
        let alt = match interpret(scans, current, drawing, &p.interpret, true) {
            Ok(alt) => Some(alt),
            Err(HitlError::Rejected(_)) => None,
            Err(e) => return Err(e),
        };
        if let Some(mut alt) = alt.filter(|a| a.s_a != h.s_a || a.s_b != h.s_b) {
            if h.mode == RelationMode::Collinear && alt.mode == RelationMode::Colocation {
                alt.mode = RelationMode::Collinear;
            }
            let alt_solved = self.correct(scans, current, &alt, active, p)?;
            let alt_cost = self.base_chi2(&alt_solved.poses)?;
            if alt_cost <= allowed {
                alt.notes.push(format!(
                    "the passes kept first (poses {} and {}) would have put the robot's \
                     measurements at chi2 {cost:.0}, beyond the {allowed:.0} their noise allows; \
                     the passes nearest the drawings give {alt_cost:.0}",
                    span(&h.x_a),
                    span(&h.x_b)
                ));
                return Ok(Some((alt, alt_solved)));
            }
        }
        Err(HitlError::Rejected(format!(
            "applying it would contradict the robot's own measurements: their chi2 would go \
             from {before:.0} to {cost:.0}, beyond the {allowed:.0} their noise allows (99.9% of \
             chi2 with {dof} dof, or that spread above the map before) with the passes it \
             selected (poses {} and {}); draw each segment along a longer, clearly separate \
             stretch of the copy you mean",
            span(&h.x_a),
            span(&h.x_b)
        )))
    }
}

/// A correction's factors' input: its observations grouped by pose.
/// The joint solve's corrections: every one of `active`, in order, then `h`.
fn specs_with(scans: &Scans, active: &[Active], h: &Interpretation) -> Result<Vec<CorrectionSpec>> {
    let mut specs = Vec::with_capacity(active.len() + 1);
    for c in active {
        specs.push(spec(scans, c.mode, &c.s_a, &c.s_b)?);
    }
    specs.push(spec(scans, h.mode, &h.s_a, &h.s_b)?);
    Ok(specs)
}

pub fn spec(scans: &Scans, mode: RelationMode, s_a: &[Row], s_b: &[Row]) -> Result<CorrectionSpec> {
    Ok(CorrectionSpec {
        mode,
        a: scans.grouped(s_a)?,
        b: scans.grouped(s_b)?,
    })
}

/// Python's `format(x, "g")` for the guard values people configure (at most 6 significant
/// digits, no trailing zeros).
fn python_g(x: f64) -> String {
    let s = format!("{x:.6}");
    let s = s.trim_end_matches('0').trim_end_matches('.');
    s.to_string()
}

#[cfg(test)]
mod tests {
    use super::{contradicted_note, contradicts};

    #[test]
    fn a_solution_contradicts_earlier_corrections_when_one_starts_to_yield_or_it_yields_to_them() {
        assert!(!contradicts(&[], &[], false));
        assert!(!contradicts(&[1.0, 0.9, 1.0], &[], false));
        assert!(contradicts(&[1.0, 0.2, 1.0], &[], false));
        // One that yielded already on the map as shown is not this correction's doing.
        assert!(!contradicts(&[1.0, 0.2, 1.0], &[1.0, 0.3], false));
        assert!(contradicts(&[0.1, 0.2, 1.0], &[1.0, 0.3], false));
        // The new one yielding: to earlier corrections (contested), or to the odometry alone.
        assert!(contradicts(&[1.0, 0.1], &[], true));
        assert!(!contradicts(&[1.0, 0.1], &[], false));
    }

    #[test]
    fn the_note_names_the_relations_that_yield() {
        assert_eq!(contradicted_note(&[], &[], false), None);
        assert_eq!(contradicted_note(&[1.0, 0.9, 1.0], &[1.0, 1.0], true), None);
        let earlier = contradicted_note(&[0.01, 1.0, 0.3, 1.0], &[1.0, 1.0, 1.0], false).unwrap();
        assert!(
            earlier.starts_with("earlier corrections #1 (weight 0.01), #3 (weight 0.30) of the 3 active yield: they contradict this one"),
            "{earlier}"
        );
        let one = contradicted_note(&[1.0, 0.2, 1.0], &[1.0, 1.0], false).unwrap();
        assert!(
            one.starts_with("earlier correction #2 (weight 0.20) of the 2 active yields"),
            "{one}"
        );
        let alone = contradicted_note(&[0.9, 0.1], &[1.0], false).unwrap();
        assert!(
            alone.contains("the robot's own measurements contradict it"),
            "{alone}"
        );
        let new = contradicted_note(&[1.0, 0.1], &[1.0], true).unwrap();
        assert!(
            new.starts_with("this correction holds only in part (weight 0.10)"),
            "{new}"
        );
        assert!(!new.contains("yield"), "{new}");
        // A relation that yielded before this correction is not this correction's doing.
        assert_eq!(
            contradicted_note(&[0.01, 1.0, 1.0], &[0.02, 1.0], false),
            None
        );
        let since = contradicted_note(&[0.01, 0.1, 1.0], &[0.02, 1.0], false).unwrap();
        assert!(
            since.starts_with("earlier correction #2 (weight 0.10) of the 2"),
            "{since}"
        );
    }
}
