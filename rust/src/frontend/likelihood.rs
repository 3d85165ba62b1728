//! A likelihood field over a set of points (a submap), for correlative scan matching (Olson,
//! "Real-time correlative scan matching", ICRA 2009): each cell holds `exp(-d^2 / 2 sigma^2)`
//! for the distance `d` to the nearest point (within `3 sigma`), and a pyramid of coarser
//! grids holds, at level `l`, the maximum over the `2^l x 2^l` block of fine cells starting at
//! each cell: an upper bound of the fine score for every translation in that block, which is
//! what branch and bound needs (Hess et al., "Real-time loop closure in 2D LIDAR SLAM", ICRA
//! 2016, section V.C; docs/ALGORITHM.md §F.2).

/// A point of the plane.
pub type Point = [f64; 2];

/// The most cells a grid may have. A grid keeps its fine level and up to 5 coarser ones (plus a
/// scratch copy while building them) at 4 bytes a cell, so 2^25 cells is at most about 1 GB;
/// the front end's maps (the last keyframes within the match range, or one submap) need a few
/// million cells, so a grid this large means a pose far from the others (issue: fuzzing #1).
pub const MAX_CELLS: usize = 1 << 25;

const TABLE: usize = 4096;

/// Why a grid was refused: its points span `width` x `height` [m], `cells` cells at
/// `resolution` [m] (more than [`MAX_CELLS`]). The front end adds which scans did it.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct GridTooLarge {
    pub width: f64,
    pub height: f64,
    pub resolution: f64,
    pub cells: f64,
}

impl std::fmt::Display for GridTooLarge {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(
            f,
            "its points would span {:.3e} x {:.3e} m, a grid of {:.3e} cells at {} m (the limit \
             is {MAX_CELLS} cells)",
            self.width, self.height, self.cells, self.resolution
        )
    }
}

#[derive(Clone, Debug)]
pub struct LikelihoodGrid {
    origin: Point,
    resolution: f64,
    nx: usize,
    ny: usize,
    /// `levels[0]` is the fine field; `levels[l]` the block maxima of `2^l` cells.
    levels: Vec<Vec<f32>>,
}

impl LikelihoodGrid {
    /// The field of `points` at `resolution` [m] with spread `sigma` [m], and `depth` coarser
    /// levels. Empty point sets give an empty grid (every score 0). A grid of more than
    /// [`MAX_CELLS`] cells (points spread too far, or a resolution that is not a positive number)
    /// is refused before anything is allocated.
    pub fn new(
        points: &[Point],
        resolution: f64,
        sigma: f64,
        depth: usize,
    ) -> Result<Self, GridTooLarge> {
        let Some((origin, nx, ny)) = Self::check_size(points, resolution, sigma, depth)? else {
            return Ok(Self {
                origin: [0.0; 2],
                resolution,
                nx: 0,
                ny: 0,
                levels: vec![Vec::new(); depth + 1],
            });
        };
        let reach = 3.0 * sigma;
        let mut fine = vec![0f32; nx * ny];
        let r = (reach / resolution).ceil() as i64;
        let inv = 1.0 / (2.0 * sigma * sigma);
        // exp(-d^2 / 2 sigma^2) tabulated over the squared distances the stencil reaches (its
        // corners included), 4096 steps: the field's cost was mostly `exp`.
        let farthest = 2.0 * ((r as f64 + 1.0) * resolution).powi(2);
        let per = (TABLE - 1) as f64 / farthest;
        let table: Vec<f32> = (0..TABLE)
            .map(|i| (-(i as f64 / per) * inv).exp() as f32)
            .collect();
        for p in points
            .iter()
            .filter(|p| p[0].is_finite() && p[1].is_finite())
        {
            let cx = ((p[0] - origin[0]) / resolution).floor() as i64;
            let cy = ((p[1] - origin[1]) / resolution).floor() as i64;
            for iy in (cy - r).max(0)..=(cy + r).min(ny as i64 - 1) {
                let y = origin[1] + (iy as f64 + 0.5) * resolution;
                for ix in (cx - r).max(0)..=(cx + r).min(nx as i64 - 1) {
                    let x = origin[0] + (ix as f64 + 0.5) * resolution;
                    let d2 = (x - p[0]).powi(2) + (y - p[1]).powi(2);
                    let v = table[((d2 * per) as usize).min(TABLE - 1)];
                    let cell = &mut fine[iy as usize * nx + ix as usize];
                    if v > *cell {
                        *cell = v;
                    }
                }
            }
        }
        let mut levels = vec![fine];
        for l in 1..=depth {
            let width = 1usize << l;
            let prev = &levels[l - 1];
            let half = width / 2;
            // Block max of width 2^l = max of two blocks of 2^(l-1), `half` apart, per axis.
            let mut row_max = vec![0f32; nx * ny];
            for iy in 0..ny {
                for ix in 0..nx {
                    let a = prev[iy * nx + ix];
                    let b = if ix + half < nx {
                        prev[iy * nx + ix + half]
                    } else {
                        0.0
                    };
                    row_max[iy * nx + ix] = a.max(b);
                }
            }
            // `prev` holds maxima over 2^(l-1) in both axes; combining shifted copies along x
            // then y gives 2^l in both.
            let mut out = vec![0f32; nx * ny];
            for iy in 0..ny {
                for ix in 0..nx {
                    let a = row_max[iy * nx + ix];
                    let b = if iy + half < ny {
                        row_max[(iy + half) * nx + ix]
                    } else {
                        0.0
                    };
                    out[iy * nx + ix] = a.max(b);
                }
            }
            levels.push(out);
        }
        Ok(Self {
            origin,
            resolution,
            nx,
            ny,
            levels,
        })
    }

