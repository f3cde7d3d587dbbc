//! The estimator starts from the real EuRoC V1_01 IMU with its static initializer
//! (the vehicle stands still for the first seconds) and gets roll and pitch right.

#![allow(clippy::expect_used)]

use agent::estimator::static_init::{read_euroc_imu_csv, static_start_sigmas, StaticInitOptions};
use agent::estimator::{Estimator, EstimatorOptions};
use common::calibration::CameraCalibration;
use common::trajectory::{interpolate_pose, read_euroc_csv};
use nalgebra::Vector3;

fn data(rel: &str) -> String {
    format!("{}/../../shared/data/{rel}", env!("CARGO_MANIFEST_DIR"))
}

#[test]
fn static_initialization_on_real_euroc_imu_recovers_roll_and_pitch_within_one_degree() {
    let imu = read_euroc_imu_csv(data("euroc_v1_01_micro/mav0/imu0/data.csv")).expect("imu");
    let gt = read_euroc_csv(data("trajectories/V1_01_easy.csv")).expect("gt");
    let mut est = Estimator::new(EstimatorOptions::default(), CameraCalibration::euroc_cam0());
    // Everything up to 4.5 s after the first image, while the vehicle stands.
    let t_end = 1403715273.262 + 4.5;
    for s in imu.iter().filter(|s| s.t <= t_end) {
        est.feed_imu(*s).expect("valid sample");
    }
    // The sigmas `agent run --dataset` starts a static run with.
    let sigmas = static_start_sigmas();
    let res = est
        .initialize_static(&StaticInitOptions::default(), &sigmas)
        .expect("standing still");
    let state = est.state().expect("initialized");
    assert_eq!(state.t, res.t);
    let truth = interpolate_pose(&gt, res.t).expect("gt covers the time");
    // Tilt error: angle between the estimated and true "up" in the IMU frame.
    let up_est = state.imu.rot.transpose() * Vector3::z();
    let up_gt = truth.rot.transpose() * Vector3::z();
    let tilt_deg = up_est.angle(&up_gt).to_degrees();
    println!(
        "tilt error {tilt_deg:.3} deg, gyro bias {:?}",
        res.bias_gyro
    );
    assert!(tilt_deg < 1.0, "tilt error {tilt_deg} deg");
    // The gyro bias starts with the window's standard error, not the
    // configured 0.02 rad/s (IMU error state: bias_gyro at 9..12).
    let var_bg = state.cov()[(9, 9)];
    let expected = res.bias_gyro_sigma.min(sigmas.sigma_bias_gyro);
    assert!(
        (var_bg.sqrt() - expected).abs() < 1e-12,
        "{var_bg} {expected}"
    );
    assert!(res.bias_gyro_sigma < 0.005, "{}", res.bias_gyro_sigma);
}

/// A noise-free IMU at rest (a synthetic test's) would claim the gyro bias
/// exactly: the prior stays at the gyro's white noise over the window.
#[test]
fn a_noise_free_static_start_keeps_the_gyro_bias_uncertain_by_the_white_noise() {
    let opts = EstimatorOptions::default();
    let floor = opts.imu.gyro_noise_density / StaticInitOptions::default().window_s.sqrt();
    let mut est = Estimator::new(opts, CameraCalibration::euroc_cam0());
    for k in 0..1200 {
        est.feed_imu(common::measurement::ImuSample {
            t: k as f64 / 400.0,
            gyro: Vector3::new(0.001, 0.0, 0.0),
            accel: Vector3::new(0.0, 0.0, 9.81),
        })
        .expect("valid sample");
    }
    let res = est
        .initialize_static(&StaticInitOptions::default(), &static_start_sigmas())
        .expect("standing still");
    assert_eq!(res.bias_gyro_sigma, 0.0);
    let state = est.state().expect("initialized");
    for i in 9..12 {
        assert!((state.cov()[(i, i)].sqrt() - floor).abs() < 1e-15);
    }
}

/// Placed in the motion capture's frame with the true heading and position
/// (as a fleet places a robot it set down on a surveyed spot), the whole
/// orientation is right to the tilt error, and the position is the given one.
#[test]
fn a_static_start_placed_with_the_true_heading_and_position_is_the_true_pose() {
    let imu = read_euroc_imu_csv(data("euroc_v1_01_micro/mav0/imu0/data.csv")).expect("imu");
    let gt = read_euroc_csv(data("trajectories/V1_01_easy.csv")).expect("gt");
    let mut est = Estimator::new(EstimatorOptions::default(), CameraCalibration::euroc_cam0());
    let t_end = 1403715273.262 + 4.5;
    for s in imu.iter().filter(|s| s.t <= t_end) {
        est.feed_imu(*s).expect("valid sample");
    }
    let truth = interpolate_pose(&gt, t_end).expect("gt covers the time");
    // The heading of the IMU's y axis in the truth's frame: EuRoC's IMU has
    // x up (its heading would turn by the tilt error / cos(67 deg)), y level.
    let yaw = truth.rot[(1, 1)].atan2(truth.rot[(0, 1)]);
    let res = est
        .initialize_static_at(
            &StaticInitOptions::default(),
            &static_start_sigmas(),
            &Vector3::y(),
            yaw,
            truth.pos,
        )
        .expect("standing still");
    let state = est.state().expect("initialized");
    let truth = interpolate_pose(&gt, res.t).expect("gt covers the time");
    let err = nalgebra::Rotation3::from_matrix_unchecked(truth.rot.transpose() * state.imu.rot)
        .angle()
        .to_degrees();
    println!(
        "whole orientation error {err:.3} deg at yaw {:.1} deg",
        yaw.to_degrees()
    );
    assert!(err < 1.0, "orientation error {err} deg");
    assert!((state.imu.pos - truth.pos).norm() < 1e-3);
}
