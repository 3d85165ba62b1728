//! The group test on loop closure candidates (docs/ALGORITHM.md §F.4): pairwise consistency
//! and the largest mutually consistent set, after Mangelson, Dominic, Eustice and Vasudevan,
//! "Pairwise Consistent Measurement Set Maximization for Robust Multi-robot Map Merging", ICRA
//! 2018.
//!
//! Two closures `a: A_a -> B_a` and `b: A_b -> B_b` (submap origin to keyframe) are consistent
//! when the cycle they close with the current estimate,
//! `(z_a^-1 (X_Aa^-1 X_Ab) z_b)^-1 (X_Ba^-1 X_Bb)`, is near the identity: within a gate that
//! grows with the cycle's extent (the estimate between the two origins and between the two
//! keyframes drifts with distance). A true revisit gives several closures that agree with each
//! other; a false one (a corridor like another) rarely agrees with the true ones.

use crate::se2::Pose2;

/// How far a cycle may be from the identity: `linear + linear_per_m * s` [m] and
/// `angular + angular_per_m * s` [rad], `s` the path length along the cycle's two stretches of
/// estimate [m]; a heading error also moves
/// the far end of a closure, so the linear gate adds the angular one times the closure's
/// length.
#[derive(Clone, Copy, Debug)]
pub struct Gate {
    /// The longest stretch of path [m] whose estimate decides a pair.
    pub reach: f64,
    pub linear: f64,
    pub linear_per_m: f64,
    pub angular: f64,
    pub angular_per_m: f64,
}

/// A candidate as the test sees it: its end poses' current estimates, the path length
/// travelled up to each, and its measurement.
#[derive(Clone, Copy, Debug)]
pub struct Cycle {
    pub from: Pose2,
    pub to: Pose2,
    pub from_travelled: f64,
    pub to_travelled: f64,
    pub measurement: Pose2,
}

fn length(p: Pose2) -> f64 {
    p.x.hypot(p.y)
}

/// Whether two candidates close a cycle within the gate. The cycle runs through the estimate
/// between the two origins and between the two keyframes; where either stretch of path is
/// longer than `gate.reach` the estimate is not trusted to decide (an old map with two passes
/// not yet brought together), and the pair counts as consistent.
pub fn consistent(a: &Cycle, b: &Cycle, gate: &Gate) -> bool {
    let path_from = (a.from_travelled - b.from_travelled).abs();
    let path_to = (a.to_travelled - b.to_travelled).abs();
    if path_from > gate.reach || path_to > gate.reach {
        return true;
    }
    let between_from = a.from.between(b.from);
    let between_to = a.to.between(b.to);
    let predicted = a
        .measurement
        .inverse()
        .compose(between_from)
        .compose(b.measurement);
    let e = predicted.between(between_to);
    let extent = path_from + path_to;
    let angular = gate.angular + gate.angular_per_m * extent;
    let lever = length(a.measurement).max(length(b.measurement));
    let linear = gate.linear + gate.linear_per_m * extent + angular * lever;
    e.theta.abs() <= angular && length(e) <= linear
}

/// The largest set of mutually consistent candidates (indices, ascending). Exact (branch and
/// bound over the consistency graph, Bron-Kerbosch with pivoting) up to `EXACT` candidates;
/// beyond, greedy by degree.
pub fn largest_consistent_set(cycles: &[Cycle], gate: &Gate) -> Vec<usize> {
    let n = cycles.len();
    let mut adjacent = vec![vec![false; n]; n];
    for i in 0..n {
        for j in i + 1..n {
            let c = consistent(&cycles[i], &cycles[j], gate);
            adjacent[i][j] = c;
            adjacent[j][i] = c;
        }
    }
    let mut best = Vec::new();
    if n <= EXACT {
        let all: Vec<usize> = (0..n).collect();
        bron_kerbosch(&adjacent, &mut Vec::new(), all, Vec::new(), &mut best);
    } else {
        // Greedy: by degree, keep each candidate consistent with all kept so far.
        let mut order: Vec<usize> = (0..n).collect();
        let degree: Vec<usize> = adjacent
            .iter()
            .map(|r| r.iter().filter(|&&b| b).count())
            .collect();
        order.sort_by_key(|&i| (std::cmp::Reverse(degree[i]), i));
        for i in order {
            if best.iter().all(|&j| adjacent[i][j]) {
                best.push(i);
            }
        }
    }
    best.sort_unstable();
    best
}

