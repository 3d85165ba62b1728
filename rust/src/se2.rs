//! SE(2) poses `(x, y, theta)`: composition, inverse, between, the exponential and logarithm maps,
//! and the chart used by the solver. theta is always kept in (-pi, pi].
//!
//! Small-angle branches use `|theta|` so negative angles take the same (Taylor) path as positive ones.

use std::f64::consts::PI;

const TAU: f64 = 2.0 * PI;

/// Wraps an angle to (-pi, pi]. Angles already in range are returned unchanged (bit for bit),
/// so tiny angles keep their full relative precision.
#[inline]
pub fn wrap_angle(a: f64) -> f64 {
    if a > -PI && a <= PI {
        return a;
    }
    let w = a.rem_euclid(TAU);
    if w > PI {
        w - TAU
    } else {
        w
    }
}

/// `(sin x, cos x)` in one call, with the `libm` crate's implementation: the solver's
/// linearization calls it for every edge, and the platform's `sin` and `cos` (glibc's) save and
/// restore the floating-point rounding mode on each call, which made them a fifth of the
/// linearization's time on City10000. The results agree to an ulp.
#[inline]
pub fn sin_cos(x: f64) -> (f64, f64) {
    libm::sincos(x)
}

/// `[[c, -s], [s, c]] * v`.
#[inline]
pub fn rotate(c: f64, s: f64, v: [f64; 2]) -> [f64; 2] {
    [c * v[0] - s * v[1], s * v[0] + c * v[1]]
}

/// `R v + t` with `R = [[c, -s], [s, c]]`: a point moved by a pose whose cosine and sine were
/// computed once for many points (scans, observation sets).
#[inline]
pub fn transform(c: f64, s: f64, t: [f64; 2], v: [f64; 2]) -> [f64; 2] {
    [c * v[0] - s * v[1] + t[0], s * v[0] + c * v[1] + t[1]]
}

/// `[[c, s], [-s, c]] * v`, the inverse rotation.
#[inline]
pub fn rotate_inv(c: f64, s: f64, v: [f64; 2]) -> [f64; 2] {
    [c * v[0] + s * v[1], -s * v[0] + c * v[1]]
}

/// `V(theta)` of the SE(2) exponential, as its two distinct entries `(A, B)`:
/// `V = [[A, -B], [B, A]]`, `A = sin(theta)/theta`, `B = (1 - cos(theta))/theta`.
#[inline]
fn v_entries(theta: f64) -> (f64, f64) {
    if theta.abs() < 1e-4 {
        let t2 = theta * theta;
        (1.0 - t2 / 6.0 + t2 * t2 / 120.0, theta * (0.5 - t2 / 24.0))
    } else {
        let (sh, ch) = sin_cos(0.5 * theta);
        (2.0 * sh * ch / theta, 2.0 * sh * sh / theta)
    }
}

/// `a(theta) = (theta/2) cot(theta/2)`, the diagonal of `V(theta)^-1 = [[a, theta/2], [-theta/2, a]]`.
#[inline]
pub fn vinv_diag(theta: f64) -> f64 {
    if theta.abs() < 1e-6 {
        1.0 - theta * theta / 12.0
    } else {
        let h = 0.5 * theta;
        h / h.tan()
    }
}

/// `d a / d theta = (sin(theta) - theta) / (4 sin^2(theta/2))`, with a series near 0 where the
/// closed form cancels.
#[inline]
pub fn vinv_diag_derivative(theta: f64) -> f64 {
    if theta.abs() < 1e-2 {
        let t2 = theta * theta;
        -theta * (1.0 / 6.0 + t2 / 180.0 + t2 * t2 / 5040.0)
    } else {
        let sh = (0.5 * theta).sin();
        (theta.sin() - theta) / (4.0 * sh * sh)
    }
}

/// A rigid transform of the plane; `t_world_robot` maps robot-frame points to world points.
#[derive(Clone, Copy, Debug, PartialEq, Default)]
pub struct Pose2 {
    pub x: f64,
    pub y: f64,
    /// Heading in (-pi, pi].
    pub theta: f64,
}

impl Pose2 {
    /// A pose; theta is wrapped to (-pi, pi].
    #[inline]
    pub fn new(x: f64, y: f64, theta: f64) -> Self {
        Self {
            x,
            y,
            theta: wrap_angle(theta),
        }
    }

