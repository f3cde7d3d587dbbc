//! Trajectory I/O: TUM / OpenVINS text, EuRoC ASL CSV ground truth, per-pose covariances.
//!
//! Orientations are `R_ItoG` and positions `p_IinG` (see [`crate::conventions`]).

use nalgebra::{Matrix3, Vector3};

/// One pose of a trajectory at time `t` (seconds).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct StampedPose {
    /// Time in seconds.
    pub t: f64,
    /// Orientation `R_ItoG`.
    pub rot: Matrix3<f64>,
    /// Position `p_IinG` in metres.
    pub pos: Vector3<f64>,
}

/// The filter's marginal covariance of one pose, in the error state of
/// [`crate::conventions`]: orientation in rad² (local frame), position in m² (global).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct StampedCovariance {
    /// Time in seconds.
    pub t: f64,
    /// 3x3 orientation block (rad²).
    pub ori: Matrix3<f64>,
    /// 3x3 position block (m²).
    pub pos: Matrix3<f64>,
}
