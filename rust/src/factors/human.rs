//! Human correction factors (docs/ALGORITHM.md §4.3): each correction adds two line variables
//! `(phi, rho)` (points p on the line satisfy `n . p = rho`, `n = (cos phi, sin phi)`) and three
//! kinds of residual blocks:
//!
//! - [`PointsToLineFactor`] (R_a, R_b): for the observations of one pose on one line,
//!   `(n . p_w(s) - rho) / sigma_f` per point, with `p_w(s) = R(theta_i) s + t_i`.
//! - [`RelationFactor`] (R_p): the stated relation between the two lines and the centroids of
//!   their observations, `cm = mean p_w(s)`, with `e_phi` the smallest angle between the lines
//!   (modulo pi: lines are undirected; perpendicular subtracts pi/2 first):
//!   colocation `[sqrt(K1) (cm_b - cm_a); sqrt(K2) e_phi]`,
//!   collinear `[sqrt(K1) n_a . (cm_b - cm_a); sqrt(K2) e_phi]`,
//!   parallel and perpendicular `[sqrt(K2) e_phi]`.
//!
//! Jacobians in the solver's chart `x (+) d = x * Exp(d)` (derivative at 0: `dt = R d_t`,
//! `dtheta = d_theta`), so `d p_w / d pose = [R, R S s]` with `S = [[0, -1], [1, 0]]`.

use std::f64::consts::{FRAC_PI_2, PI};

use super::Factor;
use super::FactorClass;
use crate::error::{input, Result};
use crate::values::{Key, Values};

/// The relation a person asserts between two features.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum RelationMode {
    Colocation,
    Collinear,
    Perpendicular,
    Parallel,
}

impl RelationMode {
    pub fn parse(name: &str) -> Result<Self> {
        match name {
            "colocation" => Ok(Self::Colocation),
            "collinear" => Ok(Self::Collinear),
            "perpendicular" => Ok(Self::Perpendicular),
            "parallel" => Ok(Self::Parallel),
            other => input(format!(
                "unknown mode {other:?}; use colocation, collinear, perpendicular or parallel"
            )),
        }
    }

    /// Rows of R_p.
    pub fn residual_dim(self) -> usize {
        match self {
            Self::Colocation => 3,
            Self::Collinear => 2,
            Self::Perpendicular | Self::Parallel => 1,
        }
    }
}

/// The smallest signed angle from line a to line b, modulo pi, in (-pi/2, pi/2]; for
/// perpendicular lines, from a direction perpendicular to a.
#[inline]
pub fn line_angle_error(mode: RelationMode, phi_a: f64, phi_b: f64) -> f64 {
    let mut e = phi_b - phi_a;
    if mode == RelationMode::Perpendicular {
        e -= FRAC_PI_2;
    }
    let e = e - PI * (e / PI).round();
    if e <= -FRAC_PI_2 {
        e + PI
    } else {
        e
    }
}

fn check_points(points: &[[f64; 2]]) -> Result<()> {
    if points.is_empty() {
        return input("a line factor needs at least one observation");
    }
    if points
        .iter()
        .any(|p| !(p[0].is_finite() && p[1].is_finite()))
    {
        return input("observation points must be finite");
    }
    Ok(())
}

/// R_a / R_b for the points one pose observed on one line.
///
/// Every point's residual is linear in the same three numbers, `w (q . s + d)` with
/// `q = R(theta)^T n` (the line's normal in the robot frame) and `d = n . t - rho`: the residual
/// vector is `w P [q; d]` with `P` the `K x 3` matrix of rows `[s_x, s_y, 1]`. With `P = Q T` (thin
/// QR, `T` upper triangular 3 x 3), `|w P v|^2 = |w T v|^2` for every `v`, so the factor is stored
/// as the (at most) three rows of `w T` instead of K rows: the same cost, gradient and
/// Gauss-Newton matrix (the Jacobians are `w P dv` and `w T dv`, and `P^T P = T^T T`), and a
/// robust kernel on the whole factor sees the same chi2, at a cost independent of the number of
/// points. A pose that saw three points or fewer keeps them as rows.
#[derive(Clone, Debug)]
pub struct PointsToLineFactor {
    keys: [Key; 2],
    pose: usize,
    line: usize,
    /// Rows `[a, b, c]` of the residual `a q_x + b q_y + c d`, the weight included.
    rows: Vec<[f64; 3]>,
}

