//! Scan-to-scan matching: point-to-line ICP (after Censi 2008, with a Huber weight and a
//! shrinking correspondence gate), started from the best of a fan of rotations around the guess
//! (a heading guess off by tens of degrees, as after a gyro fault, is outside ICP's basin), with
//! a covariance from the Gauss-Newton Hessian and the residual variance.
//!
//! Convention: the match of `current` against `reference` is the pose `[x, y, theta]` of the
//! current scan's frame in the reference scan's frame, so a current point `c` lands at
//! `R(theta) c + (x, y)` among the reference points; for consecutive scans of a chain that is
//! `z_k = x_k^-1 x_(k+1)`, the odometry's own measurement.

use kd_tree::KdTree;
use nalgebra::{Matrix3, Vector3};
use rayon::prelude::*;

use crate::error::{HitlError, Result};
use crate::geometry::{principal_normal, weighted_scatter};
use crate::se2::{transform, wrap_angle};

/// The variance [m^2] of a point-to-line residual when weighed against a prior while iterating
/// (a centimetre: a laser's range noise and a wall's texture). Not the residuals' own variance,
/// which in the first iterations measures the misalignment and would let the prior hold the
/// pose back where the scan does constrain it.
const RESIDUAL_VARIANCE: f64 = 1e-4;

/// A translation direction is degenerate when the scan's information along it is below this
/// share of the information across it: a corridor whose ends are out of range, where only the
/// normals' noise (a degree or two of tilt) seems to constrain the pose along the axis.
const DEGENERATE: f64 = 0.02;

/// The projection that drops a degenerate translation direction of the Gauss-Newton Hessian `h`
/// (the identity where there is none), after Zhang, Kaess and Singh, "On degeneracy of
/// optimization-based state estimation problems", ICRA 2016: along it the prior decides.
fn constrained(h: &Matrix3<f64>) -> Matrix3<f64> {
    let (a, b, c) = (h[(0, 0)], h[(0, 1)], h[(1, 1)]);
    let half_trace = 0.5 * (a + c);
    let root = (0.25 * (a - c).powi(2) + b * b).sqrt();
    let (major, minor) = (half_trace + root, half_trace - root);
    if major.is_nan() || major <= 0.0 || minor >= DEGENERATE * major {
        return Matrix3::identity();
    }
    // The eigenvector of the minor eigenvalue.
    let v = if b.abs() > 1e-12 * major {
        let (x, y) = (minor - c, b);
        let n = x.hypot(y);
        [x / n, y / n]
    } else if a <= c {
        [1.0, 0.0]
    } else {
        [0.0, 1.0]
    };
    let p = Vector3::new(v[0], v[1], 0.0);
    Matrix3::identity() - p * p.transpose()
}

/// How scans are matched.
#[derive(Clone, Debug)]
pub struct IcpParams {
    /// Half-width of the fan of rotation guesses around the given heading [rad].
    pub search: f64,
    /// Spacing of the fan [rad].
    pub search_step: f64,
    /// Correspondence gate at the first iteration [m]; shrinks by 0.7 an iteration ...
    pub max_pair_distance: f64,
    /// ... down to this [m].
    pub min_pair_distance: f64,
    /// Huber threshold on point-to-line residuals [m].
    pub huber: f64,
    /// Neighbourhood radius for reference normals [m].
    pub normal_radius: f64,
    pub iterations: usize,
    /// A match is good when at least this fraction of the current points ...
    pub min_overlap: f64,
    /// ... and at least this many are paired at the end.
    pub min_pairs: usize,
    /// Standard deviations added to the Hessian's covariance (it is optimistic): [m], [rad].
    pub sigma_floor: [f64; 2],
    /// Stop, failed, once the gate is within twice its floor and fewer than this share of the
    /// points pair (0: never): a match that will not reach a share it is asked for is not
    /// iterated to the end.
    pub abandon_below: f64,
}

