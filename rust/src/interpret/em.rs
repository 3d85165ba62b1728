//! EM for one drawn segment (docs/ALGORITHM.md §3.3): a two-component mixture over the
//! candidates' signed distances `d_k` to the line, feature `N(0, sigma^2)` against clutter uniform
//! over the band's width, refit by weighted total least squares until the line stops moving.
//!
//! The model, with mixing weight `pi` and band half-width `r_c`:
//!
//! `p(d) = pi N(d; 0, sigma^2) + (1 - pi) / (2 r_c)`, `w_k = pi N(d_k) / p(d_k)`,
//! `log L = sum_k ln p(d_k)`.
//!
//! The clutter density is `1 / (2 r_c)`: a clutter point's distance to the line is uniform over
//! `[-r_c, r_c]`, the width of the candidate band, which makes both components densities in the
//! same variable (metres across the line).
//!
//! All arithmetic runs in coordinates centred on the drawn segment's midpoint, where the line is
//! `n . q = r`: world coordinates can be large (UTM), and `rho` near zero keeps full precision.

use super::grid::GridIndex;
use super::snap::{snap, Snap, SnapParams};
use super::{
    canonical_normal, dot, sub, tangent, world_points_near, Point, Points, Segment, SegmentFrame,
    WorldPoints,
};
use rayon::prelude::*;

use crate::error::{HitlError, Result};
pub(super) use crate::geometry::weighted_fit;

/// The mixing weight is kept in `[MIN_MIXING, MAX_MIXING]`: at `pi = 1` the clutter component
/// has zero weight and every candidate, however far, becomes an inlier for good; at `pi = 0`
/// the feature can never come back. `1e-3` leaves the M-step's `mean(w)` untouched in practice.
pub const MIN_MIXING: f64 = 1e-3;
pub const MAX_MIXING: f64 = 1.0 - 1e-3;

/// Constants of one EM run.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct EmParams {
    /// Candidate band `r_c` (metres): points within this distance of the drawn segment take
    /// part, and the clutter density is `1 / (2 r_c)`.
    pub band: f64,
    /// `sigma_em` (metres): spread of the feature's points about its line.
    pub sigma: f64,
    /// Initial mixing weight (0 < pi0 < 1).
    pub pi0: f64,
    /// Stop when the line moves less than `tol_m` at the drawn midpoint...
    pub tol_m: f64,
    /// ...turns less than `tol_rad`...
    pub tol_rad: f64,
    /// ...and the mixing weight changes less than `tol_pi`. The design stopped on the line alone
    /// (docs/ALGORITHM.md §3, Departures); when the drawing starts several sigma off the wall the
    /// line settles within a few iterations while `pi` is still climbing from near zero, and
    /// stopping there would leave every weight below 0.5 and the segment wrongly "empty".
    pub tol_pi: f64,
    /// At most this many E+M iterations (0: only the E-step at the drawn line).
    pub max_iterations: usize,
}

impl EmParams {
    pub fn validate(&self) -> Result<()> {
        let positive = |name: &str, v: f64| {
            if v.is_finite() && v > 0.0 {
                Ok(())
            } else {
                Err(HitlError::Input(format!(
                    "{name} must be a positive number, got {v}"
                )))
            }
        };
        positive("the candidate band", self.band)?;
        positive("sigma_em", self.sigma)?;
        if !(self.pi0 > 0.0 && self.pi0 < 1.0) {
            return Err(HitlError::Input(format!(
                "the initial mixing weight must be in (0, 1), got {}",
                self.pi0
            )));
        }
        for (name, v) in [
            ("tol_m", self.tol_m),
            ("tol_rad", self.tol_rad),
            ("tol_pi", self.tol_pi),
        ] {
            if !(v.is_finite() && v >= 0.0) {
                return Err(HitlError::Input(format!(
                    "{name} must be a finite number >= 0, got {v}"
                )));
            }
        }
        Ok(())
    }
}

/// A fitted line `n . p = rho` (world frame) with the extent of its observations.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct LineFit {
    /// Unit normal, canonical: its angle `phi` is in (-pi/2, pi/2].
    pub normal: Point,
    pub phi: f64,
    pub rho: f64,
    /// Endpoints on the line, ordered along the tangent `(n_y, -n_x)`.
    pub extent: [Point; 2],
}

