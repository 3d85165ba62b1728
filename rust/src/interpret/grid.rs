//! A uniform grid over the world points, built once per call in O(P) by a counting sort, and the
//! query "every point within distance `band` of a segment", which visits only the cells that the
//! segment's band can reach (row by row), then keeps the points whose true distance is in band.

use super::{Bounds, Point, Points, Segment, SegmentFrame};
use crate::error::{HitlError, Result};

/// Cells per point at most; a map spread over a huge area gets larger cells instead of an
/// allocation proportional to its area.
const MAX_CELLS_PER_POINT: f64 = 2.0;
const MIN_MAX_CELLS: f64 = 1024.0;

/// Points bucketed into square cells; cell `(ix, iy)` covers
/// `[min_x + ix c, min_x + (ix + 1) c) x [min_y + iy c, ...)`.
#[derive(Clone, Debug)]
pub struct GridIndex {
    min: Point,
    cell: f64,
    inv_cell: f64,
    nx: usize,
    ny: usize,
    /// `items[start[c]..start[c + 1]]` are the point indices in cell `c = iy * nx + ix`.
    start: Vec<u32>,
    items: Vec<u32>,
}

impl GridIndex {
    /// Buckets `points` into cells of side about `cell` metres (the candidate band is a good
    /// choice: a query then touches a few cells across the segment).
    pub fn build(points: Points<'_>, cell: f64) -> Result<Self> {
        Self::build_in(points, cell, Bounds::of(points)?)
    }

    /// `build` with the points' bounds already known (e.g. from [`super::world_points`]).
    /// Wrong bounds cost speed, never results: points outside are clamped into the border
    /// cells, and queries clamp their ranges the same way.
    pub fn build_in(points: Points<'_>, cell: f64, bounds: Bounds) -> Result<Self> {
        if !(cell.is_finite() && cell > 0.0) {
            return Err(HitlError::Input(format!(
                "grid cell size must be a positive number of metres, got {cell}"
            )));
        }
        if points.len() >= u32::MAX as usize {
            return Err(HitlError::Input(format!(
                "{} points are more than the index holds (2^32 - 1); split the map",
                points.len()
            )));
        }
        let (mut min, mut max) = (bounds.min, bounds.max);
        if points.is_empty() || !(min[0] <= max[0] && min[1] <= max[1]) {
            min = [0.0; 2];
            max = [0.0; 2];
        }
        let max_cells = (MAX_CELLS_PER_POINT * points.len() as f64).max(MIN_MAX_CELLS);
        let mut cell = cell;
        let (mut fx, mut fy) = (0.0, 0.0);
        for _ in 0..64 {
            fx = ((max[0] - min[0]) / cell).floor() + 1.0;
            fy = ((max[1] - min[1]) / cell).floor() + 1.0;
            if fx * fy <= max_cells {
                break;
            }
            cell *= (fx * fy / max_cells).sqrt().max(1.01);
        }
        // Written so that NaN (an extent too large to subtract) also fails.
        let fits = fx * fy <= max_cells;
        if !fits {
            return Err(HitlError::Input(format!(
                "cannot index points spanning [{:?}, {:?}]; check their units",
                min, max
            )));
        }
        let (nx, ny) = (fx as usize, fy as usize);
        let mut grid = Self {
            min,
            cell,
            inv_cell: 1.0 / cell,
            nx,
            ny,
            start: vec![0; nx * ny + 1],
            items: vec![0; points.len()],
        };
        // Counting sort: count per cell, prefix sums, then place. The cell of each point is
        // kept from the counting pass so its arithmetic runs once per point.
        let mut cells = Vec::with_capacity(points.len());
        for p in points.iter() {
            let c = grid.cell_of(p);
            cells.push(c as u32);
            if let Some(s) = grid.start.get_mut(c + 1) {
                *s += 1;
            }
        }
        let mut total = 0;
        for s in grid.start.iter_mut() {
            total += *s;
            *s = total;
        }
        let mut cursor = grid.start.clone();
        for (i, &c) in cells.iter().enumerate() {
            if let Some(slot) = cursor.get_mut(c as usize) {
                if let Some(item) = grid.items.get_mut(*slot as usize) {
                    *item = i as u32;
                }
                *slot += 1;
            }
        }
        Ok(grid)
    }

    /// The side of a cell (metres); larger than asked when the map is spread out.
    pub fn cell_size(&self) -> f64 {
        self.cell
    }

