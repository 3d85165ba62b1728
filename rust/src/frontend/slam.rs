//! The scan-matching front end (docs/ALGORITHM.md §F): a raw laser log (scans with their
//! odometry) to a pose graph and a pose for every scan, and what it doubts of it.
//!
//! - Every scan is matched against the local map (the last keyframes' points) from the pose the
//!   odometry predicts: ICP from the prediction when it holds, else a correlative search by
//!   branch and bound ([`super::correlative`]) in a window whose heading half-width grows with
//!   the odometry's turn since the last match (once more over the widest window if it fails),
//!   refined by point-to-line ICP ([`super::icp`], Censi 2008), whose Hessian gives the match's
//!   covariance. A search with a distinct runner-up is counted as ambiguous; a failed one keeps
//!   the odometry.
//! - A matched scan that moved far enough from the last keyframe becomes a keyframe; unmatched
//!   scans only once the robot is lost (the local map then starts again); the others ride on
//!   their keyframe by their offset, so every scan keeps a pose.
//! - Keyframes are grouped into submaps. Every few keyframes, the finished submaps near the
//!   keyframe's estimate are searched for a loop closure in a window that grows with the
//!   distance travelled since the submap (Hess et al. 2016), accepted when the score and the ICP
//!   refinement agree; the candidates are group-tested for mutual consistency
//!   ([`super::consistency`]) before they enter the solve.
//! - The keyframe graph is optimized with Levenberg-Marquardt and dynamic covariance scaling on
//!   loop closures (Agarwal et al. 2013); the final solve is checked against the matched steps.
//! - Stretches it doubts (unmatched runs, weak matches, steps the final solve contradicts) are
//!   returned with the map.

use nalgebra::Matrix3;

use super::consistency::{largest_consistent_set, Cycle, Gate};
use super::correlative::{search, search_ranked, Window};
use super::icp::{IcpParams, Reference};
use super::likelihood::{GridTooLarge, LikelihoodGrid, Point};
use crate::error::{input, HitlError, Result};
use crate::factors::FactorClass;
use crate::graph::FactorGraph;
use crate::se2::Pose2;
use crate::solver::{optimize, Kernel, RobustKernels, SolverParams};
use crate::values::Values;

/// The front end's settings. Lengths in metres, angles in radians.
#[derive(Clone, Debug)]
pub struct SlamParams {
    pub keyframe_distance: f64,
    pub keyframe_angle: f64,
    /// Points farther than this from the robot are not matched.
    pub max_range: f64,
    /// At most this many points per scan in the correlative search (evenly taken), from those
    /// within `search_range` (the search's angular step is set by the farthest point).
    pub search_points: usize,
    pub search_range: f64,
    /// ICP from the odometry's prediction is kept, without a correlative search, when it pairs
    /// at least this share of the scan and stays well inside the local window.
    pub direct_overlap: f64,
    pub local_keyframes: usize,
    pub local_resolution: f64,
    /// The local search window for a scan whose odometry did not move ...
    pub local_window: Window,
    /// ... its angular half-width grown by this share [rad/rad] of the odometry's turn since
    /// the last matched scan ...
    pub local_turn_growth: f64,
    /// ... up to this.
    pub local_max_window: Window,
    /// A local match needs this correlative score (mean likelihood of its points).
    pub local_min_score: f64,
    /// Where ICP cannot refine the search's pose, the pose is kept only with this score.
    pub unrefined_score: f64,
    /// A match is ambiguous when a pose outside `distinct` of the best scores at least
    /// `ambiguity` times the best: the step is counted as ambiguous and keeps the best match
    /// (docs/ALGORITHM.md §F.1).
    pub ambiguity: f64,
    pub distinct: Window,
    /// Scans that could not be matched do not become keyframes until the odometry moved this
    /// far (or turned this much) from the last keyframe; the local map then starts again from
    /// that scan (the robot is lost in it).
    pub lost_distance: f64,
    pub lost_angle: f64,
    pub submap_keyframes: usize,
    pub loop_resolution: f64,
    pub loop_window: Window,
    /// The loop window grows by these fractions of the distance travelled since the submap
    /// (linear [m/m], angular [rad/m]) ...
    pub loop_growth: f64,
    pub loop_angular_growth: f64,
    /// ... up to these.
    pub loop_max_linear: f64,
    pub loop_max_angular: f64,
    /// A submap is searched when the keyframe's estimate is within the window plus this of the
    /// path the submap was built along.
    pub loop_reach: f64,
    pub loop_min_score: f64,
    /// Loop closures are searched at every this-many keyframes.
    pub loop_every: usize,
    /// An ICP refinement must pair at least this share of the scan.
    pub loop_min_overlap: f64,
    /// A loop closure's standard deviations are at least these ([m], [rad]): its submap is
    /// frozen in its first keyframe's frame, centimetres off in itself.
    pub loop_sigma_floor: [f64; 2],
    pub optimize_every: usize,
    /// DCS's Phi on loop closures (chi2 units).
    pub dcs: f64,
    /// The group test's gate on the cycle two loop closures close.
    pub consistency: Gate,
    /// The final solve contradicts a matched step between keyframes when it moves it by more
    /// than this ([m], [rad]) from its match.
    pub contradiction: [f64; 2],
    /// A match is weak when it pairs less than this share of what the recent matches pair.
    pub weak: f64,
}

