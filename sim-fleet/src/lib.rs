//! Fleet tools: simulation to files, evaluation, reports and (later) the launcher
//! and Monte-Carlo runner.
#![warn(missing_docs)]

pub mod eval;
pub mod plots;
pub mod simulate;
