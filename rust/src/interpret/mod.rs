//! Interpreting a drawn segment (docs/ALGORITHM.md §3.1 to §3.3): a uniform-grid spatial index
//! over the world points, the candidates within the band `r_c` of a segment, and the EM fit of the
//! feature line (responsibilities, weighted total least squares, mixing weight, log-likelihood).
//!
//! Lines are undirected: every quantity here is computed in a frame built from the segment's
//! midpoint and a canonical normal, so drawing a segment either way gives bit-identical results.
//!
//! Points cross this boundary as flat interleaved `x, y` slices (a C-contiguous `(P, 2)` numpy
//! array as is), wrapped in [`Points`], so the Python layer never copies the map.

mod em;
mod grid;
mod snap;

pub use em::{
    em_fit, em_fit_near, em_fit_scans, em_fit_segments, line_fit, log_likelihood, reach,
    responsibilities, EmFit, EmParams, LineFit, MAX_MIXING, MIN_MIXING,
};
pub use grid::{candidates, candidates_brute_force, GridIndex};
pub use snap::{snap, Snap, SnapParams, NEAR_TIE};

use crate::error::{HitlError, Result};
use crate::se2::transform;

/// A point of the plane, `[x, y]`, world frame unless said otherwise.
pub use crate::geometry::Point;

/// Segments shorter than this (metres) have no direction; they are rejected.
pub const MIN_SEGMENT_LENGTH: f64 = 1e-6;

/// A borrowed `(P, 2)` array of points stored as `x0, y0, x1, y1, ...`.
#[derive(Clone, Copy, Debug)]
pub struct Points<'a> {
    flat: &'a [f64],
}

impl<'a> Points<'a> {
    /// Wraps an interleaved slice; its length must be even.
    pub fn new(flat: &'a [f64]) -> Result<Self> {
        if flat.len() % 2 != 0 {
            return Err(HitlError::Input(format!(
                "points must be (x, y) pairs, got {} numbers",
                flat.len()
            )));
        }
        Ok(Self { flat })
    }

    /// Number of points.
    pub fn len(&self) -> usize {
        self.flat.len() / 2
    }

    pub fn is_empty(&self) -> bool {
        self.flat.is_empty()
    }

    /// Point `i`, or None past the end.
    #[inline]
    pub fn get(&self, i: usize) -> Option<Point> {
        let x = *self.flat.get(2 * i)?;
        let y = *self.flat.get(2 * i + 1)?;
        Some([x, y])
    }

    /// The points in order.
    pub fn iter(&self) -> impl Iterator<Item = Point> + 'a {
        self.flat.chunks_exact(2).map(|c| [c[0], c[1]])
    }

    /// Fails, naming the first offending row, unless every coordinate is finite.
    pub fn check_finite(&self, what: &str) -> Result<()> {
        match self
            .iter()
            .position(|p| !(p[0].is_finite() && p[1].is_finite()))
        {
            None => Ok(()),
            Some(i) => Err(HitlError::Input(format!(
                "{what} row {i} is not finite; remove or fix that point"
            ))),
        }
    }
}

/// A segment drawn by a person, world frame. Its direction carries no meaning.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Segment {
    pub a: Point,
    pub b: Point,
}

impl Segment {
    pub fn new(a: Point, b: Point) -> Self {
        Self { a, b }
    }
}

/// The axis-aligned bounding box of a point set.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Bounds {
    pub min: Point,
    pub max: Point,
}

impl Bounds {
    /// Contains nothing; `add` grows it.
    pub const EMPTY: Bounds = Bounds {
        min: [f64::INFINITY; 2],
        max: [f64::NEG_INFINITY; 2],
    };

    #[inline]
    pub fn add(&mut self, p: Point) {
        self.min = [self.min[0].min(p[0]), self.min[1].min(p[1])];
        self.max = [self.max[0].max(p[0]), self.max[1].max(p[1])];
    }

