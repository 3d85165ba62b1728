//! The inconsistency metric of docs/ALGORITHM.md §6: the area that some scans of a map show as free
//! space while other scans show it occupied, in m^2, on a fixed grid. A well-registered map scores
//! near zero; every misregistered wall adds the area where other scans see through it.
//!
//! [`Grid`] is the fixed grid and its exact ray traversal, [`inconsistency`] the linear-time
//! counter form, and [`inconsistency_pairwise`] the direct definition it is checked against.

mod grid;
mod inconsistency;

pub use grid::{Grid, GRID_MARGIN_CELLS, MAX_CELLS};
pub use inconsistency::{
    inconsistency, inconsistency_pairwise, Inconsistency, MetricParams, Scans, MAX_PAIRWISE_SCANS,
};
