//! Relative-pose factor (odometry, scan matching, loop closure), as GTSAM's `BetweenFactor<Pose2>`:
//!
//! `r = U Log(z_ij^-1 * (x_i^-1 * x_j))`, with `Omega_ij = U^T U`, cost `r^T r`.
//!
//! Writing `E = z^-1 x_i^-1 x_j = (t_e, theta_e)` and `Log(E) = (V^-1 t_e, theta_e)`, the Jacobians
//! in the chart `x (+) d = x * Exp(d)` (first order: `t + R d_t`, `theta + d_theta`) are
//! `dLog/dd_j = [[V^-1 R(theta_e), w], [0, 0, 1]]` and
//! `dLog/dd_i = [[-V^-1 R_z^T, -V^-1 S R_z^T t_b - w], [0, 0, -1]]`,
//! where `t_b = R_i^T (t_j - t_i)`, `S = [[0, -1], [1, 0]]`, and `w = d(V^-1)/dtheta t_e`.

use super::{check_keys, sqrt_information, whiten3, whiten3x3, Factor, FactorClass, SE2Log};
use crate::error::{input, Result};
use crate::se2::{rotate_inv, wrap_angle, Pose2};
use crate::values::{Key, Values};

#[derive(Clone, Debug)]
pub struct BetweenFactor {
    keys: [Key; 2],
    i: usize,
    j: usize,
    measured: Pose2,
    cz: f64,
    sz: f64,
    sqrt_info: [[f64; 3]; 3],
}

impl BetweenFactor {
    /// A factor saying pose `j` is at `measured` (`t_i_j`) in the frame of pose `i`, with the
    /// given 3x3 information matrix in `(x, y, theta)` order. Error messages say what is wrong
    /// with the edge; callers add which edge it is.
    pub fn new(i: usize, j: usize, measured: Pose2, information: &[[f64; 3]; 3]) -> Result<Self> {
        if i == j {
            return input(format!("joins pose {i} to itself; remove it"));
        }
        if !(measured.x.is_finite() && measured.y.is_finite() && measured.theta.is_finite()) {
            return input(format!(
                "edge {i} -> {j} has a non-finite measurement {measured:?}"
            ));
        }
        let sqrt_info = sqrt_information(information)?;
        let (cz, sz) = measured.cos_sin();
        Ok(Self {
            keys: [Key::Pose(i), Key::Pose(j)],
            i,
            j,
            measured,
            cz,
            sz,
            sqrt_info,
        })
    }

    pub fn measured(&self) -> Pose2 {
        self.measured
    }

    /// The information matrix `Omega = U^T U`.
    pub fn information(&self) -> [[f64; 3]; 3] {
        let u = &self.sqrt_info;
        let mut o = [[0.0; 3]; 3];
        for a in 0..3 {
            for b in 0..3 {
                o[a][b] = (0..3).map(|k| u[k][a] * u[k][b]).sum();
            }
        }
        o
    }

    pub fn indices(&self) -> (usize, usize) {
        (self.i, self.j)
    }

    /// Checks the indices against the poses the graph holds.
    pub fn check(&self, values: &Values) -> Result<()> {
        check_keys(&self.keys, values)
    }

    /// `(t_b, t_e, theta_e)` of the error transform.
    #[inline]
    fn error_parts(&self, values: &Values) -> ([f64; 2], [f64; 2], f64) {
        let xi = values.poses[self.i];
        let xj = values.poses[self.j];
        let (ci, si) = xi.cos_sin();
        let t_b = rotate_inv(ci, si, [xj.x - xi.x, xj.y - xi.y]);
        let t_e = rotate_inv(
            self.cz,
            self.sz,
            [t_b[0] - self.measured.x, t_b[1] - self.measured.y],
        );
        let theta_e = wrap_angle(xj.theta - xi.theta - self.measured.theta);
        (t_b, t_e, theta_e)
    }
}

impl Factor for BetweenFactor {
    fn keys(&self) -> &[Key] {
        &self.keys
    }

    fn residual_dim(&self) -> usize {
        3
    }

    fn as_between(&self) -> Option<&BetweenFactor> {
        Some(self)
    }

    fn class(&self) -> FactorClass {
        if self.i.abs_diff(self.j) == 1 {
            FactorClass::Odometry
        } else {
            FactorClass::LoopClosure
        }
    }

    fn residual(&self, values: &Values, r: &mut [f64]) {
        let (_, t_e, theta_e) = self.error_parts(values);
        r.copy_from_slice(&whiten3(&self.sqrt_info, SE2Log::residual(t_e, theta_e)));
    }