/// The outcome of EM for one segment.
#[derive(Clone, Debug, PartialEq)]
pub struct EmFit {
    /// Indices of the candidate points (ascending), within `band` of the drawn segment.
    pub candidates: Vec<usize>,
    /// Final responsibilities `w_k`, one per candidate; the observation set is `w_k > 0.5`.
    pub weights: Vec<f64>,
    pub line: LineFit,
    /// Completed E+M iterations.
    pub iterations: usize,
    /// `sum_k ln p(d_k)` at the final line and mixing weight.
    pub log_likelihood: f64,
    /// Whether the stopping rule was met (false: iteration cap, or nothing to fit).
    pub converged: bool,
    /// Final mixing weight `pi`.
    pub mixing: f64,
    /// Candidates with `w_k > 0.5`.
    pub num_inliers: usize,
    /// The line the drawn segment was snapped to before EM (`em_fit_scans` with a search), and
    /// EM ran from there; `None` when EM started at the drawn line.
    pub snap: Option<Snap>,
    /// The band EM ran on (metres): the candidate band, or the narrow one around a snapped line
    /// that EM lost at the candidate band (see [`NARROW_BAND_SIGMAS`]).
    pub band: f64,
}

/// Half-width of the band, in `sigma_em`, that EM is run again on around a snapped line it lost
/// at the full candidate band. A sparse copy of a wall with other copies 0.15-0.45 m beside it
/// (passes of a doubled corridor) is found by the search (its support against the drawing's
/// offset), but EM's clutter component is uniform over the band, and the other copies are no
/// such clutter: they hold most of the band's points, the mixing weight sinks until even a point
/// on the line has a responsibility below 0.5, and nothing is kept although the line stays put
/// (docs/ALGORITHM.md §I.9). Four sigma keeps the line's own spread (a pass blurred by a few
/// centimetres) and leaves the neighbouring copies out.
pub const NARROW_BAND_SIGMAS: f64 = 4.0;

/// The model's constants, precomputed once per run.
#[derive(Clone, Copy, Debug)]
struct Densities {
    gauss_norm: f64,
    inv_two_var: f64,
    clutter: f64,
}

impl Densities {
    fn new(sigma: f64, band: f64) -> Self {
        Self {
            gauss_norm: 1.0 / ((2.0 * std::f64::consts::PI).sqrt() * sigma),
            inv_two_var: 0.5 / (sigma * sigma),
            clutter: 0.5 / band,
        }
    }

    /// `(w, p(d))` for one signed distance.
    #[inline]
    fn responsibility(&self, d: f64, mixing: f64) -> (f64, f64) {
        let feature = mixing * self.gauss_norm * (-d * d * self.inv_two_var).exp();
        let total = feature + (1.0 - mixing) * self.clutter;
        // total >= (1 - MAX_MIXING) * clutter > 0 for every mixing the callers pass.
        (feature / total, total)
    }
}

/// `w_k = pi N(d_k; 0, sigma^2) / (pi N(d_k; 0, sigma^2) + (1 - pi) / (2 band))`.
pub fn responsibilities(distances: &[f64], mixing: f64, sigma: f64, band: f64) -> Vec<f64> {
    let dens = Densities::new(sigma, band);
    distances
        .iter()
        .map(|&d| dens.responsibility(d, mixing).0)
        .collect()
}

/// `sum_k ln(pi N(d_k; 0, sigma^2) + (1 - pi) / (2 band))`.
pub fn log_likelihood(distances: &[f64], mixing: f64, sigma: f64, band: f64) -> f64 {
    let dens = Densities::new(sigma, band);
    distances
        .iter()
        .map(|&d| dens.responsibility(d, mixing).1.ln())
        .sum()
}

/// The line `n . q = r` in the segment's local frame, and the mixing weight.
#[derive(Clone, Copy, Debug)]
struct Model {
    n: Point,
    r: f64,
    mixing: f64,
}

/// E-step: fills `w`, returns the log-likelihood.
fn e_step(local: &[Point], model: &Model, dens: &Densities, w: &mut Vec<f64>) -> f64 {
    w.clear();
    let mut ll = 0.0;
    for &q in local {
        let (wk, p) = dens.responsibility(dot(model.n, q) - model.r, model.mixing);
        w.push(wk);
        ll += p.ln();
    }
    ll
}