    pub const IDENTITY: Pose2 = Pose2 {
        x: 0.0,
        y: 0.0,
        theta: 0.0,
    };

    #[inline]
    pub fn from_array(v: [f64; 3]) -> Self {
        Self::new(v[0], v[1], v[2])
    }

    #[inline]
    /// Whether every component is finite.
    pub fn is_finite(self) -> bool {
        self.x.is_finite() && self.y.is_finite() && self.theta.is_finite()
    }

    pub fn to_array(self) -> [f64; 3] {
        [self.x, self.y, self.theta]
    }

    #[inline]
    pub fn translation(self) -> [f64; 2] {
        [self.x, self.y]
    }

    #[inline]
    pub fn cos_sin(self) -> (f64, f64) {
        let (s, c) = sin_cos(self.theta);
        (c, s)
    }

    /// `self * other`: `other` expressed in `self`'s frame, brought to `self`'s parent frame.
    #[inline]
    pub fn compose(self, other: Pose2) -> Pose2 {
        let (c, s) = self.cos_sin();
        let t = rotate(c, s, other.translation());
        Pose2::new(self.x + t[0], self.y + t[1], self.theta + other.theta)
    }

    #[inline]
    pub fn inverse(self) -> Pose2 {
        let (c, s) = self.cos_sin();
        let t = rotate_inv(c, s, self.translation());
        Pose2::new(-t[0], -t[1], -self.theta)
    }

    /// `self^-1 * other`: `t_i_j = t_world_i.between(t_world_j)`.
    #[inline]
    pub fn between(self, other: Pose2) -> Pose2 {
        let (c, s) = self.cos_sin();
        let t = rotate_inv(c, s, [other.x - self.x, other.y - self.y]);
        Pose2::new(t[0], t[1], other.theta - self.theta)
    }

    /// Maps a point from this pose's frame to the parent frame: `p_world = R p + t`.
    #[inline]
    pub fn transform_point(self, p: [f64; 2]) -> [f64; 2] {
        let (c, s) = self.cos_sin();
        let q = rotate(c, s, p);
        [q[0] + self.x, q[1] + self.y]
    }

    /// The SE(2) exponential of a tangent vector `(v_x, v_y, omega)`.
    pub fn exp(xi: [f64; 3]) -> Pose2 {
        let (a, b) = v_entries(xi[2]);
        Pose2::new(a * xi[0] - b * xi[1], b * xi[0] + a * xi[1], xi[2])
    }

    /// The SE(2) logarithm: `(V(theta)^-1 t, theta)`, theta in (-pi, pi].
    pub fn log(self) -> [f64; 3] {
        let a = vinv_diag(self.theta);
        let h = 0.5 * self.theta;
        [
            a * self.x + h * self.y,
            -h * self.x + a * self.y,
            self.theta,
        ]
    }

    /// The solver's chart: `self * Exp(delta)` (GTSAM's Pose2 retract). Its derivative at zero is
    /// the identity, so covariances in this chart match GTSAM's `Marginals`.
    #[inline]
    pub fn retract(self, delta: [f64; 3]) -> Pose2 {
        self.compose(Pose2::exp(delta))
    }

