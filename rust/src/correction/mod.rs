//! Closing the loop a person pointed at, before the joint solve (docs/ALGORITHM.md §4.1, §4.2):
//! a rigid move of everything observed after the corrected feature (`explicit`), then the gap it
//! opens spread over the chain in between (`backprop`, COP-SLAM style).

mod backprop;
pub mod engine;
mod explicit;

pub use backprop::backpropagate;
pub use engine::{CorrectionEngine, CorrectionSpec, HumanWeights, PoseObservations};
pub use explicit::{explicit_transform, Segment2};
