//! Finding the wall a person meant (issue 11): before EM, a drawn segment is snapped onto the
//! dense line of observations that best explains it.
//!
//! EM started at the drawn line (docs/ALGORITHM.md §3.3) fails when the drawing lies several
//! `sigma_em` beside its wall and the band also holds other copies, clutter or other passes: every
//! responsibility starts near zero, the mixing weight collapses, and the segment comes back
//! "empty" although a dense copy of the wall lies 15 cm away. A careful person draws near the
//! copy they mean and roughly along it, so the search here scores every line near the drawing by
//!
//! `score = ln(support) - o^2 / (2 sigma_c^2) - t^2 / (2 sigma_t^2)`,
//!
//! where `support` counts the observations within `1.5 sigma` of the line (its density: a
//! copy of a wall is hundreds of points on one line, clutter is not), `o` is the line's offset
//! from the drawing at the drawn midpoint and `t` the angle between them. The two errors of a
//! careful drawing have different sizes: a person draws beside the wall they mean, consistently
//! to one side, by up to a few decimetres (`sigma_c`), but along it: the direction errs only by
//! the endpoints' own noise (`sigma_h` each, so `sigma_t = sqrt(2) sigma_h / length`). A copy
//! of the wall turned by a few degrees, crossing the drawing, is therefore not mistaken for
//! the one drawn on.
//! The lines searched are all directions within `max_turn` of the drawn one (a Hough transform
//! restricted to the drawing's neighbourhood: per direction, a histogram of the points' offsets
//! with bins of `sigma`, every local maximum a candidate). The drawn endpoints are then projected
//! onto the best line, and EM runs from there with the usual band.
//!
//! Two copies a few centimetres apart fall in one histogram peak; telling them apart is the pair
//! rules' job (distinct visits, chosen jointly for both segments).

use super::em::weighted_fit;
use super::grid::GridIndex;
use super::{dot, sub, Point, Points, Segment, SegmentFrame};
use crate::error::{HitlError, Result};

/// Constants of the search.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct SnapParams {
    /// Points within this distance of the drawn segment are searched (metres).
    pub search_band: f64,
    /// Bin width of the offset histograms, the spread of a wall's points (`sigma_em`, metres).
    pub sigma: f64,
    /// `sigma_c`: how far beside the wall a careful person draws (metres).
    pub closeness: f64,
    /// `sigma_h`: the noise of each drawn endpoint (metres); sets the direction's tolerance.
    pub pointing: f64,
    /// A line needs at least this many points to count.
    pub min_support: usize,
}

impl SnapParams {
    pub fn validate(&self) -> Result<()> {
        for (name, v) in [
            ("the search band", self.search_band),
            ("sigma_em", self.sigma),
            ("the drawing's sigma", self.closeness),
            ("sigma_h", self.pointing),
        ] {
            if !(v.is_finite() && v > 0.0) {
                return Err(HitlError::Input(format!(
                    "{name} must be a positive number of metres, got {v}"
                )));
            }
        }
        Ok(())
    }
}

/// The line a segment was snapped to.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Snap {
    /// The drawn endpoints projected onto the chosen line (same order as drawn).
    pub segment: Segment,
    /// Distances of the drawn endpoints from the line (metres, >= 0).
    pub moved: [f64; 2],
    /// Angle between the drawn segment and the line (radians, >= 0).
    pub turn: f64,
    /// Observations within `1.5 sigma` of the line.
    pub support: usize,
    /// The score above.
    pub score: f64,
    /// The best score among lines at least `3 sigma` away from the chosen one (at the drawn
    /// midpoint), `-inf` when there is none: how clear the choice was.
    pub runner_up: f64,
    /// The drawn endpoints projected onto that runner-up line (same order as drawn) where it
    /// scores within [`NEAR_TIE`] of the chosen one, `None` otherwise: the other reading of a
    /// near tie (docs/ALGORITHM.md §I.18).
    pub runner_up_segment: Option<Segment>,
}

/// A runner-up line scoring within this much of the chosen one (`ln` of support, less the
/// closeness and direction terms: a factor of `e` in support at equal closeness) is a near tie:
/// the drawing alone does not say which of the two lines it meant.
pub const NEAR_TIE: f64 = 1.0;

/// Largest turn searched, whatever the segment's length (radians).
const MAX_TURN_CAP: f64 = 0.35;
/// Smallest turn searched, for long segments (radians).
const MAX_TURN_FLOOR: f64 = 0.05;
/// At most this many directions on each side of the drawn one.
const MAX_STEPS: usize = 120;
/// At most this many offset bins per direction (10^6 bins of 2 cm: a 20 km band).
const MAX_BINS: f64 = 1e6;

