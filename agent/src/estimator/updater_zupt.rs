//! Zero-velocity detection and update for standstills.
//!
//! A robot that stops gives the visual updates no parallax, and with nothing else
//! the filter drifts. Between two images the IMU readings of a robot at rest are
//! `ω_m = b_g + n_g` and `a_m = R_ItoGᵀ g + b_a + n_a`: a chi-square test of that
//! hypothesis on every reading (plus a bound on the estimated speed) detects the
//! standstill, and the same model, with `v = 0`, is then used as an EKF update.

use super::chi2::Chi2Table;
use super::filter::Filter;
use super::options::EstimatorOptions;
use super::state::{Means, Var};
use common::measurement::ImuSample;
use common::so3::skew;
use nalgebra::{DMatrix, DVector, Vector3};

/// Speed above which a standstill is not believed, m/s.
const MAX_SPEED_MPS: f64 = 0.1;
/// Standard deviation of the zero-velocity pseudo-measurement, m/s.
const VELOCITY_SIGMA_MPS: f64 = 0.01;

/// The zero-motion model `[ω_m − b_g; a_m − b_a − Rᵀ g]` has the same Jacobian
/// for every reading, so the stack of `N` readings is equivalent to their mean
/// with noise `R₀/N`, plus a scatter term that only enters the chi-square test:
/// `d² = r̄ᵀ (H P Hᵀ + R₀/N)⁻¹ r̄ + Σ_k (r_k − r̄)ᵀ R₀⁻¹ (r_k − r̄)`, with `6N` degrees
/// of freedom. Returns `(H, r̄ with the velocity row, R, scatter)`.
fn build(
    state: &Means,
    readings: &[ImuSample],
    opts: &EstimatorOptions,
) -> (DMatrix<f64>, DVector<f64>, DMatrix<f64>, f64) {
    let imu = &state.imu;
    let g = Vector3::new(0.0, 0.0, opts.imu.gravity_mps2);
    let g_in_i = imu.rot.transpose() * g;
    let n = readings.len() as f64;
    let dt = (readings.last().map(|s| s.t).unwrap_or(0.0)
        - readings.first().map(|s| s.t).unwrap_or(0.0))
        / (n - 1.0).max(1.0);
    let var_g = opts.imu.gyro_noise_density.powi(2) / dt.max(1e-6);
    let var_a = opts.imu.accel_noise_density.powi(2) / dt.max(1e-6);
    // Residuals z − h(x̂) with z = 0 for "reading − prediction".
    let residual = |s: &ImuSample| {
        (
            -(s.gyro - imu.bias_gyro),
            -(s.accel - imu.bias_accel - g_in_i),
        )
    };
    let (mut mg, mut ma) = (Vector3::zeros(), Vector3::zeros());
    for s in readings {
        let (rg, ra) = residual(s);
        mg += rg / n;
        ma += ra / n;
    }
    let scatter: f64 = readings
        .iter()
        .map(|s| {
            let (rg, ra) = residual(s);
            (rg - mg).norm_squared() / var_g + (ra - ma).norm_squared() / var_a
        })
        .sum();
    let ident = nalgebra::Matrix3::<f64>::identity();
    let mut h = DMatrix::zeros(9, 15);
    // ∂(ω_m − b_g)/∂δb_g = −I ; ∂(a_m − b_a − Rᵀg)/∂δθ = −[Rᵀ g]× , ∂/∂δb_a = −I ;
    // the velocity row observes δv.
    h.fixed_view_mut::<3, 3>(0, 9).copy_from(&(-ident));
    h.fixed_view_mut::<3, 3>(3, 0).copy_from(&(-skew(&g_in_i)));
    h.fixed_view_mut::<3, 3>(3, 12).copy_from(&(-ident));
    h.fixed_view_mut::<3, 3>(6, 6).copy_from(&ident);
    let mut res = DVector::zeros(9);
    res.rows_mut(0, 3).copy_from(&mg);
    res.rows_mut(3, 3).copy_from(&ma);
    res.rows_mut(6, 3).copy_from(&(-imu.vel));
    let mut r = DMatrix::zeros(9, 9);
    for i in 0..3 {
        r[(i, i)] = var_g / n;
        r[(3 + i, 3 + i)] = var_a / n;
        r[(6 + i, 6 + i)] = VELOCITY_SIGMA_MPS.powi(2);
    }
    (h, res, r, scatter)
}

/// Tests the standstill hypothesis on `readings` and, when it holds, applies the
/// zero-velocity update. Returns whether the robot was found standing still.
pub fn try_update<F: Filter + ?Sized>(
    state: &mut F,
    readings: &[ImuSample],
    opts: &EstimatorOptions,
    chi2: &Chi2Table,
) -> bool {
    if readings.len() < 2 || state.means().imu.vel.norm() > MAX_SPEED_MPS {
        return false;
    }
    let (h, res, r, scatter) = build(state.means(), readings, opts);
    // Gate on the IMU rows only: the velocity row is what we want to impose.
    let h_imu = h.rows(0, 6).into_owned();
    let res_imu = res.rows(0, 6).into_owned();
    let r_imu = r.view((0, 0), (6, 6)).into_owned();
    let Ok(d2) = state.mahalanobis(&[Var::Imu], &h_imu, &res_imu, &r_imu) else {
        return false;
    };
    if d2 + scatter > opts.chi2_multiplier * chi2.get(6 * readings.len()) {
        return false;
    }
    state.ekf_update(&[Var::Imu], &h, &res, &r).is_ok()
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::estimator::state::{ImuState, State};
    use common::calibration::CameraCalibration;

    fn still_state(vel: Vector3<f64>) -> State {
        State::new(
            0.0,
            ImuState {
                vel,
                ..ImuState::default()
            },
            DMatrix::identity(15, 15) * 1e-3,
            CameraCalibration::euroc_cam0(),
            &[],
        )
    }

    fn readings(accel: Vector3<f64>) -> Vec<ImuSample> {
        (0..40)
            .map(|k| ImuSample {
                t: k as f64 / 400.0,
                gyro: Vector3::zeros(),
                accel,
            })
            .collect()
    }

    #[test]
    fn a_robot_at_rest_is_detected_and_its_velocity_pulled_to_zero() {
        let mut s = still_state(Vector3::new(0.03, 0.0, 0.0));
        let opts = EstimatorOptions::default();
        let chi2 = Chi2Table::new(0.95, 1000);
        assert!(try_update(
            &mut s,
            &readings(Vector3::new(0.0, 0.0, 9.81)),
            &opts,
            &chi2
        ));
        assert!(s.imu.vel.norm() < 0.005, "{}", s.imu.vel);
    }

    #[test]
    fn a_robot_accelerating_is_not_taken_for_a_standstill() {
        let mut s = still_state(Vector3::zeros());
        let opts = EstimatorOptions::default();
        let chi2 = Chi2Table::new(0.95, 1000);
        // Shaking: the readings scatter far beyond the noise.
        let mut shaking = readings(Vector3::new(0.0, 0.0, 9.81));
        for (k, r) in shaking.iter_mut().enumerate() {
            r.accel.x += 0.5 * (k as f64 * 0.7).sin();
        }
        assert!(!try_update(&mut s, &shaking, &opts, &chi2));
        let mut moving = still_state(Vector3::new(1.0, 0.0, 0.0));
        assert!(!try_update(
            &mut moving,
            &readings(Vector3::new(0.0, 0.0, 9.81)),
            &opts,
            &chi2
        ));
    }
}