/// The canonical world line and its extent: the span of the projections of the points with
/// `w > 0.5`, clipped to the drawn extent plus the band past each end.
fn finish_line(
    local: &[Point],
    w: &[f64],
    n: Point,
    r: f64,
    frame: &SegmentFrame,
    band: f64,
) -> LineFit {
    let nc = canonical_normal(n);
    let rc = if dot(nc, n) >= 0.0 { r } else { -r };
    let u = tangent(nc);
    // The drawn ends project to +-half |u . u_drawn| (the frame is centred on the midpoint).
    let reach = frame.half * dot(u, frame.u).abs();
    let (lo, hi) = (-reach - band, reach + band);
    let mut span: Option<(f64, f64)> = None;
    for (q, _) in local.iter().zip(w).filter(|(_, &wk)| wk > 0.5) {
        let t = dot(u, *q);
        span = Some(match span {
            None => (t, t),
            Some((a, b)) => (a.min(t), b.max(t)),
        });
    }
    let (t0, t1) = match span {
        Some((a, b)) => (a.clamp(lo, hi), b.clamp(lo, hi)),
        None => (-reach, reach),
    };
    let foot = [frame.mid[0] + rc * nc[0], frame.mid[1] + rc * nc[1]];
    let at = |t: f64| [foot[0] + t * u[0], foot[1] + t * u[1]];
    LineFit {
        normal: nc,
        phi: nc[1].atan2(nc[0]),
        rho: rc + dot(nc, frame.mid),
        extent: [at(t0), at(t1)],
    }
}

/// EM for one drawn segment over `points` (world frame, the array `grid` was built on).
pub fn em_fit(
    points: Points<'_>,
    grid: &GridIndex,
    seg: &Segment,
    params: &EmParams,
) -> Result<EmFit> {
    params.validate()?;
    let frame = SegmentFrame::new(seg)?;
    let mut candidates = Vec::new();
    grid.query_frame(points, &frame, params.band, &mut candidates);
    let local: Vec<Point> = candidates
        .iter()
        .map(|&i| {
            points
                .get(i)
                .map(|p| sub(p, frame.mid))
                .ok_or_else(|| HitlError::Input("the grid was built on other points".into()))
        })
        .collect::<Result<_>>()?;
    let dens = Densities::new(params.sigma, params.band);
    // The drawn line passes through the midpoint, so r = 0 locally.
    let mut model = Model {
        n: frame.n,
        r: 0.0,
        mixing: params.pi0.clamp(MIN_MIXING, MAX_MIXING),
    };
    let mut w = Vec::with_capacity(local.len());
    let (mut iterations, mut converged) = (0, false);
    while iterations < params.max_iterations {
        e_step(&local, &model, &dens, &mut w);
        let Some((n, r)) = weighted_fit(&local, &w, model.n) else {
            break;
        };
        let mixing = (w.iter().sum::<f64>() / w.len() as f64).clamp(MIN_MIXING, MAX_MIXING);
        iterations += 1;
        // n is oriented like model.n, so the turn is the angle between them, modulo pi.
        let turn = (n[0] * model.n[1] - n[1] * model.n[0])
            .abs()
            .atan2(dot(n, model.n).abs());
        let shift = (r - model.r).abs();
        let dpi = (mixing - model.mixing).abs();
        model = Model { n, r, mixing };
        if shift < params.tol_m && turn < params.tol_rad && dpi < params.tol_pi {
            converged = true;
            break;
        }
    }
    // Final E-step: the weights (and so the observation set) belong to the final line.
    let log_likelihood = e_step(&local, &model, &dens, &mut w);
    let line = finish_line(&local, &w, model.n, model.r, &frame, params.band);
    let num_inliers = w.iter().filter(|&&wk| wk > 0.5).count();
    Ok(EmFit {
        candidates,
        weights: w,
        line,
        iterations,
        log_likelihood,
        converged,
        mixing: model.mixing,
        num_inliers,
        snap: None,
        band: params.band,
    })
}

/// Fails, before any work, on unusable parameters or a degenerate segment.
fn check_inputs(segments: &[Segment], params: &EmParams) -> Result<()> {
    params.validate()?;
    for seg in segments {
        SegmentFrame::new(seg)?;
    }
    Ok(())
}

/// EM for several segments over the same points, with one grid (cell = band) for all.
pub fn em_fit_segments(
    points: Points<'_>,
    segments: &[Segment],
    params: &EmParams,
) -> Result<Vec<EmFit>> {
    check_inputs(segments, params)?;
    let grid = GridIndex::build(points, params.band)?;
    segments
        .iter()
        .map(|seg| em_fit(points, &grid, seg, params))
        .collect()
}

