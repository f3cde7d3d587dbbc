//! IMU propagation of the mean and covariance (thesis Eqs. 2.7-2.32).
//!
//! Between two IMU readings the measurements are averaged (bias removed) and held
//! constant; the mean follows the exact solution for constant body rates and a
//! midpoint rotation for the specific force. The discrete state transition `Φ` and
//! noise `Q_d` (Eqs. 2.29-2.30) are written for the right (local) orientation error of
//! `common::conventions`; `Φ` is evaluated at the same values the mean used, so the
//! filter's linearization points are consistent (the FEJ property of propagation).
//! Segments are chained (`Φ_sum = Φ Φ_sum`, `Q_sum = Φ Q_sum Φᵀ + Q_d`) and applied to
//! the covariance once.

use super::filter::Filter;
use super::frame_output::GyroAtFrame;
use super::options::ImuNoise;
use super::state::{ImuFej, Means};
use common::measurement::ImuSample;
use common::so3::{exp_so3, jr_so3, skew};
use nalgebra::{Matrix3, SMatrix, Vector3};
use thiserror::Error;

type Mat15 = SMatrix<f64, 15, 15>;

/// Why the state could not be propagated; the state is unchanged.
#[derive(Debug, Error, PartialEq)]
pub enum PropagateError {
    /// The IMU buffer does not reach the target time.
    #[error("IMU data ends at {last:.6} s, before the target {target:.6} s")]
    NotEnoughImu {
        /// Last buffered IMU time.
        last: f64,
        /// Requested time.
        target: f64,
    },
    /// The target is before the state's time.
    #[error("cannot propagate backwards from {from:.6} s to {to:.6} s")]
    Backwards {
        /// State time.
        from: f64,
        /// Requested time.
        to: f64,
    },
}

/// One constant-rate segment between two IMU times.
#[derive(Clone, Copy, Debug)]
struct Segment {
    dt: f64,
    gyro: Vector3<f64>,
    accel: Vector3<f64>,
}

fn lerp(a: &ImuSample, b: &ImuSample, t: f64) -> ImuSample {
    let s = if b.t > a.t {
        (t - a.t) / (b.t - a.t)
    } else {
        0.0
    };
    ImuSample {
        t,
        gyro: a.gyro + (b.gyro - a.gyro) * s,
        accel: a.accel + (b.accel - a.accel) * s,
    }
}

/// The readings that cover `[t0, t1]`, interpolated at both ends (OpenVINS's
/// `select_imu_readings`), as averaged constant segments.
fn segments(buf: &[ImuSample], t0: f64, t1: f64) -> Result<Vec<Segment>, PropagateError> {
    let last = buf.last().map(|s| s.t).unwrap_or(f64::NEG_INFINITY);
    if last < t1 - 1e-9 || buf.len() < 2 {
        return Err(PropagateError::NotEnoughImu { last, target: t1 });
    }
    let mut pts: Vec<ImuSample> = Vec::with_capacity(16);
    for w in buf.windows(2) {
        let (a, b) = (&w[0], &w[1]);
        if b.t <= t0 || a.t >= t1 {
            continue;
        }
        if pts.is_empty() {
            pts.push(if a.t < t0 { lerp(a, b, t0) } else { *a });
        }
        pts.push(if b.t > t1 { lerp(a, b, t1) } else { *b });
    }
    if pts.is_empty() {
        // t0 precedes the buffer: hold the first reading.
        let first = buf[0];
        pts.push(ImuSample { t: t0, ..first });
        pts.push(ImuSample { t: t1, ..first });
    }
    Ok(pts
        .windows(2)
        .filter(|w| w[1].t - w[0].t > 1e-12)
        .map(|w| Segment {
            dt: w[1].t - w[0].t,
            gyro: (w[0].gyro + w[1].gyro) * 0.5,
            accel: (w[0].accel + w[1].accel) * 0.5,
        })
        .collect())
}

