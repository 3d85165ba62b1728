//! What a person meant by a drawing (docs/ALGORITHM.md §3, §I.2): EM finds the feature
//! under each drawn segment and the observations on it, then the pair rules (pose threshold,
//! one visit per segment, no shared poses, time order) turn them into
//! `h = <P_a, P_b, S_a, S_b, X_a, X_b, m>`. Every refusal is a [`HitlError::Rejected`] whose
//! message says what to draw instead.

use super::scans::{Row, Scans};
use crate::error::{HitlError, Result};
use crate::factors::RelationMode;
use crate::interpret::{
    em_fit_near, line_fit, reach, EmFit, EmParams, Points, Segment, SnapParams, WorldPoints,
};
use crate::se2::Pose2;

/// Observations spanning less than this along their line give it no direction [m].
pub const MIN_EXTENT_M: f64 = 0.05;
/// EM also waits for the mixing weight to settle (`interpret.TOLERANCE_MIXING`).
pub const TOLERANCE_MIXING: f64 = 1e-4;

/// The constants of interpretation (`Config`'s, with `sigma_h` already chosen).
#[derive(Clone, Copy, Debug)]
pub struct InterpretParams {
    pub sigma_h: f64,
    pub candidate_band: f64,
    pub search_band: f64,
    pub drawing_sigma: f64,
    pub sigma_em: f64,
    pub clutter_weight: f64,
    pub em_tolerance_m: f64,
    pub em_tolerance_rad: f64,
    pub em_max_iterations: usize,
    pub min_points_per_pose: usize,
    pub visit_gap: usize,
}

/// A drawing: two segments and the relation stated between them.
#[derive(Clone, Copy, Debug)]
pub struct Drawing {
    pub a: [[f64; 2]; 2],
    pub b: [[f64; 2]; 2],
    pub mode: RelationMode,
}

/// `h`: the interpretation of a drawing.
#[derive(Clone, Debug, PartialEq)]
pub struct Interpretation {
    pub mode: RelationMode,
    pub line_a: [[f64; 2]; 2],
    pub line_b: [[f64; 2]; 2],
    pub s_a: Vec<Row>,
    pub s_b: Vec<Row>,
    pub x_a: Vec<i64>,
    pub x_b: Vec<i64>,
    pub swapped: bool,
    pub iterations: [usize; 2],
    pub log_likelihood: [f64; 2],
    pub notes: Vec<String>,
    /// Per drawn segment (a, b, as drawn, whatever `swapped`): where its snap was a near tie
    /// (`Snap::runner_up_segment`), the drawing moved
    /// onto that next line: the other reading, tried where this one contradicts earlier
    /// corrections (docs/ALGORITHM.md §I.18).
    pub near_ties: [Option<[[f64; 2]; 2]>; 2],
}

fn rejected<T>(msg: impl Into<String>) -> Result<T> {
    Err(HitlError::Rejected(msg.into()))
}

/// `"first-last"` of ascending poses, or `"none"`.
pub fn span(poses: &[i64]) -> String {
    match (poses.first(), poses.last()) {
        (Some(a), Some(b)) => format!("{a}-{b}"),
        _ => "none".into(),
    }
}

/// What one drawn segment selected, narrowed step by step by the pair rules.
#[derive(Clone, Debug)]
struct Selection {
    name: char,
    drawn: [[f64; 2]; 2],
    fit: EmFit,
    rows: Vec<Row>,
    weights: Vec<f64>,
}

impl Selection {
    /// The observing poses, ascending, each once.
    fn poses(&self) -> Vec<i64> {
        let mut p: Vec<i64> = self.rows.iter().map(|r| r[0]).collect();
        p.sort_unstable();
        p.dedup();
        p
    }

    /// Keeps the rows of the poses in `keep` (ascending).
    fn keep_poses(&mut self, keep: &[i64]) {
        let mut rows = Vec::with_capacity(self.rows.len());
        let mut weights = Vec::with_capacity(self.rows.len());
        for (r, w) in self.rows.iter().zip(&self.weights) {
            if keep.binary_search(&r[0]).is_ok() {
                rows.push(*r);
                weights.push(*w);
            }
        }
        self.rows = rows;
        self.weights = weights;
    }