    /// The circle around the box: its centre and half its diagonal.
    pub fn circle(&self) -> (Point, f64) {
        let mid = [
            0.5 * (self.min[0] + self.max[0]),
            0.5 * (self.min[1] + self.max[1]),
        ];
        let half = [
            0.5 * (self.max[0] - self.min[0]),
            0.5 * (self.max[1] - self.min[1]),
        ];
        (mid, dot(half, half).sqrt())
    }

    pub fn merge(self, other: Bounds) -> Bounds {
        Bounds {
            min: [self.min[0].min(other.min[0]), self.min[1].min(other.min[1])],
            max: [self.max[0].max(other.max[0]), self.max[1].max(other.max[1])],
        }
    }

    /// The bounds of `points`, failing (naming the row) on a non-finite coordinate.
    pub fn of(points: Points<'_>) -> Result<Self> {
        // Two interleaved accumulators halve the dependency chains of min/max.
        let (mut even, mut odd) = (Bounds::EMPTY, Bounds::EMPTY);
        let mut finite = true;
        let mut pairs = points.flat.chunks_exact(4);
        for c in &mut pairs {
            finite &= c.iter().all(|v| v.is_finite());
            even.add([c[0], c[1]]);
            odd.add([c[2], c[3]]);
        }
        if let [x, y] = *pairs.remainder() {
            finite &= x.is_finite() & y.is_finite();
            even.add([x, y]);
        }
        if !finite {
            points.check_finite("world point")?;
        }
        Ok(even.merge(odd))
    }
}

/// World points and their bounds, from [`world_points`].
#[derive(Clone, Debug, PartialEq)]
pub struct WorldPoints {
    /// `(P, 2)` flat.
    pub flat: Vec<f64>,
    pub bounds: Bounds,
}

/// Points in the world frame: `p_world = R(theta_i) s + t_i` for each pose's scan, with their
/// bounds computed in the same pass (so the grid needs no extra pass over the map).
///
/// `poses` is `(N, 3)` flat (x, y, theta), `points` `(P, 2)` robot-frame points pose by pose,
/// and pose i owns rows `offsets[i]..offsets[i + 1]`.
pub fn world_points(poses: &[f64], points: Points<'_>, offsets: &[i64]) -> Result<WorldPoints> {
    Ok(world_points_where(poses, points, offsets, |_, _| true)?.0)
}

/// Consecutive points of a scan tested together by [`world_points_near`]: neighbouring beams
/// mostly hit one surface, so a block's bounding circle is small.
const NEAR_BLOCK: usize = 32;

/// [`world_points`] of only the points that can lie within `band` of one of `segments`, with
/// the map row of each point kept. Each scan is cut into blocks of [`NEAR_BLOCK`] consecutive
/// points; every point of a block lies within the block's bounding circle (centre and radius
/// from its robot-frame bounding box; the transform is rigid), so a block whose circle stays
/// more than `band` from every segment holds no candidate. The candidates are exactly those of
/// the whole map, in the same order, at a fraction of the cost on a large map. Every point is
/// still checked finite.
pub fn world_points_near(
    poses: &[f64],
    points: Points<'_>,
    offsets: &[i64],
    segments: &[Segment],
    band: f64,
) -> Result<(WorldPoints, Vec<usize>)> {
    world_points_where(poses, points, offsets, |centre, radius| {
        // A margin far above rounding, so the cut never drops a candidate.
        let reach = radius + band + 1e-9 * (1.0 + radius + band + dot(centre, centre).sqrt());
        segments
            .iter()
            .any(|seg| segment_distance(centre, seg) <= reach)
    })
}

/// The bounding circles of a map's scan blocks ([`NEAR_BLOCK`] consecutive points of one scan)
/// in the robot frame, computed once per map, so that [`ScanBlocks::world_points_near`] culls a
/// map of millions of points by its blocks without reading the points it drops. The points are
/// checked finite once, here.
#[derive(Clone, Debug)]
pub struct ScanBlocks {
    /// Per block: its pose, first map row, number of points, robot-frame centre and radius.
    blocks: Vec<(usize, usize, usize, Point, f64)>,
    /// Per pose: its first block (`scans[i]..scans[i + 1]` are pose i's blocks) and the
    /// robot-frame circle around all of them, so a scan far from every segment is skipped whole.
    scans: Vec<usize>,
    circles: Vec<(Point, f64)>,
}