/// The gyro at a frame's IMU time `t1`, for the twist published beside the
/// estimate: the reading interpolated at `t1` (the propagation's last rate
/// is a mean over its last interval, half a sample late), with the white
/// noise of one reading at the rate the readings of `(t0, t1]` came in.
/// An empty buffer (which propagation refuses first) gives a zero reading.
pub fn gyro_at_frame(buf: &[ImuSample], t0: f64, t1: f64, noise: &ImuNoise) -> GyroAtFrame {
    let after = buf.partition_point(|s| s.t < t1);
    let reading = match (
        after.checked_sub(1).and_then(|i| buf.get(i)),
        buf.get(after),
    ) {
        (Some(a), Some(b)) => lerp(a, b, t1).gyro,
        (Some(only), None) | (None, Some(only)) => only.gyro,
        (None, None) => Vector3::zeros(),
    };
    // Readings in (t0, t1]; the buffer is time ordered.
    let n = buf
        .partition_point(|s| s.t <= t1)
        .saturating_sub(buf.partition_point(|s| s.t <= t0));
    let rate_hz = if t1 > t0 { n as f64 / (t1 - t0) } else { 0.0 };
    GyroAtFrame::new(reading, noise.gyro_noise_density, rate_hz)
}

/// Propagates the filter's robot to IMU time `t1` with the readings in `buf`
/// (time ordered): the mean, then the covariance once with the interval's `Φ`
/// and `Q`. Returns the bias-corrected angular velocity at `t1` (for the clone's
/// time-offset Jacobian).
pub fn propagate<F: Filter + ?Sized>(
    f: &mut F,
    buf: &[ImuSample],
    t1: f64,
    noise: &ImuNoise,
    use_fej: bool,
) -> Result<Vector3<f64>, PropagateError> {
    let (phi, q, omega) = propagate_mean(f.means_mut(), buf, t1, noise, use_fej)?;
    f.propagate_covariance(&phi, &q);
    Ok(omega)
}

