//! The scan-matching front end. So far: scan-to-scan matching ([`icp`]), used to check each
//! odometry step against the two scans it joins (the evidence that puts a correction's error at
//! a heading fault instead of spreading it over a lap).

pub mod consistency;
pub mod correlative;
pub mod icp;
pub mod likelihood;
pub mod slam;

pub use icp::{match_chain, match_scans, IcpParams, ScanMatch};
