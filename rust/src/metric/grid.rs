//! The metric's fixed grid: square cells of side `resolution` from a world `origin` (the lower-left
//! corner of cell (0, 0)), cell `(ix, iy)` stored at `iy * width + ix`, and the exact traversal
//! of the cells a segment crosses (Amanatides and Woo), so no cell is skipped or sampled twice.

use crate::error::{HitlError, Result};

/// The largest grid accepted: 1e8 cells is already 1.6 GB of counters (per worker thread).
pub const MAX_CELLS: usize = 100_000_000;

/// Empty cells kept round the data by [`Grid::covering`], so that nothing lies on its border.
pub const GRID_MARGIN_CELLS: i64 = 2;

/// A fixed square grid in the world frame.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Grid {
    /// World `(x, y)` of the lower-left corner of cell (0, 0).
    pub origin: [f64; 2],
    /// Cell side [m].
    pub resolution: f64,
    /// Cells along x.
    pub width: usize,
    /// Cells along y.
    pub height: usize,
}

fn too_large(width: f64, height: f64, resolution: f64) -> HitlError {
    HitlError::Input(format!(
        "a grid of {width} x {height} cells at {resolution} m is too large (more than {MAX_CELLS} \
         cells); use a coarser resolution, or remove the far outliers from the map"
    ))
}

impl Grid {
    /// A grid as given; fails on a non-finite origin, a resolution that is not a positive
    /// number, an empty grid or one over [`MAX_CELLS`] cells.
    pub fn new(origin: [f64; 2], resolution: f64, width: usize, height: usize) -> Result<Self> {
        if !(resolution.is_finite() && resolution > 0.0) {
            return Err(HitlError::Input(format!(
                "resolution must be a positive number of metres, got {resolution}"
            )));
        }
        if !(origin[0].is_finite() && origin[1].is_finite()) {
            return Err(HitlError::Input(format!(
                "grid origin must be finite, got ({}, {})",
                origin[0], origin[1]
            )));
        }
        if width == 0 || height == 0 {
            return Err(HitlError::Input(format!(
                "grid shape must be at least 1 x 1 cells, got {width} x {height}"
            )));
        }
        if width.checked_mul(height).is_none_or(|n| n > MAX_CELLS) {
            return Err(too_large(width as f64, height as f64, resolution));
        }
        Ok(Self {
            origin,
            resolution,
            width,
            height,
        })
    }

    /// The grid covering the box `[min, max]` with [`GRID_MARGIN_CELLS`] to spare on every side;
    /// its origin is a whole multiple of the resolution, so that walls at round coordinates lie
    /// on cell boundaries whatever the data's extent.
    pub fn covering(min: [f64; 2], max: [f64; 2], resolution: f64) -> Result<Self> {
        if !(resolution.is_finite() && resolution > 0.0) {
            return Err(HitlError::Input(format!(
                "resolution must be a positive number of metres, got {resolution}"
            )));
        }
        if !(min.iter().chain(&max).all(|v| v.is_finite()) && min[0] <= max[0] && min[1] <= max[1])
        {
            return Err(HitlError::Input(
                "the map's extent is empty or not finite; give finite poses and points".into(),
            ));
        }
        let margin = GRID_MARGIN_CELLS as f64;
        let low = [
            (min[0] / resolution).floor() - margin,
            (min[1] / resolution).floor() - margin,
        ];
        let high = [
            (max[0] / resolution).floor() + margin,
            (max[1] / resolution).floor() + margin,
        ];
        let (w, h) = (high[0] - low[0] + 1.0, high[1] - low[1] + 1.0);
        // Checked in floating point first: the cell counts of a wild extent overflow integers.
        if w * h > MAX_CELLS as f64 {
            return Err(too_large(w, h, resolution));
        }
        Self::new(
            [low[0] * resolution, low[1] * resolution],
            resolution,
            w as usize,
            h as usize,
        )
    }

    /// Number of cells.
    pub fn cells(&self) -> usize {
        self.width * self.height
    }

    /// Grid coordinates of a world point: cell `(ix, iy)` is `[ix, ix + 1) x [iy, iy + 1)`.
    #[inline]
    pub fn to_grid(&self, p: [f64; 2]) -> [f64; 2] {
        [
            (p[0] - self.origin[0]) / self.resolution,
            (p[1] - self.origin[1]) / self.resolution,
        ]
    }