/// The mean part of [`propagate`]: moves `state` to `t1` and returns the
/// interval's `Φ` (at first estimates when `use_fej`), `Q` and the last angular
/// velocity.
fn propagate_mean(
    state: &mut Means,
    buf: &[ImuSample],
    t1: f64,
    noise: &ImuNoise,
    use_fej: bool,
) -> Result<(Mat15, Mat15, Vector3<f64>), PropagateError> {
    let t0 = state.t;
    if t1 < t0 {
        return Err(PropagateError::Backwards { from: t0, to: t1 });
    }
    let segs = segments(buf, t0, t1)?;
    let g = Vector3::new(0.0, 0.0, noise.gravity_mps2);
    let mut phi_sum = Mat15::identity();
    let mut q_sum = Mat15::zeros();
    let mut omega = Vector3::zeros();
    let (r0, p0, v0) = (state.imu.rot, state.imu.pos, state.imu.vel);
    let mut dt_sum = 0.0;
    for seg in &segs {
        let imu = &mut state.imu;
        let dt = seg.dt;
        let w = seg.gyro - imu.bias_gyro;
        let a = seg.accel - imu.bias_accel;
        omega = w;
        let dr = exp_so3(&(w * dt));
        let r_half = exp_so3(&(w * (0.5 * dt)));
        let r_k = imu.rot;
        // Increments in the frame I_k.
        let dv_i = r_half * a * dt;
        let dp_i = dv_i * (0.5 * dt);
        let jr = jr_so3(&(w * dt));
        let jr_half = jr_so3(&(w * (0.5 * dt)));

        let mut phi = Mat15::identity();
        phi.fixed_view_mut::<3, 3>(0, 0).copy_from(&dr.transpose());
        phi.fixed_view_mut::<3, 3>(0, 9).copy_from(&(-jr * dt));
        phi.fixed_view_mut::<3, 3>(3, 0)
            .copy_from(&(-r_k * skew(&dp_i)));
        phi.fixed_view_mut::<3, 3>(3, 6)
            .copy_from(&(Matrix3::identity() * dt));
        let dv_dbg = r_k * r_half * skew(&a) * jr_half * (0.5 * dt * dt);
        phi.fixed_view_mut::<3, 3>(3, 9)
            .copy_from(&(dv_dbg * (0.5 * dt)));
        phi.fixed_view_mut::<3, 3>(3, 12)
            .copy_from(&(-r_k * r_half * (0.5 * dt * dt)));
        phi.fixed_view_mut::<3, 3>(6, 0)
            .copy_from(&(-r_k * skew(&dv_i)));
        phi.fixed_view_mut::<3, 3>(6, 9).copy_from(&dv_dbg);
        phi.fixed_view_mut::<3, 3>(6, 12)
            .copy_from(&(-r_k * r_half * dt));

        let (sg2, sa2) = (
            noise.gyro_noise_density.powi(2),
            noise.accel_noise_density.powi(2),
        );
        let mut qd = Mat15::zeros();
        qd.fixed_view_mut::<3, 3>(0, 0)
            .copy_from(&(jr * jr.transpose() * (sg2 * dt)));
        let i3 = Matrix3::identity();
        qd.fixed_view_mut::<3, 3>(3, 3)
            .copy_from(&(i3 * (sa2 * dt.powi(3) / 4.0)));
        qd.fixed_view_mut::<3, 3>(3, 6)
            .copy_from(&(i3 * (sa2 * dt * dt / 2.0)));
        qd.fixed_view_mut::<3, 3>(6, 3)
            .copy_from(&(i3 * (sa2 * dt * dt / 2.0)));
        qd.fixed_view_mut::<3, 3>(6, 6)
            .copy_from(&(i3 * (sa2 * dt)));
        qd.fixed_view_mut::<3, 3>(9, 9)
            .copy_from(&(i3 * (noise.gyro_random_walk.powi(2) * dt)));
        qd.fixed_view_mut::<3, 3>(12, 12)
            .copy_from(&(i3 * (noise.accel_random_walk.powi(2) * dt)));

        // Mean.
        imu.pos += imu.vel * dt + r_k * dp_i - g * (0.5 * dt * dt);
        imu.vel += r_k * dv_i - g * dt;
        imu.rot = common::so3::orthonormalize(&(r_k * dr));

        phi_sum = phi * phi_sum;
        q_sum = phi * q_sum * phi.transpose() + qd;
        dt_sum += dt;
    }
    if use_fej {
        fej_transition(&mut phi_sum, state, (r0, p0, v0), dt_sum, &g);
    }
    state.imu_fej = ImuFej::of(&state.imu);
    state.t = t1;
    Ok((phi_sum, q_sum, omega))
}

