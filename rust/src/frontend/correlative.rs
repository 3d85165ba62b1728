//! Correlative scan matching by branch and bound (Olson 2009; Hess et al. 2016, section V;
//! docs/ALGORITHM.md §F.2): the pose in a window around a guess that maximizes the mean likelihood of the scan's points in a
//! [`LikelihoodGrid`], searched exactly over a lattice of rotations (step from the scan's
//! reach and the grid's resolution) and whole-cell translations, with the grid's coarse levels
//! as upper bounds so that most of the window is never scored at the fine level.

use super::likelihood::{LikelihoodGrid, Point};

/// The search window around the guess: `linear` [m] each way in x and y, `angular` [rad].
#[derive(Clone, Copy, Debug)]
pub struct Window {
    pub linear: f64,
    pub angular: f64,
}

/// The best pose found and its score (mean likelihood of the points, 0..1).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Found {
    pub pose: [f64; 3],
    pub score: f64,
}

struct Rotation {
    theta: f64,
    cells: Vec<(i64, i64)>,
}

#[derive(Clone, Copy)]
struct Candidate {
    rotation: usize,
    dx: i64,
    dy: i64,
    level: usize,
    bound: f64,
}

fn bound(grid: &LikelihoodGrid, r: &Rotation, dx: i64, dy: i64, level: usize) -> f64 {
    let sum: f64 = r
        .cells
        .iter()
        .map(|&(x, y)| grid.at(level, x.saturating_add(dx), y.saturating_add(dy)) as f64)
        .sum();
    sum / r.cells.len().max(1) as f64
}

/// The pose of `scan` (robot-frame points) in the grid's frame within `window` of `guess` with
/// the highest score, if any scores above `min_score`.
pub fn search(
    grid: &LikelihoodGrid,
    scan: &[Point],
    guess: [f64; 3],
    window: Window,
    min_score: f64,
) -> Option<Found> {
    if scan.is_empty() || grid.depth() == usize::MAX {
        return None;
    }
    let res = grid.resolution();
    let reach = scan
        .iter()
        .map(|p| p[0].hypot(p[1]))
        .fold(0.0f64, f64::max)
        .max(res);
    let step = (1.0 - res * res / (2.0 * reach * reach))
        .clamp(-1.0, 1.0)
        .acos()
        .max(1e-4);
    let n_theta = (window.angular / step).ceil() as i64;
    let w = (window.linear / res).ceil() as i64;
    let rotations: Vec<Rotation> = (-n_theta..=n_theta)
        .map(|k| {
            let theta = guess[2] + k as f64 * step;
            let (s, c) = theta.sin_cos();
            let cells = scan
                .iter()
                .map(|p| {
                    grid.cell([
                        c * p[0] - s * p[1] + guess[0],
                        s * p[0] + c * p[1] + guess[1],
                    ])
                })
                .collect();
            Rotation { theta, cells }
        })
        .collect();
    let top = grid.depth();
    let size = 1i64 << top;
    let mut start = Vec::new();
    for (ri, r) in rotations.iter().enumerate() {
        let mut dx = -w;
        while dx <= w {
            let mut dy = -w;
            while dy <= w {
                start.push(Candidate {
                    rotation: ri,
                    dx,
                    dy,
                    level: top,
                    bound: bound(grid, r, dx, dy, top),
                });
                dy += size;
            }
            dx += size;
        }
    }
    // (score, rotation, dx, dy) of the best leaf so far; the floor is `min_score`.
    let mut best = (min_score, usize::MAX, 0i64, 0i64);
    branch(grid, &rotations, start, w, &mut best);
    let (score, ri, dx, dy) = best;
    let r = rotations.get(ri)?;
    Some(Found {
        pose: [
            guess[0] + dx as f64 * res,
            guess[1] + dy as f64 * res,
            crate::se2::wrap_angle(r.theta),
        ],
        score,
    })
}

