//! The single-robot sliding-window estimator: an OpenVINS-class MSCKF with SLAM
//! features, First-Estimates Jacobians and online camera calibration.
//!
//! It does no I/O: [`Estimator`] is a state machine fed with IMU samples and camera
//! feature frames, returning the estimate and its covariance after each frame.
//! The flow of one camera frame is `Estimator::process_frame` in [`vio`].

pub mod camera_window;
pub mod chi2;
pub mod ci_diagnostics;
pub mod ci_split;
pub mod ci_system;
pub mod cooperative;
pub mod covariance;
pub mod feature_classes;
pub mod feature_db;
pub mod feature_system;
pub mod filter;
pub mod frame_alignment;
pub mod frame_output;
pub mod gated_update;
pub mod inputs;
pub mod linalg;
pub mod observability;
pub mod options;
pub mod peer_frame_states;
pub mod peer_window;
pub mod projection;
pub mod propagator;
pub mod slam_feature;
pub mod slam_pacing;
pub mod slow_start;
pub mod state;
pub mod static_init;
pub mod triangulation;
pub mod updater_ci;
pub mod updater_common;
pub mod updater_common_slam;
pub mod updater_frame;
pub mod updater_msckf;
pub mod updater_slam;
pub mod updater_zupt;
pub mod vio;
mod weight_search;
pub mod window_gate;

pub use options::EstimatorOptions;
pub use vio::{Estimator, FrameError, FrameOutput, FrameRecord, InitialState, InputError};

#[cfg(test)]
pub(crate) mod test_scene;
