//! Sparse nonlinear least squares: the normal-equation pattern with its cached symbolic
//! Cholesky analysis (`pattern`), the low-rank term of wide factors solved by Woodbury
//! (`woodbury`), Gauss-Newton / Levenberg-Marquardt (`levenberg_marquardt`), the report, and
//! marginal covariances.

mod levenberg_marquardt;
mod marginals;
mod pattern;
mod report;
mod woodbury;

pub use levenberg_marquardt::{optimize, Method, SolverParams};
pub use marginals::marginal_covariances;
pub use pattern::SparsityPattern;
pub use report::{IterationRecord, SolveReport, Termination};