impl ScanBlocks {
    pub fn new(points: Points<'_>, offsets: &[i64]) -> Result<Self> {
        if offsets.first().copied().unwrap_or(-1) != 0
            || offsets.last().copied().unwrap_or(-1) != points.len() as i64
            || offsets.windows(2).any(|w| w[1] < w[0])
        {
            return Err(HitlError::Input(format!(
                "offsets must rise from 0 to the number of points ({})",
                points.len()
            )));
        }
        points.check_finite("point")?;
        let mut blocks = Vec::with_capacity(points.len() / NEAR_BLOCK + offsets.len());
        let mut scans = Vec::with_capacity(offsets.len());
        let mut circles = Vec::with_capacity(offsets.len());
        for (i, w) in offsets.windows(2).enumerate() {
            let (first, end) = (w[0] as usize, w[1] as usize);
            scans.push(blocks.len());
            let circle = |from: usize, to: usize| {
                let mut b = Bounds::EMPTY;
                for k in from..to {
                    b.add([points.flat[2 * k], points.flat[2 * k + 1]]);
                }
                b.circle()
            };
            circles.push(if first < end {
                circle(first, end)
            } else {
                ([0.0, 0.0], 0.0)
            });
            for start in (first..end).step_by(NEAR_BLOCK) {
                let len = NEAR_BLOCK.min(end - start);
                let (mid, radius) = circle(start, start + len);
                blocks.push((i, start, len, mid, radius));
            }
        }
        scans.push(blocks.len());
        Ok(Self {
            blocks,
            scans,
            circles,
        })
    }

    /// [`world_points_near`] from the kept blocks: the same points in the same order (map
    /// rows ascending), at a cost proportional to the blocks and the points kept. `poses` must
    /// be the map's (N, 3) flat, finite.
    pub fn world_points_near(
        &self,
        poses: &[f64],
        points: Points<'_>,
        segments: &[Segment],
        band: f64,
    ) -> (WorldPoints, Vec<usize>) {
        let mut out = Vec::new();
        let mut rows = Vec::new();
        let mut bounds = Bounds::EMPTY;
        let near = |centre: Point, radius: f64| {
            // A margin far above rounding, so the cut never drops a candidate.
            let reach = radius + band + 1e-9 * (1.0 + radius + band + dot(centre, centre).sqrt());
            segments
                .iter()
                .any(|seg| segment_distance(centre, seg) <= reach)
        };
        for (i, pose) in poses.chunks_exact(3).enumerate() {
            let (first, end) = (self.scans[i], self.scans[i + 1]);
            if first == end {
                continue;
            }
            let (s, c) = pose[2].sin_cos();
            let t = [pose[0], pose[1]];
            let (mid, radius) = self.circles[i];
            if !near(transform(c, s, t, mid), radius) {
                continue;
            }
            for &(_, start, len, mid, radius) in &self.blocks[first..end] {
                if !near(transform(c, s, t, mid), radius) {
                    continue;
                }
                for k in start..start + len {
                    let world = transform(c, s, t, [points.flat[2 * k], points.flat[2 * k + 1]]);
                    bounds.add(world);
                    out.extend_from_slice(&world);
                    rows.push(k);
                }
            }
        }
        (WorldPoints { flat: out, bounds }, rows)
    }
}

