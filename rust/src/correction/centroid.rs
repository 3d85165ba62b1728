//! The centroid a colocation states (docs/ALGORITHM.md §I.15): "the same stretch of the wall"
//! is a statement about where each pass saw the wall, not about where its laser points piled
//! up. A pass samples a wall unevenly (densely where the robot drove close or slowly, or where
//! many poses saw the same part; sparsely at the far end), so the plain centroid of its points
//! sits towards its dense end, and two passes over one stretch have centroids that differ along
//! the wall by that bias. Each point is weighted instead by the length of wall it stands for:
//! half the distance to its neighbours along the set's line on either side, a gap counting at
//! most `MAX_GAP_M` (a doorway or an occlusion is not wall the pass saw). The weighted centroid
//! is then the middle of the wall the pass saw, as the explicit correction's extents' midpoints
//! are (§4.1).

use crate::geometry::fit_line;
use crate::se2::Pose2;

use super::engine::PoseObservations;

/// [m] the most a gap between two neighbouring points along the wall counts for.
pub const MAX_GAP_M: f64 = 0.5;

/// [m] every point's least weight: a set whose points all lie at one place along its line has
/// no length, and its centroid is then their plain mean.
const MIN_WEIGHT_M: f64 = 1e-12;

/// Per pose of `set` (same order), the weight of each of its points in the set's centroid: the
/// length of wall it stands for, from the points' places along the set's own total-least-squares
/// line at `poses` (see the module's docs). All ones for a set without a line (empty, or a pose
/// out of range: the caller's validation reports those).
pub fn along_wall_weights(poses: &[Pose2], set: &[PoseObservations]) -> Vec<Vec<f64>> {
    let ones = || set.iter().map(|(_, p)| vec![1.0; p.len()]).collect();
    let mut world = Vec::new();
    for (i, pts) in set {
        let Some(x) = poses.get(*i) else {
            return ones();
        };
        world.extend(pts.iter().map(|p| x.transform_point(*p)));
    }
    let Some(line) = fit_line(&world) else {
        return ones();
    };
    let dir = [-line.phi.sin(), line.phi.cos()];
    let along: Vec<f64> = world
        .iter()
        .map(|p| p[0] * dir[0] + p[1] * dir[1])
        .collect();
    let mut order: Vec<usize> = (0..along.len()).collect();
    order.sort_by(|&i, &j| along[i].total_cmp(&along[j]));
    let gap = |k: usize| (along[order[k + 1]] - along[order[k]]).min(MAX_GAP_M);
    let mut flat = vec![0.0; along.len()];
    for k in 0..order.len() {
        let left = if k > 0 { gap(k - 1) } else { 0.0 };
        let right = if k + 1 < order.len() { gap(k) } else { 0.0 };
        flat[order[k]] = (0.5 * (left + right)).max(MIN_WEIGHT_M);
    }
    let mut weights = Vec::with_capacity(set.len());
    let mut k = 0;
    for (_, pts) in set {
        weights.push(flat[k..k + pts.len()].to_vec());
        k += pts.len();
    }
    weights
}

#[cfg(test)]
mod tests {
    use super::*;

    fn centroid(poses: &[Pose2], set: &[PoseObservations], w: &[Vec<f64>]) -> [f64; 2] {
        let (mut s, mut n) = ([0.0, 0.0], 0.0);
        for ((i, pts), wi) in set.iter().zip(w) {
            for (p, &wk) in pts.iter().zip(wi) {
                let q = poses[*i].transform_point(*p);
                s = [s[0] + wk * q[0], s[1] + wk * q[1]];
                n += wk;
            }
        }
        [s[0] / n, s[1] / n]
    }

    /// A wall y = 2 seen from x = 0..4 by two poses: one sees all of it sparsely, the other
    /// piles points on its first metre. The plain centroid slides towards the pile; the
    /// weighted one stays near the stretch's middle.
    #[test]
    fn a_pile_of_points_does_not_pull_the_centroid() {
        let poses = vec![Pose2::new(0.0, 0.0, 0.0), Pose2::new(0.5, 0.0, 0.3)];
        let sparse: Vec<[f64; 2]> = (0..41).map(|k| [0.1 * k as f64, 2.0]).collect();
        let x1 = poses[1];
        let pile: Vec<[f64; 2]> = (0..400)
            .map(|k| x1.inverse().transform_point([0.0025 * k as f64, 2.0]))
            .collect();
        let set: Vec<PoseObservations> = vec![(0, sparse), (1, pile)];
        let plain: Vec<Vec<f64>> = set.iter().map(|(_, p)| vec![1.0; p.len()]).collect();
        let w = along_wall_weights(&poses, &set);
        let c0 = centroid(&poses, &set, &plain);
        let c1 = centroid(&poses, &set, &w);
        assert!(
            c0[0] < 1.0,
            "the plain centroid is pulled to the pile: {c0:?}"
        );
        assert!((c1[0] - 2.0).abs() < 0.3, "weighted centroid {c1:?}");
        assert!((c1[1] - 2.0).abs() < 1e-9);
        assert!(w.iter().flatten().all(|&v| v > 0.0 && v <= 1.0));
    }

    #[test]
    fn evenly_spaced_points_weigh_alike_and_a_doorway_counts_little() {
        let poses = vec![Pose2::new(1.0, -2.0, 0.7)];
        let even: Vec<[f64; 2]> = (0..50).map(|k| [3.0, -1.0 + 0.04 * k as f64]).collect();
        let w = along_wall_weights(&poses, &[(0, even)]);
        // Inner points stand for 4 cm each, the two ends for half that.
        assert!(w[0][1..49].iter().all(|&v| (v - 0.04).abs() < 1e-9));
        assert!((w[0][0] - 0.02).abs() < 1e-9 && (w[0][49] - 0.02).abs() < 1e-9);
        // A 3 m doorway between two metres of wall counts as MAX_GAP_M: the centroid stays in
        // the middle of what was seen, not pulled across the gap.
        let mut door: Vec<[f64; 2]> = (0..=10).map(|k| [0.1 * k as f64, 2.0]).collect();
        door.extend((0..=10).map(|k| [4.0 + 0.1 * k as f64, 2.0]));
        let w = along_wall_weights(&[Pose2::new(0.0, 0.0, 0.0)], &[(0, door)]);
        assert!((w[0][10] - 0.5 * (0.1 + MAX_GAP_M)).abs() < 1e-9);
        let out_of_range: Vec<PoseObservations> = vec![(5, vec![[1.0, 1.0]])];
        assert_eq!(along_wall_weights(&poses, &out_of_range), vec![vec![1.0]]);
        let one = along_wall_weights(&poses, &[(0, vec![[1.0, 1.0]])]);
        assert!(one[0][0] > 0.0);
    }
}