/// Snaps `seg` onto the best-scoring line of `points` near it (see the module docs); `None`
/// when no line near the drawing has `min_support` points.
pub fn snap(
    points: Points<'_>,
    grid: &GridIndex,
    seg: &Segment,
    params: &SnapParams,
) -> Result<Option<Snap>> {
    params.validate()?;
    let frame = SegmentFrame::new(seg)?;
    let mut candidates = Vec::new();
    grid.query_frame(points, &frame, params.search_band, &mut candidates);
    if candidates.len() < params.min_support.max(2) {
        return Ok(None);
    }
    let local: Vec<Point> = candidates
        .iter()
        .filter_map(|&i| points.get(i).map(|p| sub(p, frame.mid)))
        .collect();
    let ends = [sub(seg.a, frame.mid), sub(seg.b, frame.mid)];
    let half = frame.half;
    // Directions: as far as a drawing whose ends are each within the search band of the wall
    // can be turned, within [floor, cap]; steps of about sigma over the half-length.
    let max_turn = (2.0 * params.search_band)
        .atan2(2.0 * half)
        .clamp(MAX_TURN_FLOOR, MAX_TURN_CAP);
    let step = params
        .sigma
        .atan2(half.max(params.sigma))
        .max(max_turn / MAX_STEPS as f64);
    let steps = (max_turn / step).ceil().max(1.0) as i64;
    // The fan ends at max_turn exactly (a coarse step on a short stroke would overshoot it).
    let step = max_turn / steps as f64;
    // Offsets reach at most search band + half * sin(max_turn) from the midpoint.
    let reach = params.search_band + half * max_turn.sin() + params.sigma;
    let bins = (2.0 * reach / params.sigma).ceil();
    // A band of metres in bins of sigma, never a request for
    // more memory than a map holds (a sigma_h of 1e200 asked for 1e201 bins).
    if bins.is_nan() || bins > MAX_BINS {
        return Err(HitlError::Input(format!(
            "the search band ({:.3e} m) is too wide for bins of {} m; give a drawing uncertainty \
             of metres, not kilometres",
            params.search_band, params.sigma
        )));
    }
    let bins = (bins as usize).max(3);
    let mut hist = vec![0u32; bins];
    let inv = 1.0 / params.sigma;
    let var_c2 = 2.0 * params.closeness * params.closeness;
    let sigma_t = std::f64::consts::SQRT_2 * params.pointing / (2.0 * half);
    let var_t2 = 2.0 * sigma_t * sigma_t;
    // (score, turn, offset, support)
    let mut found: Vec<(f64, f64, f64, usize)> = Vec::new();
    for k in -steps..=steps {
        let turn = k as f64 * step;
        let (s, c) = turn.sin_cos();
        let n = [
            c * frame.n[0] - s * frame.n[1],
            s * frame.n[0] + c * frame.n[1],
        ];
        hist.fill(0);
        for &q in &local {
            // For v >= 0 the cast truncates, which is floor (and avoids a libm call in the
            // hottest loop of interpretation); below 0 the point is outside the histogram.
            let v = (dot(n, q) + reach) * inv;
            if v >= 0.0 {
                let b = v as usize;
                if b < bins {
                    hist[b] += 1;
                }
            }
        }
        // Support of the line at bin i's centre: bins i-1..=i+1 (+-1.5 sigma).
        let window = |i: usize| -> u32 {
            hist[i.saturating_sub(1)..=(i + 1).min(bins - 1)]
                .iter()
                .sum()
        };
        let mut prev = 0;
        let mut here = window(0);
        for i in 0..bins {
            let next = if i + 1 < bins { window(i + 1) } else { 0 };
            let support = here as usize;
            if support >= params.min_support && here >= prev && here > next {
                let offset = (i as f64 + 0.5) * params.sigma - reach;
                // The line is n . q = offset and the drawing passes through the origin.
                let score = (support as f64).ln() - offset * offset / var_c2 - turn * turn / var_t2;
                found.push((score, turn, offset, support));
            }
            prev = here;
            here = next;
        }
    }
    let Some(&(score, turn, offset, support)) = found
        .iter()
        .max_by(|x, y| x.0.total_cmp(&y.0).then(y.1.abs().total_cmp(&x.1.abs())))
    else {
        return Ok(None);
    };
    let other = found
        .iter()
        .filter(|f| (f.2 - offset).abs() > 3.0 * params.sigma)
        .max_by(|x, y| x.0.total_cmp(&y.0).then(y.1.abs().total_cmp(&x.1.abs())));
    let runner_up = other.map_or(f64::NEG_INFINITY, |f| f.0);
    let on_line = |turn: f64, offset: f64| -> (Segment, [f64; 2], f64) {
        let (s, c) = turn.sin_cos();
        let hough = [
            c * frame.n[0] - s * frame.n[1],
            s * frame.n[0] + c * frame.n[1],
        ];
        let refined = refine(&local, hough, offset, params.sigma);
        // A short drawing near a corner: the refinement can slide onto the crossing wall. A
        // person drawing along a wall is never that far off its direction; keep the
        // histogram's line.
        let refined_turn = (refined.0[0] * frame.n[1] - refined.0[1] * frame.n[0])
            .abs()
            .atan2(dot(refined.0, frame.n).abs());
        let (n, offset) = if refined_turn <= MAX_TURN_CAP + 0.05 {
            refined
        } else {
            (hough, offset)
        };
        let project = |p: Point, e: Point| -> (Point, f64) {
            let d = dot(n, e) - offset;
            ([p[0] - d * n[0], p[1] - d * n[1]], d.abs())
        };
        let (a, ea) = project(seg.a, ends[0]);
        let (b, eb) = project(seg.b, ends[1]);
        let turn = (n[0] * frame.n[1] - n[1] * frame.n[0])
            .abs()
            .atan2(dot(n, frame.n).abs());
        (Segment::new(a, b), [ea, eb], turn)
    };
    let (segment, moved, turn) = on_line(turn, offset);
    let runner_up_segment = other
        .filter(|f| score - f.0 <= NEAR_TIE)
        .map(|f| on_line(f.1, f.2).0);
    Ok(Some(Snap {
        segment,
        moved,
        turn,
        support,
        score,
        runner_up,
        runner_up_segment,
    }))
}