    /// The grid's origin and size for these settings (None for no finite point), or why it
    /// would be too large: checked before anything is allocated.
    #[allow(clippy::type_complexity)]
    pub fn check_size(
        points: &[Point],
        resolution: f64,
        sigma: f64,
        depth: usize,
    ) -> Result<Option<(Point, usize, usize)>, GridTooLarge> {
        let reach = 3.0 * sigma;
        let (mut lo, mut hi) = ([f64::INFINITY; 2], [f64::NEG_INFINITY; 2]);
        for p in points
            .iter()
            .filter(|p| p[0].is_finite() && p[1].is_finite())
        {
            lo = [lo[0].min(p[0]), lo[1].min(p[1])];
            hi = [hi[0].max(p[0]), hi[1].max(p[1])];
        }
        if lo[0] > hi[0] || lo[0].is_nan() {
            return Ok(None);
        }
        // Padding of 2^depth cells: a coarse block that starts left of (or below) the grid then
        // covers only empty cells, so reading 0 there is exact.
        let pad = reach + resolution * (1.0 + 2f64.powi(depth.min(62) as i32));
        let origin = [lo[0] - pad, lo[1] - pad];
        // Sized in floating point first: an extent too large for usize (or inf - inf = NaN)
        // must fail the check, not wrap or saturate into an allocation.
        let (width, height) = (hi[0] - lo[0], hi[1] - lo[1]);
        let fx = ((width + 2.0 * pad) / resolution).ceil() + 1.0;
        let fy = ((height + 2.0 * pad) / resolution).ceil() + 1.0;
        if (fx * fy).is_nan() || fx * fy > MAX_CELLS as f64 {
            return Err(GridTooLarge {
                width,
                height,
                resolution,
                cells: fx * fy,
            });
        }
        Ok(Some((origin, fx as usize, fy as usize)))
    }

    pub fn resolution(&self) -> f64 {
        self.resolution
    }

    pub fn depth(&self) -> usize {
        self.levels.len() - 1
    }

    /// The cell of `p` (may lie outside the grid).
    #[inline]
    pub fn cell(&self, p: Point) -> (i64, i64) {
        (
            ((p[0] - self.origin[0]) / self.resolution).floor() as i64,
            ((p[1] - self.origin[1]) / self.resolution).floor() as i64,
        )
    }

    /// The value of cell `(ix, iy)` at `level` (0 outside).
    #[inline]
    pub fn at(&self, level: usize, ix: i64, iy: i64) -> f32 {
        if ix < 0 || iy < 0 || ix >= self.nx as i64 || iy >= self.ny as i64 {
            return 0.0;
        }
        self.levels[level][iy as usize * self.nx + ix as usize]
    }

    /// The fine field at the world point `p` (0 outside).
    pub fn value(&self, p: Point) -> f32 {
        let (ix, iy) = self.cell(p);
        self.at(0, ix, iy)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn coarse_levels_bound_every_fine_cell_of_their_block() {
        let pts: Vec<Point> = (0..200)
            .map(|k| {
                let t = k as f64 * 0.05;
                [t.cos() * 3.0 + 0.1 * t, t.sin() * 2.0]
            })
            .collect();
        let g = LikelihoodGrid::new(&pts, 0.05, 0.05, 4).unwrap();
        for l in 1..=4 {
            let w = 1i64 << l;
            for iy in (-3..g.ny as i64).step_by(7) {
                for ix in (-3..g.nx as i64).step_by(5) {
                    let mut m = 0f32;
                    for dy in 0..w {
                        for dx in 0..w {
                            m = m.max(g.at(0, ix + dx, iy + dy));
                        }
                    }
                    assert_eq!(g.at(l, ix, iy), m, "level {l} at {ix},{iy}");
                }
            }
        }
        // On a point the field is near 1.
        assert!(g.value(pts[10]) > 0.6);
        assert_eq!(g.value([100.0, 100.0]), 0.0);
    }

    #[test]
    fn a_grid_over_far_apart_points_is_refused_before_allocating() {
        for far in [1e6, 1e9, 1e300, f64::MAX] {
            let err = LikelihoodGrid::new(&[[0.0, 0.0], [far, 1.0]], 0.05, 0.05, 5).unwrap_err();
            assert!(
                err.cells > MAX_CELLS as f64 || err.cells.is_nan(),
                "{far}: {err}"
            );
            assert!(err.to_string().contains("limit"), "{err}");
        }
        assert!(LikelihoodGrid::new(&[[0.0, 0.0]], 0.0, 0.05, 3).is_err());
        assert!(LikelihoodGrid::new(&[[0.0, 0.0], [100.0, 100.0]], 0.05, 0.05, 5).is_ok());
    }
}
