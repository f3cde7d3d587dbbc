//! Zero-velocity detection and update for standstills.
//!
//! A robot that stops gives the visual updates no parallax, and with nothing else
//! the filter drifts. Between two images the IMU readings of a robot at rest are
//! `ω_m = b_g + n_g` and `a_m = R_ItoGᵀ g + b_a + n_a`: a chi-square test of that
//! hypothesis on every reading (plus a bound on the estimated speed) detects the
//! standstill, and the same model, with `v = 0`, is then used as an EKF update.
//!
//! A real IMU on a vehicle at rest with its rotors or engine running vibrates
//! far beyond its datasheet noise (EuRoC V1_01 before take-off: the readings
//! scatter 10 to 480 times the datasheet variance), and fails that test. The
//! images then tell: tracks that have not moved over at least [`STILL_SPAN_S`]
//! (OpenVINS's disparity test, here against the newest clone that much older
//! than the image rather than against the last image, so that a slow drift
//! adds up and shows). The update then weighs the readings' mean by their own
//! scatter, and if even that mean is not rest (a vehicle rocking on its legs,
//! slower than the readings' span) it holds the velocity at zero alone: a
//! rendered EuRoC V1_01 from a static start otherwise drifted on the IMU for
//! 1.3 s before take-off and lost 0.6 deg of yaw there.
//!
//! A steady motion reads as rest to an IMU, and a standstill makes no clone
//! and runs no visual update, so a creep taken for one would stay one. Every
//! standstill therefore also needs the filter's velocity to agree with zero,
//! and one the IMU reads is refused when the tracks moved beyond pixel noise.

use super::chi2::Chi2Table;
use super::feature_db::FeatureDb;
use super::filter::Filter;
use super::options::EstimatorOptions;
use super::state::{Means, Var};
use common::measurement::{FeatureFrame, ImuSample};
use common::so3::skew;
use nalgebra::{DMatrix, DVector, Vector3};

/// Speed above which a standstill is not believed, m/s.
const MAX_SPEED_MPS: f64 = 0.1;
/// Standard deviation of the zero-velocity pseudo-measurement, m/s.
const VELOCITY_SIGMA_MPS: f64 = 0.01;
/// Fewest tracks shared with the reference clone for the images to tell a
/// standstill.
const MIN_DISPARITY_TRACKS: usize = 10;
/// The images' standstill is judged over at least this span, s: against the
/// newest clone this much older than the image. One frame apart, a creep or
/// a hover moves the tracks less than the threshold (3 cm/s at 3 m: 0.5 px
/// in 0.1 s); over 0.3 s it shows (1.4 px). A rendered walk that stands,
/// then creeps at 3 cm/s, with an IMU shaking 10x the filter's noise: 10 of
/// 95 creeping frames were taken for standstills one frame apart.
pub const STILL_SPAN_S: f64 = 0.3;

/// The `images` argument of [`try_update`] for `frame`: how its tracks moved
/// since the newest clone at least [`STILL_SPAN_S`] older (at a standstill no
/// clone is made, so it stays the last one before the robot stopped). The
/// reference is found now; the tracks are looked up only if asked.
pub fn image_motion<'a>(
    means: &Means,
    frame: &'a FeatureFrame,
    features: &'a FeatureDb,
) -> impl FnOnce() -> Option<TrackMotion> + 'a {
    let reference = means
        .clones
        .iter()
        .rev()
        .find(|(_, c)| c.t_cam <= frame.t - STILL_SPAN_S)
        .map(|(key, _)| *key);
    move || reference.and_then(|key| track_motion(frame, features, key))
}

/// How the tracks of an image moved since a reference clone measured them
/// (raw pixels).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct TrackMotion {
    /// Tracks measured at both.
    pub tracks: usize,
    /// Mean distance moved, px.
    pub mean_px: f64,
    /// Mean squared distance moved, px².
    pub mean_sq_px2: f64,
}

impl TrackMotion {
    /// Whether the tracks moved more than pixel noise `sigma_px` explains:
    /// between two measurements of a still point the difference has variance
    /// `2σ²` per axis, so `Σ‖Δuv‖² / 2σ²` is chi-square with `2n` degrees of
    /// freedom at a standstill.
    pub fn moved(&self, sigma_px: f64, chi2: &Chi2Table, multiplier: f64) -> bool {
        let d2 = self.tracks as f64 * self.mean_sq_px2 / (2.0 * sigma_px.powi(2));
        d2 > multiplier * chi2.get(2 * self.tracks)
    }
}

