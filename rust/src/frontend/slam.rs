//! The scan-matching front end (docs/ALGORITHM.md §F): a raw laser log (scans with their
//! odometry) to a pose graph and a pose for every scan.
//!
//! - Every scan is matched against the local map (the last keyframes' points) from the pose the
//!   odometry predicts: correlative search by branch and bound in a small window on a likelihood
//!   field ([`super::correlative`]), refined by point-to-line ICP ([`super::icp`], Censi 2008),
//!   whose Hessian gives the match's covariance.
//! - A scan that moved far enough from the last keyframe (distance or turn) becomes a keyframe;
//!   the others ride on their keyframe by their matched offset, so every scan keeps a pose.
//! - Keyframes are grouped into submaps (points in the frame of the submap's first keyframe, on
//!   a coarser likelihood field). Every few keyframes, the finished submaps near the keyframe's
//!   estimate are searched for a loop closure in a window that grows with the distance
//!   travelled since the submap (branch and bound over the whole window, as Hess et al. 2016),
//!   accepted when the score and the ICP refinement agree.
//! - The keyframe graph (matched odometry plus loop closures) is optimized with the solver's
//!   Levenberg-Marquardt and dynamic covariance scaling on loop closures (Agarwal et al. 2013),
//!   whenever closures arrived and at the end; loop closures the solve down-weights below one
//!   half are reported as rejected.

use nalgebra::Matrix3;

use super::correlative::{search, Window};
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
    pub local_window: Window,
    pub submap_keyframes: usize,
    pub loop_resolution: f64,
    pub loop_window: Window,
    /// The loop window grows by this fraction of the distance travelled since the submap.
    pub loop_growth: f64,
    pub loop_max_linear: f64,
    /// A submap is searched when the keyframe's estimate is within the window plus this of the
    /// path the submap was built along.
    pub loop_reach: f64,
    pub loop_min_score: f64,
    /// Loop closures are searched at every this-many keyframes.
    pub loop_every: usize,
    /// An ICP refinement must pair at least this share of the scan.
    pub loop_min_overlap: f64,
    pub optimize_every: usize,
    /// DCS's Phi on loop closures (chi2 units).
    pub dcs: f64,
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
            submap_keyframes: 25,
            loop_resolution: 0.1,
            loop_window: Window {
                linear: 1.0,
                angular: 20f64.to_radians(),
            },
            loop_growth: 0.05,
            loop_max_linear: 5.0,
            loop_reach: 2.0,
            loop_min_score: 0.55,
            loop_every: 3,
            loop_min_overlap: 0.6,
            optimize_every: 25,
            dcs: 10.0,
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
}

/// A loop closure found by the search: keyframe scan `from` (a submap's first) to scan `to`.
#[derive(Clone, Debug)]
pub struct LoopClosure {
    pub from: usize,
    pub to: usize,
    pub measurement: Pose2,
    pub information: [[f64; 3]; 3],
    pub score: f64,
    /// The final solve's robust weight (1 = fully trusted); below 0.5 it counts as rejected.
    pub weight: f64,
}

/// The front end's answer.
#[derive(Clone, Debug)]
pub struct SlamResult {
    /// One per scan.
    pub poses: Vec<Pose2>,
    /// Scan index of each keyframe.
    pub keyframes: Vec<usize>,
    /// Per scan k >= 1: the information of the step k-1 -> k (from its match's covariance).
    pub step_information: Vec<[[f64; 3]; 3]>,
    pub loops: Vec<LoopClosure>,
    pub submaps: usize,
}

struct Submap {
    /// Keyframe index of its first keyframe (the frame of `points`).
    origin: usize,
    points: Vec<Point>,
    grid: LikelihoodGrid,
    reference: Option<Reference>,
    /// Its keyframes' positions in its frame.
    path: Vec<Point>,
}

struct Keyframe {
    scan: usize,
    pose: Pose2,
    /// Path length travelled up to this keyframe.
    travelled: f64,
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

    let mut poses = vec![Pose2::IDENTITY; n];
    // Per scan: (keyframe index, offset from it) for non-keyframes.
    let mut riders: Vec<(usize, Pose2)> = vec![(0, Pose2::IDENTITY); n];
    let mut step_information = vec![diagonal(fallback); n];
    let mut keyframes: Vec<Keyframe> = Vec::new();
    let mut kf_edges: Vec<(usize, usize, Pose2, [[f64; 3]; 3])> = Vec::new();
    let mut loops: Vec<LoopClosure> = Vec::new();
    let mut submaps: Vec<Submap> = Vec::new();
    let mut local: Option<(LikelihoodGrid, Reference)> = None;
    let mut closures_pending = 0usize;
    let mut since_optimize = 0usize;
    let mut travelled = 0.0;

