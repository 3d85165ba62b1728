//! Robust kernels (M-estimators) on whole factors, chosen per factor class.
//!
//! A factor with whitened residual `r` and squared norm `s = |r|^2` costs `rho(s)` instead of
//! `s`. Each kernel is written in GTSAM's convention (`noiseModel::mEstimator`, loss of the
//! Mahalanobis distance `e = sqrt(s)`) times two, so the robust cost is on the chi2 scale
//! (`rho(s) = s` for small `s`) and its minimum is GTSAM's:
//!
//! | kernel | `rho(s)` | weight `rho'(s)` |
//! |---|---|---|
//! | Huber(k) | `s` if `e <= k`, else `2 k e - k^2` | `min(1, k / e)` |
//! | Cauchy(k) | `k^2 log(1 + s / k^2)` | `k^2 / (k^2 + s)` |
//! | DCS(phi) | `s` if `s <= phi`, else `phi (3 s - phi) / (phi + s)` | `min(1, (2 phi / (phi + s))^2)` |
//!
//! DCS is dynamic covariance scaling (Agarwal, Tipaldi, Spinello, Stachniss and Burgard, ICRA
//! 2013): the factor's information is scaled by `w = s_dcs^2`, `s_dcs = min(1, 2 phi / (phi +
//! chi2))`, which is the closed-form optimum of switchable constraints (Suenderhauf and Protzel,
//! 2012) with switch prior `phi`.
//!
//! The solver linearizes the reweighted problem (iteratively reweighted least squares, as GTSAM
//! and g2o): residual and Jacobian rows are scaled by `sqrt(w)`, so its gradient is the exact
//! gradient of the robust cost and its fixed points are the robust cost's stationary points.

use crate::error::{input, Result};
use crate::factors::{Factor, FactorClass};

/// An M-estimator; the parameter is in whitened units (sigmas; DCS: chi2 units, as `Phi`).
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum Kernel {
    Huber(f64),
    Cauchy(f64),
    Dcs(f64),
}

impl Kernel {
    /// Huber's 95%-efficiency constant, Cauchy's 95%-efficiency constant, and Agarwal et al.'s
    /// recommended `Phi = 1`.
    pub const HUBER_DEFAULT: f64 = 1.345;
    pub const CAUCHY_DEFAULT: f64 = 2.3849;
    pub const DCS_DEFAULT: f64 = 1.0;

    /// `"huber"`, `"cauchy:2.5"`, `"dcs:1"`: a kernel name with an optional parameter.
    pub fn parse(spec: &str) -> Result<Self> {
        let (name, param) = match spec.split_once(':') {
            Some((n, p)) => (n.trim(), Some(p.trim())),
            None => (spec.trim(), None),
        };
        let value = match param {
            None => None,
            Some(p) => match p.parse::<f64>() {
                Ok(v) if v.is_finite() && v > 0.0 && v <= 1e12 => Some(v),
                _ => {
                    return input(format!(
                    "robust kernel parameter {p:?} in {spec:?} must be a number > 0 (and <= 1e12)"
                ))
                }
            },
        };
        match name.to_ascii_lowercase().as_str() {
            "huber" => Ok(Kernel::Huber(value.unwrap_or(Self::HUBER_DEFAULT))),
            "cauchy" => Ok(Kernel::Cauchy(value.unwrap_or(Self::CAUCHY_DEFAULT))),
            "dcs" => Ok(Kernel::Dcs(value.unwrap_or(Self::DCS_DEFAULT))),
            other => input(format!(
                "unknown robust kernel {other:?}; use huber[:k], cauchy[:k] or dcs[:phi]"
            )),
        }
    }

    pub fn name(self) -> &'static str {
        match self {
            Kernel::Huber(_) => "huber",
            Kernel::Cauchy(_) => "cauchy",
            Kernel::Dcs(_) => "dcs",
        }
    }

    pub fn parameter(self) -> f64 {
        match self {
            Kernel::Huber(k) | Kernel::Cauchy(k) | Kernel::Dcs(k) => k,
        }
    }

    /// The robust cost `rho(s)` of a squared whitened residual norm `s`.
    #[inline]
    pub fn rho(self, s: f64) -> f64 {
        match self {
            Kernel::Huber(k) => {
                let e = s.sqrt();
                if e <= k {
                    s
                } else {
                    2.0 * k * e - k * k
                }
            }
            Kernel::Cauchy(k) => {
                let k2 = k * k;
                k2 * (s / k2).ln_1p()
            }
            Kernel::Dcs(phi) => {
                if s <= phi {
                    s
                } else {
                    phi * (3.0 * s - phi) / (phi + s)
                }
            }
        }
    }

    /// The weight `rho'(s)` in `(0, 1]` that scales the factor's information.
    #[inline]
    pub fn weight(self, s: f64) -> f64 {
        match self {
            Kernel::Huber(k) => {
                let e = s.sqrt();
                if e <= k {
                    1.0
                } else {
                    k / e
                }
            }
            Kernel::Cauchy(k) => {
                let k2 = k * k;
                k2 / (k2 + s)
            }
            Kernel::Dcs(phi) => {
                let w = 2.0 * phi / (phi + s);
                (w * w).min(1.0)
            }
        }
    }
}