impl Default for SlamParams {
    fn default() -> Self {
        Self {
            keyframe_distance: 0.2,
            keyframe_angle: 10f64.to_radians(),
            max_range: 20.0,
            search_points: 150,
            search_range: 10.0,
            direct_overlap: 0.7,
            local_keyframes: 15,
            local_resolution: 0.05,
            local_window: Window {
                linear: 0.25,
                angular: 8f64.to_radians(),
            },
            local_turn_growth: 0.25,
            local_max_window: Window {
                linear: 1.5,
                angular: 45f64.to_radians(),
            },
            local_min_score: 0.1,
            unrefined_score: 0.1,
            ambiguity: 0.9,
            distinct: Window {
                linear: 0.3,
                angular: 5f64.to_radians(),
            },
            lost_distance: 1.0,
            lost_angle: 45f64.to_radians(),
            submap_keyframes: 25,
            loop_resolution: 0.1,
            loop_window: Window {
                linear: 1.0,
                angular: 20f64.to_radians(),
            },
            loop_growth: 0.05,
            loop_angular_growth: 0.2f64.to_radians(),
            loop_max_linear: 5.0,
            loop_max_angular: 45f64.to_radians(),
            loop_reach: 2.0,
            loop_min_score: 0.55,
            loop_every: 3,
            loop_min_overlap: 0.6,
            loop_sigma_floor: [0.05, 1f64.to_radians()],
            optimize_every: 25,
            dcs: 10.0,
            consistency: Gate {
                reach: 10.0,
                linear: 0.2,
                linear_per_m: 0.03,
                angular: 2f64.to_radians(),
                angular_per_m: 0.3f64.to_radians(),
            },
            contradiction: [0.1, 2f64.to_radians()],
            weak: 0.5,
        }
    }
}

impl SlamParams {
    pub fn validate(&self) -> Result<()> {
        let positive = [
            ("keyframe_distance", self.keyframe_distance),
            ("max_range", self.max_range),
            ("local_resolution", self.local_resolution),
            ("loop_resolution", self.loop_resolution),
            ("loop_min_score", self.loop_min_score),
            ("dcs", self.dcs),
        ];
        for (name, v) in positive {
            if !(v.is_finite() && v > 0.0) {
                return input(format!("{name} must be a positive number, got {v}"));
            }
        }
        if self.local_keyframes == 0 || self.submap_keyframes < 2 || self.loop_every == 0 {
            return input("local_keyframes, loop_every must be >= 1 and submap_keyframes >= 2");
        }
        Ok(())
    }

    /// The local window after the odometry turned `since.turn` [rad] since the last matched
    /// scan (its heading error grows with the turn; the linear half-width stays).
    fn local_window_after(&self, since: Motion) -> Window {
        Window {
            linear: self.local_window.linear,
            angular: (self.local_window.angular + self.local_turn_growth * since.turn)
                .min(self.local_max_window.angular),
        }
    }
}

/// How a scan's pose was found.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
#[repr(u8)]
pub enum Step {
    /// ICP from the odometry's prediction (or the first scan).
    Direct = 0,
    /// The correlative search over the local window, refined by ICP.
    Searched = 1,
    /// The search found two distinct poses that explain the scan about as well: ICP from the
    /// odometry's prediction (the one nearest the odometry).
    Ambiguous = 2,
    /// No match (too few points, too low a score, or the refinement failed): the odometry.
    Failed = 3,
}

impl Step {
    pub fn matched(self) -> bool {
        !matches!(self, Step::Failed)
    }
}

/// Why a stretch of the map is doubtful.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
#[repr(u8)]
pub enum Doubt {
    /// Scans could not be matched over a keyframe's worth of motion or more: their poses are
    /// the odometry's.
    Unmatched = 0,
    /// The final solve bends steps between keyframes far from their matches: the loop
    /// closures and the local matches disagree.
    Contradicted = 1,
    /// Matches that paired far fewer of their points than the recent ones: scans that fit the
    /// local map only in part.
    Weak = 2,
    /// Poses only the widest search reached, far from the odometry's prediction, on a match
    /// that is ambiguous or weak: a glitch of the odometry, or scans from elsewhere.
    Jump = 3,
}

/// A doubtful stretch: scans `first..=last`.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct Doubtful {
    pub first: usize,
    pub last: usize,
    pub why: Doubt,
}

/// What became of a loop closure candidate.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
#[repr(u8)]
pub enum LoopStatus {
    /// In the graph (its final weight says how far the solve trusted it).
    Solved = 0,
    /// Set aside before any solve: inconsistent with the other closures of its group.
    Inconsistent = 1,
}

/// A loop closure found by the search: keyframe `from` (a submap's first) to keyframe `to`.
#[derive(Clone, Debug)]
pub struct LoopClosure {
    pub from: usize,
    pub to: usize,
    pub measurement: Pose2,
    pub information: [[f64; 3]; 3],
    pub score: f64,
    /// The final solve's robust weight (1 = fully trusted); below 0.5 it counts as rejected; 0
    /// for a closure set aside.
    pub weight: f64,
    pub status: LoopStatus,
}

/// The front end's answer.
#[derive(Clone, Debug)]
pub struct SlamResult {
    /// One per scan.
    pub poses: Vec<Pose2>,
    /// How each scan was matched.
    pub steps: Vec<Step>,
    /// The share of each scan's points its match paired with the local map (NaN: no match).
    pub overlap: Vec<f64>,
    /// Scan index of each keyframe.
    pub keyframes: Vec<usize>,
    /// Per scan k >= 1: the information of the step k-1 -> k (from its match's covariance).
    pub step_information: Vec<[[f64; 3]; 3]>,
    pub loops: Vec<LoopClosure>,
    pub doubtful: Vec<Doubtful>,
    pub submaps: usize,
}

