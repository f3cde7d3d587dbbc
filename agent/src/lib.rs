//! The agent library: one robot's estimator and, later, its peers, histories and transport.
//!
//! The estimator lives in [`estimator`] and is free of I/O: a state machine driven by
//! IMU samples and camera feature frames.
#![warn(missing_docs)]

pub mod estimator;