const EXACT: usize = 48;

fn bron_kerbosch(
    adjacent: &[Vec<bool>],
    clique: &mut Vec<usize>,
    candidates: Vec<usize>,
    mut excluded: Vec<usize>,
    best: &mut Vec<usize>,
) {
    if candidates.is_empty() {
        if excluded.is_empty() && clique.len() > best.len() {
            *best = clique.clone();
        }
        return;
    }
    if clique.len() + candidates.len() <= best.len() {
        return;
    }
    // Pivot: the vertex with the most neighbours among the candidates.
    let pivot = candidates
        .iter()
        .chain(excluded.iter())
        .copied()
        .max_by_key(|&u| (candidates.iter().filter(|&&v| adjacent[u][v]).count(), u))
        .unwrap_or(candidates[0]);
    let mut remaining = candidates.clone();
    for v in candidates.into_iter().filter(|&v| !adjacent[pivot][v]) {
        let next: Vec<usize> = remaining
            .iter()
            .copied()
            .filter(|&u| adjacent[v][u])
            .collect();
        let next_excluded: Vec<usize> = excluded
            .iter()
            .copied()
            .filter(|&u| adjacent[v][u])
            .collect();
        clique.push(v);
        bron_kerbosch(adjacent, clique, next, next_excluded, best);
        clique.pop();
        remaining.retain(|&u| u != v);
        excluded.push(v);
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    const GATE: Gate = Gate {
        reach: 100.0,
        linear: 0.2,
        linear_per_m: 0.03,
        angular: 0.035,
        angular_per_m: 0.005,
    };

    /// A closure from `from` to `to` measured as the truth `from^-1 to` composed with `error`.
    fn cycle(from: Pose2, to: Pose2, error: Pose2) -> Cycle {
        Cycle {
            from,
            to,
            from_travelled: from.x,
            to_travelled: to.x,
            measurement: from.between(to).compose(error),
        }
    }

    #[test]
    fn agreeing_closures_form_the_set_and_a_false_one_is_left_out() {
        // The estimate is off by a drift the closures all agree on: the keyframes' true poses
        // are 0.5 m and 5 degrees from their estimates, the same for all.
        let drift = Pose2::new(0.5, -0.3, 0.09);
        let mut cycles = Vec::new();
        for k in 0..5 {
            let from = Pose2::new(2.0 * k as f64, 0.0, 0.0);
            let truth_to = Pose2::new(2.0 * k as f64 + 0.4, 1.0, 0.1);
            let estimate_to = truth_to.compose(drift);
            cycles.push(Cycle {
                from,
                to: estimate_to,
                from_travelled: from.x,
                to_travelled: 2.0 * k as f64,
                measurement: from.between(truth_to),
            });
        }
        // A false closure: its measurement puts the keyframe 3 m down the corridor.
        let from = Pose2::new(0.0, 0.0, 0.0);
        let truth_to = Pose2::new(0.4, 1.0, 0.1);
        cycles.push(cycle(
            from,
            truth_to.compose(drift),
            Pose2::new(3.0, 0.0, 0.0),
        ));
        let set = largest_consistent_set(&cycles, &GATE);
        assert_eq!(set, vec![0, 1, 2, 3, 4]);
        assert!(!consistent(&cycles[0], &cycles[5], &GATE));
    }

    #[test]
    fn the_greedy_set_beyond_the_exact_size_is_consistent() {
        let n = EXACT + 10;
        let cycles: Vec<Cycle> = (0..n)
            .map(|k| {
                let from = Pose2::new(k as f64 * 0.3, 0.0, 0.0);
                let to = Pose2::new(k as f64 * 0.3, 2.0, 0.0);
                let error = if k % 7 == 3 {
                    Pose2::new(0.0, 1.5 + 0.1 * k as f64, 0.3)
                } else {
                    Pose2::IDENTITY
                };
                cycle(from, to, error)
            })
            .collect();
        let set = largest_consistent_set(&cycles, &GATE);
        assert!(set.iter().all(|&k| k % 7 != 3), "{set:?}");
        assert_eq!(set.len(), (0..n).filter(|k| k % 7 != 3).count());
    }
}