impl PointsToLineFactor {
    pub fn new(pose: usize, line: usize, points: Vec<[f64; 2]>, weight: f64) -> Result<Self> {
        check_points(&points)?;
        if !(weight.is_finite() && weight > 0.0) {
            return input(format!("line factor weight must be positive, got {weight}"));
        }
        let rows = if points.len() <= 3 {
            points
                .iter()
                .map(|p| [weight * p[0], weight * p[1], weight])
                .collect()
        } else {
            let p = nalgebra::DMatrix::from_fn(points.len(), 3, |i, j| match j {
                0 => points[i][0],
                1 => points[i][1],
                _ => 1.0,
            });
            let t = p.qr().r();
            (0..3)
                .map(|i| [weight * t[(i, 0)], weight * t[(i, 1)], weight * t[(i, 2)]])
                .collect()
        };
        Ok(Self {
            keys: [Key::Pose(pose), Key::Line(line)],
            pose,
            line,
            rows,
        })
    }
}

impl Factor for PointsToLineFactor {
    fn keys(&self) -> &[Key] {
        &self.keys
    }

    fn residual_dim(&self) -> usize {
        self.rows.len()
    }

    fn residual(&self, values: &Values, r: &mut [f64]) {
        let x = values.poses[self.pose];
        let l = values.lines[self.line];
        let (c, s) = x.cos_sin();
        let (cp, sp) = (l.phi.cos(), l.phi.sin());
        let q = [cp * c + sp * s, -cp * s + sp * c];
        let d = cp * x.x + sp * x.y - l.rho;
        for (out, row) in r.iter_mut().zip(&self.rows) {
            *out = row[0] * q[0] + row[1] * q[1] + row[2] * d;
        }
    }

    fn linearize(&self, values: &Values, r: &mut [f64], jacobians: &mut [f64]) {
        let x = values.poses[self.pose];
        let l = values.lines[self.line];
        let (c, s) = x.cos_sin();
        let (cp, sp) = (l.phi.cos(), l.phi.sin());
        // q = R^T n and d = n . t - rho; in the chart x * Exp(delta): dd/dt = n^T R = q,
        // dq/dtheta = (q_y, -q_x); along phi: dq = R^T n', dd = n' . t with n' = (-sin, cos).
        let q = [cp * c + sp * s, -cp * s + sp * c];
        let d = cp * x.x + sp * x.y - l.rho;
        let dq = [-sp * c + cp * s, sp * s + cp * c];
        let dd = -sp * x.x + cp * x.y;
        let k = self.rows.len();
        let (jp, jl) = jacobians.split_at_mut(3 * k);
        for (i, row) in self.rows.iter().enumerate() {
            r[i] = row[0] * q[0] + row[1] * q[1] + row[2] * d;
            jp[3 * i] = row[2] * q[0];
            jp[3 * i + 1] = row[2] * q[1];
            jp[3 * i + 2] = row[0] * q[1] - row[1] * q[0];
            jl[2 * i] = row[0] * dq[0] + row[1] * dq[1] + row[2] * dd;
            jl[2 * i + 1] = -row[2];
        }
    }
}

/// One pose's share of a centroid: how many of its points are in the set, and their sum
/// (robot frame).
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct CentroidShare {
    pub count: f64,
    pub sum: [f64; 2],
}

/// R_p: the relation between the two lines of a correction. Colocation and collinear depend on
/// every observing pose through the centroids; on real corrections (hundreds of poses) that
/// makes the factor wide (`Factor::is_wide`), and the solver adds its rows as a low-rank update
/// instead of a dense block of the normal equations.
#[derive(Clone, Debug)]
pub struct RelationFactor {
    mode: RelationMode,
    keys: Vec<Key>,
    line_a: usize,
    line_b: usize,
    /// Per pose (keys[2..]): share in cm_a and in cm_b.
    shares: Vec<(usize, CentroidShare, CentroidShare)>,
    total_a: f64,
    total_b: f64,
    sqrt_k1: f64,
    sqrt_k2: f64,
}

