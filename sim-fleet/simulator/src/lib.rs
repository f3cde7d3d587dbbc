//! The fleet simulator: an SE(3) B-spline per robot fitted to its trajectory file,
//! one shared landmark world, and per-robot IMU and camera feature measurements.
//!
//! Everything random comes from seeded streams ([`rng`]): a robot's measurement
//! stream is a pure function of (scenario, robot index, seed).
//!
//! Start at [`fleet::Fleet::build`], then iterate [`fleet::Fleet::stream`].
#![warn(missing_docs)]

pub mod bspline;
pub mod camera_sim;
pub mod euroc_export;
pub mod fleet;
pub mod imu;
pub mod mcap_io;
pub mod perturb;
pub mod render;
pub mod rng;
pub mod scenario;
pub mod truth;
pub mod world;

pub use fleet::{Fleet, SimError, SimEvent};
pub use scenario::Scenario;

#[cfg(test)]
mod tests;