/// `em_fit_segments` on a map as stored: `poses` `(N, 3)` flat, robot-frame `points` and
/// `offsets` `(N + 1,)` (pose i owns rows `offsets[i]..offsets[i + 1]`); candidate indices are
/// map rows. Only the scans that can reach the segments are transformed and indexed
/// ([`world_points_near`]): the same candidates, in the same order, as over the whole map, so
/// the fits are identical, while a drawing on a map of millions of points costs a few scans.
///
/// With `search`, each segment is first snapped onto the best line near it ([`snap`]) and EM
/// starts from the snapped segment (its band around the snapped segment); a segment with no
/// line near it keeps EM at the drawn line.
pub fn em_fit_scans(
    poses: &[f64],
    points: Points<'_>,
    offsets: &[i64],
    segments: &[Segment],
    params: &EmParams,
    search: Option<&SnapParams>,
) -> Result<Vec<EmFit>> {
    check_inputs(segments, params)?;
    let (world, rows) = world_points_near(poses, points, offsets, segments, reach(params, search))?;
    em_fit_near(&world, &rows, segments, params, search)
}

/// How far from a drawn segment [`em_fit_scans`] needs the map's points: the candidate band,
/// plus the search band when segments are snapped first (a snapped segment lies within the
/// search band of the drawn one, and its candidates within the band of it).
pub fn reach(params: &EmParams, search: Option<&SnapParams>) -> f64 {
    params.band + search.map_or(0.0, |s| s.search_band)
}

/// [`em_fit_scans`] on the world points already gathered within [`reach`] of `segments`
/// (`rows`: the map row of each).
pub fn em_fit_near(
    world: &WorldPoints,
    rows: &[usize],
    segments: &[Segment],
    params: &EmParams,
    search: Option<&SnapParams>,
) -> Result<Vec<EmFit>> {
    check_inputs(segments, params)?;
    if let Some(s) = search {
        s.validate()?;
    }
    let world_pts = Points::new(&world.flat)?;
    let grid = GridIndex::build_in(world_pts, params.band, world.bounds)?;
    // The segments are independent: one per core.
    segments
        .par_iter()
        .map(|seg| {
            let snapped = match search {
                Some(s) => snap(world_pts, &grid, seg, s)?,
                None => None,
            };
            let start = snapped.map_or(*seg, |s| s.segment);
            let mut fit = em_fit(world_pts, &grid, &start, params)?;
            if let Some(s) = snapped {
                // EM lost the line the search found (fewer than half its points kept): again on
                // a band that holds the line and not its neighbours.
                let narrow = params.band.min(NARROW_BAND_SIGMAS * params.sigma);
                if 2 * fit.num_inliers < s.support && narrow < params.band {
                    let params = EmParams {
                        band: narrow,
                        ..*params
                    };
                    let again = em_fit(world_pts, &grid, &start, &params)?;
                    if again.num_inliers > fit.num_inliers {
                        fit = again;
                    }
                }
            }
            fit.snap = snapped;
            // Kept rows ascend, so the candidates stay in ascending order.
            for c in &mut fit.candidates {
                *c = rows.get(*c).copied().ok_or_else(|| {
                    HitlError::Solver("a candidate outside the indexed scans".into())
                })?;
            }
            Ok(fit)
        })
        .collect()
}

/// The weighted TLS line of `points` (world frame) with its extent (points with weight > 0.5,
/// clipped to `seg` plus `band` past each end); `seg` also gives the direction when the points
/// have none. Used to refit a feature to the observations that survive the pair rules.
pub fn line_fit(points: Points<'_>, weights: &[f64], seg: &Segment, band: f64) -> Result<LineFit> {
    if weights.len() != points.len() {
        return Err(HitlError::Input(format!(
            "{} weights for {} points; give one weight per point",
            weights.len(),
            points.len()
        )));
    }
    if let Some(k) = weights.iter().position(|w| !(w.is_finite() && *w >= 0.0)) {
        return Err(HitlError::Input(format!(
            "weight {k} must be finite and >= 0, got {:?}",
            weights.get(k)
        )));
    }
    if !(band.is_finite() && band > 0.0) {
        return Err(HitlError::Input(format!(
            "the band must be a positive number of metres, got {band}"
        )));
    }
    points.check_finite("point")?;
    let frame = SegmentFrame::new(seg)?;
    let local: Vec<Point> = points.iter().map(|p| sub(p, frame.mid)).collect();
    let (n, r) = weighted_fit(&local, weights, frame.n).ok_or_else(|| {
        HitlError::Input("no point has a positive weight; there is no line to fit".into())
    })?;
    Ok(finish_line(&local, weights, n, r, &frame, band))
}

#[cfg(test)]
mod tests {
    use super::*;
    use rand::{Rng, SeedableRng};

