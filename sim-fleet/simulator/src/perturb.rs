//! The estimator's initial calibration: the truth perturbed by the scenario's
//! priors, as OpenVINS's simulator does, so online calibration is exercised.

use crate::imu::normal3;
use crate::scenario::CalibrationPerturbation;
use common::calibration::CameraCalibration;
use common::so3::exp_so3;
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
