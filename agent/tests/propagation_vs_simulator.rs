//! IMU propagation of the estimator's mean against the noise-free simulator: with
//! perfect IMU readings, integrating from the true state must follow the truth.

#![allow(clippy::expect_used)]

use agent::estimator::options::ImuNoise;
use agent::estimator::propagator::propagate;
use agent::estimator::state::{ImuState, State};
use common::calibration::CameraCalibration;
use common::measurement::ImuSample;
use common::so3::log_so3;
use nalgebra::{DMatrix, Vector3};
use simulator::{Fleet, Scenario, SimEvent};

#[test]
fn propagation_of_noise_free_imu_follows_the_simulated_truth() {
    let dir = tempfile::tempdir().expect("tempdir");
    let traj = concat!(
        env!("CARGO_MANIFEST_DIR"),
        "/../../shared/data/trajectories/V1_02_medium.txt"
    );
    let path = dir.path().join("clean.yaml");
    std::fs::write(
        &path,
        format!(
            "name: clean\nrobots:\n  - trajectory: {traj}\nsensors:\n  imu:\n    gyro_noise_density: 0.0\n    gyro_random_walk: 0.0\n    accel_noise_density: 0.0\n    accel_random_walk: 0.0\n"
        ),
    )
    .expect("scenario");
    let scenario = Scenario::load(&path).expect("load");
    let fleet = Fleet::build(&scenario, 1).expect("fleet");
    let imu: Vec<ImuSample> = fleet
        .stream(0)
        .expect("stream")
        .filter_map(|e| match e {
            SimEvent::Imu(s) => Some(s),
            SimEvent::Camera(_) => None,
        })
        .collect();
    let truth = &fleet.truths[0];
    // Start in the middle of the (aggressive) V1_02 flight.
    let t0 = imu[imu.len() / 3].t;
    let s0 = truth.state(t0).expect("truth");
    let mut state = State::new(
        t0,
        ImuState {
            rot: s0.rot,
            pos: s0.pos,
            vel: s0.vel,
            bias_gyro: Vector3::zeros(),
            bias_accel: Vector3::zeros(),
        },
        DMatrix::identity(15, 15) * 1e-6,
        CameraCalibration::euroc_cam0(),
        &[],
    );
    // Propagate frame by frame (10 Hz) for 10 s, as the filter does.
    let noise = ImuNoise::default();
    let mut worst = (0.0f64, 0.0f64);
    for k in 1..=100 {
        let t = t0 + 0.1 * k as f64;
        propagate(&mut state, &imu, t, &noise, true).expect("propagate");
        let s = truth.state(t).expect("truth");
        let dp = (state.imu.pos - s.pos).norm();
        let dr = log_so3(&(state.imu.rot.transpose() * s.rot)).norm();
        worst = (worst.0.max(dp), worst.1.max(dr));
    }
    println!(
        "after 10 s: worst position error {:.2e} m, rotation {:.2e} rad",
        worst.0, worst.1
    );
    assert!(worst.0 < 0.01, "position error {} m", worst.0);
    assert!(worst.1 < 1e-3, "rotation error {} rad", worst.1);
}