/// Re-evaluates the interval's `Φ` at the first estimates of the start state
/// (the values the previous propagation produced, before updates), keeping the
/// propagated end state: `Φ_θθ = R_{k+1}ᵀ R_kᶠ`,
/// `Φ_pθ = −[p_{k+1} − p_kᶠ − v_kᶠ Δt + ½ g Δt²]× R_kᶠ`,
/// `Φ_vθ = −[v_{k+1} − v_kᶠ + g Δt]× R_kᶠ`, and the bias columns of `p` and `v`
/// rotated from `R_k` to `R_kᶠ`. With these, the unobservable directions (global
/// position and yaw) stay unobservable across updates (FEJ, thesis Section 2.2.2).
fn fej_transition(
    phi: &mut Mat15,
    state: &Means,
    start: (Matrix3<f64>, Vector3<f64>, Vector3<f64>),
    dt: f64,
    g: &Vector3<f64>,
) {
    let (r_k, _, _) = start;
    let fej = &state.imu_fej;
    let imu = &state.imu;
    phi.fixed_view_mut::<3, 3>(0, 0)
        .copy_from(&(imu.rot.transpose() * fej.rot));
    let dp = imu.pos - fej.pos - fej.vel * dt + g * (0.5 * dt * dt);
    phi.fixed_view_mut::<3, 3>(3, 0)
        .copy_from(&(-skew(&dp) * fej.rot));
    let dv = imu.vel - fej.vel + g * dt;
    phi.fixed_view_mut::<3, 3>(6, 0)
        .copy_from(&(-skew(&dv) * fej.rot));
    let rot_fix = fej.rot * r_k.transpose();
    for row in [3, 6] {
        for col in [9, 12] {
            let b = rot_fix * phi.fixed_view::<3, 3>(row, col);
            phi.fixed_view_mut::<3, 3>(row, col).copy_from(&b);
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::estimator::state::{ImuState, State, Var};
    use common::calibration::CameraCalibration;
    use nalgebra::DMatrix;

    /// The reading is interpolated at the frame's time, and the rate counts
    /// the readings of `(t0, t1]`.
    #[test]
    fn the_gyro_at_a_frame_is_interpolated_at_its_time() {
        let buf: Vec<ImuSample> = (0..=40)
            .map(|k| ImuSample {
                t: k as f64 * 0.005,
                gyro: Vector3::new(k as f64, 0.0, 0.0),
                accel: Vector3::zeros(),
            })
            .collect();
        let noise = ImuNoise::default();
        let g = gyro_at_frame(&buf, 0.05, 0.1525, &noise);
        assert!((g.reading.x - 30.5).abs() < 1e-9, "{}", g.reading.x);
        // 20 readings (0.055 ... 0.15) in 0.1025 s.
        let rate = 20.0 / 0.1025;
        assert!((g.noise_var - noise.gyro_noise_density.powi(2) * rate).abs() < 1e-15);
        // On a reading, and past the buffer's end.
        assert_eq!(gyro_at_frame(&buf, 0.0, 0.1, &noise).reading.x, 20.0);
        assert_eq!(gyro_at_frame(&buf, 0.1, 0.5, &noise).reading.x, 40.0);
        assert_eq!(gyro_at_frame(&[], 0.0, 0.1, &noise).noise_var, 0.0);
    }

    fn state_at(imu: ImuState) -> State {
        State::new(
            0.0,
            imu,
            DMatrix::identity(15, 15) * 1e-4,
            CameraCalibration::euroc_cam0(),
            &[],
        )
    }

    fn imu_of(t: f64) -> (Vector3<f64>, Vector3<f64>) {
        (
            Vector3::new(0.3 * (t).sin(), -0.2, 0.5 * (0.5 * t).cos()),
            Vector3::new(0.5 * t.cos(), 0.2, 9.81 + 0.3 * (2.0 * t).sin()),
        )
    }

    fn nominal() -> ImuState {
        ImuState {
            rot: exp_so3(&Vector3::new(0.1, -0.2, 0.3)),
            pos: Vector3::new(1.0, 2.0, 3.0),
            vel: Vector3::new(0.5, -0.3, 0.1),
            bias_gyro: Vector3::new(0.01, -0.02, 0.005),
            bias_accel: Vector3::new(0.05, 0.02, -0.03),
        }
    }

    fn buffer(t_end: f64) -> Vec<ImuSample> {
        (0..=(t_end * 400.0) as usize)
            .map(|k| {
                let t = k as f64 / 400.0;
                let (gyro, accel) = imu_of(t);
                ImuSample { t, gyro, accel }
            })
            .collect()
    }

    /// Perturbs the IMU state by δx (15) with the boxplus of the conventions.
    fn boxplus(s: &ImuState, dx: &nalgebra::SVector<f64, 15>) -> ImuState {
        let v = |i: usize| Vector3::new(dx[i], dx[i + 1], dx[i + 2]);
        ImuState {
            rot: s.rot * exp_so3(&v(0)),
            pos: s.pos + v(3),
            vel: s.vel + v(6),
            bias_gyro: s.bias_gyro + v(9),
            bias_accel: s.bias_accel + v(12),
        }
    }

    fn boxminus(a: &ImuState, b: &ImuState) -> nalgebra::SVector<f64, 15> {
        let mut d = nalgebra::SVector::<f64, 15>::zeros();
        d.fixed_rows_mut::<3>(0)
            .copy_from(&common::so3::log_so3(&(b.rot.transpose() * a.rot)));
        d.fixed_rows_mut::<3>(3).copy_from(&(a.pos - b.pos));
        d.fixed_rows_mut::<3>(6).copy_from(&(a.vel - b.vel));
        d.fixed_rows_mut::<3>(9)
            .copy_from(&(a.bias_gyro - b.bias_gyro));
        d.fixed_rows_mut::<3>(12)
            .copy_from(&(a.bias_accel - b.bias_accel));
        d
    }

    #[test]
    fn the_state_transition_matches_numerical_differentiation_of_the_mean() {
        let buf = buffer(0.2);
        let t1 = 0.1;
        // Numerical Φ: perturb each error-state direction and propagate the mean.
        let x0 = nominal();
        let mut base = state_at(x0.clone());
        propagate(&mut base, &buf, t1, &ImuNoise::default(), false).unwrap();
        let h = 1e-6;
        let mut phi_num = Mat15::zeros();
        for i in 0..15 {
            let mut dx = nalgebra::SVector::<f64, 15>::zeros();
            dx[i] = h;
            let mut sp = state_at(boxplus(&x0, &dx));
            propagate(&mut sp, &buf, t1, &ImuNoise::default(), false).unwrap();
            let mut sm = state_at(boxplus(&x0, &(-dx)));
            propagate(&mut sm, &buf, t1, &ImuNoise::default(), false).unwrap();
            let col = (boxminus(&sp.imu, &base.imu) - boxminus(&sm.imu, &base.imu)) / (2.0 * h);
            phi_num.set_column(i, &col);
        }
        // Analytic Φ: propagate a covariance with zero process noise from P0 = I.
        let zero = ImuNoise {
            gyro_noise_density: 0.0,
            gyro_random_walk: 0.0,
            accel_noise_density: 0.0,
            accel_random_walk: 0.0,
            ..ImuNoise::default()
        };
        let mut cross = State::new(
            0.0,
            x0,
            DMatrix::identity(15, 15),
            CameraCalibration::euroc_cam0(),
            &[],
        );
        // Augment a copy of the IMU block: after propagation P(IMU, copy) = Φ.
        cross
            .augment(
                Var::Clone(0),
                &[(Var::Imu, DMatrix::identity(15, 15).rows(0, 6).into_owned())],
                &DMatrix::zeros(6, 6),
            )
            .unwrap();
        propagate(&mut cross, &buf, t1, &zero, false).unwrap();
        let p_ic = cross.block(Var::Imu, Var::Clone(0)).unwrap(); // Φ[:, 0..6]
        let err = (p_ic - phi_num.columns(0, 6)).abs().max();
        assert!(err < 1e-5, "Φ (orientation/position columns) error {err}");
        // Full Φ via P1 = Φ Φᵀ with P0 = I.
        let p1 = cross.block(Var::Imu, Var::Imu).unwrap();
        let p1_num = phi_num * phi_num.transpose();
        let err = (p1 - DMatrix::from_iterator(15, 15, p1_num.iter().copied()))
            .abs()
            .max();
        assert!(err < 1e-5, "Φ Φᵀ error {err}");
    }

    #[test]
    fn propagation_needs_imu_up_to_the_target_and_refuses_to_go_back() {
        let buf = buffer(0.1);
        let mut s = state_at(nominal());
        assert!(matches!(
            propagate(&mut s, &buf, 0.2, &ImuNoise::default(), false),
            Err(PropagateError::NotEnoughImu { .. })
        ));
        propagate(&mut s, &buf, 0.05, &ImuNoise::default(), false).unwrap();
        assert!(matches!(
            propagate(&mut s, &buf, 0.01, &ImuNoise::default(), false),
            Err(PropagateError::Backwards { .. })
        ));
    }

    #[test]
    fn covariance_grows_with_the_configured_noise() {
        let buf = buffer(1.1);
        let mut s = state_at(nominal());
        s.set_cov(DMatrix::zeros(15, 15)).unwrap();
        propagate(&mut s, &buf, 1.0, &ImuNoise::default(), false).unwrap();
        let p = s.cov();
        // Gyro bias variance grows as σ_wg² t.
        assert!((p[(9, 9)] - 1.9393e-05f64.powi(2)).abs() < 1e-12);
        // Orientation variance at least σ_g² t.
        assert!(p[(0, 0)] >= 1.6968e-04f64.powi(2) * 0.99);
    }
}
