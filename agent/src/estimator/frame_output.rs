//! What an estimator returns after each frame: the estimate, its marginal
//! covariances, what each update did and what it cost.

use super::cooperative::CoopFrameStats;
use super::state::Means;
use super::{updater_msckf, updater_slam};
use common::trajectory::{StampedCovariance, StampedPose};
use nalgebra::{Matrix3, Vector3};

/// Wall-clock cost of one frame, in milliseconds.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct FrameTiming {
    /// Propagation and cloning.
    pub propagate_ms: f64,
    /// MSCKF update.
    pub msckf_ms: f64,
    /// SLAM update.
    pub slam_update_ms: f64,
    /// SLAM delayed initialization.
    pub slam_init_ms: f64,
    /// Marginalization and clean-up.
    pub marginalize_ms: f64,
    /// Cooperative matching and updates (also in [`FrameRecord::coop`]).
    pub cooperation_ms: f64,
    /// Everything (wall clock).
    pub total_ms: f64,
    /// Everything, in this thread's CPU time (what benchmarks with several
    /// agents per core compare).
    pub cpu_ms: f64,
}

/// The estimate after one frame.
#[derive(Clone, Debug)]
pub struct FrameOutput {
    /// `R_ItoG`.
    pub rot: Matrix3<f64>,
    /// `p_IinG`, m.
    pub pos: Vector3<f64>,
    /// `v_IinG`, m/s.
    pub vel: Vector3<f64>,
    /// Orientation covariance (local error, rad²).
    pub cov_ori: Matrix3<f64>,
    /// Position covariance (m²).
    pub cov_pos: Matrix3<f64>,
    /// Its time, what the updates did and what the frame cost.
    pub record: FrameRecord,
}

impl FrameOutput {
    /// The output for a robot's `means` with its orientation and position
    /// covariance blocks, the frame's cost and what its updates did.
    pub fn of(
        means: &Means,
        cov_ori: Matrix3<f64>,
        cov_pos: Matrix3<f64>,
        timing: FrameTiming,
        (msckf, slam, coop): (
            updater_msckf::MsckfStats,
            updater_slam::SlamStats,
            CoopFrameStats,
        ),
        zero_velocity: bool,
    ) -> Self {
        Self {
            rot: means.imu.rot,
            pos: means.imu.pos,
            vel: means.imu.vel,
            cov_ori,
            cov_pos,
            record: FrameRecord {
                t: means.t,
                msckf_features: msckf.used,
                msckf,
                slam_features: means.features.len(),
                slam,
                zero_velocity,
                coop,
                timing,
            },
        }
    }

    /// IMU time of the estimate, s.
    pub fn t(&self) -> f64 {
        self.record.t
    }

    /// The estimated pose at [`Self::t`].
    pub fn pose(&self) -> StampedPose {
        StampedPose {
            t: self.t(),
            rot: self.rot,
            pos: self.pos,
        }
    }

    /// Its orientation and position covariance.
    pub fn covariance(&self) -> StampedCovariance {
        StampedCovariance {
            t: self.t(),
            ori: self.cov_ori,
            pos: self.cov_pos,
        }
    }
}

/// What a frame's updates did and what it cost: all of a frame's output but
/// the estimate, and what a run keeps of it (the estimate and covariances
/// are kept as poses, [`crate::runner::RobotRun`]).
#[derive(Clone, Copy, Debug, Default)]
pub struct FrameRecord {
    /// IMU time of the estimate, s.
    pub t: f64,
    /// Features used in the MSCKF update.
    pub msckf_features: usize,
    /// What the MSCKF update did (used, gated out, failed).
    pub msckf: updater_msckf::MsckfStats,
    /// SLAM features in the state.
    pub slam_features: usize,
    /// What the SLAM step did.
    pub slam: updater_slam::SlamStats,
    /// The frame was a standstill handled by a zero-velocity update.
    pub zero_velocity: bool,
    /// What the cooperative updates did.
    pub coop: CoopFrameStats,
    /// Cost of the frame.
    pub timing: FrameTiming,
}

/// Thread CPU time since `start`, ms (0 where the platform has no thread clock).
pub fn cpu_ms(start: Option<cpu_time::ThreadTime>) -> f64 {
    start.map_or(0.0, |t| t.elapsed().as_secs_f64() * 1e3)
}
