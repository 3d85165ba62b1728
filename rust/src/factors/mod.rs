//! Factors: residual blocks of the least-squares cost. Each one is whitened (its cost is
//! `|r|^2`, the information already folded in) and linearizes itself with analytic Jacobians
//! in the solver's chart (see `Pose2::retract`).

mod between;
pub mod human;
mod prior;

pub use between::BetweenFactor;
pub use human::{CentroidShare, PointsToLineFactor, RelationFactor, RelationMode};
pub use prior::PriorFactor;

use crate::error::{input, Result};
use crate::se2::{vinv_diag, vinv_diag_derivative};
use crate::values::{Key, Values};

/// A factor on more variables than this is "wide": the solver keeps its rows out of the sparse
/// Cholesky factor and adds them back as a low-rank (Woodbury) update, because its `J^T J` is a
/// dense clique over all its variables. Both treatments give the same solution, and at 8 keys
/// both cost next to nothing (a 24 x 24 dense block against one extra triangular solve per
/// row), so the exact threshold hardly matters: the relations that need it couple the hundreds
/// of poses observing a wall (on the campus map the dense block made the factor 9x larger),
/// and relations over a few poses keep the plain sparse path (the SciPy cross-check of the
/// joint solve has one of each).
pub const WIDE_KEYS: usize = 8;

/// What kind of evidence a factor is. Robust kernels are chosen per class (odometry can be
/// trusted differently from loop closures or from a person's drawing).
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
pub enum FactorClass {
    /// A relative pose between consecutive poses (`|i - j| = 1`): the robot's own motion.
    Odometry,
    /// A relative pose between any other two poses (scan matching, place recognition).
    LoopClosure,
    /// A human correction's point-to-line factors (each line on its observations).
    Human,
    /// A prior on one pose.
    Prior,
    /// A human correction's relation between its two lines (same wall, parallel, ...).
    Relation,
}

impl FactorClass {
    pub const ALL: [FactorClass; 5] = [
        FactorClass::Odometry,
        FactorClass::LoopClosure,
        FactorClass::Human,
        FactorClass::Prior,
        FactorClass::Relation,
    ];

    pub fn name(self) -> &'static str {
        match self {
            FactorClass::Odometry => "odometry",
            FactorClass::LoopClosure => "loop",
            FactorClass::Human => "human",
            FactorClass::Prior => "prior",
            FactorClass::Relation => "relation",
        }
    }

    pub fn parse(s: &str) -> Result<Self> {
        match s {
            "odometry" | "odom" => Ok(FactorClass::Odometry),
            "loop" | "loops" | "loop_closure" | "loop-closure" => Ok(FactorClass::LoopClosure),
            "human" => Ok(FactorClass::Human),
            "prior" => Ok(FactorClass::Prior),
            "relation" => Ok(FactorClass::Relation),
            other => input(format!(
                "unknown edge class {other:?}; use odometry, loop, human, relation or prior"
            )),
        }
    }

    /// Index into per-class tables (the order of [`FactorClass::ALL`]).
    pub fn index(self) -> usize {
        self as usize
    }
}

/// One residual block. `jacobians` is filled key by key, each block row-major
/// `residual_dim x key.dim()`, laid out in the order of `keys()`.
pub trait Factor: Send + Sync + std::fmt::Debug {
    fn keys(&self) -> &[Key];
    /// Whether the solver should treat this factor's rows as a low-rank update (see
    /// [`WIDE_KEYS`]) instead of adding their dense coupling to the sparse normal equations.
    fn is_wide(&self) -> bool {
        self.keys().len() > WIDE_KEYS
    }
    fn residual_dim(&self) -> usize;
    /// What kind of evidence this factor is (robust kernels are chosen per class).
    fn class(&self) -> FactorClass {
        FactorClass::Human
    }
    /// The factor as a relative-pose edge, if it is one (initial guesses compose these).
    fn as_between(&self) -> Option<&BetweenFactor> {
        None
    }
    /// Whitened residual only.
    fn residual(&self, values: &Values, r: &mut [f64]);
    /// Whitened residual and Jacobians.
    fn linearize(&self, values: &Values, r: &mut [f64], jacobians: &mut [f64]);
    /// `|r|^2` (the factor's chi2 contribution).
    fn chi2(&self, values: &Values) -> f64 {
        let mut r = [0.0; 16];
        let d = self.residual_dim();
        if d <= r.len() {
            self.residual(values, &mut r[..d]);
            r[..d].iter().map(|v| v * v).sum()
        } else {
            let mut r = vec![0.0; d];
            self.residual(values, &mut r);
            r.iter().map(|v| v * v).sum()
        }
    }
}