/// Odometry motion accumulated since some scan.
#[derive(Clone, Copy, Debug, Default)]
struct Motion {
    distance: f64,
    turn: f64,
}

impl Motion {
    fn add(&mut self, step: Pose2) {
        self.distance += step.translation_len();
        self.turn += step.theta.abs();
    }
}

struct Submap {
    /// Keyframe index of its first keyframe (the frame of `points`).
    origin: usize,
    points: Vec<Point>,
    normals: Vec<Option<[f64; 2]>>,
    grid: LikelihoodGrid,
    reference: Option<Reference>,
    /// Its keyframes' positions in its frame.
    path: Vec<Point>,
    /// The path length at the last keyframe a solved loop closure holds it to (0: none).
    tied: f64,
}

struct Keyframe {
    scan: usize,
    pose: Pose2,
    /// Path length travelled up to this keyframe.
    travelled: f64,
    /// Its scan's normals in its own frame, taken when it joined the local map.
    normals: Vec<Option<[f64; 2]>>,
}

/// The local map: the last keyframes' points in the world at their current estimates, ready
/// for ICP; its likelihood grid is built only when a scan needs the correlative search.
struct LocalMap {
    reference: Reference,
    points: Vec<Point>,
    grid: Option<LikelihoodGrid>,
}

fn information_of(cov: &[[f64; 3]; 3], fallback: [f64; 3]) -> [[f64; 3]; 3] {
    let m = Matrix3::from_fn(|i, j| cov[i][j]);
    match m.try_inverse() {
        Some(inv) if inv.iter().all(|v| v.is_finite()) && inv[(0, 0)] > 0.0 => {
            let mut o = [[0.0; 3]; 3];
            for i in 0..3 {
                for j in 0..3 {
                    o[i][j] = 0.5 * (inv[(i, j)] + inv[(j, i)]);
                }
            }
            o
        }
        _ => diagonal(fallback),
    }
}

fn diagonal(sigmas: [f64; 3]) -> [[f64; 3]; 3] {
    let mut o = [[0.0; 3]; 3];
    for i in 0..3 {
        o[i][i] = 1.0 / (sigmas[i] * sigmas[i]);
    }
    o
}

/// The information of an unmatched motion: the odometry's, loose enough that loop closures
/// and later matches correct it (5 cm + 20% of the distance; 2 deg + 20% of the turn + 2 deg
/// per metre).
fn odometry_information(m: Motion) -> [[f64; 3]; 3] {
    let t = 0.05 + 0.2 * m.distance;
    let r = 2f64.to_radians() + 0.2 * m.turn + 2f64.to_radians() * m.distance;
    diagonal([t, t, r])
}

fn subsample(points: &[Point], n: usize) -> Vec<Point> {
    if points.len() <= n {
        return points.to_vec();
    }
    let step = points.len() as f64 / n as f64;
    (0..n).map(|k| points[(k as f64 * step) as usize]).collect()
}

/// The points a correlative search scores: those within `search_range` (the angular step of
/// the search shrinks with the farthest point), at most `search_points` of them.
fn search_points(scan: &[Point], params: &SlamParams) -> Vec<Point> {
    let near: Vec<Point> = scan
        .iter()
        .copied()
        .filter(|p| p[0].hypot(p[1]) <= params.search_range)
        .collect();
    subsample(
        if near.len() >= 10 { &near } else { scan },
        params.search_points,
    )
}

fn to_array(p: Pose2) -> [f64; 3] {
    [p.x, p.y, p.theta]
}

trait Length {
    fn translation_len(self) -> f64;
}

impl Length for Pose2 {
    fn translation_len(self) -> f64 {
        self.x.hypot(self.y)
    }
}

fn within(p: Pose2, w: Window) -> bool {
    p.translation_len() <= w.linear && p.theta.abs() <= w.angular
}