/// The world points of the blocks of [`NEAR_BLOCK`] scan points for which `keep(world centre,
/// radius)` of the block's bounding circle holds, with their map rows and bounds.
fn world_points_where(
    poses: &[f64],
    points: Points<'_>,
    offsets: &[i64],
    keep: impl Fn(Point, f64) -> bool,
) -> Result<(WorldPoints, Vec<usize>)> {
    check_layout(poses, points, offsets)?;
    let mut out = Vec::new();
    let mut rows = Vec::new();
    let mut bounds = Bounds::EMPTY;
    for (i, (pose, w)) in poses.chunks_exact(3).zip(offsets.windows(2)).enumerate() {
        let (x, y, theta) = (pose[0], pose[1], pose[2]);
        // Both bounds lie in 0..=P: check_layout checked the ends and that they never decrease.
        let first = w[0] as usize;
        let Some(src) = points.flat.get(2 * first..2 * w[1] as usize) else {
            return Err(HitlError::Input(format!(
                "offsets of pose {i} point past the end of the points"
            )));
        };
        let (s, c) = theta.sin_cos();
        for (b, block) in src.chunks(2 * NEAR_BLOCK).enumerate() {
            let start = first + b * NEAR_BLOCK;
            let mut boxed = Bounds::EMPTY;
            for (k, p) in block.chunks_exact(2).enumerate() {
                if !(p[0].is_finite() && p[1].is_finite()) {
                    return Err(HitlError::Input(format!(
                        "point row {} is not finite; remove or fix that point",
                        start + k
                    )));
                }
                boxed.add([p[0], p[1]]);
            }
            let (mid, radius) = boxed.circle();
            let centre = [c * mid[0] - s * mid[1] + x, s * mid[0] + c * mid[1] + y];
            if !keep(centre, radius) {
                continue;
            }
            for (k, p) in block.chunks_exact(2).enumerate() {
                let world = transform(c, s, [x, y], [p[0], p[1]]);
                bounds.add(world);
                out.extend_from_slice(&world);
                rows.push(start + k);
            }
        }
    }
    Ok((WorldPoints { flat: out, bounds }, rows))
}

/// Distance from `p` to the segment `seg` (to its nearer end past either end).
fn segment_distance(p: Point, seg: &Segment) -> f64 {
    let d = sub(seg.b, seg.a);
    let len_sq = dot(d, d);
    let t = if len_sq > 0.0 {
        (dot(sub(p, seg.a), d) / len_sq).clamp(0.0, 1.0)
    } else {
        0.0
    };
    let q = [seg.a[0] + t * d[0], seg.a[1] + t * d[1]];
    let e = sub(p, q);
    dot(e, e).sqrt()
}

/// The shape checks shared by the scan transforms: `poses` `(N, 3)` flat and finite, `offsets`
/// `(N + 1,)` non-decreasing from 0 to the number of points.
fn check_layout(poses: &[f64], points: Points<'_>, offsets: &[i64]) -> Result<()> {
    let n = poses.len() / 3;
    if poses.len() % 3 != 0 {
        return Err(HitlError::Input(format!(
            "poses must have shape (N, 3), got {} numbers",
            poses.len()
        )));
    }
    if offsets.len() != n + 1 {
        return Err(HitlError::Input(format!(
            "offsets must have N + 1 = {} entries, got {}",
            n + 1,
            offsets.len()
        )));
    }
    if offsets.first().copied().unwrap_or(-1) != 0
        || offsets.last().copied().unwrap_or(-1) != points.len() as i64
    {
        return Err(HitlError::Input(format!(
            "offsets must run from 0 to the number of points ({})",
            points.len()
        )));
    }
    for (i, (pose, w)) in poses.chunks_exact(3).zip(offsets.windows(2)).enumerate() {
        let (x, y, theta) = (pose[0], pose[1], pose[2]);
        if !(x.is_finite() && y.is_finite() && theta.is_finite()) {
            return Err(HitlError::Input(format!(
                "pose {i} is not finite ({x}, {y}, {theta}); give finite poses"
            )));
        }
        if w[1] < w[0] {
            return Err(HitlError::Input(format!(
                "offsets must be non-decreasing (entry {i} is {} > {})",
                w[0], w[1]
            )));
        }
    }
    Ok(())
}

pub(crate) use crate::geometry::{dot, sub};

/// The unit normal of a line, made unique: angle in (-pi/2, pi/2]. `n` and `-n` describe the
/// same undirected line, and both map to the same canonical vector bit for bit (adding 0.0
/// turns a -0.0 component into +0.0).
#[inline]
pub(crate) fn canonical_normal(n: Point) -> Point {
    if n[0] < 0.0 || (n[0] == 0.0 && n[1] < 0.0) {
        [-n[0] + 0.0, -n[1] + 0.0]
    } else {
        [n[0] + 0.0, n[1] + 0.0]
    }
}

