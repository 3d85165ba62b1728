//! Chordal relaxation (Carlone, Tron, Daniilidis and Dellaert, "Initialization techniques for 3D
//! SLAM: a survey on rotation estimation and its use in pose graph optimization", ICRA 2015; the
//! 2D case is what GTSAM's LAGO initializes), as two sparse linear least-squares problems:
//!
//! 1. Rotations. Each pose's rotation is the unit vector `r_i = (cos th_i, sin th_i)`, relaxed to
//!    a free 2-vector. Edge `(i, j)` with measured rotation `dth` gives the residual
//!    `r_j - Rot(dth) r_i`, weighted by the edge's marginal rotation information
//!    `w = 1 / Sigma_thth` (`Sigma = Omega^-1`); the anchor's `r` is fixed. Then
//!    `th_i = atan2(s_i, c_i)`, which projects each relaxed vector back onto the circle.
//! 2. Positions, with those rotations fixed: `(t_j - t_i) - R_i t_ij`, weighted by
//!    `W = R_i Omega_tt' R_i^T` where `Omega_tt' = (Sigma_tt)^-1` is the marginal translation
//!    information; the anchor's position is fixed.
//!
//! Both are solved by the sparse Cholesky of [`super::linear`], on one shared analysis, as
//! corrections to the spanning-tree guess of [`super::tree`].

use super::linear::{mat_mul, mat_vec, transpose, BlockSystem, EdgeTerm, Mat2, IDENTITY};
use crate::error::{input, Result};
use crate::se2::Pose2;

/// The marginal informations of one edge: `(w_rot, Omega_tt')`, the Schur complements
/// `Omega_thth - o^T Omega_tt^-1 o` and `Omega_tt - o o^T / Omega_thth` with `o = Omega_t,th`
/// (equal to `1 / Sigma_thth` and `(Sigma_tt)^-1`).
pub(super) fn marginal_information(o: &[[f64; 3]; 3]) -> (f64, Mat2) {
    let det_tt = o[0][0] * o[1][1] - o[0][1] * o[1][0];
    let (a, b) = (o[0][2], o[1][2]);
    // o^T Omega_tt^-1 o with Omega_tt^-1 = [[o11, -o01], [-o10, o00]] / det_tt.
    let quad = (o[1][1] * a * a - (o[0][1] + o[1][0]) * a * b + o[0][0] * b * b) / det_tt;
    let w_rot = o[2][2] - quad;
    let t = o[2][2];
    let w_tt = [
        [o[0][0] - a * a / t, o[0][1] - a * b / t],
        [o[1][0] - a * b / t, o[1][1] - b * b / t],
    ];
    (w_rot, w_tt)
}

/// Checks that an information matrix is finite, symmetric and positive definite, in the words
/// of the crate's factor constructors.
pub(super) fn check_information(k: usize, edge: (usize, usize), o: &[[f64; 3]; 3]) -> Result<()> {
    let (i, j) = edge;
    for r in 0..3 {
        for c in 0..3 {
            let (v, w) = (o[r][c], o[c][r]);
            if !v.is_finite() {
                return input(format!(
                    "edge {k} ({i} -> {j}): information matrix entry ({r}, {c}) is {v}; use finite numbers"
                ));
            }
            if (v - w).abs() > 1e-9 * (1.0 + v.abs().max(w.abs())) {
                return input(format!(
                    "edge {k} ({i} -> {j}): information matrix is not symmetric ({r},{c})={v} vs ({c},{r})={w}; pass a symmetric matrix"
                ));
            }
        }
    }
    // Cholesky: every pivot must be positive.
    let l00 = o[0][0];
    let ok = l00 > 0.0 && {
        let l10 = o[1][0] / l00.sqrt();
        let p1 = o[1][1] - l10 * l10;
        p1 > 0.0 && {
            let l20 = o[2][0] / l00.sqrt();
            let l21 = (o[2][1] - l20 * l10) / p1.sqrt();
            o[2][2] - l20 * l20 - l21 * l21 > 0.0
        }
    };
    let (w_rot, w_tt) = marginal_information(o);
    let det_tt = w_tt[0][0] * w_tt[1][1] - w_tt[0][1] * w_tt[1][0];
    if !(ok && w_rot > 0.0 && w_tt[0][0] > 0.0 && det_tt > 0.0 && w_rot.is_finite()) {
        return input(format!(
            "edge {k} ({i} -> {j}): information matrix is not positive definite; give each edge an SPD information matrix"
        ));
    }
    Ok(())
}