/// Runs the front end over `scans` (robot-frame points per scan) with their `odometry` poses
/// (any frame: only their steps are used). `progress(done)` is called every few hundred scans.
pub fn run(
    scans: &[Vec<Point>],
    odometry: &[Pose2],
    params: &SlamParams,
    progress: &mut dyn FnMut(usize),
) -> Result<SlamResult> {
    params.validate()?;
    let n = scans.len();
    if odometry.len() != n {
        return input(format!("{} odometry poses for {n} scans", odometry.len()));
    }
    if n == 0 {
        return input("the log has no scans");
    }
    if let Some(k) = odometry.iter().position(|p| !p.is_finite()) {
        return input(format!("odometry pose {k} is not finite"));
    }
    let scans: Vec<Vec<Point>> = scans
        .iter()
        .map(|s| {
            s.iter()
                .copied()
                .filter(|p| {
                    p[0].is_finite() && p[1].is_finite() && p[0].hypot(p[1]) <= params.max_range
                })
                .collect()
        })
        .collect();
    let icp = IcpParams {
        search: 0.0,
        max_pair_distance: 0.3,
        min_pair_distance: 0.05,
        iterations: 30,
        min_overlap: 0.3,
        sigma_floor: [0.005, 0.1f64.to_radians()],
        ..IcpParams::default()
    };
    let fallback = [0.1, 0.1, 2f64.to_radians()];
    let loop_icp = IcpParams {
        sigma_floor: params.loop_sigma_floor,
        ..icp.clone()
    };
    // ICP from the prediction is abandoned early where it will not pair the share a direct
    // match needs (on Freiburg 079 most scans see beyond the local map and go on to the search).
    let direct_icp = IcpParams {
        abandon_below: params.direct_overlap,
        ..icp.clone()
    };

    let mut poses = vec![Pose2::IDENTITY; n];
    let mut steps = vec![Step::Direct; n];
    // Per scan: the share of its points its match paired with the local map (NaN: none).
    let mut overlap = vec![f64::NAN; n];
    // Per scan: placed by a doubtful jump (`Doubt::Jump`).
    let mut jumps = vec![false; n];
    // Per scan: (keyframe index, offset from it) for non-keyframes.
    let mut riders: Vec<(usize, Pose2)> = vec![(0, Pose2::IDENTITY); n];
    let mut step_information = vec![diagonal(fallback); n];
    let mut keyframes: Vec<Keyframe> = Vec::new();
    let mut kf_edges: Vec<(usize, usize, Pose2, [[f64; 3]; 3])> = Vec::new();
    // Which keyframe edges are matched (the keyframe's own scan was matched).
    let mut kf_edge_matched: Vec<bool> = Vec::new();
    let mut loops: Vec<LoopClosure> = Vec::new();
    let mut groups = Groups::default();
    let mut submaps: Vec<Submap> = Vec::new();
    let mut local: Option<LocalMap> = None;
    // The local map holds keyframes from this one on (it starts again where the robot was lost).
    let mut local_first = 0usize;
    let mut since_optimize = 0usize;
    let mut travelled = 0.0;
    // The odometry's motion since the last matched scan, and since the last keyframe.
    let mut since_match = Motion::default();
    let mut since_keyframe = Motion::default();
    let mut recent_overlap = RecentOverlap::default();

    for k in 0..n {
        let odo_step = if k == 0 {
            Pose2::IDENTITY
        } else {
            odometry[k - 1].between(odometry[k])
        };
        let predicted = if k == 0 {
            odometry[0]
        } else {
            poses[k - 1].compose(odo_step)
        };
        travelled += odo_step.translation_len();
        since_match.add(odo_step);
        since_keyframe.add(odo_step);
        let scan = &scans[k];
        let mut pose = predicted;
        let mut info = odometry_information(since_match);
        let mut step = if k == 0 { Step::Direct } else { Step::Failed };
        if let Some(map) = local.as_mut() {
            if scan.len() >= 10 {
                let window = params.local_window_after(since_match);
                let prediction = Prediction {
                    pose: predicted,
                    information: info,
                    window,
                    recent: &recent_overlap,
                };
                let (found, how, paired, jumped) =
                    match_local(map, scan, &prediction, params, &icp, &direct_icp)?;
                step = how;
                overlap[k] = paired;
                jumps[k] = jumped;
                if how.matched() && !paired.is_nan() {
                    recent_overlap.push(paired);
                }
                if let Some((p, cov)) = found {
                    pose = p;
                    info = information_of(&cov, fallback);
                }
            }
        }
        if step.matched() {
            since_match = Motion::default();
        }
        poses[k] = pose;
        steps[k] = step;
        step_information[k] = info;
        let new_keyframe = match keyframes.last() {
            None => true,
            Some(last) => {
                let d = last.pose.between(pose);
                if step.matched() {
                    d.translation_len() >= params.keyframe_distance
                        || d.theta.abs() >= params.keyframe_angle
                } else {
                    since_keyframe.distance >= params.lost_distance
                        || since_keyframe.turn >= params.lost_angle
                }
            }
        };
        if !new_keyframe {
            let last = keyframes.len() - 1;
            riders[k] = (last, keyframes[last].pose.between(pose));
            continue;
        }
        let kf = keyframes.len();
        if let Some(prev) = keyframes.last() {
            // The matched step from the previous keyframe: its information is that of the
            // match (the local map is the previous keyframes' own points); an unmatched one
            // carries the odometry's since that keyframe.
            let edge_info = if step.matched() {
                info
            } else {
                odometry_information(since_keyframe)
            };
            kf_edges.push((kf - 1, kf, prev.pose.between(pose), edge_info));
            kf_edge_matched.push(step.matched());
        }
        if !step.matched() && kf > 0 {
            local_first = kf; // lost: the local map starts again from here
        }
        since_keyframe = Motion::default();
        keyframes.push(Keyframe {
            scan: k,
            pose,
            travelled,
            normals: Vec::new(),
        });
        riders[k] = (kf, Pose2::IDENTITY);
        since_optimize += 1;

        // Loop closures against finished submaps near the estimate.
        if kf % params.loop_every == 0 && scan.len() >= 10 && step.matched() {
            let sparse = search_points(scan, params);
            // A closure pairs as much of the scan as the local matches do here, up to
            // `loop_min_overlap`.
            let loop_overlap = recent_overlap
                .median()
                .map_or(params.loop_min_overlap, |m| m.min(params.loop_min_overlap));
            for sm in submaps.iter_mut() {
                if kf < sm.origin + params.submap_keyframes + params.local_keyframes {
                    continue; // the last submaps: their match is the local map's, not a loop
                }
                let origin = &keyframes[sm.origin];
                // The path since the submap, or since the last closure the solve holds it to.
                let since = (travelled - origin.travelled.max(sm.tied)).max(0.0);
                let window = Window {
                    linear: (params.loop_window.linear + params.loop_growth * since)
                        .min(params.loop_max_linear),
                    angular: (params.loop_window.angular + params.loop_angular_growth * since)
                        .min(params.loop_max_angular),
                };
                // Near the path the submap was built along (its keyframes' positions).
                let here = origin.pose.between(pose).translation();
                let near = sm.path.iter().any(|q| {
                    (q[0] - here[0]).hypot(q[1] - here[1]) <= window.linear + params.loop_reach
                });
                if !near {
                    continue;
                }
                let guess = origin.pose.between(pose);
                let Some(found) = search(
                    &sm.grid,
                    &sparse,
                    to_array(guess),
                    window,
                    params.loop_min_score,
                ) else {
                    continue;
                };
                let reference = sm.reference.get_or_insert_with(|| {
                    Reference::with_normals(&sm.points, &sm.normals, icp.normal_radius)
                });
                let refined = reference.icp(scan, found.pose, &loop_icp);
                let jump = Pose2::from_array(found.pose).between(Pose2::from_array(refined.pose));
                if !(refined.ok
                    && refined.overlap >= loop_overlap
                    && jump.translation_len() <= 2.0 * params.loop_resolution
                    && jump.theta.abs() <= 3f64.to_radians())
                {
                    continue;
                }
                groups.pending.push(LoopClosure {
                    from: sm.origin,
                    to: kf,
                    measurement: Pose2::from_array(refined.pose),
                    information: information_of(&refined.covariance, fallback),
                    score: found.score,
                    weight: 1.0,
                    status: LoopStatus::Solved,
                });
            }
        }

        if since_optimize >= params.optimize_every && !groups.pending.is_empty() {
            if groups.test(&keyframes, &mut loops, params) {
                optimize_keyframes(&mut keyframes, &kf_edges, &mut loops, params)?;
                poses[k] = keyframes[kf].pose;
                // The solve holds each submap to the keyframes it closed on: from there on its
                // relative pose drifts with the path since then, not since the submap.
                for l in loops.iter().filter(|l| l.weight >= 0.5) {
                    // Submaps are in the order of their origins.
                    if let Ok(i) = submaps.binary_search_by_key(&l.from, |sm| sm.origin) {
                        submaps[i].tied = submaps[i].tied.max(keyframes[l.to].travelled);
                    }
                }
            }
            since_optimize = 0;
        }

        // The local map: the last keyframes' points in the world, at the current estimates;
        // the new keyframe's normals are taken among them once, and kept in its frame.
        let first = keyframes
            .len()
            .saturating_sub(params.local_keyframes)
            .max(local_first);
        let mut pts = Vec::new();
        let mut known = Vec::new();
        for key in &keyframes[first..kf] {
            let (c, s) = key.pose.cos_sin();
            pts.extend(scans[key.scan].iter().map(|p| key.pose.transform_point(*p)));
            known.extend(
                key.normals
                    .iter()
                    .map(|m| m.map(|v| [c * v[0] - s * v[1], s * v[0] + c * v[1]])),
            );
        }
        pts.extend(scans[k].iter().map(|p| pose.transform_point(*p)));
        let reference = Reference::with_normals(&pts, &known, icp.normal_radius);
        let (c, s) = pose.cos_sin();
        keyframes[kf].normals = reference.normals()[known.len()..]
            .iter()
            .map(|m| m.map(|v| [c * v[0] + s * v[1], -s * v[0] + c * v[1]]))
            .collect();
        // Checked now, built when a scan needs it: a grid too large means a pose far off. The
        // keyframe before is always in the check, also where the local map starts again: a
        // jump too far for one grid is damaged data, not a place the robot got lost in.
        let check_from = first.min(kf.saturating_sub(1));
        let mut span = std::borrow::Cow::Borrowed(&pts[..]);
        if check_from < first {
            let mut wider: Vec<Point> = keyframes[check_from..first]
                .iter()
                .flat_map(|key| scans[key.scan].iter().map(|p| key.pose.transform_point(*p)))
                .collect();
            wider.extend_from_slice(&pts);
            span = std::borrow::Cow::Owned(wider);
        }
        LikelihoodGrid::check_size(&span, params.local_resolution, params.local_resolution, 3)
            .map_err(|e| far_off(&keyframes[check_from..], n, "the local map", e))?;
        local = Some(LocalMap {
            reference,
            points: pts,
            grid: None,
        });

        // A submap is finished every `submap_keyframes` keyframes.
        if (kf + 1) % params.submap_keyframes == 0 {
            let origin = kf + 1 - params.submap_keyframes;
            let o = keyframes[origin].pose;
            let mut pts = Vec::new();
            let mut normals = Vec::new();
            for key in &keyframes[origin..=kf] {
                let rel = o.between(key.pose);
                let (c, s) = rel.cos_sin();
                pts.extend(scans[key.scan].iter().map(|p| rel.transform_point(*p)));
                normals.extend(
                    key.normals
                        .iter()
                        .map(|m| m.map(|v| [c * v[0] - s * v[1], s * v[0] + c * v[1]])),
                );
            }
            let path = keyframes[origin..=kf]
                .iter()
                .map(|key| o.between(key.pose).translation())
                .collect();
            let grid = LikelihoodGrid::new(&pts, params.loop_resolution, params.loop_resolution, 5)
                .map_err(|e| far_off(&keyframes[origin..=kf], n, "a submap", e))?;
            submaps.push(Submap {
                origin,
                grid,
                points: pts,
                normals,
                reference: None,
                path,
                tied: 0.0,
            });
        }
        if k % 500 == 0 {
            progress(k);
        }
    }
    groups.test(&keyframes, &mut loops, params);
    if loops.iter().any(|l| l.status == LoopStatus::Solved) {
        optimize_keyframes(&mut keyframes, &kf_edges, &mut loops, params)?;
    }
    for k in 0..n {
        let (kf, offset) = riders[k];
        poses[k] = keyframes[kf].pose.compose(offset);
    }
    let mut doubtful = unmatched_stretches(&steps, odometry, params);
    doubtful.extend(weak_stretches(&steps, &overlap, odometry, params));
    doubtful.extend(jump_stretches(&jumps));
    doubtful.extend(contradicted_stretches(
        &keyframes,
        &kf_edges,
        &kf_edge_matched,
        params,
    ));
    doubtful.sort_by_key(|d| (d.first, d.last));
    progress(n);
    Ok(SlamResult {
        poses,
        steps,
        overlap,
        keyframes: keyframes.iter().map(|k| k.scan).collect(),
        step_information,
        loops,
        doubtful,
        submaps: submaps.len(),
    })
}

