//! What an estimator returns after each frame: the estimate, its marginal
//! covariances, what each update did and what it cost.

use super::cooperative::CoopFrameStats;
use super::state::{ImuState, Means};
use super::{updater_msckf, updater_slam};
use common::so3::skew;
use common::trajectory::{ImuEstimate, StampedCovariance, StampedPose};
use nalgebra::{Matrix3, Matrix6, SMatrix, Vector3};

/// The covariance of the IMU state's 15 error coordinates: orientation (local,
/// rad), position (m), velocity (m/s), gyro bias (rad/s), accel bias (m/s²).
pub type ImuCovariance = SMatrix<f64, 15, 15>;

/// The gyroscope at a frame: its reading at the frame's IMU time, and the
/// variance of its white noise per axis ([`super::propagator::gyro_at_frame`]).
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct GyroAtFrame {
    /// The raw reading (bias included), rad/s, IMU frame.
    pub reading: Vector3<f64>,
    /// White-noise variance of one reading per axis, (rad/s)².
    pub noise_var: f64,
}

impl GyroAtFrame {
    /// From the reading at the frame's IMU time, the gyro's noise density
    /// (rad/s/√Hz) and the readings' rate (Hz): one discrete reading's
    /// variance is density² times the rate (an upper bound for a reading
    /// interpolated between two). A rate that is not positive and finite
    /// gives no noise term.
    pub fn new(reading: Vector3<f64>, noise_density: f64, rate_hz: f64) -> Self {
        let noise_var = if rate_hz.is_finite() && rate_hz > 0.0 {
            noise_density * noise_density * rate_hz
        } else {
            0.0
        };
        Self { reading, noise_var }
    }
}

/// The body's velocity and angular rate, both in the IMU frame, with their
/// 6x6 covariance in that order (the `twist` of ROS's `nav_msgs/Odometry`,
/// whose `child_frame_id` is the body).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct BodyTwist {
    /// `R_ItoGᵀ v_IinG`, m/s.
    pub linear: Vector3<f64>,
    /// The gyro reading less the estimated bias, rad/s.
    pub angular: Vector3<f64>,
    /// Covariance of `[linear; angular]`.
    pub cov: Matrix6<f64>,
}

impl Default for BodyTwist {
    fn default() -> Self {
        Self {
            linear: Vector3::zeros(),
            angular: Vector3::zeros(),
            cov: Matrix6::zeros(),
        }
    }
}

impl BodyTwist {
    /// What a run keeps of it at time `t`: the twist and its standard
    /// deviations.
    pub fn stamped(&self, t: f64) -> StampedTwist {
        StampedTwist {
            t,
            linear: self.linear,
            angular: self.angular,
            sigma: std::array::from_fn(|i| self.cov[(i, i)].max(0.0).sqrt()),
        }
    }
}

/// A body twist at a time, with the standard deviations of its six
/// components (what a run records per frame; the covariance's cross terms
/// go only to the live odometry).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct StampedTwist {
    /// IMU time, s.
    pub t: f64,
    /// Velocity in the body (IMU) frame, m/s.
    pub linear: Vector3<f64>,
    /// Angular rate in the body frame, rad/s.
    pub angular: Vector3<f64>,
    /// Standard deviations of `[linear; angular]`.
    pub sigma: [f64; 6],
}

/// The body twist of `imu`, with its covariance carried from the IMU block
/// `cov` to first order. With `R = R̂ Exp(δθ)`, `Rᵀ v = R̂ᵀ v̂ + ⌊R̂ᵀ v̂⌋× δθ +
/// R̂ᵀ δv`, and the rate's error is `-δb_g` plus the reading's white noise.
pub fn body_twist(imu: &ImuState, cov: &ImuCovariance, gyro: &GyroAtFrame) -> BodyTwist {
    let linear = imu.rot.transpose() * imu.vel;
    let mut j = SMatrix::<f64, 6, 15>::zeros();
    j.fixed_view_mut::<3, 3>(0, 0).copy_from(&skew(&linear));
    j.fixed_view_mut::<3, 3>(0, 6)
        .copy_from(&imu.rot.transpose());
    j.fixed_view_mut::<3, 3>(3, 9)
        .copy_from(&(-Matrix3::identity()));
    let mut twist_cov = j * cov * j.transpose();
    for i in 3..6 {
        twist_cov[(i, i)] += gyro.noise_var;
    }
    BodyTwist {
        linear,
        angular: gyro.reading - imu.bias_gyro,
        cov: twist_cov,
    }
}

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
    /// Orientation covariance (local error, rad²).
    pub cov_ori: Matrix3<f64>,
    /// Position covariance (m²).
    pub cov_pos: Matrix3<f64>,
    /// The velocity and the biases with their covariances, for consistency
    /// studies against a simulator's truth.
    pub imu: ImuEstimate,
    /// Velocity and angular rate in the body (IMU) frame, with their covariance.
    pub twist: BodyTwist,
    /// Its time, what the updates did and what the frame cost.
    pub record: FrameRecord,
}

