//! The estimator's initial calibration: the truth perturbed by the scenario's
//! priors, as OpenVINS's simulator does, so online calibration is exercised;
//! and, when asked, the error of the estimator's initial state.

use crate::imu::normal3;
use crate::scenario::{CalibrationPerturbation, EstimatorSpec, InitialError};
use common::calibration::CameraCalibration;
use common::so3::exp_so3;
use nalgebra::Vector3;
use rand_chacha::ChaCha8Rng;
use rand_distr::{Distribution, StandardNormal};

/// The truth plus zero-mean Gaussian errors with the given standard deviations;
/// the truth itself when the perturbation is disabled.
pub fn perturb_calibration(
    truth: &CameraCalibration,
    p: &CalibrationPerturbation,
    rng: &mut ChaCha8Rng,
) -> CameraCalibration {
    let mut c = truth.clone();
    if !p.enabled {
        return c;
    }
    let mut n = || -> f64 { StandardNormal.sample(rng) };
    c.time_offset_s += p.time_offset_s * n();
    for i in 0..4 {
        c.camera.intrinsics[i] += p.intrinsics_px * n();
    }
    for i in 0..4 {
        c.camera.distortion[i] += p.distortion * n();
    }
    // Right perturbation of R_CtoI (conventions): R = R̂ Exp(δθ).
    let dtheta = normal3(rng) * p.extrinsic_rot_rad;
    c.rot_c_to_i *= exp_so3(&dtheta);
    c.p_c_in_i += normal3(rng) * p.extrinsic_pos_m;
    c
}

/// The error an estimator starts with: `estimate = truth ⊞ error`, with the
/// orientation perturbed on the right (`R̂ = R Exp(δθ)`; the prior is isotropic,
/// so the side does not change the distribution).
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct StartError {
    /// Orientation, rad.
    pub rot: Vector3<f64>,
    /// Position, m.
    pub pos: Vector3<f64>,
    /// Velocity, m/s.
    pub vel: Vector3<f64>,
    /// Gyroscope bias, rad/s.
    pub bias_gyro: Vector3<f64>,
    /// Accelerometer bias, m/s².
    pub bias_accel: Vector3<f64>,
}

/// Zero with `initial_error: truth`; otherwise one draw from the prior the
/// estimator states (`init_sigma_*`).
pub fn start_error(spec: &EstimatorSpec, rng: &mut ChaCha8Rng) -> StartError {
    match spec.initial_error {
        InitialError::Truth => StartError::default(),
        InitialError::Sampled => StartError {
            rot: normal3(rng) * spec.init_sigma_ori_rad,
            pos: normal3(rng) * spec.init_sigma_pos_m,
            vel: normal3(rng) * spec.init_sigma_vel_mps,
            bias_gyro: normal3(rng) * spec.init_sigma_bias,
            bias_accel: normal3(rng) * spec.init_sigma_bias,
        },
    }
}