    fn linearize(&self, values: &Values, r: &mut [f64], jacobians: &mut [f64]) {
        let (t_b, t_e, theta_e) = self.error_parts(values);
        let (log, ce, se) = SE2Log::new(t_e, theta_e);
        r.copy_from_slice(&whiten3(&self.sqrt_info, log.r));

        let vr = log.vinv_times([[ce, -se], [se, ce]]);
        let jj = [
            [vr[0][0], vr[0][1], log.w[0]],
            [vr[1][0], vr[1][1], log.w[1]],
            [0.0, 0.0, 1.0],
        ];

        let (cz, sz) = (self.cz, self.sz);
        let vrz = log.vinv_times([[cz, sz], [-sz, cz]]);
        let u = rotate_inv(cz, sz, t_b);
        let m = log.vinv_vec([u[1], -u[0]]); // -V^-1 S u
        let ji = [
            [-vrz[0][0], -vrz[0][1], m[0] - log.w[0]],
            [-vrz[1][0], -vrz[1][1], m[1] - log.w[1]],
            [0.0, 0.0, -1.0],
        ];
        let (first, second) = jacobians.split_at_mut(9);
        whiten3x3(&self.sqrt_info, &ji, first);
        whiten3x3(&self.sqrt_info, &jj, &mut second[..9]);
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::factors::testing::check_jacobians;
    use std::f64::consts::PI;

    fn info() -> [[f64; 3]; 3] {
        [[40.0, 3.0, 1.0], [3.0, 25.0, -2.0], [1.0, -2.0, 900.0]]
    }

    #[test]
    fn residual_is_zero_at_the_measurement_and_matches_closed_form() {
        let xi = Pose2::new(1.0, 2.0, 0.3);
        let z = Pose2::new(0.5, -0.2, 0.7);
        let xj = xi.compose(z);
        let values = Values::from_poses(vec![xi, xj]);
        let identity = [[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]];
        let f = BetweenFactor::new(0, 1, z, &identity).unwrap();
        let mut r = [0.0; 3];
        f.residual(&values, &mut r);
        assert!(r.iter().all(|v| v.abs() < 1e-14), "{r:?}");
        // Perturb x_j by a known tangent: the residual is exactly Log(z^-1 x_i^-1 x_j).
        let xj2 = Pose2::new(3.0, -1.0, -2.5);
        let values = Values::from_poses(vec![xi, xj2]);
        f.residual(&values, &mut r);
        let expect = z.inverse().compose(xi.between(xj2)).log();
        for k in 0..3 {
            assert!((r[k] - expect[k]).abs() < 1e-13);
        }
        assert!((f.chi2(&values) - expect.iter().map(|v| v * v).sum::<f64>()).abs() < 1e-12);
    }

    #[test]
    fn whitening_gives_r_omega_r() {
        let z = Pose2::new(0.5, -0.2, 0.7);
        let values =
            Values::from_poses(vec![Pose2::new(0.1, 0.2, 0.3), Pose2::new(1.0, 0.5, -0.4)]);
        let f = BetweenFactor::new(0, 1, z, &info()).unwrap();
        let e = z
            .inverse()
            .compose(values.poses[0].between(values.poses[1]))
            .log();
        let o = info();
        let mut quad = 0.0;
        for a in 0..3 {
            for b in 0..3 {
                quad += e[a] * o[a][b] * e[b];
            }
        }
        assert!((f.chi2(&values) - quad).abs() < 1e-10 * quad);
    }

    #[test]
    fn jacobians_match_central_differences() {
        let angles = [-PI + 1e-3, -1.0, -1e-9, 0.0, 1e-9, 0.4, PI - 1e-3];
        for &ti in &angles {
            for &tj in &angles {
                for &tz in &[0.0, 0.5, -2.0] {
                    let xi = Pose2::new(0.3, -1.2, ti);
                    // x_j chosen so that theta_e stays away from the +-pi cut, where the
                    // wrapped residual is discontinuous and differences are meaningless.
                    let xj = Pose2::new(2.1, 0.7, tj);
                    let z = Pose2::new(1.5, 0.4, tz);
                    let te = wrap_angle(tj - ti - tz);
                    if PI - te.abs() < 1e-3 {
                        continue;
                    }
                    let values = Values::from_poses(vec![xi, xj]);
                    let f = BetweenFactor::new(0, 1, z, &info()).unwrap();
                    check_jacobians(&f, &values, 1e-6, 1e-7);
                }
            }
        }
    }

    #[test]
    fn bad_inputs_are_errors() {
        let z = Pose2::new(1.0, 0.0, 0.0);
        assert!(BetweenFactor::new(1, 1, z, &info()).is_err());
        let mut bad = info();
        bad[2][2] = -1.0;
        let err = BetweenFactor::new(0, 1, z, &bad).unwrap_err();
        assert!(err.to_string().contains("positive definite"), "{err}");
        bad = info();
        bad[0][1] = 7.0;
        assert!(BetweenFactor::new(0, 1, z, &bad)
            .unwrap_err()
            .to_string()
            .contains("symmetric"));
        bad = info();
        bad[1][1] = f64::NAN;
        assert!(BetweenFactor::new(0, 1, z, &bad).is_err());
        assert!(BetweenFactor::new(
            0,
            1,
            Pose2 {
                x: f64::INFINITY,
                y: 0.0,
                theta: 0.0
            },
            &info()
        )
        .is_err());
    }
}