/// What the odometry says of a scan before it is matched: its pose, the odometry's information
/// since the last match (the direct match's prior, docs §F.1), the search window that motion
/// asks for, and what the recent matches paired.
struct Prediction<'a> {
    pose: Pose2,
    information: [[f64; 3]; 3],
    window: Window,
    recent: &'a RecentOverlap,
}

/// Matches `scan` against the local map from `predicted`: ICP from the prediction when it
/// holds well inside the window, else the correlative search over the window (ambiguous when a
/// distinct pose scores about as well), refined by ICP. The pose and covariance when matched,
/// how, the share of the scan paired, and whether the pose is a doubtful jump (`Doubt::Jump`).
#[allow(clippy::type_complexity)]
fn match_local(
    map: &mut LocalMap,
    scan: &[Point],
    prediction: &Prediction<'_>,
    params: &SlamParams,
    icp: &IcpParams,
    direct_icp: &IcpParams,
) -> Result<(Option<(Pose2, [[f64; 3]; 3])>, Step, f64, bool)> {
    let (predicted, window) = (prediction.pose, prediction.window);
    let direct = map.reference.icp_with_prior(
        scan,
        to_array(predicted),
        Some(&prediction.information),
        direct_icp,
    );
    let moved = predicted.between(Pose2::from_array(direct.pose));
    let half = Window {
        linear: 0.5 * window.linear,
        angular: 0.5 * window.angular,
    };
    if direct.ok && direct.overlap >= params.direct_overlap && within(moved, half) {
        return Ok((
            Some((Pose2::from_array(direct.pose), direct.covariance)),
            Step::Direct,
            direct.overlap,
            false,
        ));
    }
    if map.grid.is_none() {
        let grid = LikelihoodGrid::new(
            &map.points,
            params.local_resolution,
            params.local_resolution,
            3,
        )
        .map_err(|e| HitlError::Input(format!("the local map of the front end: {e}")))?;
        map.grid = Some(grid);
    }
    let grid = map.grid.as_ref().expect("built above");
    let sparse = search_points(scan, params);
    // The window the motion asks for, then once the widest: an odometry glitch (a heading
    // jump the odometry did not report as motion) falls outside the first.
    let mut windows = vec![window];
    if window.linear < params.local_max_window.linear
        || window.angular < params.local_max_window.angular
    {
        windows.push(params.local_max_window);
    }
    let last = windows.len() - 1;
    for (i, w) in windows.into_iter().enumerate() {
        let Some(ranked) = search_ranked(
            grid,
            &sparse,
            to_array(predicted),
            w,
            params.local_min_score,
            Some((params.distinct, params.ambiguity)),
        ) else {
            continue;
        };
        if ranked.on_edge && i < last {
            // The peak is at the window's border: it may lie beyond (a glitch of the
            // odometry larger than the motion's window), so the widest window decides.
            continue;
        }
        let how = if ranked.runner_up.is_some() {
            Step::Ambiguous
        } else {
            Step::Searched
        };
        let start = ranked.best.pose;
        let refined = map.reference.icp(scan, start, icp);
        let moved = Pose2::from_array(start).between(Pose2::from_array(refined.pose));
        let found = if refined.ok && within(moved, params.local_window) {
            (Pose2::from_array(refined.pose), refined.covariance)
        } else if ranked.best.score >= params.unrefined_score {
            // The search's own pose, known to its lattice: a cell and a rotation step.
            let r = params.local_resolution;
            let a = 2f64.to_radians();
            let cov = [[r * r, 0.0, 0.0], [0.0, r * r, 0.0], [0.0, 0.0, a * a]];
            (Pose2::from_array(start), cov)
        } else {
            continue;
        };
        // A pose only the widest window reached says the odometry jumped; on a match that is
        // not clear (ambiguous, or pairing under half what matches here pair) it is doubtful.
        let jump = i > 0 && !within(predicted.between(found.0), window);
        let doubtful_jump = jump
            && (ranked.runner_up.is_some()
                || prediction
                    .recent
                    .median()
                    .is_some_and(|q| refined.overlap < params.weak * q));
        return Ok((Some(found), how, refined.overlap, doubtful_jump));
    }
    Ok((None, Step::Failed, 0.0, false))
}