    /// Runs of the observing poses with no gap over `gap`, with their point counts.
    fn runs(&self, gap: usize) -> Vec<(Vec<i64>, usize)> {
        let counts = pose_counts(&self.rows);
        let mut out: Vec<(Vec<i64>, usize)> = Vec::new();
        let mut last: Option<i64> = None;
        for (p, c) in counts {
            match (out.last_mut(), last) {
                (Some((run, total)), Some(l)) if p - l <= gap as i64 => {
                    run.push(p);
                    *total += c;
                }
                _ => out.push((vec![p], c)),
            }
            last = Some(p);
        }
        out
    }
}

/// Each observing pose (ascending) and how many of `rows` it owns.
fn pose_counts(rows: &[Row]) -> Vec<(i64, usize)> {
    let mut poses: Vec<i64> = rows.iter().map(|r| r[0]).collect();
    poses.sort_unstable();
    let mut counts: Vec<(i64, usize)> = Vec::new();
    for p in poses {
        match counts.last_mut() {
            Some((q, c)) if *q == p => *c += 1,
            _ => counts.push((p, 1)),
        }
    }
    counts
}

/// `S` = candidates with `w > 0.5`, as (pose, point) rows, restricted to the poses that own at
/// least `min_points` of them (T_p, the paper's outlier rejection).
fn select(
    name: char,
    drawn: [[f64; 2]; 2],
    fit: EmFit,
    scans: &Scans,
    min_points: usize,
) -> Selection {
    let mut rows = Vec::new();
    let mut weights = Vec::new();
    for (&k, &w) in fit.candidates.iter().zip(&fit.weights) {
        if w > 0.5 {
            rows.push(scans.row_of(k));
            weights.push(w);
        }
    }
    let mut sel = Selection {
        name,
        drawn,
        fit,
        rows,
        weights,
    };
    let keep: Vec<i64> = pose_counts(&sel.rows)
        .into_iter()
        .filter(|(_, c)| *c >= min_points)
        .map(|(p, _)| p)
        .collect();
    sel.keep_poses(&keep);
    sel
}

fn why_empty(sel: &Selection, band: f64, min_points: usize) -> String {
    let fit = &sel.fit;
    if fit.candidates.is_empty() {
        format!("no map points within {band:.2} m of segment {}", sel.name)
    } else if fit.num_inliers == 0 {
        format!(
            "{} points near segment {}, none of them on one line",
            fit.candidates.len(),
            sel.name
        )
    } else {
        format!(
            "{} points on the line under segment {}, but no pose saw {min_points} or more of them",
            fit.num_inliers, sel.name
        )
    }
}

/// Keeps the visit (run of pose indices with no gap over `gap`) with the most points.
fn one_visit(sel: &mut Selection, gap: usize, notes: &mut Vec<String>) {
    let visits = sel.runs(gap);
    if visits.len() <= 1 {
        return;
    }
    // The earliest on a tie, so the rule is deterministic.
    let mut best = 0;
    for (k, v) in visits.iter().enumerate() {
        if v.1 > visits[best].1 {
            best = k;
        }
    }
    let dropped: Vec<String> = visits
        .iter()
        .enumerate()
        .filter(|(k, _)| *k != best)
        .map(|(_, (v, c))| format!("poses {} ({c} points)", span(v)))
        .collect();
    notes.push(format!(
        "segment {} covers {} visits; kept poses {} ({} points), dropped {}",
        sel.name,
        visits.len(),
        span(&visits[best].0),
        visits[best].1,
        dropped.join(", ")
    ));
    let keep = visits[best].0.clone();
    sel.keep_poses(&keep);
}

fn snap_note(sel: &Selection) -> Option<String> {
    let snap = sel.fit.snap.as_ref()?;
    let clear = if snap.runner_up.is_finite() {
        format!(
            "score {:.2} against {:.2} for the next line",
            snap.score, snap.runner_up
        )
    } else {
        "no other line near it".to_string()
    };
    Some(format!(
        "segment {}: the nearest dense line has {} points; the drawing was moved {:.2} m and \
         {:.2} m onto it and turned {:.1} deg ({clear})",
        sel.name,
        snap.support,
        snap.moved[0],
        snap.moved[1],
        snap.turn.to_degrees()
    ))
}

