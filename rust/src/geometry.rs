//! Lines in the plane: the total-least-squares fit (weighted PCA of a 2D point set) and the
//! point-to-line distance. The only copy: interpretation's EM, the scan matcher's normals and the
//! correction engine's starting lines all use these (SE(2) pose math is in [`crate::se2`]).

use crate::values::Line2;

/// A point or vector in the plane.
pub type Point = [f64; 2];

/// The scatter of a point set has no principal direction when its two eigenvalues differ by
/// less than this fraction of their sum (one point, or an isotropic cloud).
pub const ISOTROPIC: f64 = 1e-12;

#[inline]
pub fn dot(a: Point, b: Point) -> f64 {
    a[0] * b[0] + a[1] * b[1]
}

#[inline]
pub fn sub(a: Point, b: Point) -> Point {
    [a[0] - b[0], a[1] - b[1]]
}

/// Signed distance of `p` from the line `n . p = rho` (`n` a unit normal).
#[inline]
pub fn line_distance(n: Point, rho: f64, p: Point) -> f64 {
    dot(n, p) - rho
}

/// The weighted centroid and scatter `(sxx, sxy, syy)` of `points`; `None` when the weights
/// carry no mass. Weights are scaled by the largest first, so tiny responsibilities (a drawing
/// far from its wall) stay away from subnormal numbers; the result depends only on relative
/// weights.
pub fn weighted_scatter(points: &[Point], weights: &[f64]) -> Option<(Point, [f64; 3])> {
    let w_max = weights.iter().copied().fold(0.0_f64, f64::max);
    if !(w_max > 0.0 && w_max.is_finite()) {
        return None;
    }
    let scale = 1.0 / w_max;
    let (mut sw, mut sx, mut sy) = (0.0, 0.0, 0.0);
    for (q, &wk) in points.iter().zip(weights) {
        let wk = wk * scale;
        sw += wk;
        sx += wk * q[0];
        sy += wk * q[1];
    }
    let c = [sx / sw, sy / sw];
    let (mut sxx, mut sxy, mut syy) = (0.0, 0.0, 0.0);
    for (q, &wk) in points.iter().zip(weights) {
        let wk = wk * scale;
        let (dx, dy) = (q[0] - c[0], q[1] - c[1]);
        sxx += wk * dx * dx;
        sxy += wk * dx * dy;
        syy += wk * dy * dy;
    }
    Some((c, [sxx, sxy, syy]))
}

/// The unit normal of the principal axis of the scatter `(sxx, sxy, syy)` (the eigenvector of
/// its smallest eigenvalue), or `None` when it has no principal direction ([`ISOTROPIC`]).
pub fn principal_normal(scatter: [f64; 3]) -> Option<Point> {
    let [sxx, sxy, syy] = scatter;
    let spread = (sxx - syy).hypot(2.0 * sxy);
    // Also None for a NaN spread.
    if spread.partial_cmp(&(ISOTROPIC * (sxx + syy))) != Some(std::cmp::Ordering::Greater) {
        return None;
    }
    // Principal axis angle of [[sxx, sxy], [sxy, syy]]; the normal is perpendicular to it.
    let theta = 0.5 * (2.0 * sxy).atan2(sxx - syy);
    let (s, c) = theta.sin_cos();
    Some([-s, c])
}

/// Weighted total least squares: the line `(n, rho)` through the weighted centroid along the
/// principal axis of the weighted scatter, in closed form. The normal is oriented like `prev`,
/// which is also used when the scatter has no principal direction. `None` when the weights
/// carry no mass.
pub fn weighted_fit(points: &[Point], weights: &[f64], prev: Point) -> Option<(Point, f64)> {
    let (c, scatter) = weighted_scatter(points, weights)?;
    let n = match principal_normal(scatter) {
        Some(n) if dot(n, prev) < 0.0 => [-n[0], -n[1]],
        Some(n) => n,
        None => prev,
    };
    Some((n, dot(n, c)))
}

/// The total-least-squares line of `points` as `(phi, rho)`, its normal oriented away from the
/// origin's side where that is defined (`rho >= 0`); a set without a principal direction gets
/// the normal (1, 0). `None` for an empty set or non-finite points.
pub fn fit_line(points: &[Point]) -> Option<Line2> {
    if points.is_empty()
        || points
            .iter()
            .any(|p| !(p[0].is_finite() && p[1].is_finite()))
    {
        return None;
    }
    let ones = vec![1.0; points.len()];
    let (n, rho) = weighted_fit(points, &ones, [1.0, 0.0])?;
    let (n, rho) = if rho < 0.0 {
        ([-n[0], -n[1]], -rho)
    } else {
        (n, rho)
    };
    Some(Line2 {
        phi: n[1].atan2(n[0]),
        rho,
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_fit_recovers_a_noisy_line_and_its_distances() {
        // Points on 0.6 x + 0.8 y = 2, in pairs 1 mm either side of it along the normal.
        let n = [0.6, 0.8];
        let pts: Vec<Point> = (0..50)
            .map(|k| {
                let t = -2.0 + 0.1 * (k / 2) as f64;
                let off = if k % 2 == 0 { 1e-3 } else { -1e-3 };
                [
                    2.0 * n[0] - t * n[1] + off * n[0],
                    2.0 * n[1] + t * n[0] + off * n[1],
                ]
            })
            .collect();
        let line = fit_line(&pts).unwrap();
        assert!((line.phi - 0.8_f64.atan2(0.6)).abs() < 1e-9);
        assert!((line.rho - 2.0).abs() < 1e-9);
        let normal = [line.phi.cos(), line.phi.sin()];
        assert!((line_distance(normal, line.rho, [0.0, 0.0]) + 2.0).abs() < 1e-9);
        // The same line through the other orientation of the normal.
        let (m, rho) = weighted_fit(&pts, &vec![1.0; pts.len()], [-0.6, -0.8]).unwrap();
        assert!(dot(m, [-0.6, -0.8]) > 0.999_999 && (rho + 2.0).abs() < 1e-9);
    }

    #[test]
    fn degenerate_sets_fall_back_or_refuse() {
        assert!(fit_line(&[]).is_none());
        assert!(fit_line(&[[f64::NAN, 0.0]]).is_none());
        let one = fit_line(&[[3.0, 4.0]]).unwrap();
        assert_eq!((one.phi, one.rho), (0.0, 3.0));
        assert!(weighted_fit(&[[0.0, 0.0]], &[0.0], [1.0, 0.0]).is_none());
        // A square's corners are isotropic: the previous normal is kept.
        let square = [[0.0, 0.0], [1.0, 0.0], [1.0, 1.0], [0.0, 1.0]];
        let (m, _) = weighted_fit(&square, &[1.0; 4], [0.0, 1.0]).unwrap();
        assert_eq!(m, [0.0, 1.0]);
    }
}