/// Loop closure candidates waiting for the group test: those found since the last test.
#[derive(Default)]
struct Groups {
    pending: Vec<LoopClosure>,
}

impl Groups {
    /// The group test (module `consistency`) over the waiting candidates: when the largest
    /// mutually consistent set has two or more, it joins `loops` and the candidates that
    /// contradict it are set aside (in `loops`, weight 0, never solved); otherwise every
    /// candidate joins and the solve's robust kernel weighs them. Whether any joined.
    fn test(
        &mut self,
        keyframes: &[Keyframe],
        loops: &mut Vec<LoopClosure>,
        params: &SlamParams,
    ) -> bool {
        let all: Vec<LoopClosure> = std::mem::take(&mut self.pending);
        if all.is_empty() {
            return false;
        }
        let cycles: Vec<Cycle> = all
            .iter()
            .map(|l| Cycle {
                from: keyframes[l.from].pose,
                to: keyframes[l.to].pose,
                from_travelled: keyframes[l.from].travelled,
                to_travelled: keyframes[l.to].travelled,
                measurement: l.measurement,
            })
            .collect();
        let set = largest_consistent_set(&cycles, &params.consistency);
        let mut joined = false;
        for (i, mut l) in all.into_iter().enumerate() {
            if set.len() < 2 || set.binary_search(&i).is_ok() {
                joined = true;
            } else {
                l.status = LoopStatus::Inconsistent;
                l.weight = 0.0;
            }
            loops.push(l);
        }
        joined
    }
}