    /// Number of cells.
    pub fn num_cells(&self) -> usize {
        self.nx * self.ny
    }

    /// The cell coordinate of `v` (metres from the grid's corner), clamped into `0..n`.
    #[inline]
    fn clamp_ix(&self, v: f64, n: usize) -> usize {
        // `as usize` truncates towards zero and saturates: negative and NaN go to 0, huge
        // values to usize::MAX; for v >= 0 truncation is the floor.
        ((v * self.inv_cell) as usize).min(n - 1)
    }

    #[inline]
    fn cell_of(&self, p: Point) -> usize {
        let ix = self.clamp_ix(p[0] - self.min[0], self.nx);
        let iy = self.clamp_ix(p[1] - self.min[1], self.ny);
        iy * self.nx + ix
    }

    /// Indices (ascending) of the points within distance `band` of the segment, ends included:
    /// `dist(p, segment) <= band`. `points` must be the array the grid was built on.
    pub fn query(&self, points: Points<'_>, seg: &Segment, band: f64) -> Result<Vec<usize>> {
        check_band(band)?;
        let frame = SegmentFrame::new(seg)?;
        let mut out = Vec::new();
        self.query_frame(points, &frame, band, &mut out);
        Ok(out)
    }

    pub(crate) fn query_frame(
        &self,
        points: Points<'_>,
        frame: &SegmentFrame,
        band: f64,
        out: &mut Vec<usize>,
    ) {
        out.clear();
        if points.is_empty() {
            return;
        }
        let [a, b] = frame.endpoints();
        let band_sq = band * band;
        // Rounding in the cell arithmetic is covered by padding every range by a small fraction
        // of a cell and one whole cell of columns; the exact distance test decides membership.
        let pad = 0.01 * self.cell;
        let y_lo = a[1].min(b[1]) - band - pad;
        let y_hi = a[1].max(b[1]) + band + pad;
        let row_lo = self.clamp_ix(y_lo - self.min[1], self.ny);
        let row_hi = self.clamp_ix(y_hi - self.min[1], self.ny);
        let dy = b[1] - a[1];
        for iy in row_lo..=row_hi {
            // The part of the segment whose y is within band of this row of cells.
            let slab_lo = self.min[1] + iy as f64 * self.cell - band - pad;
            let slab_hi = self.min[1] + (iy + 1) as f64 * self.cell + band + pad;
            let (t0, t1) = if dy == 0.0 {
                if a[1] < slab_lo || a[1] > slab_hi {
                    continue;
                }
                (0.0, 1.0)
            } else {
                let (s0, s1) = ((slab_lo - a[1]) / dy, (slab_hi - a[1]) / dy);
                (s0.min(s1).max(0.0), s0.max(s1).min(1.0))
            };
            if t0 > t1 {
                continue;
            }
            let xa = a[0] + t0 * (b[0] - a[0]);
            let xb = a[0] + t1 * (b[0] - a[0]);
            let x_lo = xa.min(xb) - band - pad;
            let x_hi = xa.max(xb) + band + pad;
            let col_lo = self.clamp_ix(x_lo - self.min[0], self.nx).saturating_sub(1);
            let col_hi = (self.clamp_ix(x_hi - self.min[0], self.nx) + 1).min(self.nx - 1);
            let row = iy * self.nx;
            let (Some(&s), Some(&e)) = (
                self.start.get(row + col_lo),
                self.start.get(row + col_hi + 1),
            ) else {
                continue;
            };
            // Cells of one row are contiguous in `items`, so the row's span is one slice.
            for &i in self.items.get(s as usize..e as usize).unwrap_or(&[]) {
                let i = i as usize;
                if let Some(p) = points.get(i) {
                    if frame.distance_sq(p) <= band_sq {
                        out.push(i);
                    }
                }
            }
        }
        out.sort_unstable();
    }
}

fn check_band(band: f64) -> Result<()> {
    if band.is_finite() && band > 0.0 {
        Ok(())
    } else {
        Err(HitlError::Input(format!(
            "the candidate band must be a positive number of metres, got {band}"
        )))
    }
}

/// Indices (ascending) of the points within `band` of the segment, through a grid built for
/// this one query (O(P) to build, then only the reachable cells are read).
pub fn candidates(points: Points<'_>, seg: &Segment, band: f64) -> Result<Vec<usize>> {
    check_band(band)?;
    GridIndex::build(points, band)?.query(points, seg, band)
}

