//! Sparse nonlinear least squares: the normal-equation pattern with its cached symbolic
//! Cholesky analysis (`pattern`), the low-rank term of wide factors solved by Woodbury
//! (`woodbury`), robust kernels per factor class (`robust`), the algorithms (`gauss_newton`,
//! `levenberg_marquardt`, `dogleg`) over a shared problem with honest convergence tests
//! (`problem`), the entry point (`optimize`), the report, and marginal covariances.

mod dogleg;
mod gauss_newton;
mod levenberg_marquardt;
mod marginals;
mod optimize;
mod ordering;
mod params;
mod pattern;
mod problem;
mod report;
mod robust;
mod woodbury;

pub use marginals::marginal_covariances;
pub use optimize::optimize;
pub(crate) use ordering::block_amd;
pub use params::{Method, SolverParams};
pub use pattern::SparsityPattern;
pub use report::{IterationRecord, SolveReport, Termination};
pub use robust::{Kernel, RobustKernels};