/// How the tracks of `frame` moved since the clone `reference` measured them,
/// or `None` if fewer than 10 tracks (`MIN_DISPARITY_TRACKS`) were measured
/// at both.
pub fn track_motion(
    frame: &FeatureFrame,
    features: &FeatureDb,
    reference: u64,
) -> Option<TrackMotion> {
    let (mut sum, mut sum_sq, mut n) = (0.0, 0.0, 0usize);
    for o in &frame.features {
        if let Some(m) = features.get(o.id).and_then(|f| f.measurement_at(reference)) {
            let d = (o.uv - m.uv).norm();
            sum += d;
            sum_sq += d * d;
            n += 1;
        }
    }
    (n >= MIN_DISPARITY_TRACKS).then(|| TrackMotion {
        tracks: n,
        mean_px: sum / n as f64,
        mean_sq_px2: sum_sq / n as f64,
    })
}

/// The zero-motion model `[ω_m − b_g; a_m − b_a − Rᵀ g]` has the same Jacobian
/// for every reading, so the stack of `N` readings is equivalent to their mean
/// with noise `R₀/N`, plus a scatter term that only enters the chi-square test:
/// `d² = r̄ᵀ (H P Hᵀ + R₀/N)⁻¹ r̄ + Σ_k (r_k − r̄)ᵀ R₀⁻¹ (r_k − r̄)`, with `6N` degrees
/// of freedom. Returns `(H, r̄ with the velocity row, R, scatter)`.
///
/// `own_scatter`: the mean's noise per axis is the larger of the datasheet's
/// and the readings' own sample variance (a vibrating vehicle at rest).
fn build(
    state: &Means,
    readings: &[ImuSample],
    opts: &EstimatorOptions,
    own_scatter: bool,
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
    // Per axis: gyro x, y, z, then accelerometer x, y, z.
    let mut var = [var_g, var_g, var_g, var_a, var_a, var_a];
    if own_scatter && readings.len() > 1 {
        let mut sample = [0.0; 6];
        for s in readings {
            let (rg, ra) = residual(s);
            for i in 0..3 {
                sample[i] += (rg[i] - mg[i]).powi(2) / (n - 1.0);
                sample[3 + i] += (ra[i] - ma[i]).powi(2) / (n - 1.0);
            }
        }
        for (v, s) in var.iter_mut().zip(sample) {
            *v = v.max(s);
        }
    }
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
    for (i, v) in var.iter().enumerate() {
        r[(i, i)] = v / n;
    }
    for i in 6..9 {
        r[(i, i)] = VELOCITY_SIGMA_MPS.powi(2);
    }
    (h, res, r, scatter)
}

/// Tests the standstill hypothesis on `readings` and, when it holds, applies the
/// zero-velocity update. `images`: how the image's tracks moved over at least
/// [`STILL_SPAN_S`] ([`track_motion`]), asked at most once and only for a
/// slow robot. A standstill is taken when the readings pass the IMU test and
/// the tracks did not move beyond pixel noise, or when the tracks moved less
/// than `zupt_max_disparity_px` and the readings agree with rest on average,
/// weighed by their own scatter. Either way the velocity the filter holds
/// must agree with zero. Returns whether the robot was found standing still.
pub fn try_update<F: Filter + ?Sized>(
    state: &mut F,
    readings: &[ImuSample],
    opts: &EstimatorOptions,
    chi2: &Chi2Table,
    images: impl FnOnce() -> Option<TrackMotion>,
) -> bool {
    if readings.len() < 2 || state.means().imu.vel.norm() > MAX_SPEED_MPS {
        return false;
    }
    let motion = images();
    let datasheet = build(state.means(), readings, opts, false);
    let still = match standstill_test(state, &datasheet, readings.len(), opts, chi2, false) {
        // The images, when they tell, must not have seen motion: once a
        // standstill is taken no clone is made and no visual update runs, so
        // a creep the IMU cannot feel would otherwise be held still for as
        // long as it lasts (the reference clone stays, and its span grows).
        Ok(update) => match motion {
            Some(m) if m.moved(opts.pixel_sigma_px, chi2, opts.chi2_multiplier) => {
                Err(Refusal::TracksMoved(m.mean_px))
            }
            _ => Ok(update),
        },
        Err(Refusal::Readings) => match motion {
            Some(m) if m.mean_px < opts.zupt_max_disparity_px => {
                let own = build(state.means(), readings, opts, true);
                match standstill_test(state, &own, readings.len(), opts, chi2, true) {
                    // Not rest even by their own scatter: a wobble slower
                    // than the readings' span (a vehicle rocking on its
                    // legs before take-off; the readings' mean is then not
                    // gravity). The images still say the camera stood: its
                    // velocity is what they tell, the readings nothing.
                    Err(Refusal::Readings) => velocity_only(state, &own, opts, chi2),
                    other => other,
                }
            }
            Some(m) => Err(Refusal::ReadingsAndTracks(m.mean_px)),
            None => Err(Refusal::ReadingsNoReference),
        },
        Err(e) => Err(e),
    };
    match still {
        Ok((h, res, r)) => {
            let ok = state.ekf_update(&[Var::Imu], &h, &res, &r).is_ok();
            // The gyro bias is what a wobble taken for rest would pull.
            let bg = state.means().imu.bias_gyro;
            tracing::debug!(t = state.means().t, ok, bias_gyro = ?bg.as_slice(), "standstill");
            ok
        }
        Err(why) => {
            // Why a robot that may be at rest is not taken for it: the first
            // thing to look at when a start drifts.
            tracing::debug!(t = state.means().t, ?why, "no standstill");
            false
        }
    }
}