impl RelationFactor {
    /// `shares`: (pose, share in S_a, share in S_b) for every pose of X_a and X_b.
    pub fn new(
        mode: RelationMode,
        line_a: usize,
        line_b: usize,
        shares: Vec<(usize, CentroidShare, CentroidShare)>,
        k1: f64,
        k2: f64,
    ) -> Result<Self> {
        if line_a == line_b {
            return input("a relation needs two different lines");
        }
        if !(k1.is_finite() && k1 > 0.0 && k2.is_finite() && k2 > 0.0) {
            return input(format!("K1 and K2 must be positive, got {k1} and {k2}"));
        }
        let total_a: f64 = shares.iter().map(|s| s.1.count).sum();
        let total_b: f64 = shares.iter().map(|s| s.2.count).sum();
        if total_a <= 0.0 || total_b <= 0.0 {
            return input("both lines of a relation need observations");
        }
        let mut keys = vec![Key::Line(line_a), Key::Line(line_b)];
        // Angle-only relations do not depend on the poses: keep them out of the keys, or the
        // factor would couple every observing pose in the normal equations for nothing.
        let shares = if matches!(mode, RelationMode::Parallel | RelationMode::Perpendicular) {
            Vec::new()
        } else {
            shares
        };
        for (n, s) in shares.iter().enumerate() {
            if shares[..n].iter().any(|o| o.0 == s.0) {
                return input(format!("pose {} is listed twice in a relation", s.0));
            }
            if !(s.1.sum.iter().chain(&s.2.sum).all(|v| v.is_finite())) {
                return input("observation points must be finite");
            }
            keys.push(Key::Pose(s.0));
        }
        Ok(Self {
            mode,
            keys,
            line_a,
            line_b,
            shares,
            total_a,
            total_b,
            sqrt_k1: k1.sqrt(),
            sqrt_k2: k2.sqrt(),
        })
    }

    /// The centroids cm_a and cm_b at `values`.
    pub fn centroids(&self, values: &Values) -> ([f64; 2], [f64; 2]) {
        let mut ca = [0.0; 2];
        let mut cb = [0.0; 2];
        for &(i, sa, sb) in &self.shares {
            let x = values.poses[i];
            let (c, s) = x.cos_sin();
            for (acc, sh, total) in [(&mut ca, sa, self.total_a), (&mut cb, sb, self.total_b)] {
                if sh.count > 0.0 {
                    acc[0] += (sh.count * x.x + c * sh.sum[0] - s * sh.sum[1]) / total;
                    acc[1] += (sh.count * x.y + s * sh.sum[0] + c * sh.sum[1]) / total;
                }
            }
        }
        (ca, cb)
    }
}

impl Factor for RelationFactor {
    fn keys(&self) -> &[Key] {
        &self.keys
    }

    fn class(&self) -> FactorClass {
        FactorClass::Relation
    }

    fn residual_dim(&self) -> usize {
        self.mode.residual_dim()
    }

    fn residual(&self, values: &Values, r: &mut [f64]) {
        let la = values.lines[self.line_a];
        let lb = values.lines[self.line_b];
        let e = self.sqrt_k2 * line_angle_error(self.mode, la.phi, lb.phi);
        match self.mode {
            RelationMode::Colocation => {
                let (ca, cb) = self.centroids(values);
                r[0] = self.sqrt_k1 * (cb[0] - ca[0]);
                r[1] = self.sqrt_k1 * (cb[1] - ca[1]);
                r[2] = e;
            }
            RelationMode::Collinear => {
                let (ca, cb) = self.centroids(values);
                r[0] = self.sqrt_k1
                    * (la.phi.cos() * (cb[0] - ca[0]) + la.phi.sin() * (cb[1] - ca[1]));
                r[1] = e;
            }
            RelationMode::Perpendicular | RelationMode::Parallel => r[0] = e,
        }
    }