    /// Box-Muller, to keep the tests free of an extra crate.
    fn normal(rng: &mut impl Rng) -> f64 {
        let u1: f64 = rng.random_range(f64::EPSILON..1.0);
        let u2: f64 = rng.random_range(0.0..1.0);
        (-2.0 * u1.ln()).sqrt() * (2.0 * std::f64::consts::PI * u2).cos()
    }

    fn params() -> EmParams {
        EmParams {
            band: 0.3,
            sigma: 0.03,
            pi0: 0.5,
            tol_m: 1e-4,
            tol_rad: 1e-4,
            tol_pi: 1e-4,
            max_iterations: 50,
        }
    }

    /// Points on the line through `p0` at angle `phi` (direction), with noise, plus clutter
    /// spread over a box around it.
    fn wall(rng: &mut impl Rng, p0: Point, phi: f64, len: f64, n: usize, noise: f64) -> Vec<f64> {
        let (s, c) = phi.sin_cos();
        let mut out = Vec::new();
        for _ in 0..n {
            let t = rng.random_range(0.0..len);
            let e = noise * normal(rng);
            out.push(p0[0] + t * c - e * s);
            out.push(p0[1] + t * s + e * c);
        }
        for _ in 0..n / 3 {
            out.push(p0[0] + rng.random_range(-1.0..len + 1.0) * c + rng.random_range(-0.5..0.5));
            out.push(p0[1] + rng.random_range(-1.0..len + 1.0) * s + rng.random_range(-0.5..0.5));
        }
        out
    }

    fn angle_mod_pi(a: f64) -> f64 {
        let r = a.rem_euclid(std::f64::consts::PI);
        r.min(std::f64::consts::PI - r)
    }

    #[test]
    fn recovers_a_noisy_wall_from_a_sloppy_drawing() {
        let mut rng = rand::rngs::StdRng::seed_from_u64(3);
        for trial in 0..40 {
            let phi = rng.random_range(-3.2..3.2);
            let p0 = [rng.random_range(-50.0..50.0), rng.random_range(-50.0..50.0)];
            let flat = wall(&mut rng, p0, phi, 5.0, 600, 0.015);
            let pts = Points::new(&flat).unwrap();
            // Drawn 2 degrees off and ~5 cm off at the ends.
            let (s, c) = (phi + 0.035).sin_cos();
            let a = [p0[0] + 0.5 * c + 0.04, p0[1] + 0.5 * s - 0.03];
            let b = [a[0] + 4.0 * c, a[1] + 4.0 * s];
            let fit = em_fit_segments(pts, &[Segment::new(a, b)], &params()).unwrap();
            let fit = &fit[0];
            assert!(fit.converged, "trial {trial}");
            let want_n = [-(phi.sin()), phi.cos()];
            let turn = angle_mod_pi(fit.line.phi - want_n[1].atan2(want_n[0]));
            assert!(turn < 0.2_f64.to_radians(), "trial {trial}: {turn}");
            // Distance of the true line from the fitted one at the wall's middle.
            let mid = [p0[0] + 2.5 * phi.cos(), p0[1] + 2.5 * phi.sin()];
            let off = dot(fit.line.normal, mid) - fit.line.rho;
            assert!(off.abs() < 0.01, "trial {trial}: {off}");
            // Clutter far from the wall is out, nearly every wall point is in.
            for (&i, &w) in fit.candidates.iter().zip(&fit.weights) {
                let p = pts.get(i).unwrap();
                let d = (dot(want_n, sub(p, p0))).abs();
                if d > 0.2 {
                    assert!(w < 0.5, "trial {trial}: clutter at {d} has w = {w}");
                }
            }
            assert!(fit.num_inliers > 400, "trial {trial}: {}", fit.num_inliers);
        }
    }