/// A zero-velocity update: `(H, r, R)`.
type ZuptUpdate = (DMatrix<f64>, DVector<f64>, DMatrix<f64>);

/// What [`build`] gives: the update and the readings' scatter term.
type Built = (DMatrix<f64>, DVector<f64>, DMatrix<f64>, f64);

/// Why a frame was not taken for a standstill.
#[derive(Clone, Copy, Debug, PartialEq)]
enum Refusal {
    /// The readings do not agree with rest against the datasheet noise.
    Readings,
    /// ... and no clone old enough to tell the tracks' motion.
    ReadingsNoReference,
    /// ... and the tracks moved this many pixels on average.
    ReadingsAndTracks(f64),
    /// The readings agree with rest, the tracks moved (mean px).
    TracksMoved(f64),
    /// The velocity the filter holds does not agree with zero.
    Velocity,
    /// The test's covariance could not be inverted.
    Singular,
}

/// The zero-velocity update's `(H, r, R)` if the readings pass the standstill
/// test: every reading against the datasheet noise, or with `own_scatter`
/// their mean against the noise of [`build`] (the scatter then says nothing);
/// and, either way, the estimated velocity against zero. A steady motion
/// reads as rest to an IMU (a ground robot creeping straight at 5 cm/s: 177
/// of 190 creeping frames were taken for standstills without this test, and
/// the position ATE grew from 0.10 to 0.65 m), and to the images when slow
/// (a hover at 5 cm/s moves the tracks 3 m away by 0.4 px per frame): a
/// velocity the filter knows to be nonzero refuses it.
fn standstill_test<F: Filter + ?Sized>(
    state: &F,
    built: &Built,
    readings: usize,
    opts: &EstimatorOptions,
    chi2: &Chi2Table,
    own_scatter: bool,
) -> Result<ZuptUpdate, Refusal> {
    let (h, res, r, scatter) = built;
    // The IMU rows (0..6) and the velocity rows (6..9), each on its own.
    let rows = |first: usize, n: usize| {
        let d2 = state.mahalanobis(
            &[Var::Imu],
            &h.rows(first, n).into_owned(),
            &res.rows(first, n).into_owned(),
            &r.view((first, first), (n, n)).into_owned(),
        );
        d2.map_err(|_| Refusal::Singular)
    };
    let gate = |d2: f64, dof: usize| d2 <= opts.chi2_multiplier * chi2.get(dof);
    let imu_d2 = rows(0, 6)?;
    let readings_at_rest = if own_scatter {
        gate(imu_d2, 6)
    } else {
        gate(imu_d2 + scatter, 6 * readings)
    };
    if !readings_at_rest {
        return Err(Refusal::Readings);
    }
    if !gate(rows(6, 3)?, 3) {
        return Err(Refusal::Velocity);
    }
    Ok((h.clone(), res.clone(), r.clone()))
}