/// One run of a selection's poses: one pass of the robot.
struct Visit {
    poses: Vec<i64>,
    points: usize,
    /// RMS distance of its points to the drawn line [m].
    rms: f64,
}

impl Visit {
    fn score(&self, sigma_c: f64) -> f64 {
        (self.points as f64).ln() - self.rms * self.rms / (2.0 * sigma_c * sigma_c)
    }

    fn before(&self, other: &Visit) -> bool {
        self.poses.last() < other.poses.first()
    }
}

/// Signed distance of each of `sel`'s points (at `poses`) to its drawn line.
fn offsets_from_drawing(sel: &Selection, scans: &Scans, poses: &[Pose2]) -> Result<Vec<f64>> {
    let [p0, p1] = sel.drawn;
    let d = [p1[0] - p0[0], p1[1] - p0[1]];
    let len = d[0].hypot(d[1]);
    let normal = [-d[1] / len, d[0] / len];
    Ok(scans
        .world(poses, &sel.rows)?
        .iter()
        .map(|w| (w[0] - p0[0]) * normal[0] + (w[1] - p0[1]) * normal[1])
        .collect())
}

/// `sel`'s points from the poses `keep` says yes to as one visit of `poses`, with `dist` its
/// points' [`offsets_from_drawing`]; `None` when it has no such point.
fn visit_of(
    sel: &Selection,
    dist: &[f64],
    poses: Vec<i64>,
    keep: impl Fn(i64) -> bool,
) -> Option<Visit> {
    let (mut count, mut sum) = (0usize, 0.0);
    for (r, e) in sel.rows.iter().zip(dist) {
        if keep(r[0]) {
            count += 1;
            sum += e * e;
        }
    }
    (count > 0).then(|| Visit {
        poses,
        points: count,
        rms: (sum / count as f64).sqrt(),
    })
}

fn visits(sel: &Selection, scans: &Scans, poses: &[Pose2], gap: usize) -> Result<Vec<Visit>> {
    let dist = offsets_from_drawing(sel, scans, poses)?;
    Ok(sel
        .runs(gap)
        .into_iter()
        .filter_map(|(run, _)| {
            let (lo, hi) = (run[0], run[run.len() - 1]);
            let within = run.clone();
            visit_of(sel, &dist, run, |p| {
                p >= lo && p <= hi && within.binary_search(&p).is_ok()
            })
        })
        .collect())
}

/// All of `sel` as one visit (its poses, points and RMS distance to its drawing).
fn whole_visit(sel: &Selection, scans: &Scans, poses: &[Pose2]) -> Result<Option<Visit>> {
    let dist = offsets_from_drawing(sel, scans, poses)?;
    Ok(visit_of(sel, &dist, sel.poses(), |_| true))
}

/// Chooses one visit per segment jointly: the pair of visits, one before the other in time,
/// with the best summed score (support against distance to each drawing). False (nothing
/// changed) when no two visits are apart in time.
fn joint_visits(
    a: &mut Selection,
    b: &mut Selection,
    scans: &Scans,
    poses: &[Pose2],
    gap: usize,
    sigma_c: f64,
    notes: &mut Vec<String>,
) -> Result<bool> {
    let (va, vb) = (visits(a, scans, poses, gap)?, visits(b, scans, poses, gap)?);
    let mut best: Option<(f64, usize, usize)> = None;
    for (i, x) in va.iter().enumerate() {
        for (j, y) in vb.iter().enumerate() {
            if !(x.before(y) || y.before(x)) {
                continue;
            }
            let total = x.score(sigma_c) + y.score(sigma_c);
            if best.is_none_or(|(t, _, _)| total > t) {
                best = Some((total, i, j));
            }
        }
    }
    let Some((_, i, j)) = best else {
        return Ok(false);
    };
    for (sel, vs, kept) in [(a, &va, i), (b, &vb, j)] {
        if vs.len() > 1 {
            let dropped: Vec<String> = vs
                .iter()
                .enumerate()
                .filter(|(k, _)| *k != kept)
                .map(|(_, v)| {
                    format!(
                        "poses {} ({} points, {:.2} m)",
                        span(&v.poses),
                        v.points,
                        v.rms
                    )
                })
                .collect();
            let k = &vs[kept];
            notes.push(format!(
                "segment {} covers {} visits; kept poses {} ({} points, {:.2} m from the \
                 drawing), dropped {}",
                sel.name,
                vs.len(),
                span(&k.poses),
                k.points,
                k.rms,
                dropped.join(", ")
            ));
        }
        sel.keep_poses(&vs[kept].poses);
    }
    Ok(true)
}