impl std::fmt::Display for Kernel {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(f, "{}:{}", self.name(), self.parameter())
    }
}

/// A kernel for each factor class (`None`: plain least squares).
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct RobustKernels {
    per_class: [Option<Kernel>; 5],
}

impl RobustKernels {
    pub fn none() -> Self {
        Self::default()
    }

    pub fn set(&mut self, class: FactorClass, kernel: Option<Kernel>) {
        self.per_class[class.index()] = kernel;
    }

    pub fn with(mut self, class: FactorClass, kernel: Kernel) -> Self {
        self.set(class, Some(kernel));
        self
    }

    pub fn get(&self, class: FactorClass) -> Option<Kernel> {
        self.per_class[class.index()]
    }

    pub fn is_empty(&self) -> bool {
        self.per_class.iter().all(Option::is_none)
    }

    /// The kernel of each factor, in factor order (empty when no class has one, so the solver's
    /// plain path pays nothing).
    pub fn per_factor(&self, factors: &[Box<dyn Factor>]) -> Vec<Option<Kernel>> {
        if self.is_empty() {
            return Vec::new();
        }
        factors.iter().map(|f| self.get(f.class())).collect()
    }
}

/// The cost of one factor with squared whitened norm `s` under an optional kernel.
#[inline]
pub(crate) fn robust_cost(kernel: Option<Kernel>, s: f64) -> f64 {
    match kernel {
        Some(k) => k.rho(s),
        None => s,
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    const KERNELS: [Kernel; 6] = [
        Kernel::Huber(1.345),
        Kernel::Huber(0.3),
        Kernel::Cauchy(2.3849),
        Kernel::Cauchy(0.5),
        Kernel::Dcs(1.0),
        Kernel::Dcs(7.0),
    ];

    #[test]
    fn weight_is_the_derivative_of_rho() {
        for k in KERNELS {
            for s in [1e-6f64, 0.01, 0.3, 0.99, 1.7, 4.0, 30.0, 1e4] {
                let h = 1e-6 * s.max(1e-3);
                let fd = (k.rho(s + h) - k.rho(s - h)) / (2.0 * h);
                let w = k.weight(s);
                assert!(
                    (fd - w).abs() < 1e-5 * (1.0 + w),
                    "{k}: s={s} fd={fd} w={w}"
                );
                assert!(w > 0.0 && w <= 1.0);
            }
        }
    }

    #[test]
    fn small_residuals_cost_as_least_squares() {
        for k in KERNELS {
            let s = 1e-8;
            assert!((k.rho(s) - s).abs() < 1e-12, "{k}");
            assert!((k.weight(s) - 1.0).abs() < 1e-7, "{k}");
        }
    }

    #[test]
    fn kernels_are_continuous_at_their_thresholds() {
        for k in [Kernel::Huber(1.5), Kernel::Dcs(2.0)] {
            let t = match k {
                Kernel::Huber(c) => c * c,
                Kernel::Dcs(phi) => phi,
                Kernel::Cauchy(_) => 1.0,
            };
            assert!((k.rho(t * (1.0 - 1e-12)) - k.rho(t * (1.0 + 1e-12))).abs() < 1e-9);
        }
    }

    #[test]
    fn parse_reads_names_and_parameters() {
        assert_eq!(Kernel::parse("huber").unwrap(), Kernel::Huber(1.345));
        assert_eq!(Kernel::parse("Cauchy:2").unwrap(), Kernel::Cauchy(2.0));
        assert_eq!(Kernel::parse("dcs:0.5").unwrap(), Kernel::Dcs(0.5));
        for bad in [
            "tukey",
            "huber:",
            "huber:-1",
            "dcs:nan",
            "cauchy:inf",
            "dcs:0",
        ] {
            assert!(Kernel::parse(bad).is_err(), "{bad}");
        }
    }
}
