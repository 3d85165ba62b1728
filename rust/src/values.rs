//! The optimization variables: poses and (for human corrections) lines, addressed by [`Key`].
//! The solver updates them through their charts (`retract`), never by plain addition.

use crate::se2::{wrap_angle, Pose2};

/// A variable: a pose (3 dof) or a line `(phi, rho)` (2 dof).
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, PartialOrd, Ord)]
pub enum Key {
    Pose(usize),
    Line(usize),
}

impl Key {
    /// Degrees of freedom of the variable.
    #[inline]
    pub fn dim(self) -> usize {
        match self {
            Key::Pose(_) => 3,
            Key::Line(_) => 2,
        }
    }
}

/// A line `{p : n . p = rho}` with unit normal `n = (cos phi, sin phi)`, phi in (-pi, pi].
#[derive(Clone, Copy, Debug, PartialEq, Default)]
pub struct Line2 {
    pub phi: f64,
    pub rho: f64,
}

/// Current estimate of every variable.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct Values {
    pub poses: Vec<Pose2>,
    pub lines: Vec<Line2>,
}

impl Values {
    pub fn from_poses(poses: Vec<Pose2>) -> Self {
        Self {
            poses,
            lines: Vec::new(),
        }
    }

    /// `x (+) delta` for one variable; `delta.len() == key.dim()`.
    #[inline]
    pub fn retract(&mut self, key: Key, delta: &[f64]) {
        match key {
            Key::Pose(i) => self.poses[i] = self.poses[i].retract([delta[0], delta[1], delta[2]]),
            Key::Line(i) => {
                let l = &mut self.lines[i];
                l.phi = wrap_angle(l.phi + delta[0]);
                l.rho += delta[1];
            }
        }
    }

    /// Whether `key` names an existing variable.
    pub fn contains(&self, key: Key) -> bool {
        match key {
            Key::Pose(i) => i < self.poses.len(),
            Key::Line(i) => i < self.lines.len(),
        }
    }
}
