//! Sparse nonlinear least squares: the normal-equation pattern with its ordering and cached
//! symbolic Cholesky analysis (`pattern`), the Hessian and gradient accumulated into it
//! (`assembly`), the numeric factorization with the damped and undamped solves
//! (`linear_solve`; the supernodal numeric Cholesky in `supernodal`, the factor's triangular
//! solves in `factor`), the low-rank term of wide factors solved by Woodbury (`woodbury`), the
//! system in natural variable order for cross-checks (`natural_system`), robust kernels per
//! factor class (`robust`), the algorithms (`gauss_newton`, `levenberg_marquardt`, `dogleg`)
//! over a shared problem with honest convergence tests (`problem`), the entry point
//! (`optimize`), the report, and marginal covariances.

mod assembly;
mod dogleg;
mod factor;
mod gauss_newton;
mod levenberg_marquardt;
mod linear_solve;
mod marginals;
mod natural_system;
mod optimize;
mod ordering;
mod params;
mod pattern;
mod problem;
mod report;
mod robust;
mod supernodal;
#[cfg(test)]
mod test_problems;
mod woodbury;

pub(crate) use linear_solve::sym_upper_mul_add;
pub use marginals::marginal_covariances;
pub use optimize::optimize;
pub(crate) use ordering::block_amd;
pub use params::{Method, SolverParams};
pub use pattern::SparsityPattern;
pub use report::{IterationRecord, SolveReport, Termination};
pub use robust::{Kernel, RobustKernels};