    /// A pass by a wall among other passes' copies 0.14-0.3 m beside it (the case seen on the Intel
    /// log in the full evaluation, "551 points near segment a, none of them on one line"): the
    /// search finds the line drawn on, but it holds a small share of the band's points, so on
    /// the full band EM's mixing weight sinks until no responsibility reaches 0.5 although the
    /// line stays put. On the narrow band EM keeps the line and most of its points.
    #[test]
    fn a_sparse_pass_in_a_blur_of_copies_is_kept_on_the_narrow_band() {
        // The drawing is within 4 cm of its line; a tight closeness keeps the search on it, so
        // that what is tested is EM after it.
        let search = SnapParams {
            search_band: 0.5,
            sigma: 0.03,
            closeness: 0.05,
            pointing: 0.1,
            min_support: 8,
        };
        let (mut lost_count, mut held_full, mut rescued) = (0, 0, 0);
        for seed in 0..20 {
            let mut rng = rand::rngs::StdRng::seed_from_u64(100 + seed);
            let phi: f64 = rng.random_range(-3.2..3.2);
            let (s, c) = phi.sin_cos();
            let at = |t: f64, e: f64| [3.0 + t * c - e * s, -7.0 + t * s + e * c];
            let mut flat = Vec::new();
            let line = rng.random_range(70..90);
            for _ in 0..line {
                flat.extend(at(rng.random_range(0.0..3.5), 0.015 * normal(&mut rng)));
            }
            // Other passes' copies of the wall 0.14-0.3 m to either side, up to a degree off:
            // most of the band's points.
            for k in 0..8 {
                let side = if k % 2 == 0 { 1.0 } else { -1.0 };
                let o = side * rng.random_range(0.14..0.3);
                let turn = rng.random_range(-1f64..1.0).to_radians().tan();
                for _ in 0..2 * line {
                    let t: f64 = rng.random_range(-0.5..4.0);
                    flat.extend(at(t, o + turn * (t - 1.75) + 0.015 * normal(&mut rng)));
                }
            }
            let offsets = [0, (flat.len() / 2) as i64];
            let pts = Points::new(&flat).unwrap();
            let e = rng.random_range(-0.04..0.04);
            let drawn = Segment::new(at(3.4, e + 0.03), at(0.1, e - 0.03));
            let fits =
                em_fit_scans(&[0.0; 3], pts, &offsets, &[drawn], &params(), Some(&search)).unwrap();
            let fit = &fits[0];
            let snapped = fit.snap.expect("the search finds the sparse line");
            let want = [-s, c];
            let holds = |f: &EmFit| {
                let mine = f
                    .candidates
                    .iter()
                    .zip(&f.weights)
                    .filter(|(&i, &w)| i < line && w > 0.5)
                    .count();
                let turn = angle_mod_pi(f.line.phi - want[1].atan2(want[0]));
                let off = dot(f.line.normal, at(1.75, 0.0)) - f.line.rho;
                2 * mine > line && turn < 1.5f64.to_radians() && off.abs() < 0.015
            };
            // Only where EM on the full band, from the same snapped segment, loses the line (keeps
            // fewer than half the line's support) does it run again on the narrow band.
            let full = em_fit_segments(pts, &[snapped.segment], &params()).unwrap();
            let lost = 2 * full[0].num_inliers < snapped.support;
            assert!(lost || fit.band == params().band, "seed {seed}");
            if lost {
                lost_count += 1;
                held_full += usize::from(holds(&full[0]));
                rescued += usize::from(holds(fit));
            }
        }
        // The layouts are hard enough for the full band to lose the line often; the narrow band
        // gets most of them back.
        assert!(
            lost_count >= 5,
            "the full band lost the line on only {lost_count} of 20"
        );
        assert!(
            5 * rescued >= 4 * lost_count && rescued >= held_full + lost_count / 2,
            "of {lost_count} lost, the line held on {rescued} (on the full band alone {held_full})"
        );
    }

    #[test]
    fn converges_from_several_sigma_away() {
        // Drawn 15 cm (5 sigma) beside a clean wall: pi first collapses, then must climb back.
        let flat: Vec<f64> = (0..200).flat_map(|k| [k as f64 * 0.02, 0.0]).collect();
        let pts = Points::new(&flat).unwrap();
        let seg = Segment::new([0.0, 0.15], [4.0, 0.15]);
        let fit = &em_fit_segments(pts, &[seg], &params()).unwrap()[0];
        assert!(fit.converged);
        assert_eq!(fit.num_inliers, 200);
        assert!(fit.line.rho.abs() < 1e-9);
    }

    #[test]
    fn result_does_not_depend_on_drawing_direction() {
        let mut rng = rand::rngs::StdRng::seed_from_u64(11);
        let flat = wall(&mut rng, [1.0, 2.0], 2.2, 4.0, 300, 0.02);
        let pts = Points::new(&flat).unwrap();
        let (s, c) = 2.21_f64.sin_cos();
        let a = [1.0 + 0.3 * c, 2.0 + 0.3 * s];
        let b = [1.0 + 3.5 * c + 0.02, 2.0 + 3.5 * s];
        let fwd = em_fit_segments(pts, &[Segment::new(a, b)], &params()).unwrap();
        let rev = em_fit_segments(pts, &[Segment::new(b, a)], &params()).unwrap();
        assert_eq!(fwd, rev);
    }