/// The tangent that goes with a normal (the normal turned by -90 degrees).
#[inline]
pub(crate) fn tangent(n: Point) -> Point {
    [n[1], -n[0]]
}

/// A segment in its direction-free frame: midpoint, half-length, canonical normal and tangent.
/// Everything derived from a segment goes through this so that `a <-> b` cannot matter.
#[derive(Clone, Copy, Debug)]
pub(crate) struct SegmentFrame {
    pub mid: Point,
    pub half: f64,
    pub n: Point,
    pub u: Point,
}

impl SegmentFrame {
    pub fn new(seg: &Segment) -> Result<Self> {
        let coords = [seg.a[0], seg.a[1], seg.b[0], seg.b[1]];
        if !coords.iter().all(|v| v.is_finite()) {
            return Err(HitlError::Input(format!(
                "segment {:?} -> {:?} has a non-finite coordinate; draw it again",
                seg.a, seg.b
            )));
        }
        let d = sub(seg.b, seg.a);
        let len = d[0].hypot(d[1]);
        if len < MIN_SEGMENT_LENGTH {
            return Err(HitlError::Input(format!(
                "segment {:?} -> {:?} has length {len:.3e} m; draw a segment along the feature",
                seg.a, seg.b
            )));
        }
        // Swapping a and b negates d exactly, so the canonical normal is the same bits.
        let n = canonical_normal([-d[1] / len, d[0] / len]);
        Ok(Self {
            mid: [0.5 * (seg.a[0] + seg.b[0]), 0.5 * (seg.a[1] + seg.b[1])],
            half: 0.5 * len,
            n,
            u: tangent(n),
        })
    }

    /// Squared distance from `p` to the segment (not the infinite line).
    #[inline]
    pub fn distance_sq(&self, p: Point) -> f64 {
        let q = sub(p, self.mid);
        let along = (dot(q, self.u).abs() - self.half).max(0.0);
        let across = dot(q, self.n);
        along * along + across * across
    }