    for k in 0..n {
        let predicted = if k == 0 {
            odometry[0]
        } else {
            poses[k - 1].compose(odometry[k - 1].between(odometry[k]))
        };
        if k > 0 {
            travelled += odometry[k - 1].between(odometry[k]).translation_len();
        }
        let scan = &scans[k];
        let mut pose = predicted;
        let mut info = diagonal(fallback);
        if let Some((grid, reference)) = &local {
            if scan.len() >= 10 {
                // ICP from the odometry's prediction first; the correlative search (the
                // expensive, robust start) only where that does not match well.
                let direct = reference.icp(scan, to_array(predicted), &icp);
                let moved = predicted.between(Pose2::from_array(direct.pose));
                let (start, refined) = if direct.ok
                    && direct.overlap >= params.direct_overlap
                    && moved.translation_len() <= 0.5 * params.local_window.linear
                    && moved.theta.abs() <= 0.5 * params.local_window.angular
                {
                    (to_array(predicted), direct)
                } else {
                    let sparse = search_points(scan, params);
                    let start =
                        search(grid, &sparse, to_array(predicted), params.local_window, 0.1)
                            .map_or(to_array(predicted), |f| f.pose);
                    (start, reference.icp(scan, start, &icp))
                };
                let moved = Pose2::from_array(start).between(Pose2::from_array(refined.pose));
                if refined.ok
                    && moved.translation_len() <= params.local_window.linear
                    && moved.theta.abs() <= params.local_window.angular
                {
                    pose = Pose2::from_array(refined.pose);
                    info = information_of(&refined.covariance, fallback);
                } else {
                    pose = Pose2::from_array(start);
                }
            }
        }
        poses[k] = pose;
        step_information[k] = info;
        let new_keyframe = match keyframes.last() {
            None => true,
            Some(last) => {
                let d = last.pose.between(pose);
                d.translation_len() >= params.keyframe_distance
                    || d.theta.abs() >= params.keyframe_angle
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
            // match (the local map is the previous keyframes' own points).
            kf_edges.push((kf - 1, kf, prev.pose.between(pose), info));
        }
        keyframes.push(Keyframe {
            scan: k,
            pose,
            travelled,
        });
        riders[k] = (kf, Pose2::IDENTITY);
        since_optimize += 1;

        // Loop closures against finished submaps near the estimate.
        if kf % params.loop_every == 0 && scan.len() >= 10 {
            let sparse = search_points(scan, params);
            for sm in submaps.iter_mut() {
                let origin = &keyframes[sm.origin];
                let since = (travelled - origin.travelled).max(0.0);
                let linear = (params.loop_window.linear + params.loop_growth * since)
                    .min(params.loop_max_linear);
                if kf < sm.origin + 2 * params.submap_keyframes {
                    continue; // the last submaps: their match is the local map's, not a loop
                }
                // Near the path the submap was built along (its keyframes' positions).
                let here = origin.pose.between(pose).translation();
                let near = sm
                    .path
                    .iter()
                    .any(|q| (q[0] - here[0]).hypot(q[1] - here[1]) <= linear + params.loop_reach);
                if !near {
                    continue;
                }
                let guess = origin.pose.between(pose);
                let window = Window {
                    linear,
                    angular: params.loop_window.angular,
                };
                let Some(found) = search(
                    &sm.grid,
                    &sparse,
                    to_array(guess),
                    window,
                    params.loop_min_score,
                ) else {
                    continue;
                };
                let reference = sm
                    .reference
                    .get_or_insert_with(|| Reference::new(&sm.points, icp.normal_radius));
                let refined = reference.icp(scan, found.pose, &icp);
                let jump = Pose2::from_array(found.pose).between(Pose2::from_array(refined.pose));
                if !(refined.ok
                    && refined.overlap >= params.loop_min_overlap
                    && jump.translation_len() <= 2.0 * params.loop_resolution
                    && jump.theta.abs() <= 3f64.to_radians())
                {
                    continue;
                }
                loops.push(LoopClosure {
                    from: sm.origin,
                    to: kf,
                    measurement: Pose2::from_array(refined.pose),
                    information: information_of(&refined.covariance, fallback),
                    score: found.score,
                    weight: 1.0,
                });
                closures_pending += 1;
            }
        }

        if closures_pending > 0 && since_optimize >= params.optimize_every {
            optimize_keyframes(&mut keyframes, &kf_edges, &mut loops, params)?;
            closures_pending = 0;
            since_optimize = 0;
            poses[k] = keyframes[kf].pose;
        }

        // The local map: the last keyframes' points in the world, at the current estimates.
        let first = keyframes.len().saturating_sub(params.local_keyframes);
        let mut pts = Vec::new();
        for key in &keyframes[first..] {
            pts.extend(scans[key.scan].iter().map(|p| key.pose.transform_point(*p)));
        }
        let grid = LikelihoodGrid::new(&pts, params.local_resolution, params.local_resolution, 3)
            .map_err(|e| far_off(&keyframes[first..], n, "the local map", e))?;
        local = Some((grid, Reference::new(&pts, icp.normal_radius)));

        // A submap is finished every `submap_keyframes` keyframes.
        if (kf + 1) % params.submap_keyframes == 0 {
            let origin = kf + 1 - params.submap_keyframes;
            let o = keyframes[origin].pose;
            let mut pts = Vec::new();
            for key in &keyframes[origin..=kf] {
                let rel = o.between(key.pose);
                pts.extend(scans[key.scan].iter().map(|p| rel.transform_point(*p)));
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
                reference: None,
                path,
            });
        }
        if k % 500 == 0 {
            progress(k);
        }
    }
    if !loops.is_empty() {
        optimize_keyframes(&mut keyframes, &kf_edges, &mut loops, params)?;
    }
    for k in 0..n {
        let (kf, offset) = riders[k];
        poses[k] = keyframes[kf].pose.compose(offset);
    }
    progress(n);
    Ok(SlamResult {
        poses,
        keyframes: keyframes.iter().map(|k| k.scan).collect(),
        step_information,
        loops,
        submaps: submaps.len(),
    })
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
    for l in loops.iter() {
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
    for (l, w) in loops.iter_mut().zip(report.weights.iter().skip(first_loop)) {
        l.weight = *w;
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
