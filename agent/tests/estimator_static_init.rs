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
}