/// The largest information entry accepted (as the file readers' limit): beyond it, whitened
/// residuals and `J^T J` leave float64's range for ordinary residuals.
pub const MAX_INFORMATION: f64 = 1e30;

/// Upper Cholesky factor `U` of a 3x3 information matrix (`Omega = U^T U`), so that the whitened
/// residual is `U r`. Fails with a clear message when Omega is not symmetric positive definite.
pub fn sqrt_information(omega: &[[f64; 3]; 3]) -> Result<[[f64; 3]; 3]> {
    for (i, row) in omega.iter().enumerate() {
        for (j, v) in row.iter().enumerate() {
            if !v.is_finite() {
                return input(format!(
                    "information matrix entry ({i}, {j}) is {v}; use finite numbers"
                ));
            }
            if v.abs() > MAX_INFORMATION {
                return input(format!(
                    "information matrix entry ({i}, {j}) is {v:e}, beyond +/-{MAX_INFORMATION:e}: \
                     weighted squared residuals would overflow; for an edge meant to be exact use \
                     a large but sane weight such as 1e12"
                ));
            }
            let w = omega[j][i];
            if (v - w).abs() > 1e-9 * (1.0 + v.abs().max(w.abs())) {
                return input(format!(
                    "information matrix is not symmetric ({i},{j})={v} vs ({j},{i})={w}; pass a symmetric matrix"
                ));
            }
        }
    }
    // Cholesky Omega = L L^T, then U = L^T.
    let mut l = [[0.0f64; 3]; 3];
    for i in 0..3 {
        for j in 0..=i {
            let mut s = omega[i][j];
            for k in 0..j {
                s -= l[i][k] * l[j][k];
            }
            if i == j {
                if s <= 0.0 || !s.is_finite() {
                    return input(
                        "information matrix is not positive definite; give each edge an SPD information matrix",
                    );
                }
                l[i][i] = s.sqrt();
            } else {
                l[i][j] = s / l[j][j];
            }
        }
    }
    let mut u = [[0.0f64; 3]; 3];
    for i in 0..3 {
        for j in 0..3 {
            u[i][j] = l[j][i];
        }
    }
    Ok(u)
}

/// `U r` for upper-triangular U.
#[inline]
pub(crate) fn whiten3(u: &[[f64; 3]; 3], r: [f64; 3]) -> [f64; 3] {
    [
        u[0][0] * r[0] + u[0][1] * r[1] + u[0][2] * r[2],
        u[1][1] * r[1] + u[1][2] * r[2],
        u[2][2] * r[2],
    ]
}

/// Writes `U J` (J a row-major 3x3) into `out` (row-major 3x3).
#[inline]
pub(crate) fn whiten3x3(u: &[[f64; 3]; 3], j: &[[f64; 3]; 3], out: &mut [f64]) {
    for col in 0..3 {
        let c = whiten3(u, [j[0][col], j[1][col], j[2][col]]);
        out[col] = c[0];
        out[3 + col] = c[1];
        out[6 + col] = c[2];
    }
}

/// The SE(2) error `e = Log(E)` of a relative pose `E` given as its translation `t` and wrapped
/// angle `theta`, with the derivative pieces every SE(2) residual needs:
/// `r_t = V(theta)^-1 t`, `dr_t/dt = V^-1`, `dr_t/dtheta = w = a'(theta) t - S t / 2`.
pub(crate) struct SE2Log {
    pub r: [f64; 3],
    /// `V^-1 = [[a, h], [-h, a]]` with `h = theta/2`.
    pub a: f64,
    pub h: f64,
    pub w: [f64; 2],
}

