//! The explicit correction (docs/ALGORITHM.md §4.1): the rigid SE(2) transform `A` that brings the
//! drawn feature `P_b` into the mode's relation with `P_a`, moving nothing along the mode's
//! null-space.
//!
//! Rotation: the smallest angle taking line b onto line a modulo pi (perpendicular: onto a
//! direction perpendicular to a), about `cm_b`, the centre of `P_b`. Translation: colocation
//! `cm_a - cm_b`, collinear the component along a's normal only, perpendicular and parallel none.

use crate::error::{input, Result};
use crate::factors::human::{line_angle_error, RelationMode};
use crate::se2::Pose2;

/// A segment by its endpoints (world frame).
pub type Segment2 = [[f64; 2]; 2];

fn direction_angle(s: &Segment2) -> Result<f64> {
    let (dx, dy) = (s[1][0] - s[0][0], s[1][1] - s[0][1]);
    if !(dx.is_finite() && dy.is_finite()) {
        return input("segment endpoints must be finite");
    }
    if dx.hypot(dy) < 1e-9 {
        return input("a zero-length segment has no direction");
    }
    Ok(dy.atan2(dx))
}

/// `A` as a pose: `p_new = A * p_old` for every moved pose.
pub fn explicit_transform(mode: RelationMode, p_a: &Segment2, p_b: &Segment2) -> Result<Pose2> {
    let ang_a = direction_angle(p_a)?;
    let ang_b = direction_angle(p_b)?;
    // line_angle_error(a, b) is the angle from a to b; rotating b by its negative aligns it.
    let dphi = -line_angle_error(mode, ang_a, ang_b);
    let cm_a = [0.5 * (p_a[0][0] + p_a[1][0]), 0.5 * (p_a[0][1] + p_a[1][1])];
    let cm_b = [0.5 * (p_b[0][0] + p_b[1][0]), 0.5 * (p_b[0][1] + p_b[1][1])];
    let diff = [cm_a[0] - cm_b[0], cm_a[1] - cm_b[1]];
    let shift = match mode {
        RelationMode::Colocation => diff,
        RelationMode::Collinear => {
            let n = [-ang_a.sin(), ang_a.cos()];
            let d = n[0] * diff[0] + n[1] * diff[1];
            [d * n[0], d * n[1]]
        }
        RelationMode::Perpendicular | RelationMode::Parallel => [0.0, 0.0],
    };
    // A = T(cm_b + shift) R(dphi) T(-cm_b)
    let (c, s) = (dphi.cos(), dphi.sin());
    let rc = [c * cm_b[0] - s * cm_b[1], s * cm_b[0] + c * cm_b[1]];
    Ok(Pose2::new(
        cm_b[0] + shift[0] - rc[0],
        cm_b[1] + shift[1] - rc[1],
        dphi,
    ))
}

#[cfg(test)]
mod tests {
    use super::*;

    fn apply(a: Pose2, s: &Segment2) -> Segment2 {
        [a.transform_point(s[0]), a.transform_point(s[1])]
    }

    fn dir(s: &Segment2) -> f64 {
        (s[1][1] - s[0][1]).atan2(s[1][0] - s[0][0])
    }

    #[test]
    fn each_mode_establishes_its_relation_and_nothing_more() {
        let pa: Segment2 = [[0.0, 0.0], [4.0, 0.0]];
        let pb: Segment2 = [[6.0, 1.0], [9.0, 1.3]];
        let mid = |s: &Segment2| [0.5 * (s[0][0] + s[1][0]), 0.5 * (s[0][1] + s[1][1])];
        // colocation: same direction and same centre
        let a = explicit_transform(RelationMode::Colocation, &pa, &pb).unwrap();
        let nb = apply(a, &pb);
        assert!(line_angle_error(RelationMode::Parallel, dir(&pa), dir(&nb)).abs() < 1e-12);
        assert!((mid(&nb)[0] - 2.0).abs() < 1e-12 && mid(&nb)[1].abs() < 1e-12);
        // collinear: on a's line; the centre moved only along a's normal (y), not along a (x)
        let a = explicit_transform(RelationMode::Collinear, &pa, &pb).unwrap();
        let nb = apply(a, &pb);
        assert!(nb[0][1].abs() < 1e-12 && nb[1][1].abs() < 1e-12);
        assert!(
            (mid(&nb)[0] - mid(&pb)[0]).abs() < 1e-12,
            "slid along the line"
        );
        // parallel: rotation about cm_b only
        let a = explicit_transform(RelationMode::Parallel, &pa, &pb).unwrap();
        let nb = apply(a, &pb);
        assert!(line_angle_error(RelationMode::Parallel, dir(&pa), dir(&nb)).abs() < 1e-12);
        assert!(
            (mid(&nb)[0] - mid(&pb)[0]).abs() < 1e-12 && (mid(&nb)[1] - mid(&pb)[1]).abs() < 1e-12
        );
        // perpendicular
        let pc: Segment2 = [[5.0, 0.0], [5.2, 3.0]];
        let a = explicit_transform(RelationMode::Perpendicular, &pa, &pc).unwrap();
        let nc = apply(a, &pc);
        assert!(line_angle_error(RelationMode::Perpendicular, dir(&pa), dir(&nc)).abs() < 1e-12);
        assert!((mid(&nc)[0] - mid(&pc)[0]).abs() < 1e-12);
    }

    #[test]
    fn drawing_direction_does_not_matter() {
        let pa: Segment2 = [[0.0, 0.0], [4.0, 0.1]];
        let pb: Segment2 = [[6.0, 1.0], [9.0, 2.3]];
        let ra: Segment2 = [pa[1], pa[0]];
        let rb: Segment2 = [pb[1], pb[0]];
        for mode in [
            RelationMode::Colocation,
            RelationMode::Collinear,
            RelationMode::Perpendicular,
            RelationMode::Parallel,
        ] {
            let base = explicit_transform(mode, &pa, &pb).unwrap();
            for (x, y) in [(&ra, &pb), (&pa, &rb), (&ra, &rb)] {
                let other = explicit_transform(mode, x, y).unwrap();
                assert!((base.x - other.x).abs() < 1e-12 && (base.y - other.y).abs() < 1e-12);
                assert!((base.theta - other.theta).abs() < 1e-12);
            }
        }
    }

    #[test]
    fn a_wall_near_135_degrees_does_not_flip() {
        // The released code treated lines as directed and rotated by pi here.
        let pa: Segment2 = [[0.0, 0.0], [-1.0, 1.0]];
        let pb: Segment2 = [[5.0, 5.0], [6.0, 4.02]];
        let a = explicit_transform(RelationMode::Parallel, &pa, &pb).unwrap();
        assert!(a.theta.abs() < 0.05, "{}", a.theta);
    }

    #[test]
    fn degenerate_segments_are_errors() {
        let p: Segment2 = [[1.0, 1.0], [1.0, 1.0]];
        let q: Segment2 = [[0.0, 0.0], [1.0, 0.0]];
        assert!(explicit_transform(RelationMode::Parallel, &p, &q).is_err());
        assert!(
            explicit_transform(RelationMode::Parallel, &q, &[[f64::NAN, 0.0], [1.0, 1.0]]).is_err()
        );
    }
}