    fn linearize(&self, values: &Values, r: &mut [f64], jacobians: &mut [f64]) {
        self.residual(values, r);
        let d = self.residual_dim();
        jacobians[..d * (4 + 3 * self.shares.len())].fill(0.0);
        let (ja, rest) = jacobians.split_at_mut(2 * d);
        let (jb, jp) = rest.split_at_mut(2 * d);
        // The angle row is the last one in every mode.
        let last = d - 1;
        ja[2 * last] = -self.sqrt_k2;
        jb[2 * last] = self.sqrt_k2;
        if matches!(
            self.mode,
            RelationMode::Perpendicular | RelationMode::Parallel
        ) {
            return;
        }
        let la = values.lines[self.line_a];
        let (cp, sp) = (la.phi.cos(), la.phi.sin());
        if self.mode == RelationMode::Collinear {
            let (ca, cb) = self.centroids(values);
            ja[0] = self.sqrt_k1 * (-sp * (cb[0] - ca[0]) + cp * (cb[1] - ca[1]));
        }
        for (n, &(i, sa, sb)) in self.shares.iter().enumerate() {
            let (c, s) = values.poses[i].cos_sin();
            // d(cm_b - cm_a)/d pose_i, a 2x3 matrix [coef * R, R S sum].
            let coef = sb.count / self.total_b - sa.count / self.total_a;
            let sum = [
                sb.sum[0] / self.total_b - sa.sum[0] / self.total_a,
                sb.sum[1] / self.total_b - sa.sum[1] / self.total_a,
            ];
            let rs = [-(s * sum[0] + c * sum[1]), c * sum[0] - s * sum[1]];
            let m = [[coef * c, -coef * s, rs[0]], [coef * s, coef * c, rs[1]]];
            let block = &mut jp[3 * d * n..3 * d * (n + 1)];
            match self.mode {
                RelationMode::Colocation => {
                    for row in 0..2 {
                        for col in 0..3 {
                            block[3 * row + col] = self.sqrt_k1 * m[row][col];
                        }
                    }
                }
                _ => {
                    for col in 0..3 {
                        block[col] = self.sqrt_k1 * (cp * m[0][col] + sp * m[1][col]);
                    }
                }
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::factors::testing::check_jacobians;
    use crate::se2::Pose2;
    use crate::values::Line2;

    fn values() -> Values {
        Values {
            poses: vec![
                Pose2::new(0.3, -0.2, 0.4),
                Pose2::new(2.0, 1.0, -1.2),
                Pose2::new(-1.0, 0.5, 2.9),
            ],
            lines: vec![
                Line2 { phi: 0.3, rho: 1.2 },
                Line2 {
                    phi: 1.9,
                    rho: -0.4,
                },
            ],
        }
    }

    #[test]
    fn angle_error_is_modulo_pi_and_smallest() {
        use RelationMode::*;
        assert!((line_angle_error(Parallel, 0.1, 0.1 + PI) - 0.0).abs() < 1e-15);
        assert!((line_angle_error(Parallel, 0.1, 0.3 - PI) - 0.2).abs() < 1e-12);
        assert!((line_angle_error(Collinear, 3.0, -3.0) - (2.0 * PI - 6.0)).abs() < 1e-12);
        assert!((line_angle_error(Perpendicular, 0.0, FRAC_PI_2 + 0.01) - 0.01).abs() < 1e-12);
        assert!((line_angle_error(Perpendicular, 0.0, -FRAC_PI_2 - 0.01) + 0.01).abs() < 1e-12);
        for k in -3..=3 {
            let e = line_angle_error(Parallel, 0.5, 0.5 + 0.7 + k as f64 * PI);
            assert!((e - 0.7).abs() < 1e-12, "{k}: {e}");
        }
    }

    #[test]
    fn point_to_line_residual_and_jacobians() {
        let v = values();
        let pts = vec![[1.0, 0.5], [-0.3, 2.0], [0.0, 0.0]];
        let f = PointsToLineFactor::new(1, 0, pts.clone(), 1.0 / 0.03).unwrap();
        let mut r = vec![0.0; 3];
        f.residual(&v, &mut r);
        let x = v.poses[1];
        let l = v.lines[0];
        for (k, p) in pts.iter().enumerate() {
            let w = x.transform_point(*p);
            let expect = (l.phi.cos() * w[0] + l.phi.sin() * w[1] - l.rho) / 0.03;
            assert!((r[k] - expect).abs() < 1e-12);
        }
        check_jacobians(&f, &v, 1e-6, 1e-6);
    }

    #[test]
    fn many_points_compress_to_three_rows_with_the_same_normal_equations() {
        let v = values();
        let pts: Vec<[f64; 2]> = (0..40)
            .map(|k| {
                let t = k as f64;
                [
                    0.3 * t - 4.0 + 0.01 * (7.0 * t).sin(),
                    2.0 + 0.05 * (3.0 * t).cos(),
                ]
            })
            .collect();
        let w = 1.0 / 0.03;
        let f = PointsToLineFactor::new(2, 1, pts.clone(), w).unwrap();
        assert_eq!(f.residual_dim(), 3);
        check_jacobians(&f, &v, 1e-6, 1e-6);
        // The per-point reference: one factor per point (three points or fewer stay rows).
        let singles: Vec<PointsToLineFactor> = pts
            .iter()
            .map(|p| PointsToLineFactor::new(2, 1, vec![*p], w).unwrap())
            .collect();
        let (mut h_ref, mut g_ref, mut c_ref) = ([[0.0; 5]; 5], [0.0; 5], 0.0);
        for s in &singles {
            let (mut r, mut j) = ([0.0; 1], [0.0; 5]);
            s.linearize(&v, &mut r, &mut j);
            c_ref += r[0] * r[0];
            for a in 0..5 {
                g_ref[a] += j[a] * r[0];
                for b in 0..5 {
                    h_ref[a][b] += j[a] * j[b];
                }
            }
        }
        let (mut r, mut j) = (vec![0.0; 3], vec![0.0; 15]);
        f.linearize(&v, &mut r, &mut j);
        let row = |i: usize| {
            [
                j[3 * i],
                j[3 * i + 1],
                j[3 * i + 2],
                j[9 + 2 * i],
                j[9 + 2 * i + 1],
            ]
        };
        let (mut h, mut g) = ([[0.0; 5]; 5], [0.0; 5]);
        for i in 0..3 {
            let ji = row(i);
            for a in 0..5 {
                g[a] += ji[a] * r[i];
                for b in 0..5 {
                    h[a][b] += ji[a] * ji[b];
                }
            }
        }
        let cost: f64 = r.iter().map(|x| x * x).sum();
        assert!((cost - c_ref).abs() <= 1e-10 * c_ref, "{cost} vs {c_ref}");
        assert!((f.chi2(&v) - c_ref).abs() <= 1e-10 * c_ref);
        for a in 0..5 {
            assert!(
                (g[a] - g_ref[a]).abs() <= 1e-9 * (1.0 + g_ref[a].abs()),
                "g[{a}]"
            );
            for b in 0..5 {
                let scale = 1.0 + h_ref[a][b].abs();
                assert!((h[a][b] - h_ref[a][b]).abs() <= 1e-9 * scale, "H[{a}][{b}]");
            }
        }
    }

    fn shares() -> Vec<(usize, CentroidShare, CentroidShare)> {
        vec![
            (
                0,
                CentroidShare {
                    count: 3.0,
                    sum: [1.0, 2.0],
                },
                CentroidShare::default(),
            ),
            (
                1,
                CentroidShare {
                    count: 2.0,
                    sum: [-0.5, 0.7],
                },
                CentroidShare::default(),
            ),
            (
                2,
                CentroidShare::default(),
                CentroidShare {
                    count: 4.0,
                    sum: [2.0, -1.0],
                },
            ),
        ]
    }

    #[test]
    fn relation_jacobians_every_mode() {
        for mode in [
            RelationMode::Colocation,
            RelationMode::Collinear,
            RelationMode::Perpendicular,
            RelationMode::Parallel,
        ] {
            let f = RelationFactor::new(mode, 0, 1, shares(), 1e6, 1e7).unwrap();
            check_jacobians(&f, &values(), 1e-6, 1e-4);
        }
    }

    #[test]
    fn centroids_are_means_of_world_points() {
        let f = RelationFactor::new(RelationMode::Colocation, 0, 1, shares(), 1.0, 1.0).unwrap();
        let v = values();
        let (ca, cb) = f.centroids(&v);
        // Pose 0 has 3 points summing to (1, 2): their world sum is R*(1,2) + 3 t.
        let w0 = v.poses[0].transform_point([1.0, 2.0]);
        let w0 = [w0[0] + 2.0 * v.poses[0].x, w0[1] + 2.0 * v.poses[0].y];
        let w1 = v.poses[1].transform_point([-0.5, 0.7]);
        let w1 = [w1[0] + v.poses[1].x, w1[1] + v.poses[1].y];
        assert!((ca[0] - (w0[0] + w1[0]) / 5.0).abs() < 1e-12);
        assert!((ca[1] - (w0[1] + w1[1]) / 5.0).abs() < 1e-12);
        let w2 = v.poses[2].transform_point([2.0, -1.0]);
        assert!((cb[0] - (w2[0] + 3.0 * v.poses[2].x) / 4.0).abs() < 1e-12);
    }

    #[test]
    fn angle_only_relations_touch_only_the_lines() {
        for mode in [RelationMode::Parallel, RelationMode::Perpendicular] {
            let f = RelationFactor::new(mode, 0, 1, shares(), 1.0, 1.0).unwrap();
            assert_eq!(f.keys(), &[Key::Line(0), Key::Line(1)]);
        }
        let f = RelationFactor::new(RelationMode::Collinear, 0, 1, shares(), 1.0, 1.0).unwrap();
        assert_eq!(f.keys().len(), 5);
    }

    #[test]
    fn bad_inputs_are_errors() {
        assert!(PointsToLineFactor::new(0, 0, vec![], 1.0).is_err());
        assert!(PointsToLineFactor::new(0, 0, vec![[f64::NAN, 0.0]], 1.0).is_err());
        assert!(RelationFactor::new(RelationMode::Parallel, 0, 0, shares(), 1.0, 1.0).is_err());
        assert!(RelationFactor::new(RelationMode::Parallel, 0, 1, vec![], 1.0, 1.0).is_err());
        assert!(RelationMode::parse("same").is_err());
    }
}