/// A few iterations of weighted total least squares on the points near the line `n . q = r`,
/// with Cauchy weights at scale `sigma` over those within `3 sigma`: the histogram's line is
/// only as good as its bins and directions; this puts it on its points.
fn refine(local: &[Point], mut n: Point, mut r: f64, sigma: f64) -> (Point, f64) {
    let mut w = vec![0.0; local.len()];
    for _ in 0..5 {
        for (wk, &q) in w.iter_mut().zip(local) {
            let d = (dot(n, q) - r) / sigma;
            *wk = if d.abs() <= 3.0 {
                1.0 / (1.0 + d * d)
            } else {
                0.0
            };
        }
        // EM's weighted TLS; the normal keeps the orientation of the last one.
        let Some((m, rho)) = weighted_fit(local, &w, n) else {
            break;
        };
        (n, r) = (m, rho);
    }
    (n, r)
}

#[cfg(test)]
mod tests {
    use super::*;
    use rand::{Rng, SeedableRng};

    fn params() -> SnapParams {
        SnapParams {
            search_band: 0.5,
            sigma: 0.03,
            closeness: 0.2,
            pointing: 0.1,
            min_support: 8,
        }
    }

    /// Points along the line y = `y` (x in [x0, x1]) with noise, every 5 cm.
    fn wall(rng: &mut impl Rng, y: f64, x0: f64, x1: f64, tilt: f64, noise: f64) -> Vec<f64> {
        let mut out = Vec::new();
        let mut x = x0;
        while x <= x1 {
            let n: f64 = (0..12).map(|_| rng.random::<f64>()).sum::<f64>() - 6.0;
            out.push(x);
            out.push(y + tilt * (x - x0) + noise * n);
            x += 0.05;
        }
        out
    }

    fn run(flat: &[f64], seg: Segment) -> Option<Snap> {
        let pts = Points::new(flat).unwrap();
        let grid = GridIndex::build(pts, 0.3).unwrap();
        snap(pts, &grid, &seg, &params()).unwrap()
    }

    #[test]
    fn a_drawing_beside_its_wall_snaps_onto_it_and_not_onto_the_far_copy() {
        let mut rng = rand::rngs::StdRng::seed_from_u64(1);
        let mut flat = wall(&mut rng, 0.0, 0.0, 6.0, 0.0, 0.015);
        flat.extend(wall(&mut rng, 0.6, 0.0, 6.0, 0.0, 0.015));
        // Clutter over the whole area.
        for _ in 0..400 {
            flat.push(rng.random::<f64>() * 6.0);
            flat.push(rng.random::<f64>() * 1.2 - 0.3);
        }
        for (y0, y1, want) in [(0.15, 0.18, 0.0), (-0.12, -0.2, 0.0), (0.42, 0.45, 0.6)] {
            let s = run(&flat, Segment::new([1.0, y0], [5.0, y1])).unwrap();
            for p in [s.segment.a, s.segment.b] {
                assert!((p[1] - want).abs() < 0.02, "{s:?} wanted y = {want}");
            }
            assert!(s.support > 60, "{s:?}");
        }
    }

