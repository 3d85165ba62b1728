//! Closing the loop a person pointed at, before the joint solve (docs/ALGORITHM.md §4.1, §4.2):
//! a rigid move of everything observed after the corrected feature (`explicit`), then the gap it
//! opens spread over the chain in between (`backprop`, COP-SLAM style). The engine holds the
//! map's factors and solves; `interpretation` finds what a drawing means on the map's `scans`;
//! `apply` is one correction end to end, guards included, in one call.

mod apply;
mod backprop;
pub mod engine;
mod explicit;
mod interpretation;
mod scans;

pub use apply::{
    chi2_limit, Active, Applied, ApplyParams, Chain, ConsistencyMetric,
    COLOCATION_CONSISTENCY_MARGIN,
};
pub use backprop::backpropagate;
pub use engine::{CorrectionEngine, CorrectionSpec, HumanWeights, PoseObservations};
pub use explicit::{explicit_transform, Segment2};
pub use interpretation::{interpret, span, Drawing, InterpretParams, Interpretation};
pub use scans::{Row, Scans};
