//! The true motion of one robot on the fleet clock.

use crate::bspline::{SplineError, SplineSe3, SplineState};
use common::trajectory::StampedPose;
use nalgebra::Vector3;

/// Control points are at least this far apart in time (OpenVINS's setting), seconds.
pub const MIN_CONTROL_DT_S: f64 = 0.05;

/// A robot's true trajectory: a spline fitted to its file, re-timed so the file's
/// first pose is at fleet time `start_time_s`.
#[derive(Clone, Debug)]
pub struct RobotTruth {
    /// The spline on the fleet clock.
    pub spline: SplineSe3,
    /// Fleet time minus the trajectory file's time, s (recordings made with the
    /// same clock as the file, e.g. its IMU, shift by this much).
    pub time_shift_s: f64,
}

impl RobotTruth {
    /// Fits the spline to `poses` (file timestamps), shifting them to start at `start_time_s`.
    pub fn new(poses: &[StampedPose], start_time_s: f64) -> Result<Self, SplineError> {
        let t0 = poses.first().map(|p| p.t).unwrap_or(0.0);
        let shifted: Vec<StampedPose> = poses
            .iter()
            .map(|p| StampedPose {
                t: p.t - t0 + start_time_s,
                ..*p
            })
            .collect();
        Ok(Self {
            spline: SplineSe3::fit(&shifted, MIN_CONTROL_DT_S)?,
            time_shift_s: start_time_s - t0,
        })
    }

    /// First fleet time with a defined state.
    pub fn start_time(&self) -> f64 {
        self.spline.start_time()
    }

    /// Last fleet time with a defined state.
    pub fn end_time(&self) -> f64 {
        self.spline.end_time()
    }

    /// Kinematic state at fleet time `t`.
    pub fn state(&self, t: f64) -> Option<SplineState> {
        self.spline.state(t)
    }

    /// The first time, stepping 0.1 s from the start, at which the robot is at least
    /// `min_distance_m` from where it started (OpenVINS starts its filter there).
    pub fn motion_start_time(&self, min_distance_m: f64) -> f64 {
        let t0 = self.start_time();
        let Some(p0) = self.spline.pose(t0).map(|p| p.trans) else {
            return t0;
        };
        let mut t = t0;
        while t + 0.1 <= self.end_time() {
            let p: Vector3<f64> = self.spline.pose(t).map(|p| p.trans).unwrap_or(p0);
            if (p - p0).norm() >= min_distance_m {
                return t;
            }
            t += 0.1;
        }
        t0
    }
}