/// What a segment interpreted again needs: the candidates near both segments (world points
/// and their map rows), EM and the snapping search.
struct Refit<'a> {
    world: &'a WorldPoints,
    rows: &'a [usize],
    em: &'a EmParams,
    snap: Option<&'a SnapParams>,
    min_points: usize,
}

impl Refit<'_> {
    /// `sel`'s segment interpreted again (snapping and EM) on the candidates observed from the
    /// poses `keep` says yes to. None when nothing is selected.
    fn on(
        &self,
        sel: &Selection,
        scans: &Scans,
        keep: impl Fn(i64) -> bool,
    ) -> Result<Option<Selection>> {
        let mut flat = Vec::with_capacity(self.world.flat.len());
        let mut rows = Vec::with_capacity(self.rows.len());
        for (xy, &k) in self.world.flat.chunks_exact(2).zip(self.rows) {
            if keep(scans.row_of(k)[0]) {
                flat.extend_from_slice(xy);
                rows.push(k);
            }
        }
        if rows.is_empty() {
            return Ok(None);
        }
        let world = WorldPoints {
            flat,
            bounds: self.world.bounds,
        };
        let seg = Segment::new(sel.drawn[0], sel.drawn[1]);
        let Some(fit) = em_fit_near(&world, &rows, &[seg], self.em, self.snap)?.pop() else {
            return Ok(None);
        };
        let again = select(sel.name, sel.drawn, fit, scans, self.min_points);
        Ok((!again.rows.is_empty()).then_some(again))
    }
}

/// Where both segments selected one pass (the pair rules refused "the same visit"), each
/// segment in turn is interpreted again without that pass's observations, and the pair is
/// kept if the rules accept it and the new selection lies nearer its drawing than the shared
/// pass does: a segment drawn on a sparse copy a few centimetres from a denser one snaps to
/// the denser line, and the copy the person drew on is the one left when that line is taken
/// out. The better-scoring of the two pairs (docs/ALGORITHM.md §I.2's score) wins. None
/// (the refusal stands) when neither qualifies.
fn apart(
    a: &Selection,
    b: &Selection,
    refit: &Refit<'_>,
    scans: &Scans,
    poses: &[Pose2],
    gap: usize,
    sigma_c: f64,
) -> Result<Option<(Paired, Vec<String>)>> {
    let xb = b.poses();
    let shared: Vec<i64> = a
        .poses()
        .into_iter()
        .filter(|p| xb.binary_search(p).is_ok())
        .collect();
    if shared.is_empty() {
        return Ok(None);
    }
    let is_shared = |p: i64| shared.binary_search(&p).is_ok();
    let mut best: Option<(f64, Paired, Vec<String>)> = None;
    for redo_b in [true, false] {
        let (keep, redo) = if redo_b { (a, b) } else { (b, a) };
        let dist = offsets_from_drawing(redo, scans, poses)?;
        let Some(shared_rms) = visit_of(redo, &dist, shared.clone(), is_shared).map(|v| v.rms)
        else {
            continue;
        };
        let Some(again) = refit.on(redo, scans, |p| !is_shared(p))? else {
            continue;
        };
        let (mut sa, mut sb) = if redo_b {
            (keep.clone(), again)
        } else {
            (again, keep.clone())
        };
        let mut notes = Vec::new();
        joint_visits(&mut sa, &mut sb, scans, poses, gap, sigma_c, &mut notes)?;
        let Ok(paired) = pair_rules(sa, sb, gap, &mut notes) else {
            continue;
        };
        let (Some(va), Some(vb)) = (
            whole_visit(&paired.a, scans, poses)?,
            whole_visit(&paired.b, scans, poses)?,
        ) else {
            continue;
        };
        let (redone, new_rms) = if paired.a.name == redo.name {
            (&paired.a, va.rms)
        } else {
            (&paired.b, vb.rms)
        };
        if new_rms >= shared_rms {
            continue;
        }
        let total = va.score(sigma_c) + vb.score(sigma_c);
        notes.insert(
            0,
            format!(
                "segments a and b both selected poses {} (segment {}'s points there {:.2} m from \
                 its drawing); segment {} interpreted again without them selects poses {} \
                 ({} points, {:.2} m from its drawing)",
                span(&shared),
                redo.name,
                shared_rms,
                redo.name,
                span(&redone.poses()),
                redone.rows.len(),
                new_rms
            ),
        );
        if best.as_ref().is_none_or(|(t, _, _)| total > *t) {
            best = Some((total, paired, notes));
        }
    }
    Ok(best.map(|(_, paired, notes)| (paired, notes)))
}

