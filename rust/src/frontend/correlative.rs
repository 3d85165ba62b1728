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

/// The best match and, when asked for, the best one at a distinct pose (the runner-up).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Ranked {
    pub best: Found,
    /// The best pose farther than the distinct window from `best` scoring at least the asked
    /// share of its score: a second explanation of the scan, so the match is ambiguous.
    pub runner_up: Option<Found>,
    /// The best pose is on the window's border (its outermost rotation or cell): the score
    /// may still rise outside, so the true peak may lie beyond the window.
    pub on_edge: bool,
}

/// Leaves within `cells` translation cells and `rotations` rotation steps of a pose are skipped.
#[derive(Clone, Copy)]
struct Exclusion {
    rotation: usize,
    dx: i64,
    dy: i64,
    cells: i64,
    rotations: usize,
}

impl Exclusion {
    fn covers(&self, rotation: usize, dx: i64, dy: i64) -> bool {
        rotation.abs_diff(self.rotation) <= self.rotations
            && (dx - self.dx).abs() <= self.cells
            && (dy - self.dy).abs() <= self.cells
    }
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
    search_ranked(grid, scan, guess, window, min_score, None).map(|r| r.best)
}

/// [`search`], and with `distinct = Some((d, ratio))` also the best pose outside the window `d`
/// around the best that scores at least `ratio` times the best (a second branch and bound
/// whose floor is that share, so it prunes most of the window at once).
pub fn search_ranked(
    grid: &LikelihoodGrid,
    scan: &[Point],
    guess: [f64; 3],
    window: Window,
    min_score: f64,
    distinct: Option<(Window, f64)>,
) -> Option<Ranked> {
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
    branch(grid, &rotations, start.clone(), w, None, &mut best);
    let found = |(score, ri, dx, dy): (f64, usize, i64, i64)| {
        rotations.get(ri).map(|r: &Rotation| Found {
            pose: [
                guess[0] + dx as f64 * res,
                guess[1] + dy as f64 * res,
                crate::se2::wrap_angle(r.theta),
            ],
            score,
        })
    };
    let top_found = found(best)?;
    let on_edge =
        best.1 == 0 || best.1 + 1 == rotations.len() || best.2.abs() >= w || best.3.abs() >= w;
    let runner_up = distinct.and_then(|(d, ratio)| {
        let exclusion = Exclusion {
            rotation: best.1,
            dx: best.2,
            dy: best.3,
            cells: (d.linear / res).floor() as i64,
            rotations: (d.angular / step).floor() as usize,
        };
        let mut second = ((ratio * best.0).max(min_score), usize::MAX, 0i64, 0i64);
        branch(grid, &rotations, start, w, Some(&exclusion), &mut second);
        found(second)
    });
    Some(Ranked {
        best: top_found,
        runner_up,
        on_edge,
    })
}

fn branch(
    grid: &LikelihoodGrid,
    rotations: &[Rotation],
    mut candidates: Vec<Candidate>,
    w: i64,
    exclusion: Option<&Exclusion>,
    best: &mut (f64, usize, i64, i64),
) {
    candidates.sort_by(|a, b| b.bound.total_cmp(&a.bound));
    for c in candidates {
        if c.bound <= best.0 {
            return; // sorted: nothing further can beat the best
        }
        if c.level == 0 {
            // At the fine level the bound is the score itself.
            if !exclusion.is_some_and(|e| e.covers(c.rotation, c.dx, c.dy)) {
                *best = (c.bound, c.rotation, c.dx, c.dy);
            }
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
        branch(grid, rotations, children, w, exclusion, best);
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

    /// The map seen from `truth`, in the robot frame.
    fn seen_from(map: &[Point], truth: [f64; 3]) -> Vec<Point> {
        let (s, c) = truth[2].sin_cos();
        map.iter()
            .step_by(3)
            .map(|p| {
                let d = [p[0] - truth[0], p[1] - truth[1]];
                [c * d[0] + s * d[1], -s * d[0] + c * d[1]]
            })
            .collect()
    }

    #[test]
    fn a_peak_beyond_the_window_shows_as_a_best_pose_on_its_border() {
        let map = room();
        let grid = LikelihoodGrid::new(&map, 0.05, 0.05, 4).unwrap();
        let narrow = Window {
            linear: 0.25,
            angular: 8f64.to_radians(),
        };
        let wide = Window {
            linear: 1.5,
            angular: 45f64.to_radians(),
        };
        let inside = search_ranked(
            &grid,
            &seen_from(&map, [0.1, -0.05, 0.04]),
            [0.0; 3],
            narrow,
            0.1,
            None,
        )
        .unwrap();
        assert!(!inside.on_edge, "{inside:?}");
        for truth in [[0.6, 0.0, 0.0], [0.0, 0.0, 0.3]] {
            let scan = seen_from(&map, truth);
            let near = search_ranked(&grid, &scan, [0.0; 3], narrow, 0.1, None).unwrap();
            assert!(near.on_edge, "{truth:?}: {near:?}");
            let far = search_ranked(&grid, &scan, [0.0; 3], wide, 0.1, None).unwrap();
            assert!(
                !far.on_edge && far.best.score > near.best.score,
                "{truth:?}: {far:?}"
            );
            assert!((far.best.pose[0] - truth[0]).abs() <= 0.05, "{far:?}");
            assert!((far.best.pose[2] - truth[2]).abs() <= 0.02, "{far:?}");
        }
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

    #[test]
    fn a_corridor_has_a_runner_up_along_it_and_a_room_corner_none() {
        let window = Window {
            linear: 0.8,
            angular: 0.15,
        };
        let distinct = Window {
            linear: 0.3,
            angular: 5f64.to_radians(),
        };
        // Two long parallel walls: shifted along them, the scan fits as well.
        let corridor: Vec<Point> = (0..400)
            .flat_map(|k| {
                let x = -10.0 + 0.05 * k as f64;
                [[x, 1.0], [x, -1.0]]
            })
            .collect();
        let grid = LikelihoodGrid::new(&corridor, 0.05, 0.05, 3).unwrap();
        let scan: Vec<Point> = corridor
            .iter()
            .filter(|p| p[0].abs() < 4.0)
            .step_by(2)
            .copied()
            .collect();
        let ranked =
            search_ranked(&grid, &scan, [0.0; 3], window, 0.3, Some((distinct, 0.9))).unwrap();
        let runner_up = ranked
            .runner_up
            .expect("the corridor is ambiguous along its axis");
        assert!(runner_up.score >= 0.9 * ranked.best.score);
        assert!((runner_up.pose[0] - ranked.best.pose[0]).abs() > distinct.linear);
        // The room corner with its box: one pose only.
        let map = room();
        let grid = LikelihoodGrid::new(&map, 0.05, 0.05, 3).unwrap();
        let scan: Vec<Point> = map.iter().step_by(3).copied().collect();
        let ranked =
            search_ranked(&grid, &scan, [0.0; 3], window, 0.3, Some((distinct, 0.9))).unwrap();
        assert!(ranked.runner_up.is_none(), "{ranked:?}");
        assert!(
            ranked.best.pose[0].abs() <= 0.06 && ranked.best.pose[1].abs() <= 0.06,
            "{ranked:?}"
        );
    }
}