impl Default for IcpParams {
    fn default() -> Self {
        Self {
            search: 45f64.to_radians(),
            search_step: 1.5f64.to_radians(),
            max_pair_distance: 0.5,
            min_pair_distance: 0.1,
            huber: 0.05,
            normal_radius: 0.25,
            iterations: 40,
            min_overlap: 0.25,
            min_pairs: 25,
            sigma_floor: [0.02, 1.0f64.to_radians()],
            abandon_below: 0.0,
        }
    }
}

/// The outcome of one match.
#[derive(Clone, Debug, PartialEq)]
pub struct ScanMatch {
    /// Enough overlap and a well-posed Hessian: `pose` and `covariance` mean something.
    pub ok: bool,
    pub pose: [f64; 3],
    pub covariance: [[f64; 3]; 3],
    /// Fraction of the current scan's points paired with a reference line at the end.
    pub overlap: f64,
    /// Root mean square point-to-line residual of the paired points [m].
    pub rms: f64,
}

impl ScanMatch {
    fn failed(guess: [f64; 3]) -> Self {
        Self {
            ok: false,
            pose: guess,
            covariance: [[0.0; 3]; 3],
            overlap: 0.0,
            rms: f64::INFINITY,
        }
    }
}

/// The normal of the line through the neighbours of `p` within `radius`, if they form one.
fn normal_at(tree: &KdTree<([f64; 2], usize)>, p: &[f64; 2], radius: f64) -> Option<[f64; 2]> {
    let near: Vec<[f64; 2]> = tree
        .within_radius(p, radius)
        .into_iter()
        .map(|e| e.0)
        .collect();
    if near.len() < 3 {
        return None;
    }
    let (_, scatter) = weighted_scatter(&near, &vec![1.0; near.len()])?;
    // Eigenvalues of the 2x2 scatter: a line when the minor one is small.
    let [sxx, sxy, syy] = scatter;
    let half_trace = 0.5 * (sxx + syy);
    let root = (0.25 * (sxx - syy).powi(2) + sxy * sxy).sqrt();
    let (major, minor) = (half_trace + root, half_trace - root);
    if major <= 0.0 || minor > 0.05 * major {
        return None; // a corner or a blob, not a line
    }
    principal_normal(scatter)
}

/// A reference scan ready for matching: its points in an R*-tree, with a unit normal where its
/// neighbourhood is a line.
pub struct Reference {
    /// A k-d tree over `points`, each with its index.
    tree: KdTree<([f64; 2], usize)>,
    points: Vec<[f64; 2]>,
    normals: Vec<Option<[f64; 2]>>,
}

impl Reference {
    /// Every point's normal from its neighbours within `radius`.
    pub fn new(points: &[[f64; 2]], radius: f64) -> Self {
        Self::with_normals(points, &[], radius)
    }

    /// The first `known.len()` points take their normals from `known` (computed earlier, e.g.
    /// when their scan joined the map); the others get theirs from their neighbours within
    /// `radius` among all the points.
    pub fn with_normals(points: &[[f64; 2]], known: &[Option<[f64; 2]>], radius: f64) -> Self {
        let tree = KdTree::build_by_ordered_float(
            points.iter().enumerate().map(|(i, p)| (*p, i)).collect(),
        );
        let mut normals = known[..known.len().min(points.len())].to_vec();
        normals.extend(
            points[normals.len()..]
                .iter()
                .map(|p| normal_at(&tree, p, radius)),
        );
        Self {
            tree,
            points: points.to_vec(),
            normals,
        }
    }

    /// The unit normals of the points (None where the neighbourhood is not a line).
    pub fn normals(&self) -> &[Option<[f64; 2]>] {
        &self.normals
    }

    /// The nearest reference point to `q` and its squared distance.
    fn nearest(&self, q: [f64; 2]) -> (usize, f64) {
        match self.tree.nearest(&q) {
            Some(e) => (e.item.1, e.squared_distance),
            None => (0, f64::INFINITY),
        }
    }