impl SE2Log {
    /// The residual alone, `Log(E)`, without derivative pieces (used for trial costs).
    #[inline]
    pub fn residual(t: [f64; 2], theta: f64) -> [f64; 3] {
        let a = vinv_diag(theta);
        let h = 0.5 * theta;
        [a * t[0] + h * t[1], -h * t[0] + a * t[1], theta]
    }

    /// The residual and the derivative pieces; also returns `(cos theta, sin theta)`, all from a
    /// single `sin_cos(theta / 2)`.
    #[inline]
    pub fn new(t: [f64; 2], theta: f64) -> (Self, f64, f64) {
        let h = 0.5 * theta;
        let (sh, ch) = crate::se2::sin_cos(h);
        let (c, s) = (1.0 - 2.0 * sh * sh, 2.0 * sh * ch);
        let (a, da) = if theta.abs() < 1e-2 {
            (vinv_diag(theta), vinv_diag_derivative(theta))
        } else {
            (h * ch / sh, (s - theta) / (4.0 * sh * sh))
        };
        let log = Self {
            r: [a * t[0] + h * t[1], -h * t[0] + a * t[1], theta],
            a,
            h,
            w: [da * t[0] + 0.5 * t[1], da * t[1] - 0.5 * t[0]],
        };
        (log, c, s)
    }

    /// `V^-1 M` for a 2x2 M given by columns.
    #[inline]
    pub fn vinv_times(&self, m: [[f64; 2]; 2]) -> [[f64; 2]; 2] {
        // m is [row][col]
        let (a, h) = (self.a, self.h);
        [
            [a * m[0][0] + h * m[1][0], a * m[0][1] + h * m[1][1]],
            [-h * m[0][0] + a * m[1][0], -h * m[0][1] + a * m[1][1]],
        ]
    }

    #[inline]
    pub fn vinv_vec(&self, v: [f64; 2]) -> [f64; 2] {
        [
            self.a * v[0] + self.h * v[1],
            -self.h * v[0] + self.a * v[1],
        ]
    }
}

/// Checks that every key of a new factor names an existing variable.
pub(crate) fn check_keys(keys: &[Key], values: &Values) -> Result<()> {
    for &k in keys {
        if !values.contains(k) {
            return input(format!("factor refers to {k:?}, which does not exist"));
        }
    }
    Ok(())
}

#[cfg(test)]
pub(crate) mod testing {
    //! Central-difference Jacobian checks shared by every factor's tests.
    use super::Factor;
    use crate::values::Values;

    pub fn check_jacobians(f: &dyn Factor, values: &Values, rtol: f64, atol: f64) {
        let d = f.residual_dim();
        let total: usize = f.keys().iter().map(|k| k.dim()).sum();
        let mut r = vec![0.0; d];
        let mut jac = vec![0.0; d * total];
        f.linearize(values, &mut r, &mut jac);
        let mut r_only = vec![0.0; d];
        f.residual(values, &mut r_only);
        for (a, b) in r.iter().zip(r_only.iter()) {
            assert!(
                (a - b).abs() <= 1e-14 * (1.0 + a.abs()),
                "residual() and linearize() disagree"
            );
        }
        let h = 1e-6;
        let mut offset = 0;
        for &key in f.keys() {
            let kd = key.dim();
            for c in 0..kd {
                let mut plus = values.clone();
                let mut minus = values.clone();
                let mut delta = vec![0.0; kd];
                delta[c] = h;
                plus.retract(key, &delta);
                delta[c] = -h;
                minus.retract(key, &delta);
                let mut rp = vec![0.0; d];
                let mut rm = vec![0.0; d];
                f.residual(&plus, &mut rp);
                f.residual(&minus, &mut rm);
                for row in 0..d {
                    let fd = (rp[row] - rm[row]) / (2.0 * h);
                    let an = jac[offset + row * kd + c];
                    assert!(
                        (fd - an).abs() <= atol + rtol * fd.abs().max(an.abs()),
                        "{key:?} d r[{row}] / d delta[{c}]: analytic {an} vs numeric {fd}"
                    );
                }
            }
            offset += d * kd;
        }
    }
}