    #[test]
    fn one_iteration_is_responsibilities_then_weighted_pca() {
        let mut rng = rand::rngs::StdRng::seed_from_u64(5);
        let flat = wall(&mut rng, [0.0, 0.0], 0.3, 3.0, 100, 0.03);
        let pts = Points::new(&flat).unwrap();
        let (s, c) = 0.32_f64.sin_cos();
        let seg = Segment::new([0.1 * c, 0.1 * s], [2.9 * c, 2.9 * s + 0.05]);
        let mut p = params();
        p.max_iterations = 0;
        let zero = &em_fit_segments(pts, &[seg], &p).unwrap()[0];
        // At zero iterations the weights are the E-step at the drawn line.
        let frame = SegmentFrame::new(&seg).unwrap();
        let d: Vec<f64> = zero
            .candidates
            .iter()
            .map(|&i| dot(frame.n, sub(pts.get(i).unwrap(), frame.mid)))
            .collect();
        let w0 = responsibilities(&d, 0.5, p.sigma, p.band);
        for (a, b) in w0.iter().zip(&zero.weights) {
            assert!((a - b).abs() < 1e-15);
        }
        assert!((zero.log_likelihood - log_likelihood(&d, 0.5, p.sigma, p.band)).abs() < 1e-9);
        // One iteration: the weighted TLS of those weights, as line_fit computes it.
        p.max_iterations = 1;
        let one = &em_fit_segments(pts, &[seg], &p).unwrap()[0];
        let cand: Vec<f64> = zero
            .candidates
            .iter()
            .flat_map(|&i| pts.get(i).unwrap())
            .collect();
        let refit = line_fit(Points::new(&cand).unwrap(), &w0, &seg, p.band).unwrap();
        assert!((refit.phi - one.line.phi).abs() < 1e-12);
        assert!((refit.rho - one.line.rho).abs() < 1e-12);
        let mean = w0.iter().sum::<f64>() / w0.len() as f64;
        assert!((one.mixing - mean).abs() < 1e-15);
    }

    #[test]
    fn weighted_pca_matches_the_eigenvector() {
        // A cloud with a known principal axis at 30 degrees and unequal weights.
        let mut rng = rand::rngs::StdRng::seed_from_u64(9);
        let (s, c) = 30f64.to_radians().sin_cos();
        let mut local = Vec::new();
        let mut w = Vec::new();
        for _ in 0..500 {
            let (t, e) = (3.0 * normal(&mut rng), 0.1 * normal(&mut rng));
            local.push([t * c - e * s + 1.0, t * s + e * c - 2.0]);
            w.push(rng.random_range(0.0..1.0));
        }
        let (n, r) = weighted_fit(&local, &w, [0.0, 1.0]).unwrap();
        // n must be an eigenvector of the weighted scatter with the smaller eigenvalue.
        let sw: f64 = w.iter().sum();
        let cx = local.iter().zip(&w).map(|(q, wk)| wk * q[0]).sum::<f64>() / sw;
        let cy = local.iter().zip(&w).map(|(q, wk)| wk * q[1]).sum::<f64>() / sw;
        let (mut a, mut b, mut d) = (0.0, 0.0, 0.0);
        for (q, wk) in local.iter().zip(&w) {
            a += wk * (q[0] - cx) * (q[0] - cx);
            b += wk * (q[0] - cx) * (q[1] - cy);
            d += wk * (q[1] - cy) * (q[1] - cy);
        }
        let lambda_min = 0.5 * (a + d) - (0.25 * (a - d) * (a - d) + b * b).sqrt();
        let sn = [a * n[0] + b * n[1], b * n[0] + d * n[1]];
        assert!((sn[0] - lambda_min * n[0]).abs() < 1e-9 * (a + d));
        assert!((sn[1] - lambda_min * n[1]).abs() < 1e-9 * (a + d));
        assert!((r - (n[0] * cx + n[1] * cy)).abs() < 1e-12);
        assert!(n[1] > 0.0, "oriented like prev");
    }

