//! Prior on one pose, as GTSAM's `PriorFactor<Pose2>`: `r = U Log(z^-1 x)`, `Omega = U^T U`.
//! Jacobian in the chart `x (+) d = x * Exp(d)` (first order: `t + R d_t`, `theta + d_theta`): `[[V^-1 R(theta_e), w], [0, 0, 1]]`.

use super::{check_keys, sqrt_information, whiten3, whiten3x3, Factor, FactorClass, SE2Log};
use crate::error::{input, Result};
use crate::se2::{rotate_inv, wrap_angle, Pose2};
use crate::values::{Key, Values};

#[derive(Clone, Debug)]
pub struct PriorFactor {
    keys: [Key; 1],
    i: usize,
    measured: Pose2,
    cz: f64,
    sz: f64,
    sqrt_info: [[f64; 3]; 3],
}

impl PriorFactor {
    pub fn new(i: usize, measured: Pose2, information: &[[f64; 3]; 3]) -> Result<Self> {
        if !(measured.x.is_finite() && measured.y.is_finite() && measured.theta.is_finite()) {
            return input(format!(
                "prior on pose {i} has a non-finite value {measured:?}"
            ));
        }
        let sqrt_info = sqrt_information(information)
            .map_err(|e| crate::error::HitlError::Input(format!("prior on pose {i}: {e}")))?;
        let (cz, sz) = measured.cos_sin();
        Ok(Self {
            keys: [Key::Pose(i)],
            i,
            measured,
            cz,
            sz,
            sqrt_info,
        })
    }

    pub fn index(&self) -> usize {
        self.i
    }

    pub fn check(&self, values: &Values) -> Result<()> {
        check_keys(&self.keys, values)
    }

    #[inline]
    fn error_parts(&self, values: &Values) -> ([f64; 2], f64) {
        let x = values.poses[self.i];
        let t_e = rotate_inv(
            self.cz,
            self.sz,
            [x.x - self.measured.x, x.y - self.measured.y],
        );
        (t_e, wrap_angle(x.theta - self.measured.theta))
    }
}

impl Factor for PriorFactor {
    fn keys(&self) -> &[Key] {
        &self.keys
    }

    fn residual_dim(&self) -> usize {
        3
    }

    fn class(&self) -> FactorClass {
        FactorClass::Prior
    }

    fn residual(&self, values: &Values, r: &mut [f64]) {
        let (t_e, theta_e) = self.error_parts(values);
        r.copy_from_slice(&whiten3(&self.sqrt_info, SE2Log::residual(t_e, theta_e)));
    }

    fn linearize(&self, values: &Values, r: &mut [f64], jacobians: &mut [f64]) {
        let (t_e, theta_e) = self.error_parts(values);
        let (log, ce, se) = SE2Log::new(t_e, theta_e);
        r.copy_from_slice(&whiten3(&self.sqrt_info, log.r));
        let vr = log.vinv_times([[ce, -se], [se, ce]]);
        let j = [
            [vr[0][0], vr[0][1], log.w[0]],
            [vr[1][0], vr[1][1], log.w[1]],
            [0.0, 0.0, 1.0],
        ];
        whiten3x3(&self.sqrt_info, &j, &mut jacobians[..9]);
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::factors::testing::check_jacobians;
    use std::f64::consts::PI;

    #[test]
    fn residual_is_log_of_error() {
        let z = Pose2::new(1.0, -2.0, 2.9);
        let x = Pose2::new(0.5, 0.5, -3.0);
        let f =
            PriorFactor::new(0, z, &[[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]]).unwrap();
        let mut r = [0.0; 3];
        f.residual(&Values::from_poses(vec![x]), &mut r);
        let e = z.between(x).log();
        for k in 0..3 {
            assert!((r[k] - e[k]).abs() < 1e-13);
        }
        f.residual(&Values::from_poses(vec![z]), &mut r);
        assert!(r.iter().all(|v| v.abs() < 1e-15));
    }

    #[test]
    fn jacobians_match_central_differences() {
        let info = [[10.0, 1.0, 0.5], [1.0, 20.0, 0.0], [0.5, 0.0, 100.0]];
        for &t in &[-PI + 1e-3, -1e-9, 0.0, 1e-9, 1.0, PI - 1e-3] {
            for &tz in &[0.0, 0.3, -1.3] {
                if PI - wrap_angle(t - tz).abs() < 1e-3 {
                    continue;
                }
                let f = PriorFactor::new(0, Pose2::new(0.2, 0.1, tz), &info).unwrap();
                check_jacobians(
                    &f,
                    &Values::from_poses(vec![Pose2::new(1.3, -0.4, t)]),
                    1e-6,
                    1e-7,
                );
            }
        }
    }
}