/// Runs of scans placed by doubtful jumps.
fn jump_stretches(jumps: &[bool]) -> Vec<Doubtful> {
    let mut out: Vec<Doubtful> = Vec::new();
    for (k, _) in jumps.iter().enumerate().filter(|(_, &j)| j) {
        match out.last_mut() {
            Some(last) if last.last + 1 == k => last.last = k,
            _ => out.push(Doubtful {
                first: k,
                last: k,
                why: Doubt::Jump,
            }),
        }
    }
    out
}

/// Runs of scans that could not be matched, over at least a keyframe's worth of odometry
/// motion (a shorter run is re-anchored by the next match against the same local map).
fn unmatched_stretches(steps: &[Step], odometry: &[Pose2], params: &SlamParams) -> Vec<Doubtful> {
    let mut out = Vec::new();
    let mut k = 1;
    while k < steps.len() {
        if steps[k].matched() {
            k += 1;
            continue;
        }
        let first = k;
        let mut motion = Motion::default();
        while k < steps.len() && !steps[k].matched() {
            motion.add(odometry[k - 1].between(odometry[k]));
            k += 1;
        }
        if motion.distance >= params.keyframe_distance || motion.turn >= params.keyframe_angle {
            out.push(Doubtful {
                first,
                last: k - 1,
                why: Doubt::Unmatched,
            });
        }
    }
    out
}

/// Runs of at least `WEAK_RUN` matched scans in a row whose matches paired less than
/// `params.weak` of the share the recent matches paired (the median of the last `WEAK_WINDOW`):
/// scans that fit the local map only in part, as ones from another place do. Relative, so that
/// a hall, where every match pairs little, is not doubtful for it; a run, because one scan
/// turning into a room it has not seen pairs little too.
fn weak_stretches(
    steps: &[Step],
    overlap: &[f64],
    odometry: &[Pose2],
    params: &SlamParams,
) -> Vec<Doubtful> {
    let mut out = Vec::new();
    let mut recent = RecentOverlap::default();
    let mut run: Option<(usize, usize, usize)> = None; // (first, last, weak scans)
    let mut close = |run: &mut Option<(usize, usize, usize)>| {
        if let Some((first, last, count)) = run.take() {
            let mut motion = Motion::default();
            for k in first.max(1)..=last {
                motion.add(odometry[k - 1].between(odometry[k]));
            }
            let moved =
                motion.distance >= params.keyframe_distance || motion.turn >= params.keyframe_angle;
            if count >= WEAK_RUN && moved {
                out.push(Doubtful {
                    first,
                    last,
                    why: Doubt::Weak,
                });
            }
        }
    };
    for (k, (&step, &q)) in steps.iter().zip(overlap).enumerate() {
        if !step.matched() || q.is_nan() {
            continue;
        }
        if let Some(median) = recent.median() {
            if q < params.weak * median {
                run = Some(match run {
                    Some((first, _, count)) => (first, k, count + 1),
                    None => (k, k, 1),
                });
                continue; // a weak match does not lower the bar for the next
            }
        }
        close(&mut run);
        recent.push(q);
    }
    close(&mut run);
    out
}

const WEAK_RUN: usize = 3;
const WEAK_WINDOW: usize = 50;

/// The shares of their scans that the last `WEAK_WINDOW` matches paired. Their median is what a
/// match pairs in this place with this laser: most of the scan in an office, a third where the
/// beams are sparse and the walls far.
#[derive(Default)]
struct RecentOverlap(std::collections::VecDeque<f64>);

impl RecentOverlap {
    fn push(&mut self, q: f64) {
        self.0.push_back(q);
        if self.0.len() > WEAK_WINDOW {
            self.0.pop_front();
        }
    }

