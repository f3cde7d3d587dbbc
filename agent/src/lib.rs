//! The agent library: one robot's estimator and, later, its peers, histories and
//! transport.
//!
//! * [`estimator`]: the filter, free of I/O: a state machine driven by IMU samples
//!   and camera feature frames.
//! * [`runner`]: one robot of a simulated scenario through its estimator.
//! * [`transport`]: publish/subscribe between agents (Zenoh, iceoryx2, in-process).
#![warn(missing_docs)]

pub mod estimator;
pub mod runner;
pub mod transport;
