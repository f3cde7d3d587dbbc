//! Shared vocabulary of the multi-robot VIO system.
//!
//! * [`conventions`]: frames, rotation directions, error-state definition and
//!   file quaternion orders, stated once for the whole workspace.
//! * [`so3`]: SO(3)/SE(3) math (`exp`, `log`, right Jacobians, skew).
//! * [`camera`]: pinhole + radtan / equidistant models with Jacobians.
//! * [`base64`]: bytes in JSON messages.
//! * [`calibration`]: a camera's intrinsics, camera-IMU extrinsics and time offset.
//! * [`descriptor`]: 256-bit binary descriptors.
//! * [`epipolar`]: fundamental matrix (eight-point, Sampson error, RANSAC).
//! * [`exit_report`]: how the binaries print the error that ends them.
//! * [`image`]: 8-bit grayscale images and their PNG encoding.
//! * [`loopback_ports`]: free loopback ports for Zenoh peers started together.
//! * [`estimator_options`]: the estimator's options and their defaults.
//! * [`measurement`]: IMU samples and camera feature frames.
//! * [`trajectory`]: TUM / EuRoC ground-truth readers and a TUM writer.
//! * [`messages`]: what agents send each other, and its wire format.
//! * [`metrics`]: ATE, RPE and NEES.
//! * [`summary`]: the `summary.json` schema shared by the agent and the fleet tools.
#![warn(missing_docs)]

pub mod base64;
pub mod calibration;
pub mod camera;
pub mod conventions;
pub mod descriptor;
pub mod epipolar;
pub mod estimator_options;
pub mod exit_report;
pub mod image;
pub mod loopback_ports;
pub mod measurement;
pub mod messages;
pub mod metrics;
pub mod ros_cdr;
pub mod so3;
pub mod summary;
pub mod trajectory;