/// The zero-velocity rows of `built` alone, if the filter's velocity agrees
/// with zero.
fn velocity_only<F: Filter + ?Sized>(
    state: &F,
    built: &Built,
    opts: &EstimatorOptions,
    chi2: &Chi2Table,
) -> Result<ZuptUpdate, Refusal> {
    let (h, res, r, _) = built;
    let h = h.rows(6, 3).into_owned();
    let res = res.rows(6, 3).into_owned();
    let r = r.view((6, 6), (3, 3)).into_owned();
    let d2 = state
        .mahalanobis(&[Var::Imu], &h, &res, &r)
        .map_err(|_| Refusal::Singular)?;
    if d2 > opts.chi2_multiplier * chi2.get(3) {
        return Err(Refusal::Velocity);
    }
    Ok((h, res, r))
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::estimator::state::{ImuState, State};
    use common::calibration::CameraCalibration;

    /// 50 tracks that moved 0.1 px.
    const STILL: TrackMotion = TrackMotion {
        tracks: 50,
        mean_px: 0.1,
        mean_sq_px2: 0.01,
    };

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
            &chi2,
            || None
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
        assert!(!try_update(&mut s, &shaking, &opts, &chi2, || None));
        let mut moving = still_state(Vector3::new(1.0, 0.0, 0.0));
        assert!(!try_update(
            &mut moving,
            &readings(Vector3::new(0.0, 0.0, 9.81)),
            &opts,
            &chi2,
            || None
        ));
    }

    /// A robot creeping straight: its IMU reads rest, its tracks moved 2.5 px
    /// (rms) where 1 px noise explains 2.
    #[test]
    fn a_standstill_the_imu_reads_is_refused_when_the_tracks_moved() {
        let opts = EstimatorOptions::default();
        let chi2 = Chi2Table::new(0.95, 1000);
        let moved = TrackMotion {
            tracks: 50,
            mean_px: 2.2,
            mean_sq_px2: 6.25,
        };
        let at_rest = readings(Vector3::new(0.0, 0.0, 9.81));
        let mut s = still_state(Vector3::new(0.03, 0.0, 0.0));
        assert!(!try_update(&mut s, &at_rest, &opts, &chi2, || Some(moved)));
        assert_eq!(s.imu.vel.x, 0.03);
        assert!(try_update(&mut s, &at_rest, &opts, &chi2, || Some(STILL)));
    }

    #[test]
    fn tracks_moved_beyond_pixel_noise_are_told_from_noise() {
        let chi2 = Chi2Table::new(0.95, 1000);
        let with = |mean_sq_px2| TrackMotion {
            tracks: 50,
            mean_px: 0.0,
            mean_sq_px2,
        };
        // Two measurements of a still point, 1 px noise each: 4 px² expected
        // (2 px² per axis); the 95 % bound of 50 tracks is 4.97 px².
        assert!(!with(4.0).moved(1.0, &chi2, 1.0));
        assert!(!with(4.9).moved(1.0, &chi2, 1.0));
        assert!(with(5.1).moved(1.0, &chi2, 1.0));
        // The same motion under 2 px noise is noise.
        assert!(!with(5.1).moved(2.0, &chi2, 1.0));
    }

    /// A vehicle at rest with its rotors running: the readings scatter 20
    /// times the datasheet's deviation around rest. The IMU test refuses it;
    /// with the images still, the update pulls the velocity to zero.
    #[test]
    fn a_vibrating_robot_at_rest_is_taken_for_a_standstill_only_when_the_images_are_still() {
        let opts = EstimatorOptions::default();
        let chi2 = Chi2Table::new(0.95, 1000);
        let sd = opts.imu.accel_noise_density * (400f64).sqrt() * 20.0;
        let mut vibrating = readings(Vector3::new(0.0, 0.0, 9.81));
        for (k, r) in vibrating.iter_mut().enumerate() {
            let phase = k as f64 * 2.1;
            r.accel += Vector3::new(phase.sin(), phase.cos(), (1.3 * phase).sin()) * sd;
        }
        let mut s = still_state(Vector3::new(0.03, 0.0, 0.0));
        assert!(!try_update(&mut s, &vibrating, &opts, &chi2, || None));
        assert!(try_update(&mut s, &vibrating, &opts, &chi2, || Some(STILL)));
        assert!(s.imu.vel.norm() < 0.005, "{}", s.imu.vel);
        // Still images do not make a moving robot stand, even a slow one the
        // filter knows is moving (0.05 m/s, σ 0.01).
        let mut moving = still_state(Vector3::new(1.0, 0.0, 0.0));
        assert!(!try_update(&mut moving, &vibrating, &opts, &chi2, || Some(
            STILL
        )));
        let mut drifting = State::new(
            0.0,
            ImuState {
                vel: Vector3::new(0.05, 0.0, 0.0),
                ..ImuState::default()
            },
            DMatrix::identity(15, 15) * 1e-4,
            CameraCalibration::euroc_cam0(),
            &[],
        );
        assert!(!try_update(&mut drifting, &vibrating, &opts, &chi2, || {
            Some(STILL)
        }));
    }

    /// A vehicle rocking on its legs before take-off: for the span of one
    /// image its readings lean 0.3 m/s² one way, far from rest even by their
    /// own scatter. With the images still, only the velocity is pulled to
    /// zero: the lean says nothing of the tilt or the accelerometer bias.
    #[test]
    fn a_slow_wobble_at_rest_pulls_only_the_velocity() {
        let opts = EstimatorOptions::default();
        let chi2 = Chi2Table::new(0.95, 1000);
        let mut leaning = readings(Vector3::new(0.3, 0.0, 9.81));
        for (k, r) in leaning.iter_mut().enumerate() {
            r.accel.y += if k % 2 == 0 { 0.05 } else { -0.05 };
        }
        // A filter sure of its tilt and bias (1 mrad, 1 mm/s²): the lean is
        // not explained by them.
        let settled = || {
            let mut p = DMatrix::identity(15, 15) * 1e-6;
            p.view_mut((6, 6), (3, 3)).fill_diagonal(1e-3);
            State::new(
                0.0,
                ImuState {
                    vel: Vector3::new(0.03, 0.0, 0.0),
                    ..ImuState::default()
                },
                p,
                CameraCalibration::euroc_cam0(),
                &[],
            )
        };
        let mut s = settled();
        assert!(!try_update(&mut s, &leaning, &opts, &chi2, || None));
        assert!(try_update(&mut s, &leaning, &opts, &chi2, || Some(STILL)));
        assert!(s.imu.vel.norm() < 0.005, "{}", s.imu.vel);
        assert_eq!(s.imu.bias_accel, Vector3::zeros());
        assert_eq!(s.imu.rot, nalgebra::Matrix3::identity());
        // Tracks that moved beyond the threshold still refuse it.
        let moved = TrackMotion {
            tracks: 50,
            mean_px: 1.5,
            mean_sq_px2: 2.25,
        };
        let mut s = settled();
        assert!(!try_update(&mut s, &leaning, &opts, &chi2, || Some(moved)));
    }

    #[test]
    fn track_motion_is_the_pixel_motion_of_the_tracks_since_the_reference_clone() {
        use crate::estimator::feature_db::FeatureMeasurement;
        use common::measurement::FeatureObservation;
        use nalgebra::Vector2;
        let mut db = FeatureDb::new();
        let mut frame = FeatureFrame {
            t: 1.0,
            camera: 0,
            features: Vec::new(),
        };
        for id in 0..12u64 {
            let uv = Vector2::new(10.0 * id as f64, 50.0);
            // Tracks 0-11 measured at clone 7; track 11 also later, at 8.
            for key in [7, 8].into_iter().take(if id == 11 { 2 } else { 1 }) {
                db.insert(
                    id,
                    FeatureMeasurement {
                        clone_key: key,
                        t: key as f64,
                        uv,
                        uvn: Vector2::zeros(),
                    },
                )
                .unwrap();
            }
            frame.features.push(FeatureObservation {
                id,
                uv: uv + Vector2::new(0.3, 0.4),
                descriptor: Default::default(),
            });
        }
        // The 12 tracks measured at clone 7 moved 0.5 px each.
        let m = track_motion(&frame, &db, 7).unwrap();
        assert_eq!(m.tracks, 12);
        assert!((m.mean_px - 0.5).abs() < 1e-12, "{m:?}");
        assert!((m.mean_sq_px2 - 0.25).abs() < 1e-12, "{m:?}");
        // Against clone 8 only one track: too few to tell.
        assert_eq!(track_motion(&frame, &db, 8), None);
    }
}