impl FrameOutput {
    /// The output for a robot's `means` with the covariance of its IMU state,
    /// the gyro reading at the frame, the frame's cost and what its updates did.
    pub fn of(
        means: &Means,
        cov_imu: &ImuCovariance,
        gyro: &GyroAtFrame,
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
            cov_ori: cov_imu.fixed_view::<3, 3>(0, 0).into_owned(),
            cov_pos: cov_imu.fixed_view::<3, 3>(3, 3).into_owned(),
            imu: ImuEstimate {
                t: means.t,
                vel: means.imu.vel,
                bias_gyro: means.imu.bias_gyro,
                bias_accel: means.imu.bias_accel,
                cov_vel: cov_imu.fixed_view::<3, 3>(6, 6).into_owned(),
                cov_bias_gyro: cov_imu.fixed_view::<3, 3>(9, 9).into_owned(),
                cov_bias_accel: cov_imu.fixed_view::<3, 3>(12, 12).into_owned(),
            },
            twist: body_twist(&means.imu, cov_imu, gyro),
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

#[cfg(test)]
mod tests {
    use super::*;
    use common::so3::exp_so3;
    use nalgebra::SVector;

    /// The twist of the state `imu ⊞ dx` (15 error coordinates).
    fn twist_at(imu: &ImuState, gyro: &GyroAtFrame, dx: &SVector<f64, 15>) -> SVector<f64, 6> {
        let d = |i: usize| Vector3::new(dx[i], dx[i + 1], dx[i + 2]);
        let rot = imu.rot * exp_so3(&d(0));
        let vel = imu.vel + d(6);
        let bias = imu.bias_gyro + d(9);
        let linear = rot.transpose() * vel;
        let angular = gyro.reading - bias;
        SVector::<f64, 6>::from_iterator(linear.iter().chain(angular.iter()).copied())
    }

    #[test]
    fn the_twist_covariance_matches_numerical_differentiation() {
        let imu = ImuState {
            rot: exp_so3(&Vector3::new(0.3, -0.7, 1.9)),
            pos: Vector3::new(1.0, 2.0, 3.0),
            vel: Vector3::new(0.8, -1.3, 0.4),
            bias_gyro: Vector3::new(0.01, -0.02, 0.005),
            bias_accel: Vector3::new(0.1, 0.0, -0.1),
        };
        let gyro = GyroAtFrame::new(
            Vector3::new(0.2, 0.1, -0.4) + imu.bias_gyro,
            1.6968e-4,
            200.0,
        );
        assert!((gyro.noise_var - 1.6968e-4_f64.powi(2) * 200.0).abs() < 1e-18);
        // A dense covariance with every cross term.
        let a = SMatrix::<f64, 15, 15>::from_fn(|r, c| ((r * 7 + c * 3) % 11) as f64 * 1e-3);
        let cov = a * a.transpose() + ImuCovariance::identity() * 1e-4;
        let twist = body_twist(&imu, &cov, &gyro);
        assert!((twist.linear - imu.rot.transpose() * imu.vel).norm() < 1e-15);
        assert!((twist.angular - Vector3::new(0.2, 0.1, -0.4)).norm() < 1e-15);

        let h = 1e-6;
        let mut j = SMatrix::<f64, 6, 15>::zeros();
        for k in 0..15 {
            let mut dx = SVector::<f64, 15>::zeros();
            dx[k] = h;
            let col = (twist_at(&imu, &gyro, &dx) - twist_at(&imu, &gyro, &(-dx))) / (2.0 * h);
            j.set_column(k, &col);
        }
        let mut expected = j * cov * j.transpose();
        for i in 3..6 {
            expected[(i, i)] += gyro.noise_var;
        }
        let err = (twist.cov - expected).norm() / expected.norm();
        assert!(err < 1e-8, "relative error {err}");
        assert!((twist.cov - twist.cov.transpose()).norm() < 1e-15);
    }

    #[test]
    fn no_readings_rate_means_no_white_noise_term() {
        for rate in [0.0, -1.0, f64::NAN, f64::INFINITY] {
            let g = GyroAtFrame::new(Vector3::zeros(), 1e-3, rate);
            assert_eq!(g.noise_var, 0.0);
        }
    }
}
