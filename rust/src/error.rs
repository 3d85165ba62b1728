//! The crate's one error type. Every fallible public function returns it; the Python layer maps
//! each variant once to the package's exception classes (`python/mod.rs`).

use thiserror::Error;

/// What went wrong, with a message that says what to do about it.
#[derive(Debug, Error, Clone, PartialEq)]
pub enum HitlError {
    /// The caller's data cannot be used as given (shapes, ids, NaN, indefinite information, gauge).
    #[error("{0}")]
    Input(String),
    /// The optimizer could not produce a solution.
    #[error("{0}")]
    Solver(String),
    /// A drawing that cannot be turned into a correction; the message says what to draw instead.
    #[error("{0}")]
    Rejected(String),
}

pub type Result<T> = std::result::Result<T, HitlError>;

pub(crate) fn input<T>(msg: impl Into<String>) -> Result<T> {
    Err(HitlError::Input(msg.into()))
}