    /// How many of `current` (every `stride`-th) land within `gate` of a reference point.
    fn score(&self, current: &[[f64; 2]], pose: [f64; 3], gate: f64, stride: usize) -> usize {
        let (c, s) = (pose[2].cos(), pose[2].sin());
        current
            .iter()
            .step_by(stride)
            .filter(|p| {
                let q = transform(c, s, [pose[0], pose[1]], **p);
                self.nearest(q).1 <= gate * gate
            })
            .count()
    }

    /// Point-to-line ICP from `start`; returns the pose, the final Hessian and its residuals.
    pub fn icp(&self, current: &[[f64; 2]], start: [f64; 3], p: &IcpParams) -> ScanMatch {
        self.icp_with_prior(current, start, None, p)
    }

    /// [`Reference::icp`] with a Gaussian prior on the pose centred on `start`, `information`
    /// its information (world frame, x y theta): a translation direction the scan does not
    /// constrain (`DEGENERATE`: along a corridor whose ends are out of range) is left to the
    /// prior alone, so the pose stays at `start` along it instead of sliding on the residuals'
    /// noise. The covariance returned is the scan's own, without the prior (the caller's graph
    /// holds the odometry).
    pub fn icp_with_prior(
        &self,
        current: &[[f64; 2]],
        start: [f64; 3],
        information: Option<&[[f64; 3]; 3]>,
        p: &IcpParams,
    ) -> ScanMatch {
        let prior = information.map(|m| Matrix3::from_fn(|i, j| m[i][j]));
        let offset = |pose: [f64; 3]| {
            Vector3::new(
                pose[0] - start[0],
                pose[1] - start[1],
                wrap_angle(pose[2] - start[2]),
            )
        };
        let mut pose = start;
        let mut gate = p.max_pair_distance;
        let mut last = (Matrix3::zeros(), 0usize, 0.0f64, 0.0f64);
        for iteration in 0..p.iterations {
            let (c, s) = (pose[2].cos(), pose[2].sin());
            let mut h = Matrix3::<f64>::zeros();
            let mut g = Vector3::<f64>::zeros();
            let (mut pairs, mut sq, mut wsum) = (0usize, 0.0, 0.0);
            for pt in current {
                let q = [
                    c * pt[0] - s * pt[1] + pose[0],
                    s * pt[0] + c * pt[1] + pose[1],
                ];
                let (item, d2) = self.nearest(q);
                if d2 > gate * gate {
                    continue;
                }
                let Some(n) = self.normals[item] else {
                    continue;
                };
                let r = self.points[item];
                let e = n[0] * (q[0] - r[0]) + n[1] * (q[1] - r[1]);
                let dq = [-s * pt[0] - c * pt[1], c * pt[0] - s * pt[1]];
                let j = Vector3::new(n[0], n[1], n[0] * dq[0] + n[1] * dq[1]);
                let w = if e.abs() <= p.huber {
                    1.0
                } else {
                    p.huber / e.abs()
                };
                h += w * j * j.transpose();
                g += w * e * j;
                pairs += 1;
                sq += w * e * e;
                wsum += w;
            }
            last = (h, pairs, sq, wsum);
            if pairs < 3 {
                break;
            }
            if gate <= 2.0 * p.min_pair_distance
                && (pairs as f64) < p.abandon_below * current.len() as f64
            {
                return ScanMatch {
                    overlap: pairs as f64 / current.len().max(1) as f64,
                    ..ScanMatch::failed(pose)
                };
            }
            let (a, b) = match prior {
                Some(prior) => {
                    let keep = constrained(&h);
                    let (h, g) = (keep * h * keep, keep * g);
                    (
                        h / RESIDUAL_VARIANCE + prior,
                        g / RESIDUAL_VARIANCE + prior * offset(pose),
                    )
                }
                None => (h, g),
            };
            let Some(step) = (a + Matrix3::identity() * 1e-9)
                .try_inverse()
                .map(|hi| hi * b)
            else {
                break;
            };
            pose = [
                pose[0] - step[0],
                pose[1] - step[1],
                wrap_angle(pose[2] - step[2]),
            ];
            let small = step[0].abs() < 1e-5 && step[1].abs() < 1e-5 && step[2].abs() < 1e-6;
            gate = (gate * 0.7).max(p.min_pair_distance);
            if small && gate <= p.min_pair_distance && iteration > 2 {
                break;
            }
        }
        let (h, pairs, sq, wsum) = last;
        let overlap = pairs as f64 / current.len().max(1) as f64;
        let rms = if wsum > 0.0 {
            (sq / wsum).sqrt()
        } else {
            f64::INFINITY
        };
        let dof = (pairs as f64 - 3.0).max(1.0);
        let variance = (sq / dof).max(1e-6);
        let Some(cov) = h.try_inverse().map(|hi| hi * variance) else {
            return ScanMatch {
                overlap,
                rms,
                ..ScanMatch::failed(pose)
            };
        };
        let [fs, fr] = p.sigma_floor;
        let mut covariance = [[0.0; 3]; 3];
        for i in 0..3 {
            for j in 0..3 {
                covariance[i][j] = cov[(i, j)];
            }
        }
        covariance[0][0] += fs * fs;
        covariance[1][1] += fs * fs;
        covariance[2][2] += fr * fr;
        let finite = covariance.iter().flatten().all(|v| v.is_finite());
        ScanMatch {
            ok: finite && pairs >= p.min_pairs && overlap >= p.min_overlap,
            pose,
            covariance,
            overlap,
            rms,
        }
    }
}