#[inline]
fn rot(c: f64, s: f64) -> Mat2 {
    [[c, -s], [s, c]]
}

/// The chordal initial guess; the anchor keeps its given pose.
pub(super) fn chordal(
    poses: &[Pose2],
    edges: &[(usize, usize)],
    measurements: &[Pose2],
    information: &[[[f64; 3]; 3]],
    anchor: usize,
) -> Result<Vec<Pose2>> {
    let n = poses.len();
    for (k, (&e, o)) in edges.iter().zip(information).enumerate() {
        check_information(k, e, o)?;
    }
    // The spanning-tree guess: checks connectivity, and is the starting point both solves
    // correct (exact on consistent data, which the correction then keeps to rounding level).
    let start = super::tree::tree(poses, edges, measurements, anchor)?;
    if n == 1 {
        return Ok(poses.to_vec());
    }
    let mut system = BlockSystem::new(n, anchor, edges)?;
    let a = poses[anchor];

    // 1. Rotations.
    let r_start: Vec<[f64; 2]> = start
        .iter()
        .map(|p| {
            let (c, s) = p.cos_sin();
            [c, s]
        })
        .collect();
    let r = system.solve(edges, &r_start, |k| {
        let (c, s) = measurements[k].cos_sin();
        let (w, _) = marginal_information(&information[k]);
        EdgeTerm {
            m: rot(c, s),
            c: [0.0, 0.0],
            w: [[w, 0.0], [0.0, w]],
        }
    })?;
    drop(r_start);
    let theta: Vec<f64> = r
        .iter()
        .enumerate()
        .map(|(v, rv)| {
            if v == anchor {
                a.theta
            } else {
                rv[1].atan2(rv[0])
            }
        })
        .collect();
    drop(r);

    // 2. Positions.
    let t_start: Vec<[f64; 2]> = start.iter().map(|p| [p.x, p.y]).collect();
    drop(start);
    let t = system.solve(edges, &t_start, |k| {
        let (i, _) = edges[k];
        let ri = rot(theta[i].cos(), theta[i].sin());
        let (_, w_tt) = marginal_information(&information[k]);
        let z = measurements[k];
        EdgeTerm {
            m: IDENTITY,
            c: mat_vec(&ri, [z.x, z.y]),
            w: mat_mul(&mat_mul(&ri, &w_tt), &transpose(&ri)),
        }
    })?;
    drop(t_start);

    Ok(t.iter()
        .zip(&theta)
        .enumerate()
        .map(|(v, (tv, &th))| {
            if v == anchor {
                a
            } else {
                Pose2::new(tv[0], tv[1], th)
            }
        })
        .collect())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn marginal_information_inverts_the_covariance_blocks() {
        let o = [[50.0, 3.0, 4.0], [3.0, 40.0, -6.0], [4.0, -6.0, 300.0]];
        let m = nalgebra::Matrix3::from_row_slice(&o.concat());
        let sigma = m.try_inverse().unwrap();
        let (w_rot, w_tt) = marginal_information(&o);
        assert!((w_rot - 1.0 / sigma[(2, 2)]).abs() < 1e-10 * w_rot);
        let stt = sigma.fixed_view::<2, 2>(0, 0).into_owned();
        let inv = stt.try_inverse().unwrap();
        for r in 0..2 {
            for c in 0..2 {
                assert!((w_tt[r][c] - inv[(r, c)]).abs() < 1e-10 * 50.0);
            }
        }
    }

    #[test]
    fn bad_information_is_an_input_error() {
        let not_pd = [[1.0, 2.0, 0.0], [2.0, 1.0, 0.0], [0.0, 0.0, 1.0]];
        let not_sym = [[1.0, 0.5, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]];
        let nan = [[f64::NAN, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]];
        let zero = [[0.0; 3]; 3];
        for (o, what) in [
            (not_pd, "positive definite"),
            (not_sym, "symmetric"),
            (nan, "finite"),
            (zero, "positive definite"),
        ] {
            match check_information(4, (1, 2), &o) {
                Err(crate::HitlError::Input(m)) => {
                    assert!(m.contains(what) && m.contains("edge 4"), "{m}")
                }
                other => panic!("{other:?}"),
            }
        }
    }
}