/// The same set by testing every point: the reference the index is checked against.
pub fn candidates_brute_force(points: Points<'_>, seg: &Segment, band: f64) -> Result<Vec<usize>> {
    check_band(band)?;
    points.check_finite("world point")?;
    let frame = SegmentFrame::new(seg)?;
    let band_sq = band * band;
    Ok(points
        .iter()
        .enumerate()
        .filter(|(_, p)| frame.distance_sq(*p) <= band_sq)
        .map(|(i, _)| i)
        .collect())
}

#[cfg(test)]
mod tests {
    use super::*;
    use rand::{Rng, SeedableRng};

    fn random_points(rng: &mut impl Rng, n: usize, scale: f64) -> Vec<f64> {
        (0..2 * n)
            .map(|_| rng.random_range(-scale..scale))
            .collect()
    }

    #[test]
    fn index_matches_brute_force_on_random_queries() {
        let mut rng = rand::rngs::StdRng::seed_from_u64(7);
        for trial in 0..300 {
            let n = rng.random_range(0..400);
            let scale = [0.5, 5.0, 50.0][trial % 3];
            let flat = random_points(&mut rng, n, scale);
            let pts = Points::new(&flat).unwrap();
            let band = rng.random_range(0.01..scale);
            let cell = band * rng.random_range(0.3..3.0);
            let grid = GridIndex::build(pts, cell).unwrap();
            for _ in 0..5 {
                let mut e = [0.0; 4];
                for v in &mut e {
                    *v = rng.random_range(-1.5 * scale..1.5 * scale);
                }
                let seg = Segment::new([e[0], e[1]], [e[2], e[3]]);
                let got = grid.query(pts, &seg, band).unwrap();
                let want = candidates_brute_force(pts, &seg, band).unwrap();
                assert_eq!(got, want, "trial {trial}");
            }
        }
    }

    #[test]
    fn axis_aligned_segments_and_points_on_cell_edges() {
        // A lattice with spacing equal to the cell size puts every point on a cell boundary.
        let flat: Vec<f64> = (0..21)
            .flat_map(|i| (0..21).flat_map(move |j| [i as f64 * 0.5, j as f64 * 0.5]))
            .collect();
        let pts = Points::new(&flat).unwrap();
        let grid = GridIndex::build(pts, 0.5).unwrap();
        for seg in [
            Segment::new([1.0, 2.0], [8.0, 2.0]),
            Segment::new([3.0, 0.0], [3.0, 10.0]),
            Segment::new([0.0, 0.0], [10.0, 10.0]),
            Segment::new([-5.0, -5.0], [-1.0, -1.0]),
        ] {
            for band in [0.25, 0.5, 1.0, 1.7] {
                assert_eq!(
                    grid.query(pts, &seg, band).unwrap(),
                    candidates_brute_force(pts, &seg, band).unwrap()
                );
            }
        }
    }

    #[test]
    fn spread_out_maps_get_bigger_cells() {
        let flat = [0.0, 0.0, 1e7, 1e7, 5.0, 5.0];
        let pts = Points::new(&flat).unwrap();
        let grid = GridIndex::build(pts, 0.3).unwrap();
        assert!(grid.num_cells() as f64 <= MIN_MAX_CELLS);
        let seg = Segment::new([4.0, 5.0], [6.0, 5.0]);
        assert_eq!(grid.query(pts, &seg, 0.3).unwrap(), vec![2]);
    }

    #[test]
    fn bad_input_is_an_input_error() {
        let flat = [0.0, 0.0, f64::NAN, 1.0];
        let pts = Points::new(&flat).unwrap();
        assert!(matches!(
            GridIndex::build(pts, 0.3),
            Err(HitlError::Input(_))
        ));
        let ok = Points::new(&[0.0, 0.0]).unwrap();
        assert!(GridIndex::build(ok, 0.0).is_err());
        let seg = Segment::new([0.0, 0.0], [1.0, 0.0]);
        assert!(candidates(ok, &seg, -1.0).is_err());
        assert!(candidates(ok, &seg, f64::NAN).is_err());
        assert_eq!(candidates(ok, &seg, 0.1).unwrap(), vec![0]);
        let empty = Points::new(&[]).unwrap();
        assert!(candidates(empty, &seg, 0.1).unwrap().is_empty());
    }
}
