//! The agent library: one robot's estimator and, later, its peers, histories and
//! transport.
//!
//! * [`estimator`]: the filter, free of I/O: a state machine driven by IMU samples
//!   and camera feature frames.
//! * [`frontend`]: camera images to feature frames (KLT + ORB; feature `vision`).
//! * [`dataset`]: real sequences in the EuRoC ASL layout (images, IMU, ground truth).
//! * [`runner`]: one robot of a simulated scenario through its estimator.
//! * [`transport`]: publish/subscribe between agents (Zenoh, iceoryx2, in-process).
#![warn(missing_docs)]

pub mod agent_log;
pub mod agent_log_views;
pub mod agent_output;
pub mod central;
pub mod config;
pub mod cooperation;
pub mod dataset;
#[cfg(feature = "vision")]
pub mod dataset_cli;
#[cfg(feature = "vision")]
pub mod dataset_run;
pub mod estimator;
pub mod fleet_clock;
pub mod frontend;
pub mod history_catchup;
pub mod history_retention;
pub mod history_store;
pub mod hybrid;
#[cfg(feature = "vision")]
pub mod image_runner;
pub mod inbox;
#[cfg(feature = "vision")]
pub mod live_cli;
pub mod node;
pub mod node_images;
pub mod outbox;
pub mod peer_events;
pub mod peer_history;
pub mod rendered_run;
pub mod ros_input;
pub mod run_files;
pub mod runner;
pub mod status_log;
pub mod transport;
