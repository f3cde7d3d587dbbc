//! Fleet tools: evaluation, reports and (later) the launcher and Monte-Carlo runner.
#![warn(missing_docs)]
