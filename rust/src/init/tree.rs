//! Spanning-tree initialization (g2o's and TORO's default): compose the relative-pose
//! measurements outward from the anchor along a spanning tree.
//!
//! The tree prefers odometry: Kruskal-style with a union-find, first every odometry edge
//! (`|i - j| == 1`), then the loop closures, each group in the caller's order. A breadth-first
//! search from the anchor then composes poses along it: for edge `(i, j)` with measurement `z`
//! (pose of j in the frame of i), `x_j = x_i z` walking i -> j and `x_i = x_j z^-1` walking
//! j -> i. O(n + m) time and memory.

use super::UnionFind;
use crate::error::Result;
use crate::se2::Pose2;

/// Indices (into `edges`) of the spanning tree's edges: odometry first, then loop closures.
/// Fails with an Input error naming poses the edges do not connect to the anchor.
pub(super) fn spanning_tree(
    num_poses: usize,
    edges: &[(usize, usize)],
    anchor: usize,
) -> Result<Vec<usize>> {
    let mut uf = UnionFind::new(num_poses);
    let mut tree = Vec::with_capacity(num_poses.saturating_sub(1));
    for odometry in [true, false] {
        for (k, &(i, j)) in edges.iter().enumerate() {
            if (i.abs_diff(j) == 1) == odometry && uf.union(i, j) {
                tree.push(k);
            }
        }
        if tree.len() + 1 == num_poses {
            break;
        }
    }
    uf.check_reaches_all(anchor)?;
    Ok(tree)
}

/// Poses composed along the spanning tree from the anchor, which keeps its given pose.
pub(super) fn tree(
    poses: &[Pose2],
    edges: &[(usize, usize)],
    measurements: &[Pose2],
    anchor: usize,
) -> Result<Vec<Pose2>> {
    let n = poses.len();
    let tree = spanning_tree(n, edges, anchor)?;

    // Tree adjacency (CSR of edge indices, both directions).
    let mut ptr = vec![0usize; n + 1];
    for &k in &tree {
        let (i, j) = edges[k];
        ptr[i + 1] += 1;
        ptr[j + 1] += 1;
    }
    for v in 0..n {
        ptr[v + 1] += ptr[v];
    }
    let mut fill = ptr.clone();
    let mut adj = vec![0usize; ptr[n]];
    for &k in &tree {
        let (i, j) = edges[k];
        adj[fill[i]] = k;
        fill[i] += 1;
        adj[fill[j]] = k;
        fill[j] += 1;
    }
    drop(fill);

    let mut out = poses.to_vec();
    let mut visited = vec![false; n];
    let mut queue = Vec::with_capacity(n);
    visited[anchor] = true;
    queue.push(anchor);
    let mut head = 0;
    while head < queue.len() {
        let u = queue[head];
        head += 1;
        let xu = out[u];
        for &k in &adj[ptr[u]..ptr[u + 1]] {
            let (i, j) = edges[k];
            let (v, x) = if i == u {
                (j, xu.compose(measurements[k]))
            } else {
                (i, xu.compose(measurements[k].inverse()))
            };
            if !visited[v] {
                visited[v] = true;
                out[v] = x;
                queue.push(v);
            }
        }
    }
    Ok(out)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn odometry_is_preferred_over_earlier_loop_closures() {
        // The loop closure (0, 2) comes first in the file but odometry spans the graph.
        let edges = [(0, 2), (0, 1), (2, 1), (3, 2)];
        assert_eq!(spanning_tree(4, &edges, 0).unwrap(), vec![1, 2, 3]);
        // A gap in the odometry is bridged by the first loop closure, in file order.
        let edges = [(0, 1), (3, 0), (2, 0), (2, 3)];
        assert_eq!(spanning_tree(4, &edges, 0).unwrap(), vec![0, 3, 1]);
    }

    #[test]
    fn composes_through_loop_closures_both_ways() {
        // Truth: 0 at the origin, 1 and 2 reached only by loop closures (one reversed).
        let truth = [
            Pose2::new(0.0, 0.0, 0.3),
            Pose2::new(2.0, 1.0, -1.2),
            Pose2::new(-1.0, 4.0, 2.9),
        ];
        let edges = [(0, 2), (1, 0)];
        let z: Vec<Pose2> = edges
            .iter()
            .map(|&(i, j)| truth[i].between(truth[j]))
            .collect();
        let given = [truth[0], Pose2::IDENTITY, Pose2::IDENTITY];
        let got = tree(&given, &edges, &z, 0).unwrap();
        for (g, t) in got.iter().zip(&truth) {
            assert!((g.x - t.x).abs() < 1e-12 && (g.y - t.y).abs() < 1e-12);
            assert!(crate::se2::wrap_angle(g.theta - t.theta).abs() < 1e-12);
        }
    }
}