    /// The median, once half the window is filled.
    fn median(&self) -> Option<f64> {
        if self.0.len() < WEAK_WINDOW / 2 {
            return None;
        }
        let mut sorted: Vec<f64> = self.0.iter().copied().collect();
        sorted.sort_by(f64::total_cmp);
        Some(sorted[sorted.len() / 2])
    }
}

/// Stretches between keyframes whose matched step the final solve moved by more than
/// `params.contradiction` (merged when adjacent).
fn contradicted_stretches(
    keyframes: &[Keyframe],
    edges: &[(usize, usize, Pose2, [[f64; 3]; 3])],
    matched: &[bool],
    params: &SlamParams,
) -> Vec<Doubtful> {
    let mut out: Vec<Doubtful> = Vec::new();
    for ((i, j, z, _), &m) in edges.iter().zip(matched) {
        if !m {
            continue;
        }
        let solved = keyframes[*i].pose.between(keyframes[*j].pose);
        let r = z.between(solved);
        if r.translation_len() <= params.contradiction[0]
            && r.theta.abs() <= params.contradiction[1]
        {
            continue;
        }
        let (first, last) = (keyframes[*i].scan, keyframes[*j].scan);
        match out.last_mut() {
            Some(d) if d.last >= first => d.last = last,
            _ => out.push(Doubtful {
                first,
                last,
                why: Doubt::Contradicted,
            }),
        }
    }
    out
}

/// The error for a grid over `keys` (the last being the newest keyframe) that would be too
/// large: the newest keyframe's jump from the one before it is what grew the grid past the
/// limit (the grid before it was built fine), so both scans are named, counted from 1 as in the
/// log.
fn far_off(keys: &[Keyframe], scans: usize, what: &str, e: GridTooLarge) -> HitlError {
    let advice = "a pose far from the others (a damaged line or an odometry jump in the log?): \
                  check the log at those scans, or split it there";
    let last = keys.last();
    let before = keys.len().checked_sub(2).and_then(|k| keys.get(k));
    let (Some(last), Some(before)) = (last, before) else {
        return HitlError::Input(format!(
            "{what} of the front end is too large to build: {e}; {advice}"
        ));
    };
    let jump = before.pose.between(last.pose).translation_len();
    HitlError::Input(format!(
        "scan {} of {scans} is at ({:.6e}, {:.6e}) m, {jump:.3e} m from scan {} (the keyframe \
         before it); {what} of the front end over them is too large to build: {e}; {advice}",
        last.scan + 1,
        last.pose.x,
        last.pose.y,
        before.scan + 1,
    ))
}

/// Optimizes the keyframe graph, DCS on the loop closures; updates the keyframes' poses and the
/// closures' weights.
fn optimize_keyframes(
    keyframes: &mut [Keyframe],
    odometry: &[(usize, usize, Pose2, [[f64; 3]; 3])],
    loops: &mut [LoopClosure],
    params: &SlamParams,
) -> Result<()> {
    let m = keyframes.len();
    let mut edges = Vec::with_capacity(odometry.len() + loops.len());
    let mut z = Vec::with_capacity(edges.capacity());
    let mut info = Vec::with_capacity(edges.capacity());
    for (i, j, meas, inf) in odometry {
        edges.push((*i, *j));
        z.push(to_array(*meas));
        info.push(*inf);
    }
    let solved: Vec<usize> = (0..loops.len())
        .filter(|&i| loops[i].status == LoopStatus::Solved)
        .collect();
    for &i in &solved {
        let l = &loops[i];
        edges.push((l.from, l.to));
        z.push(to_array(l.measurement));
        info.push(l.information);
    }
    let mut graph = FactorGraph::from_edges(m, &edges, &z, &info, 0)?;
    let mut values = Values::from_poses(keyframes.iter().map(|k| k.pose).collect());
    let solver = SolverParams {
        max_iterations: 50,
        robust: RobustKernels::none().with(FactorClass::LoopClosure, Kernel::Dcs(params.dcs)),
        ..SolverParams::default()
    };
    let report = optimize(&mut graph, &mut values, &solver)?;
    for (k, p) in keyframes.iter_mut().zip(values.poses) {
        k.pose = p;
    }
    let first_loop = odometry.len();
    for (&i, w) in solved.iter().zip(report.weights.iter().skip(first_loop)) {
        loops[i].weight = *w;
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    fn wall() -> Vec<Point> {
        (0..40).map(|k| [2.0, -1.0 + 0.05 * k as f64]).collect()
    }

    #[test]
    fn a_pose_far_from_the_others_is_an_input_error_naming_it_not_an_allocation() {
        for far in [1e6, 1e9, 1e300] {
            let scans = vec![wall(); 4];
            let odometry = [0.0, 0.1, far, 0.3].map(|x| Pose2::new(x, 0.0, 0.0));
            let err = run(&scans, &odometry, &SlamParams::default(), &mut |_| {}).unwrap_err();
            let HitlError::Input(msg) = &err else {
                panic!("{far}: {err:?}");
            };
            // Scan 2 rides on scan 1's keyframe (0.1 m); scan 3 is the far one.
            assert!(msg.contains("scan 3 of 4"), "{msg}");
            assert!(msg.contains("from scan 1 "), "{msg}");
            assert!(msg.contains("split it"), "{msg}");
        }
    }
}
