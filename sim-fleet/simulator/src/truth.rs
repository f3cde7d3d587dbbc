//! The true motion of one robot on the fleet clock.

use crate::bspline::{SplineError, SplineSe3, SplineState};
use common::so3::Se3;
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

    /// The same truth in another frame (every pose `T` becomes `f ∘ T`).
    pub fn transformed(&self, f: &Se3) -> Self {
        Self {
            spline: self.spline.transformed(f),
            time_shift_s: self.time_shift_s,
        }
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

    /// The first time, stepping 0.1 s from the start, at which the path the robot
    /// has travelled (the sum of the 0.1 s steps) exceeds `min_distance_m`:
    /// OpenVINS's simulator starts its filter there. The path, not the distance
    /// from the start: a robot that wanders near its start (a corridor walk that
    /// turns around) starts where OpenVINS starts, not tens of seconds later.
    pub fn motion_start_time(&self, min_distance_m: f64) -> f64 {
        let t0 = self.start_time();
        let Some(mut prev) = self.spline.pose(t0).map(|p| p.trans) else {
            return t0;
        };
        let mut travelled = 0.0;
        let mut t = t0;
        while t + 0.1 <= self.end_time() {
            let p: Vector3<f64> = self.spline.pose(t).map(|p| p.trans).unwrap_or(prev);
            travelled += (p - prev).norm();
            prev = p;
            if travelled > min_distance_m {
                return t;
            }
            t += 0.1;
        }
        t0
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use nalgebra::Matrix3;

    /// Swings back and forth along x, `amplitude_m` either side of the start, with
    /// a period of 4 s, for 20 s (100 Hz poses).
    fn swinging(amplitude_m: f64) -> RobotTruth {
        let poses: Vec<StampedPose> = (0..=2000)
            .map(|k| {
                let t = k as f64 * 0.01;
                let x = amplitude_m * (std::f64::consts::TAU * t / 4.0).sin();
                StampedPose {
                    t,
                    rot: Matrix3::identity(),
                    pos: Vector3::new(x, 0.0, 1.0),
                }
            })
            .collect();
        RobotTruth::new(&poses, 0.0).expect("spline")
    }

    #[test]
    fn the_start_follows_the_travelled_path_not_the_distance_from_the_start() {
        // 0.3 m either side: never 1.1 m from the start, but 1.2 m of path per
        // period, so the path passes 1.1 m a little before 4 s.
        let truth = swinging(0.3);
        let t = truth.motion_start_time(1.1);
        assert!(t > 3.0 && t < 4.0, "start at {t}");
        // On the 0.1 s grid from the spline's start.
        let steps = (t - truth.start_time()) / 0.1;
        assert!((steps - steps.round()).abs() < 1e-9, "{steps}");
    }

    #[test]
    fn a_robot_that_never_travels_far_enough_starts_at_the_beginning() {
        let truth = swinging(0.0);
        assert_eq!(truth.motion_start_time(1.1), truth.start_time());
    }
}
