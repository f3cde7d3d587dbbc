//! Fleet tools: simulation to files, evaluation, reports, the Monte-Carlo runner
//! and (later) the launcher.
#![warn(missing_docs)]

pub mod eval;
pub mod montecarlo;
pub mod plots;
pub mod simulate;