    /// The endpoints, in the canonical order (along the tangent).
    pub fn endpoints(&self) -> [Point; 2] {
        let (m, u, h) = (self.mid, self.u, self.half);
        [
            [m[0] - h * u[0], m[1] - h * u[1]],
            [m[0] + h * u[0], m[1] + h * u[1]],
        ]
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn frame_does_not_depend_on_direction() {
        let s = Segment::new([1.25, -3.5], [4.75, 2.125]);
        let r = Segment::new(s.b, s.a);
        let (f, g) = (
            SegmentFrame::new(&s).unwrap(),
            SegmentFrame::new(&r).unwrap(),
        );
        assert_eq!(f.mid, g.mid);
        assert_eq!(f.half, g.half);
        assert_eq!(f.n, g.n);
        assert_eq!(f.u, g.u);
        assert!(f.n[0] >= 0.0);
    }

    #[test]
    fn segment_distance_is_metric_past_the_ends() {
        let f = SegmentFrame::new(&Segment::new([0.0, 0.0], [10.0, 0.0])).unwrap();
        assert!((f.distance_sq([5.0, 3.0]) - 9.0).abs() < 1e-12);
        assert!((f.distance_sq([13.0, 4.0]) - 25.0).abs() < 1e-12);
        assert!((f.distance_sq([-3.0, -4.0]) - 25.0).abs() < 1e-12);
        assert_eq!(f.distance_sq([2.0, 0.0]), 0.0);
    }

    #[test]
    fn bad_segments_are_input_errors() {
        let z = Segment::new([1.0, 1.0], [1.0, 1.0 + 1e-9]);
        assert!(matches!(SegmentFrame::new(&z), Err(HitlError::Input(_))));
        let n = Segment::new([f64::NAN, 1.0], [2.0, 1.0]);
        assert!(matches!(SegmentFrame::new(&n), Err(HitlError::Input(_))));
    }

    #[test]
    fn points_wrapper_checks_shape_and_finiteness() {
        assert!(Points::new(&[1.0, 2.0, 3.0]).is_err());
        let p = Points::new(&[1.0, 2.0, f64::INFINITY, 0.0]).unwrap();
        assert_eq!(p.len(), 2);
        assert_eq!(p.get(0), Some([1.0, 2.0]));
        assert_eq!(p.get(2), None);
        assert!(p.check_finite("points").is_err());
    }

    #[test]
    fn world_points_transform_each_scan() {
        let poses = [1.0, 2.0, std::f64::consts::FRAC_PI_2, -1.0, 0.0, 0.0];
        let pts = [1.0, 0.0, 0.0, 1.0, 2.0, 3.0];
        let w = world_points(&poses, Points::new(&pts).unwrap(), &[0, 2, 3]).unwrap();
        let want = [1.0, 3.0, 0.0, 2.0, 1.0, 3.0];
        for (a, b) in w.flat.iter().zip(want) {
            assert!((a - b).abs() < 1e-12, "{w:?}");
        }
        assert_eq!(w.bounds, Bounds::of(Points::new(&w.flat).unwrap()).unwrap());
        assert!((w.bounds.min[0]).abs() < 1e-12 && (w.bounds.max[1] - 3.0).abs() < 1e-12);
        let p = Points::new(&pts).unwrap();
        assert!(world_points(&poses, p, &[0, 2]).is_err());
        assert!(world_points(&poses, p, &[0, 3, 2]).is_err());
        assert!(world_points(&poses, p, &[1, 2, 3]).is_err());
        assert!(world_points(&[0.0, f64::NAN, 0.0], p, &[0, 3]).is_err());
        let inf = [0.0, 0.0, f64::INFINITY, 1.0];
        let err = world_points(&[0.0; 3], Points::new(&inf).unwrap(), &[0, 2]).unwrap_err();
        assert!(err.to_string().contains("row 1"), "{err}");
    }

    #[test]
    fn scan_blocks_keep_exactly_the_points_of_the_per_point_cut() {
        use rand::{Rng, SeedableRng};
        let mut rng = rand::rngs::StdRng::seed_from_u64(7);
        for _ in 0..20 {
            let n = rng.random_range(1..40);
            let mut offsets = vec![0i64];
            let mut flat = Vec::new();
            for _ in 0..n {
                let k = rng.random_range(0..100);
                for _ in 0..k {
                    flat.push(rng.random_range(-8.0..8.0));
                    flat.push(rng.random_range(-8.0..8.0));
                }
                offsets.push(offsets.last().unwrap() + k);
            }
            let poses: Vec<f64> = (0..n)
                .flat_map(|_| {
                    [
                        rng.random_range(-20.0..20.0),
                        rng.random_range(-20.0..20.0),
                        rng.random_range(-4.0..4.0),
                    ]
                })
                .collect();
            let segments = [
                Segment::new(
                    [rng.random_range(-20.0..20.0), 0.0],
                    [3.0, rng.random_range(-9.0..9.0)],
                ),
                Segment::new([-5.0, -5.0], [rng.random_range(-20.0..20.0), 2.0]),
            ];
            let pts = Points::new(&flat).unwrap();
            let blocks = ScanBlocks::new(pts, &offsets).unwrap();
            for band in [0.1, 1.0, 4.0] {
                let want = world_points_near(&poses, pts, &offsets, &segments, band).unwrap();
                let got = blocks.world_points_near(&poses, pts, &segments, band);
                assert_eq!(got.1, want.1);
                assert_eq!(got.0, want.0);
            }
        }
    }

    #[test]
    fn bounds_of_odd_and_even_counts() {
        for n in 0..7 {
            let flat: Vec<f64> = (0..2 * n).map(|k| ((k * 37) % 11) as f64 - 5.0).collect();
            let pts = Points::new(&flat).unwrap();
            let mut want = Bounds::EMPTY;
            pts.iter().for_each(|p| want.add(p));
            assert_eq!(Bounds::of(pts).unwrap(), want);
        }
        assert!(Bounds::of(Points::new(&[1.0, 2.0, 3.0, f64::NAN, 0.0, 0.0]).unwrap()).is_err());
    }
}