    #[test]
    fn degenerate_inputs() {
        // No candidates: nothing to fit, the drawn line comes back, no error.
        let flat = [100.0, 100.0];
        let pts = Points::new(&flat).unwrap();
        let seg = Segment::new([0.0, 0.0], [1.0, 0.0]);
        let fit = &em_fit_segments(pts, &[seg], &params()).unwrap()[0];
        assert!(fit.candidates.is_empty() && !fit.converged && fit.iterations == 0);
        assert_eq!(fit.line.extent, [[0.0, 0.0], [1.0, 0.0]]);
        assert_eq!(fit.log_likelihood, 0.0);
        // One candidate: no direction of its own, the drawn one is kept.
        let one = Points::new(&[0.5, 0.01]).unwrap();
        let fit = &em_fit_segments(one, &[seg], &params()).unwrap()[0];
        assert!((fit.line.phi - std::f64::consts::FRAC_PI_2).abs() < 1e-12);
        assert!((fit.line.rho - 0.01).abs() < 1e-12);
        // Bad parameters and weights are input errors.
        for bad in [
            EmParams {
                band: 0.0,
                ..params()
            },
            EmParams {
                sigma: -1.0,
                ..params()
            },
            EmParams {
                pi0: 1.0,
                ..params()
            },
            EmParams {
                tol_m: f64::NAN,
                ..params()
            },
        ] {
            assert!(matches!(
                em_fit_segments(pts, &[seg], &bad),
                Err(HitlError::Input(_))
            ));
        }
        assert!(line_fit(one, &[0.0], &seg, 0.3).is_err());
        assert!(line_fit(one, &[1.0, 1.0], &seg, 0.3).is_err());
        assert!(line_fit(one, &[f64::NAN], &seg, 0.3).is_err());
        assert!(em_fit_segments(pts, &[Segment::new([0.0, 0.0], [0.0, 0.0])], &params()).is_err());
    }

    #[test]
    fn scans_out_of_reach_change_nothing() {
        // Scans of a wall near the segments, many far away (some very long beams): the fits over
        // the scans that can reach equal those over the whole map bit for bit, candidates as map
        // rows in ascending order.
        let mut rng = rand::rngs::StdRng::seed_from_u64(7);
        let (mut poses, mut pts, mut offsets) = (Vec::new(), Vec::new(), vec![0i64]);
        for i in 0..400 {
            let far = i % 3 != 0;
            let (x, y, th) = if far {
                (
                    rng.random_range(-200.0..200.0),
                    rng.random_range(20.0..200.0),
                    0.3,
                )
            } else {
                (
                    rng.random_range(-3.0..3.0),
                    1.5,
                    rng.random_range(-0.5..0.5),
                )
            };
            poses.extend([x, y, th]);
            for k in 0..rng.random_range(0..30) {
                // A wall at world y = 0 as seen from (x, y, th), plus clutter; every tenth
                // scan of the far ones has a 500 m beam.
                let (wx, wy) = if far && k == 0 && i % 10 == 1 {
                    (x + 500.0, y)
                } else if rng.random_range(0.0..1.0) < 0.8 {
                    (x + rng.random_range(-4.0..4.0), 0.01 * normal(&mut rng))
                } else {
                    (x + rng.random_range(-4.0..4.0), rng.random_range(-1.0..1.0))
                };
                let (dx, dy) = (wx - x, wy - y);
                let (s, c) = f64::sin_cos(th);
                pts.extend([c * dx + s * dy, -s * dx + c * dy]);
            }
            offsets.push((pts.len() / 2) as i64);
        }
        let segs = [
            Segment::new([-2.0, 0.05], [2.0, -0.02]),
            Segment::new([1.0, 0.0], [5.0, 0.1]),
        ];
        let p = Points::new(&pts).unwrap();
        let culled = em_fit_scans(&poses, p, &offsets, &segs, &params(), None).unwrap();
        let world = super::super::world_points(&poses, p, &offsets).unwrap();
        let whole = em_fit_segments(Points::new(&world.flat).unwrap(), &segs, &params()).unwrap();
        assert_eq!(culled, whole);
        assert!(culled.iter().all(|f| f.candidates.len() > 20));
        let (kept, rows) =
            super::super::world_points_near(&poses, p, &offsets, &segs, 0.3).unwrap();
        assert!(
            rows.len() < pts.len() / 2 / 2,
            "{} of {}",
            rows.len(),
            pts.len() / 2
        );
        assert_eq!(kept.flat.len(), 2 * rows.len());
        // A non-finite point is an error even in a scan out of reach.
        let mut bad = pts.clone();
        let last = bad.len() - 1;
        bad[last] = f64::NAN;
        let err = em_fit_scans(
            &poses,
            Points::new(&bad).unwrap(),
            &offsets,
            &segs,
            &params(),
            None,
        );
        assert!(err.unwrap_err().to_string().contains("not finite"));
    }
}
