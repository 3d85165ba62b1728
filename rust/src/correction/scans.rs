//! A map's scans as the correction engine reads them: robot-frame points pose by pose
//! (`offsets[i]..offsets[i + 1]` are pose i's), held once per map with the bounding circles of
//! their blocks, so that a drawing reads only the scans that can reach it.

use crate::error::{input, Result};
use crate::interpret::{Points, ScanBlocks, Segment, WorldPoints};
use crate::se2::Pose2;

/// One observation: `(pose, index of the point within that pose's scan)`.
pub type Row = [i64; 2];

#[derive(Clone, Debug)]
pub struct Scans {
    points: Vec<f64>,
    offsets: Vec<i64>,
    blocks: ScanBlocks,
}

impl Scans {
    /// `points` `(P, 2)` flat, robot frame; `offsets` `(N + 1,)` rising from 0 to P.
    pub fn new(points: Vec<f64>, offsets: Vec<i64>) -> Result<Self> {
        let blocks = ScanBlocks::new(Points::new(&points)?, &offsets)?;
        Ok(Self {
            points,
            offsets,
            blocks,
        })
    }

    /// Robot-frame points `(P, 2)`, flat.
    pub fn points(&self) -> &[f64] {
        &self.points
    }

    /// `(N + 1,)`: pose i's points are rows `offsets[i]..offsets[i + 1]`.
    pub fn offsets(&self) -> &[i64] {
        &self.offsets
    }

    pub fn num_poses(&self) -> usize {
        self.offsets.len() - 1
    }

    pub fn num_points(&self) -> usize {
        self.points.len() / 2
    }

    /// The pose owning map row `k` (scans may be empty).
    pub fn owner(&self, k: usize) -> usize {
        self.offsets.partition_point(|&o| o <= k as i64) - 1
    }

    /// The map row of observation `row`, checked.
    pub fn map_row(&self, row: Row) -> Result<usize> {
        let [i, k] = row;
        let n = self.num_poses() as i64;
        if !(0..n).contains(&i) {
            return input(format!(
                "pose {i} of an observation is out of range (0..{n})"
            ));
        }
        let (first, end) = (self.offsets[i as usize], self.offsets[i as usize + 1]);
        if !(0..end - first).contains(&k) {
            return input(format!(
                "point {k} of pose {i} does not exist (its scan has {} points)",
                end - first
            ));
        }
        Ok((first + k) as usize)
    }

    /// `(pose, index within its scan)` of map row `k`.
    pub fn row_of(&self, k: usize) -> Row {
        let i = self.owner(k);
        [i as i64, k as i64 - self.offsets[i]]
    }

    /// Robot-frame point of map row `k`.
    #[inline]
    pub fn point(&self, k: usize) -> [f64; 2] {
        [self.points[2 * k], self.points[2 * k + 1]]
    }

    /// World points of `rows` at `poses`.
    pub fn world(&self, poses: &[Pose2], rows: &[Row]) -> Result<Vec<[f64; 2]>> {
        rows.iter()
            .map(|&r| {
                let k = self.map_row(r)?;
                Ok(poses[r[0] as usize].transform_point(self.point(k)))
            })
            .collect()
    }

    /// Observations grouped by pose (ascending pose, the rows' order within a pose), as the
    /// joint solve takes them.
    pub fn grouped(&self, rows: &[Row]) -> Result<Vec<(usize, Vec<[f64; 2]>)>> {
        let mut sorted: Vec<(usize, usize)> = rows
            .iter()
            .map(|&r| Ok((r[0] as usize, self.map_row(r)?)))
            .collect::<Result<_>>()?;
        sorted.sort_by_key(|r| r.0);
        let mut out: Vec<(usize, Vec<[f64; 2]>)> = Vec::new();
        for (i, k) in sorted {
            let p = self.point(k);
            match out.last_mut() {
                Some((j, v)) if *j == i => v.push(p),
                _ => out.push((i, vec![p])),
            }
        }
        Ok(out)
    }

    /// World points of every scan block that can lie within `band` of a segment, with their
    /// map rows (ascending). `poses` `(N, 3)` flat and finite.
    pub fn near(
        &self,
        poses: &[f64],
        segments: &[Segment],
        band: f64,
    ) -> Result<(WorldPoints, Vec<usize>)> {
        if poses.len() != 3 * self.num_poses() {
            return input(format!(
                "expected {} poses, got {}",
                self.num_poses(),
                poses.len() / 3
            ));
        }
        Ok(self
            .blocks
            .world_points_near(poses, Points::new(&self.points)?, segments, band))
    }
}