    #[test]
    fn a_drawing_between_two_copies_names_the_other_reading() {
        // Two equally dense copies 0.3 m apart and a stroke midway: the snap picks one, scores
        // the other nearly the same, and projects the stroke onto it as the other reading.
        let mut rng = rand::rngs::StdRng::seed_from_u64(5);
        let mut flat = wall(&mut rng, 0.0, 0.0, 6.0, 0.0, 0.01);
        flat.extend(wall(&mut rng, 0.3, 0.0, 6.0, 0.0, 0.01));
        let s = run(&flat, Segment::new([5.0, 0.16], [1.0, 0.14])).unwrap();
        let chosen = s.segment.a[1];
        let want = if chosen.abs() < 0.02 { 0.3 } else { 0.0 };
        assert!(chosen.abs() < 0.02 || (chosen - 0.3).abs() < 0.02, "{s:?}");
        assert!(s.score - s.runner_up < 0.5, "{s:?}");
        let other = s.runner_up_segment.expect("the other copy");
        for p in [other.a, other.b] {
            assert!((p[1] - want).abs() < 0.02, "{s:?}");
        }
        // Drawn order kept: a near x = 5, b near x = 1.
        assert!(other.a[0] > 4.9 && other.b[0] < 1.1, "{other:?}");
        // A stroke on one copy: the other is far behind in score.
        let clear = run(&flat, Segment::new([1.0, 0.01], [5.0, 0.0])).unwrap();
        assert!(clear.segment.a[1].abs() < 0.02, "{clear:?}");
        assert!(clear.score - clear.runner_up > 1.0, "{clear:?}");
        assert!(clear.runner_up_segment.is_none(), "{clear:?}");
    }

    #[test]
    fn finds_a_tilted_wall_and_keeps_the_drawn_ends_in_order() {
        let mut rng = rand::rngs::StdRng::seed_from_u64(2);
        let tilt = 0.06f64.tan();
        let flat = wall(&mut rng, 0.0, 0.0, 4.0, tilt, 0.01);
        let s = run(&flat, Segment::new([3.5, 0.35], [0.5, 0.1])).unwrap();
        assert!(
            (s.segment.a[1] - tilt * s.segment.a[0]).abs() < 0.01,
            "{s:?}"
        );
        assert!(
            (s.segment.b[1] - tilt * s.segment.b[0]).abs() < 0.01,
            "{s:?}"
        );
        // Drawing direction does not change the line.
        let r = run(&flat, Segment::new([0.5, 0.1], [3.5, 0.35])).unwrap();
        assert!((r.segment.b[1] - s.segment.a[1]).abs() < 1e-9);
    }

    #[test]
    fn a_short_drawing_at_a_corner_keeps_to_its_wall() {
        // A 22 cm stroke along the end of a short wall y = 0 that meets a dense wall x = 0.3:
        // the refinement alone slides onto the crossing wall (63 degrees); the snapped line must
        // stay within the searched turn of the stroke.
        let mut rng = rand::rngs::StdRng::seed_from_u64(4);
        let mut flat = wall(&mut rng, 0.0, 0.0, 0.25, 0.0, 0.01);
        for k in 0..400 {
            flat.push(0.3 + 0.005 * ((k % 3) as f64 - 1.0));
            flat.push(-1.0 + 0.005 * k as f64);
        }
        let s = run(&flat, Segment::new([0.1, 0.1], [0.3, 0.0])).unwrap();
        assert!(s.turn <= MAX_TURN_CAP + 0.05 + 1e-12, "{s:?}");
    }

    #[test]
    fn nothing_dense_nearby_gives_none() {
        let mut rng = rand::rngs::StdRng::seed_from_u64(3);
        let mut flat = Vec::new();
        for _ in 0..30 {
            flat.push(rng.random::<f64>() * 4.0);
            flat.push(rng.random::<f64>() * 1.0 - 0.5);
        }
        assert!(run(&flat, Segment::new([0.0, 0.0], [4.0, 0.0])).is_none());
        let far = wall(&mut rng, 3.0, 0.0, 4.0, 0.0, 0.01);
        assert!(run(&far, Segment::new([0.0, 0.0], [4.0, 0.0])).is_none());
    }
}
