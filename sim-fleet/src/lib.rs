//! Fleet tools: simulation to files, evaluation, reports, the Monte-Carlo runner
//! and the fleet launcher (`fleet_run`).
#![warn(missing_docs)]

pub mod anees;
pub mod compare;
pub mod convert;
pub mod eval;
pub mod export;
pub mod fleet_run;
pub mod live_run;
pub mod montecarlo;
pub mod paired;
pub mod plots;
pub mod simulate;