/// Matches `current` against `reference` from `guess` (see the module's convention).
pub fn match_scans(
    reference: &[[f64; 2]],
    current: &[[f64; 2]],
    guess: [f64; 3],
    params: &IcpParams,
) -> ScanMatch {
    if reference.len() < 3 || current.len() < 3 || !guess.iter().all(|v| v.is_finite()) {
        return ScanMatch::failed(guess);
    }
    let r = Reference::new(reference, params.normal_radius);
    // The fan: rotations around the guess, scored by how many points land near the reference.
    let stride = (current.len() / 120).max(1);
    let steps = (params.search / params.search_step.max(1e-6)).round() as i64;
    let mut best = (r.score(current, guess, 0.15, stride), 0i64);
    for k in -steps..=steps {
        if k == 0 {
            continue;
        }
        let cand = [
            guess[0],
            guess[1],
            wrap_angle(guess[2] + k as f64 * params.search_step),
        ];
        let score = r.score(current, cand, 0.15, stride);
        if score > best.0 || (score == best.0 && k.abs() < best.1.abs()) {
            best = (score, k);
        }
    }
    let from_fan = [
        guess[0],
        guess[1],
        wrap_angle(guess[2] + best.1 as f64 * params.search_step),
    ];
    let mut out = r.icp(current, from_fan, params);
    if best.1 != 0 {
        let plain = r.icp(current, guess, params);
        if (plain.overlap, -plain.rms) > (out.overlap, -out.rms) {
            out = plain;
        }
    }
    out
}

