//! Error back-propagation, COP-SLAM style (docs/ALGORITHM.md §4.2). The explicit move opens a gap
//! between the last unmoved pose and the first moved one; it is closed by spreading the needed
//! change over the relative transforms of the chain between `max(X_a)` (fixed) and `min(X_b)`
//! (already moved): first the rotation, weighted by each edge's rotational variance, then - after
//! recomposing - the remaining translation, weighted by each edge's (isotropic) translational
//! variance. Weights sum to exactly one, so the chain meets the moved block exactly. O(chain
//! length).

use crate::error::{input, Result};
use crate::se2::{rotate, wrap_angle, Pose2};

/// Weights proportional to `var`, summing to exactly 1 (the last one takes the rounding).
fn weights(var: &[f64]) -> Result<Vec<f64>> {
    if var.iter().any(|v| !(v.is_finite() && *v >= 0.0)) {
        return input("edge variances must be finite and non-negative");
    }
    let total: f64 = var.iter().sum();
    let n = var.len();
    let mut w: Vec<f64> = if total > 0.0 {
        var.iter().map(|v| v / total).collect()
    } else {
        vec![1.0 / n as f64; n]
    };
    if let Some((last, rest)) = w.split_last_mut() {
        *last = 1.0 - rest.iter().sum::<f64>();
    }
    Ok(w)
}

/// Rewrites `poses[start + 1 .. end]` so the chain from `poses[start]` meets `poses[end]`.
///
/// `original` holds the poses before the explicit move (their relative transforms are what gets
/// adjusted); `poses[end..]` already carry the move. `rot_var[k]` and `trans_var[k]` are the
/// variances of chain edge `k -> k + 1`. Returns the adjusted relative transforms of the chain.
pub fn backpropagate(
    poses: &mut [Pose2],
    original: &[Pose2],
    start: usize,
    end: usize,
    rot_var: &[f64],
    trans_var: &[f64],
) -> Result<Vec<Pose2>> {
    let n = poses.len();
    if original.len() != n || rot_var.len() + 1 < n || trans_var.len() + 1 < n {
        return input("backpropagate: poses, original poses and edge variances disagree in size");
    }
    if !(start < end && end < n) {
        return input(format!(
            "backpropagate: need start < end < {n}, got {start} and {end}"
        ));
    }
    if end == start + 1 {
        // Adjacent blocks: no poses in between, no gap to spread.
        return Ok(vec![original[start].between(original[end])]);
    }
    let z: Vec<Pose2> = (start..end)
        .map(|k| original[k].between(original[k + 1]))
        .collect();
    let target = poses[end];
    let composed_theta = poses[start].theta + z.iter().map(|e| e.theta).sum::<f64>();
    let c_theta = wrap_angle(target.theta - composed_theta);
    let w_rot = weights(&rot_var[start..end])?;
    let w_tr = weights(&trans_var[start..end])?;

    // Rotation: each edge turns by its share; recompose.
    let mut q = Vec::with_capacity(end - start + 1);
    q.push(poses[start]);
    let mut heading = poses[start].theta;
    for (k, e) in z.iter().enumerate() {
        let prev = q[k];
        let (c, s) = (heading.cos(), heading.sin());
        let t = rotate(c, s, [e.x, e.y]);
        heading += e.theta + w_rot[k] * c_theta;
        q.push(Pose2 {
            x: prev.x + t[0],
            y: prev.y + t[1],
            theta: heading,
        });
    }
    // Translation: what is left at the end, spread by translational weight (world frame).
    let last = q[end - start];
    let c_t = [target.x - last.x, target.y - last.y];
    let mut cum = 0.0;
    let mut adjusted = Vec::with_capacity(end - start);
    let mut prev = poses[start];
    for k in 0..(end - start) {
        cum += w_tr[k];
        let next = if k + 1 == end - start {
            target
        } else {
            let qk = q[k + 1];
            Pose2::new(qk.x + cum * c_t[0], qk.y + cum * c_t[1], qk.theta)
        };
        adjusted.push(prev.between(next));
        if k + 1 < end - start {
            poses[start + 1 + k] = next;
        }
        prev = next;
    }
    Ok(adjusted)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn chain(n: usize) -> Vec<Pose2> {
        let mut p = vec![Pose2::IDENTITY];
        for k in 1..n {
            let step = Pose2::new(0.5, 0.02 * (k as f64).sin(), 0.1 + 0.05 * (k as f64).cos());
            let last = p[k - 1];
            p.push(last.compose(step));
        }
        p
    }

    #[test]
    fn the_chain_meets_the_moved_block_exactly() {
        let original = chain(40);
        let (start, end) = (10, 25);
        let a = Pose2::new(0.7, -0.4, 0.5);
        let mut poses = original.clone();
        for p in poses.iter_mut().skip(end) {
            *p = a.compose(*p);
        }
        let rot: Vec<f64> = (0..39).map(|k| 1e-4 * (1.0 + (k % 5) as f64)).collect();
        let tr: Vec<f64> = (0..39).map(|k| 1e-3 * (1.0 + (k % 3) as f64)).collect();
        let adjusted = backpropagate(&mut poses, &original, start, end, &rot, &tr).unwrap();
        // Composing the adjusted relative transforms from the fixed pose reaches the moved one.
        let mut p = poses[start];
        for (k, z) in adjusted.iter().enumerate() {
            p = p.compose(*z);
            let want = poses[start + 1 + k];
            assert!((p.x - want.x).abs() < 1e-9 && (p.y - want.y).abs() < 1e-9);
            assert!(wrap_angle(p.theta - want.theta).abs() < 1e-9);
        }
        // Unmoved and moved parts are untouched.
        assert_eq!(&poses[..=start], &original[..=start]);
        for k in end..40 {
            assert_eq!(poses[k], a.compose(original[k]));
        }
        // The rotation was spread by rotational variance: each edge turned by w_k * C_theta.
        let total: f64 = (start..end).map(|k| rot[k]).sum();
        let orig_z: Vec<Pose2> = (start..end)
            .map(|k| original[k].between(original[k + 1]))
            .collect();
        let c_theta: f64 = adjusted
            .iter()
            .zip(&orig_z)
            .map(|(x, o)| wrap_angle(x.theta - o.theta))
            .sum();
        for (k, (x, o)) in adjusted.iter().zip(&orig_z).enumerate() {
            let share = wrap_angle(x.theta - o.theta);
            assert!((share - c_theta * rot[start + k] / total).abs() < 1e-12);
        }
    }

    #[test]
    fn weights_sum_to_one_exactly() {
        let w = weights(&[0.1, 0.2, 0.3, 1e-9, 7.0]).unwrap();
        assert_eq!(w.iter().sum::<f64>(), 1.0);
        let w = weights(&[0.0, 0.0]).unwrap();
        assert_eq!(w, vec![0.5, 0.5]);
        assert!(weights(&[f64::NAN]).is_err());
    }

    #[test]
    fn adjacent_blocks_and_bad_ranges() {
        let original = chain(5);
        let mut poses = original.clone();
        let v = vec![1.0; 4];
        assert!(backpropagate(&mut poses, &original, 1, 2, &v, &v).is_ok());
        assert_eq!(poses, original);
        assert!(backpropagate(&mut poses, &original, 3, 3, &v, &v).is_err());
        assert!(backpropagate(&mut poses, &original, 1, 9, &v, &v).is_err());
    }
}