/// The pair rules' outcome: the two selections in time order and their poses.
struct Paired {
    a: Selection,
    b: Selection,
    xa: Vec<i64>,
    xb: Vec<i64>,
    swapped: bool,
}

fn setdiff(x: &[i64], remove: &[i64]) -> Vec<i64> {
    x.iter()
        .copied()
        .filter(|p| remove.binary_search(p).is_err())
        .collect()
}

/// The design's pair rules (docs/ALGORITHM.md §3.5): refuse one set selected twice; keep one
/// visit per segment (the one with most points); drop poses that see both; order the pair in
/// time.
fn pair_rules(
    mut a: Selection,
    mut b: Selection,
    gap: usize,
    notes: &mut Vec<String>,
) -> Result<Paired> {
    if a.rows == b.rows {
        let poses = a.poses();
        return rejected(format!(
            "segments a and b select the same observations ({} points from poses {}); draw each \
             segment on a different copy of the feature",
            a.rows.len(),
            span(&poses)
        ));
    }
    one_visit(&mut a, gap, notes);
    one_visit(&mut b, gap, notes);
    let (mut xa, mut xb) = (a.poses(), b.poses());
    let common: Vec<i64> = xa
        .iter()
        .copied()
        .filter(|p| xb.binary_search(p).is_ok())
        .collect();
    if !common.is_empty() {
        if common.len() == xa.len() || common.len() == xb.len() {
            let (inner, other, xi, xo) = if common.len() == xa.len() {
                (&a, &b, &xa, &xb)
            } else {
                (&b, &a, &xb, &xa)
            };
            return rejected(format!(
                "segments a and b are seen from the same visit: every pose that sees segment {} \
                 (poses {}) also sees segment {} (poses {}), so one cannot be moved relative to \
                 the other; draw the two segments on copies of the feature seen at different \
                 times",
                inner.name,
                span(xi),
                other.name,
                span(xo)
            ));
        }
        a.keep_poses(&setdiff(&xa, &common));
        b.keep_poses(&setdiff(&xb, &common));
        notes.push(format!(
            "removed {} poses seen by both segments ({})",
            common.len(),
            span(&common)
        ));
        xa = a.poses();
        xb = b.poses();
    }
    let (first_a, last_a) = (xa[0], xa[xa.len() - 1]);
    let (first_b, last_b) = (xb[0], xb[xb.len() - 1]);
    if last_a < first_b {
        Ok(Paired {
            a,
            b,
            xa,
            xb,
            swapped: false,
        })
    } else if last_b < first_a {
        notes.push("swapped a and b: the segment drawn second was observed first".into());
        Ok(Paired {
            a: b,
            b: a,
            xa: xb,
            xb: xa,
            swapped: true,
        })
    } else {
        rejected(format!(
            "the observations interleave in time: segment a is seen from poses {}, segment b \
             from poses {}; draw each segment where the map shows one pass of the robot",
            span(&xa),
            span(&xb)
        ))
    }
}

/// P = the weighted TLS line of the final S and its extent.
fn refit(sel: &Selection, scans: &Scans, poses: &[Pose2], band: f64) -> Result<[[f64; 2]; 2]> {
    let world: Vec<f64> = scans
        .world(poses, &sel.rows)?
        .into_iter()
        .flatten()
        .collect();
    let seg = Segment::new(sel.drawn[0], sel.drawn[1]);
    let fit = line_fit(Points::new(&world)?, &sel.weights, &seg, band)?;
    Ok(fit.extent)
}