/// Matches every scan `k + 1` of a chain against scan `k` from `guesses[k]` (in parallel).
/// `offsets` (`N + 1`) delimit the scans in `points`.
pub fn match_chain(
    points: &[[f64; 2]],
    offsets: &[usize],
    guesses: &[[f64; 3]],
    params: &IcpParams,
) -> Result<Vec<ScanMatch>> {
    let n = offsets.len().saturating_sub(1);
    if offsets.is_empty() || offsets[n] != points.len() || offsets.windows(2).any(|w| w[0] > w[1]) {
        return Err(HitlError::Input(
            "offsets must rise from 0 to the number of points".into(),
        ));
    }
    if guesses.len() + 1 != n.max(1) {
        return Err(HitlError::Input(format!(
            "{} guesses for {n} scans; give one per consecutive pair",
            guesses.len()
        )));
    }
    Ok((0..guesses.len())
        .into_par_iter()
        .map(|k| {
            let reference = &points[offsets[k]..offsets[k + 1]];
            let current = &points[offsets[k + 1]..offsets[k + 2]];
            match_scans(reference, current, guesses[k], params)
        })
        .collect())
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A room's walls seen from `pose` (robot frame): points every 2 cm on a 6 x 4 m rectangle
    /// with a 1 m box, within 8 m.
    fn room(pose: [f64; 3]) -> Vec<[f64; 2]> {
        let walls: [([f64; 2], [f64; 2]); 6] = [
            ([0.0, 0.0], [6.0, 0.0]),
            ([6.0, 0.0], [6.0, 4.0]),
            ([6.0, 4.0], [0.0, 4.0]),
            ([0.0, 4.0], [0.0, 0.0]),
            ([2.0, 1.0], [3.0, 1.0]),
            ([3.0, 1.0], [3.0, 1.6]),
        ];
        let (c, s) = (pose[2].cos(), pose[2].sin());
        let mut out = Vec::new();
        for (a, b) in walls {
            let len: f64 = (b[0] - a[0]).hypot(b[1] - a[1]);
            let k = (len / 0.02) as usize;
            for i in 0..=k {
                let t = i as f64 / k as f64;
                let w = [a[0] + t * (b[0] - a[0]), a[1] + t * (b[1] - a[1])];
                let d = [w[0] - pose[0], w[1] - pose[1]];
                out.push([c * d[0] + s * d[1], -s * d[0] + c * d[1]]);
            }
        }
        out
    }

    fn between(a: [f64; 3], b: [f64; 3]) -> [f64; 3] {
        let (c, s) = (a[2].cos(), a[2].sin());
        let d = [b[0] - a[0], b[1] - a[1]];
        [
            c * d[0] + s * d[1],
            -s * d[0] + c * d[1],
            wrap_angle(b[2] - a[2]),
        ]
    }

    /// Two parallel walls 2 m apart along x, with a slight waviness (the normals tilt by about
    /// a degree, as real walls' do), 12 m long: a corridor whose ends are out of sight.
    fn corridor() -> Vec<[f64; 2]> {
        let mut out = Vec::new();
        for i in 0..600 {
            let x = -6.0 + 0.02 * i as f64;
            let wave = 0.004 * (x * 7.0).sin();
            out.push([x, -1.0 + wave]);
            out.push([x, 1.0 - wave]);
        }
        out
    }

    #[test]
    fn a_corridor_leaves_its_axis_to_the_prior_and_a_room_constrains_both_directions() {
        let walls = Reference::new(&corridor(), 0.25);
        let p = IcpParams {
            search: 0.0,
            max_pair_distance: 0.3,
            min_pair_distance: 0.05,
            ..IcpParams::default()
        };
        // The scan: the corridor's middle 6 m seen from (0.0, 0.05), started (and the prior
        // centred) 0.02 m off across and 0.02 m off along the axis, where the points cannot tell.
        let scan: Vec<[f64; 2]> = corridor()
            .into_iter()
            .filter(|q| q[0].abs() <= 3.0)
            .map(|q| [q[0], q[1] - 0.05])
            .collect();
        let start = [0.02, 0.07, 0.0];
        let information = [[400.0, 0.0, 0.0], [0.0, 400.0, 0.0], [0.0, 0.0, 800.0]];
        let m = walls.icp_with_prior(&scan, start, Some(&information), &p);
        assert!(m.ok, "{m:?}");
        assert!(
            (m.pose[1] - 0.05).abs() < 0.01,
            "across the axis the scan decides: {m:?}"
        );
        assert!(
            (m.pose[0] - start[0]).abs() < 0.01,
            "along it the prior: {m:?}"
        );
        // The Hessian's projection: a corridor's drops the axis, a room's keeps both.
        let mut h = Matrix3::zeros();
        h[(1, 1)] = 100.0;
        h[(0, 0)] = 0.5;
        let keep = constrained(&h);
        assert!((keep[(0, 0)]).abs() < 1e-12 && (keep[(1, 1)] - 1.0).abs() < 1e-12);
        h[(0, 0)] = 10.0;
        assert_eq!(constrained(&h), Matrix3::identity());
        // Rotated by 30 degrees, the corridor's axis is found as such.
        let (c, s) = (30f64.to_radians().cos(), 30f64.to_radians().sin());
        let r = Matrix3::new(c, -s, 0.0, s, c, 0.0, 0.0, 0.0, 1.0);
        let mut h = Matrix3::zeros();
        h[(1, 1)] = 100.0;
        h[(2, 2)] = 5.0;
        let keep = constrained(&(r * h * r.transpose()));
        let axis = Vector3::new(c, s, 0.0);
        assert!((keep * axis).norm() < 1e-9, "{keep}");
        let across = Vector3::new(-s, c, 0.0);
        assert!((keep * across - across).norm() < 1e-9, "{keep}");
    }

    #[test]
    fn finds_the_motion_from_a_heading_off_by_thirty_degrees() {
        let (a, b) = ([4.0, 2.5, 0.3], [4.3, 2.4, 0.45]);
        let truth = between(a, b);
        for off in [0.0, 0.2, -0.52, 0.6] {
            let guess = [truth[0] + 0.03, truth[1] - 0.02, truth[2] + off];
            let m = match_scans(&room(a), &room(b), guess, &IcpParams::default());
            assert!(m.ok, "offset {off}: {m:?}");
            assert!((m.pose[0] - truth[0]).abs() < 0.01, "{m:?} vs {truth:?}");
            assert!((m.pose[1] - truth[1]).abs() < 0.01, "{m:?} vs {truth:?}");
            assert!((m.pose[2] - truth[2]).abs() < 0.003, "{m:?} vs {truth:?}");
            assert!(m.covariance[2][2] > 0.0 && m.overlap > 0.9);
        }
    }

    #[test]
    fn scans_with_nothing_in_common_do_not_match() {
        let far: Vec<[f64; 2]> = (0..200).map(|i| [50.0 + 0.01 * i as f64, 30.0]).collect();
        let m = match_scans(
            &room([3.0, 2.0, 0.0]),
            &far,
            [0.0; 3],
            &IcpParams::default(),
        );
        assert!(!m.ok);
    }

    #[test]
    fn a_chain_is_matched_pair_by_pair_and_checks_its_input() {
        let poses = [[1.0, 1.0, 0.0], [1.3, 1.1, 0.1], [1.7, 1.2, 0.25]];
        let mut points = Vec::new();
        let mut offsets = vec![0];
        for p in poses {
            points.extend(room(p));
            offsets.push(points.len());
        }
        let guesses = [between(poses[0], poses[1]), between(poses[1], poses[2])];
        let out = match_chain(&points, &offsets, &guesses, &IcpParams::default()).unwrap();
        assert_eq!(out.len(), 2);
        assert!(out.iter().all(|m| m.ok));
        assert!(match_chain(&points, &offsets, &guesses[..1], &IcpParams::default()).is_err());
        assert!(match_chain(&points, &[0, 5], &[], &IcpParams::default()).is_err());
    }

    #[test]
    fn a_match_short_of_the_share_asked_for_is_abandoned_and_one_above_it_is_not() {
        let (a, b) = ([4.0, 2.5, 0.3], [4.3, 2.4, 0.45]);
        let truth = between(a, b);
        let reference = Reference::new(&room(a), 0.25);
        let guess = [truth[0] + 0.03, truth[1] - 0.02, truth[2] + 0.01];
        let plain = IcpParams::default();
        let full = reference.icp(&room(b), guess, &plain);
        assert!(full.ok && full.overlap > 0.9, "{full:?}");
        // Above its share the early stop changes nothing.
        let asked = IcpParams {
            abandon_below: 0.7,
            ..plain.clone()
        };
        assert_eq!(reference.icp(&room(b), guess, &asked), full);
        // Half the scan seen elsewhere: it cannot pair 70%, and stops, failed.
        let mut half = room(b);
        let n = half.len();
        for p in half.iter_mut().take(n / 2) {
            p[0] += 40.0;
        }
        let stopped = reference.icp(&half, guess, &asked);
        assert!(!stopped.ok && stopped.overlap < 0.7, "{stopped:?}");
    }
}