    /// Inverse of [`Pose2::retract`]: `Log(self^-1 * other)`.
    #[inline]
    pub fn local(self, other: Pose2) -> [f64; 3] {
        self.between(other).log()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    const THETAS: [f64; 5] = [-PI + 1e-9, -1e-9, 0.0, 1e-9, PI - 1e-9];

    fn close(a: [f64; 3], b: [f64; 3], tol: f64) -> bool {
        a.iter().zip(b.iter()).enumerate().all(|(k, (x, y))| {
            let d = if k == 2 { wrap_angle(x - y) } else { x - y };
            d.abs() <= tol
        })
    }

    fn draws() -> Vec<Pose2> {
        // A fixed pseudo-random set (LCG) plus the edge angles, so failures are reproducible.
        let mut state: u64 = 0x2545_f491_4f6c_dd1d;
        let mut next = || {
            state = state
                .wrapping_mul(6364136223846793005)
                .wrapping_add(1442695040888963407);
            ((state >> 11) as f64 / (1u64 << 53) as f64) * 2.0 - 1.0
        };
        let mut out: Vec<Pose2> = THETAS.iter().map(|&t| Pose2::new(0.7, -1.3, t)).collect();
        for _ in 0..200 {
            out.push(Pose2::new(10.0 * next(), 10.0 * next(), PI * next()));
        }
        out
    }

    #[test]
    fn wrap_angle_range_and_precision() {
        assert_eq!(wrap_angle(-1e-9), -1e-9);
        assert_eq!(wrap_angle(PI), PI);
        assert_eq!(wrap_angle(-PI), PI);
        assert!((wrap_angle(3.0 * PI) - PI).abs() < 1e-12);
        assert!((wrap_angle(-3.5 * PI) - 0.5 * PI).abs() < 1e-12);
        for k in -5..=5 {
            let a = 0.3 + k as f64 * TAU;
            assert!((wrap_angle(a) - 0.3).abs() < 1e-12, "{a}");
        }
    }

    #[test]
    fn group_identities_at_edge_angles_and_random_draws() {
        let ps = draws();
        for (i, &a) in ps.iter().enumerate() {
            let b = ps[(i * 7 + 3) % ps.len()];
            assert!(close(a.compose(a.inverse()).to_array(), [0.0; 3], 1e-12));
            assert!(close(a.inverse().compose(a).to_array(), [0.0; 3], 1e-12));
            assert!(close(
                a.compose(a.between(b)).to_array(),
                b.to_array(),
                1e-12
            ));
            assert!(close(
                a.between(b).to_array(),
                a.inverse().compose(b).to_array(),
                1e-12
            ));
            assert!(close(a.retract(a.local(b)).to_array(), b.to_array(), 1e-9));
            assert!(close(Pose2::exp(a.log()).to_array(), a.to_array(), 1e-9));
            let c = ps[(i * 13 + 5) % ps.len()];
            let lhs = a.compose(b).compose(c);
            let rhs = a.compose(b.compose(c));
            assert!(close(lhs.to_array(), rhs.to_array(), 1e-11));
            let p = [0.3, -2.0];
            let q = a.inverse().transform_point(a.transform_point(p));
            assert!((q[0] - p[0]).abs() < 1e-12 && (q[1] - p[1]).abs() < 1e-12);
        }
    }

    #[test]
    fn log_exp_round_trip_at_edge_angles() {
        for &t in &THETAS {
            for &(vx, vy) in &[(0.0, 0.0), (1.0, -2.0), (-0.5, 0.25)] {
                let xi = [vx, vy, t];
                let back = Pose2::exp(xi).log();
                assert!(close(back, xi, 1e-9), "theta {t}: {back:?} vs {xi:?}");
            }
        }
    }

    #[test]
    fn small_angle_branches_are_odd_and_continuous() {
        for &t in &[1e-9, 1e-7, 1e-5, 1e-4, 1e-3, 1e-2, 0.1] {
            let (ap, bp) = v_entries(t);
            let (an, bn) = v_entries(-t);
            assert_eq!(ap, an);
            assert_eq!(bp, -bn);
            assert_eq!(vinv_diag(t), vinv_diag(-t));
            assert_eq!(vinv_diag_derivative(t), -vinv_diag_derivative(-t));
        }
        // Both sides of each branch threshold agree with the closed form to high precision.
        for &t in &[0.99e-4, 1.01e-4] {
            let (a, b) = v_entries(t);
            assert!((a - t.sin() / t).abs() < 1e-15);
            assert!((b - (1.0 - t.cos()) / t).abs() < 1e-12);
        }
        for &t in &[0.99e-2, 1.01e-2] {
            let h = 1e-6;
            let fd = (vinv_diag(t + h) - vinv_diag(t - h)) / (2.0 * h);
            assert!((vinv_diag_derivative(t) - fd).abs() < 1e-9);
        }
    }

    #[test]
    fn exp_matches_closed_form_at_quarter_turn() {
        let p = Pose2::exp([1.0, 0.0, PI / 2.0]);
        // V(pi/2) [1, 0] = [sin/θ, (1-cos)/θ] = [2/pi, 2/pi]
        assert!((p.x - 2.0 / PI).abs() < 1e-15 && (p.y - 2.0 / PI).abs() < 1e-15);
        let q = Pose2::new(1.0, 2.0, PI / 2.0).compose(Pose2::new(1.0, 0.0, 0.0));
        assert!((q.x - 1.0).abs() < 1e-15 && (q.y - 3.0).abs() < 1e-15);
    }
}