fn branch(
    grid: &LikelihoodGrid,
    rotations: &[Rotation],
    mut candidates: Vec<Candidate>,
    w: i64,
    best: &mut (f64, usize, i64, i64),
) {
    candidates.sort_by(|a, b| b.bound.total_cmp(&a.bound));
    for c in candidates {
        if c.bound <= best.0 {
            return; // sorted: nothing further can beat the best
        }
        if c.level == 0 {
            // At the fine level the bound is the score itself.
            *best = (c.bound, c.rotation, c.dx, c.dy);
            continue;
        }
        let half = 1i64 << (c.level - 1);
        let r = &rotations[c.rotation];
        let mut children = Vec::with_capacity(4);
        for (ox, oy) in [(0, 0), (half, 0), (0, half), (half, half)] {
            let (dx, dy) = (c.dx + ox, c.dy + oy);
            if dx > w || dy > w {
                continue;
            }
            children.push(Candidate {
                rotation: c.rotation,
                dx,
                dy,
                level: c.level - 1,
                bound: bound(grid, r, dx, dy, c.level - 1),
            });
        }
        branch(grid, rotations, children, w, best);
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// An L-shaped room corner with a box, seen from the origin.
    fn room() -> Vec<Point> {
        let mut pts = Vec::new();
        for k in 0..200 {
            let t = k as f64 * 0.03;
            pts.push([t - 2.0, 3.0]);
            pts.push([4.0, t - 2.5]);
            if k < 40 {
                pts.push([1.0 + 0.02 * k as f64, -1.0]);
            }
        }
        pts
    }

    #[test]
    fn finds_the_true_pose_from_a_guess_off_by_decimetres_and_degrees() {
        let map = room();
        let grid = LikelihoodGrid::new(&map, 0.05, 0.05, 4).unwrap();
        let truth: [f64; 3] = [0.37, -0.21, 0.12];
        // The scan: the map seen from `truth`, in the robot frame.
        let (s, c) = truth[2].sin_cos();
        let scan: Vec<Point> = map
            .iter()
            .step_by(3)
            .map(|p| {
                let d = [p[0] - truth[0], p[1] - truth[1]];
                [c * d[0] + s * d[1], -s * d[0] + c * d[1]]
            })
            .collect();
        let guess = [0.0, 0.0, 0.0];
        let window = Window {
            linear: 0.6,
            angular: 0.25,
        };
        let found = search(&grid, &scan, guess, window, 0.3).unwrap();
        assert!((found.pose[0] - truth[0]).abs() <= 0.05, "{found:?}");
        assert!((found.pose[1] - truth[1]).abs() <= 0.05, "{found:?}");
        assert!((found.pose[2] - truth[2]).abs() <= 0.02, "{found:?}");
        assert!(found.score > 0.7);
        // The same search done exhaustively at the fine level gives the same score.
        let res = grid.resolution();
        let reach = scan.iter().map(|p| p[0].hypot(p[1])).fold(0.0f64, f64::max);
        let step = (1.0 - res * res / (2.0 * reach * reach)).acos();
        let n = (window.angular / step).ceil() as i64;
        let w = (window.linear / res).ceil() as i64;
        let mut best = 0.0f64;
        for k in -n..=n {
            let theta = k as f64 * step;
            let (s, c) = theta.sin_cos();
            let cells: Vec<(i64, i64)> = scan
                .iter()
                .map(|p| grid.cell([c * p[0] - s * p[1], s * p[0] + c * p[1]]))
                .collect();
            for dx in -w..=w {
                for dy in -w..=w {
                    let sc: f64 = cells
                        .iter()
                        .map(|&(x, y)| grid.at(0, x + dx, y + dy) as f64)
                        .sum::<f64>()
                        / cells.len() as f64;
                    best = best.max(sc);
                }
            }
        }
        assert!(
            (found.score - best).abs() < 1e-9,
            "{} vs {best}",
            found.score
        );
        // Nothing above an impossible floor.
        assert!(search(&grid, &scan, guess, window, 1.01).is_none());
    }
}
