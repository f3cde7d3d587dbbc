//! Synthetic trajectories for the metric tests.

use nalgebra::Vector3;

use crate::so3::exp_so3;
use crate::trajectory::StampedPose;

/// A pose with yaw `yaw` (rad) about `z` at `pos`.
pub fn pose(t: f64, yaw: f64, pos: Vector3<f64>) -> StampedPose {
    StampedPose {
        t,
        rot: exp_so3(&Vector3::new(0.0, 0.0, yaw)),
        pos,
    }
}

/// A curvy 3D trajectory with varied orientations, `n` poses at 10 Hz.
pub fn wiggly(n: usize) -> Vec<StampedPose> {
    (0..n)
        .map(|i| {
            let s = i as f64 * 0.1;
            StampedPose {
                t: 100.0 + s,
                rot: exp_so3(&Vector3::new(0.3 * s.sin(), 0.2 * (0.7 * s).cos(), 0.5 * s)),
                pos: Vector3::new(3.0 * s.cos(), 2.0 * (1.3 * s).sin(), 0.5 * (0.4 * s).sin()),
            }
        })
        .collect()
}