    /// Index of the cell holding world point `p`, or None outside the grid.
    #[inline]
    pub fn cell_of(&self, p: [f64; 2]) -> Option<usize> {
        let [gx, gy] = self.to_grid(p);
        // The comparisons also reject NaN.
        if gx >= 0.0 && gy >= 0.0 && gx < self.width as f64 && gy < self.height as f64 {
            let (ix, iy) = (
                (gx as usize).min(self.width - 1),
                (gy as usize).min(self.height - 1),
            );
            Some(iy * self.width + ix)
        } else {
            None
        }
    }

    /// Calls `visit` with the index of every cell the segment `a -> b` (world frame) crosses,
    /// each once, in order from `a`: the cell holding `a`, then each cell entered through a
    /// boundary up to the cell holding `b`; through an exact corner the traversal steps
    /// diagonally (the two side cells are only touched at a point). The part of the segment
    /// outside the grid is ignored.
    pub fn traverse(&self, a: [f64; 2], b: [f64; 2], mut visit: impl FnMut(usize)) {
        let (ga, gb) = (self.to_grid(a), self.to_grid(b));
        if !ga.iter().chain(&gb).all(|v| v.is_finite()) {
            return;
        }
        let (w, h) = (self.width as f64, self.height as f64);
        let d = [gb[0] - ga[0], gb[1] - ga[1]];
        // Liang-Barsky clipping to [0, w] x [0, h]; a segment inside is used bit for bit.
        let (mut t0, mut t1) = (0.0_f64, 1.0_f64);
        for (p, q) in [
            (-d[0], ga[0]),
            (d[0], w - ga[0]),
            (-d[1], ga[1]),
            (d[1], h - ga[1]),
        ] {
            if p == 0.0 {
                if q < 0.0 {
                    return;
                }
            } else {
                let r = q / p;
                if p < 0.0 {
                    t0 = t0.max(r);
                } else {
                    t1 = t1.min(r);
                }
            }
        }
        if t0 > t1 {
            return; // outside the grid
        }
        let (pa, pb) = if t0 == 0.0 && t1 == 1.0 {
            (ga, gb)
        } else {
            (
                [ga[0] + t0 * d[0], ga[1] + t0 * d[1]],
                [ga[0] + t1 * d[0], ga[1] + t1 * d[1]],
            )
        };
        let clamp = |v: f64, n: usize| (v.max(0.0) as usize).min(n - 1) as i64;
        let (mut ix, mut iy) = (clamp(pa[0], self.width), clamp(pa[1], self.height));
        let (ex, ey) = (clamp(pb[0], self.width), clamp(pb[1], self.height));
        let (dx, dy) = (pb[0] - pa[0], pb[1] - pa[1]);
        let (sx, sy) = ((ex - ix).signum(), (ey - iy).signum());
        // Parameter of the next x (y) boundary and the parameter step between boundaries.
        let (mut tx, tdx) = match sx {
            1 => ((ix as f64 + 1.0 - pa[0]) / dx, 1.0 / dx),
            -1 => ((pa[0] - ix as f64) / -dx, 1.0 / -dx),
            _ => (f64::INFINITY, f64::INFINITY),
        };
        let (mut ty, tdy) = match sy {
            1 => ((iy as f64 + 1.0 - pa[1]) / dy, 1.0 / dy),
            -1 => ((pa[1] - iy as f64) / -dy, 1.0 / -dy),
            _ => (f64::INFINITY, f64::INFINITY),
        };
        let width = self.width as i64;
        visit((iy * width + ix) as usize);
        // Stepping by the end cell instead of by the parameter reaching 1 makes the walk end in
        // the cell holding b whatever the rounding, and never leave the box from a to b.
        while ix != ex || iy != ey {
            if ix != ex && iy != ey && tx == ty {
                ix += sx;
                iy += sy;
                tx += tdx;
                ty += tdy;
            } else if iy == ey || (ix != ex && tx < ty) {
                ix += sx;
                tx += tdx;
            } else {
                iy += sy;
                ty += tdy;
            }
            visit((iy * width + ix) as usize);
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn unit_grid(w: usize, h: usize) -> Grid {
        Grid::new([0.0, 0.0], 1.0, w, h).unwrap()
    }

    fn cells(g: &Grid, a: [f64; 2], b: [f64; 2]) -> Vec<(usize, usize)> {
        let mut out = Vec::new();
        g.traverse(a, b, |c| out.push((c % g.width, c / g.width)));
        out
    }

    /// Cells whose interior meets the segment, found by fine sampling (a reference for
    /// segments that pass through no corner).
    fn sampled(g: &Grid, a: [f64; 2], b: [f64; 2]) -> Vec<(usize, usize)> {
        let mut out: Vec<(usize, usize)> = Vec::new();
        let n = 200_000;
        for k in 0..=n {
            let t = k as f64 / n as f64;
            let p = [a[0] + t * (b[0] - a[0]), a[1] + t * (b[1] - a[1])];
            if let Some(c) = g.cell_of(p) {
                let cell = (c % g.width, c / g.width);
                if out.last() != Some(&cell) {
                    out.push(cell);
                }
            }
        }
        out
    }

    #[test]
    fn axis_aligned_and_single_cell() {
        let g = unit_grid(10, 10);
        assert_eq!(
            cells(&g, [0.5, 0.5], [3.5, 0.5]),
            vec![(0, 0), (1, 0), (2, 0), (3, 0)]
        );
        assert_eq!(
            cells(&g, [2.5, 3.5], [2.5, 1.2]),
            vec![(2, 3), (2, 2), (2, 1)]
        );
        assert_eq!(cells(&g, [4.2, 4.3], [4.7, 4.9]), vec![(4, 4)]);
    }

    #[test]
    fn matches_dense_sampling_in_every_direction() {
        let g = unit_grid(20, 20);
        let a = [10.37, 9.61];
        for k in 0..72 {
            let angle = (k as f64 + 0.123) * std::f64::consts::PI / 36.0;
            let b = [a[0] + 8.3 * angle.cos(), a[1] + 8.3 * angle.sin()];
            assert_eq!(cells(&g, a, b), sampled(&g, a, b), "direction {k}");
        }
    }

    #[test]
    fn exact_corner_steps_diagonally() {
        let g = unit_grid(5, 5);
        assert_eq!(
            cells(&g, [0.5, 0.5], [2.5, 2.5]),
            vec![(0, 0), (1, 1), (2, 2)]
        );
        assert_eq!(
            cells(&g, [2.5, 2.5], [0.5, 0.5]),
            vec![(2, 2), (1, 1), (0, 0)]
        );
    }

    #[test]
    fn clipped_to_the_grid() {
        let g = unit_grid(4, 3);
        assert_eq!(
            cells(&g, [-2.0, 1.5], [2.5, 1.5]),
            vec![(0, 1), (1, 1), (2, 1)]
        );
        assert_eq!(cells(&g, [3.5, 0.5], [9.0, 0.5]), vec![(3, 0)]);
        assert!(cells(&g, [-3.0, -1.0], [9.0, -1.0]).is_empty());
        assert!(cells(&g, [f64::NAN, 0.5], [1.0, 0.5]).is_empty());
        let a = [-1.0, 0.25];
        let b = [10.0, 2.9];
        assert_eq!(cells(&g, a, b), sampled(&g, a, b));
    }

    #[test]
    fn covering_is_aligned_and_capped() {
        let g = Grid::covering([0.01, -1.0], [2.0, 1.0], 0.05).unwrap();
        assert_eq!(g.origin[0] / 0.05, -2.0);
        assert_eq!(g.origin[1] / 0.05, -22.0);
        assert_eq!((g.width, g.height), (40 + 5, 40 + 5));
        assert!(g.cell_of([0.01, -1.0]).is_some() && g.cell_of([2.0, 1.0]).is_some());
        let big = Grid::covering([0.0, 0.0], [1e6, 1e6], 0.05).unwrap_err();
        assert!(big.to_string().contains("too large"), "{big}");
        assert!(Grid::covering([0.0, 0.0], [f64::NAN, 1.0], 0.05).is_err());
        assert!(Grid::new([0.0, 0.0], 0.0, 3, 3).is_err());
        assert!(Grid::new([0.0, 0.0], 1.0, usize::MAX, 3).is_err());
    }
}