fn check_segment(name: char, seg: &[[f64; 2]; 2]) -> Result<()> {
    if !seg.iter().flatten().all(|v| v.is_finite()) {
        return rejected(format!(
            "segment {name} has a non-finite coordinate; draw it again"
        ));
    }
    let length = (seg[1][0] - seg[0][0]).hypot(seg[1][1] - seg[0][1]);
    if length < crate::interpret::MIN_SEGMENT_LENGTH {
        return rejected(format!(
            "segment {name} has zero length ({length:.1e} m); drag along the feature instead of \
             clicking"
        ));
    }
    Ok(())
}

/// What `drawing` means on the map shown with `poses` (docs/ALGORITHM.md §3); with
/// `nearest_visits`, both segments' visits are chosen jointly, each the pass nearest its
/// drawing, even where the design's rules would keep the biggest.
pub fn interpret(
    scans: &Scans,
    poses: &[Pose2],
    drawing: &Drawing,
    p: &InterpretParams,
    nearest_visits: bool,
) -> Result<Interpretation> {
    if poses.len() != scans.num_poses() {
        return Err(HitlError::Input(format!(
            "poses must have {} rows like the map's, got {}",
            scans.num_poses(),
            poses.len()
        )));
    }
    if poses.iter().any(|x| !x.is_finite()) {
        return Err(HitlError::Input(
            "poses contain non-finite values; give finite poses".into(),
        ));
    }
    check_segment('a', &drawing.a)?;
    check_segment('b', &drawing.b)?;
    let sigma_h = p.sigma_h;
    if !(sigma_h.is_finite() && sigma_h > 0.0) {
        return rejected(format!(
            "sigma_h must be a positive number of metres, got {sigma_h}"
        ));
    }
    let band = p.candidate_band * sigma_h;
    if band.is_nan() || band <= 0.0 {
        return Err(HitlError::Input(
            "config candidate_band must be > 0 (the band r_c would be empty)".into(),
        ));
    }
    let search = p.search_band * sigma_h;
    let t_p = p.min_points_per_pose;
    let em = EmParams {
        band,
        sigma: p.sigma_em,
        pi0: p.clutter_weight,
        tol_m: p.em_tolerance_m,
        tol_rad: p.em_tolerance_rad,
        tol_pi: TOLERANCE_MIXING,
        max_iterations: p.em_max_iterations,
    };
    let snap = (search > 0.0).then_some(SnapParams {
        search_band: search,
        sigma: p.sigma_em,
        closeness: p.drawing_sigma * sigma_h,
        pointing: sigma_h,
        min_support: t_p,
    });
    let flat: Vec<f64> = poses.iter().flat_map(|x| [x.x, x.y, x.theta]).collect();
    let segments = [
        Segment::new(drawing.a[0], drawing.a[1]),
        Segment::new(drawing.b[0], drawing.b[1]),
    ];
    let (world, rows) = scans.near(&flat, &segments, reach(&em, snap.as_ref()))?;
    let mut fits = em_fit_near(&world, &rows, &segments, &em, snap.as_ref())?.into_iter();
    let (Some(fit_a), Some(fit_b)) = (fits.next(), fits.next()) else {
        return Err(HitlError::Solver(
            "EM returned fewer fits than segments".into(),
        ));
    };
    let mut a = select('a', drawing.a, fit_a, scans, t_p);
    let mut b = select('b', drawing.b, fit_b, scans, t_p);
    let mut notes: Vec<String> = [&a, &b].into_iter().filter_map(snap_note).collect();
    for s in [&a, &b] {
        notes.push(format!(
            "segment {}: EM {} after {} iterations, {} of {} candidates on the line, {} from {} \
             poses with >= {t_p} (log-likelihood {:.1}){}",
            s.name,
            if s.fit.converged {
                "converged"
            } else {
                "stopped"
            },
            s.fit.iterations,
            s.fit.num_inliers,
            s.fit.candidates.len(),
            s.rows.len(),
            s.poses().len(),
            s.fit.log_likelihood,
            if s.fit.band < band {
                format!(
                    "; on a band of {:.2} m around the line, since at {band:.2} m, among the \
                     other copies beside it, EM held fewer than half of its points",
                    s.fit.band
                )
            } else {
                String::new()
            }
        ));
    }
    let empty: Vec<&Selection> = [&a, &b].into_iter().filter(|s| s.rows.is_empty()).collect();
    if !empty.is_empty() {
        let which: Vec<String> = empty.iter().map(|s| s.name.to_string()).collect();
        let details: Vec<String> = empty.iter().map(|s| why_empty(s, band, t_p)).collect();
        return rejected(format!(
            "no observations under segment{} {}; draw along a wall ({})",
            if empty.len() > 1 { "s" } else { "" },
            which.join(" and "),
            details.join("; ")
        ));
    }
    let sigma_c = p.drawing_sigma * sigma_h;
    let close = |x: &[[f64; 2]; 2], y: &[[f64; 2]; 2]| {
        x.iter()
            .flatten()
            .zip(y.iter().flatten())
            .all(|(u, v)| (u - v).abs() <= 1e-9)
    };
    let reversed = [drawing.b[1], drawing.b[0]];
    // One segment drawn twice points at one copy, whatever the visits under it.
    let same_drawing = close(&drawing.a, &drawing.b) || close(&drawing.a, &reversed);
    let gap = p.visit_gap;
    // The design's pair rules first (each segment's biggest visit); only where they refuse are
    // the visits chosen jointly, which keeps every drawing the rules accept as before.
    let choose = |a: &mut Selection, b: &mut Selection, notes: &mut Vec<String>| {
        joint_visits(a, b, scans, poses, gap, sigma_c, notes)
    };
    let (a0, b0) = (a.clone(), b.clone());
    let mut trial = notes.clone();
    let first = if nearest_visits && !same_drawing {
        choose(&mut a, &mut b, &mut trial)?;
        pair_rules(a, b, gap, &mut trial)
    } else {
        match pair_rules(a.clone(), b.clone(), gap, &mut trial) {
            Ok(paired) => Ok(paired),
            Err(first) => {
                trial = notes.clone();
                if same_drawing || !choose(&mut a, &mut b, &mut trial)? {
                    Err(first)
                } else {
                    pair_rules(a, b, gap, &mut trial)
                }
            }
        }
    };
    let paired = match first {
        Ok(paired) => {
            notes = trial;
            paired
        }
        // Both segments on one pass: the one drawn beside it may mean a copy next to it.
        Err(HitlError::Rejected(why)) if !same_drawing && search > 0.0 => {
            let refitter = Refit {
                world: &world,
                rows: &rows,
                em: &em,
                snap: snap.as_ref(),
                min_points: t_p,
            };
            match apart(&a0, &b0, &refitter, scans, poses, gap, sigma_c)? {
                Some((paired, more)) => {
                    notes.extend(more);
                    paired
                }
                None => return rejected(why),
            }
        }
        Err(e) => return Err(e),
    };
    let line_a = refit(&paired.a, scans, poses, band)?;
    let line_b = refit(&paired.b, scans, poses, band)?;
    for (name, [p0, q]) in [('a', line_a), ('b', line_b)] {
        let length = (q[0] - p0[0]).hypot(q[1] - p0[1]);
        if length.is_nan() || length < MIN_EXTENT_M {
            return rejected(format!(
                "the observations under segment {name} cover {length:.3} m of wall, too little \
                 to give it a direction; draw along a longer stretch of wall"
            ));
        }
    }
    let near_ties = near_ties(&paired);
    Ok(Interpretation {
        mode: drawing.mode,
        line_a,
        line_b,
        iterations: [paired.a.fit.iterations, paired.b.fit.iterations],
        log_likelihood: [paired.a.fit.log_likelihood, paired.b.fit.log_likelihood],
        s_a: paired.a.rows,
        s_b: paired.b.rows,
        x_a: paired.xa,
        x_b: paired.xb,
        swapped: paired.swapped,
        near_ties,
        notes,
    })
}

/// [`Interpretation::near_ties`] of the selections the pair rules kept.
fn near_ties(paired: &Paired) -> [Option<[[f64; 2]; 2]>; 2] {
    let mut out = [None, None];
    for s in [&paired.a, &paired.b] {
        if let Some(other) = s.fit.snap.as_ref().and_then(|snap| snap.runner_up_segment) {
            out[usize::from(s.name == 'b')] = Some([other.a, other.b]);
        }
    }
    out
}
