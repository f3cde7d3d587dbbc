//! Hybrid run: the whole V1_01 flight's real IMU with camera frames simulated
//! from its ground truth. Real noise, biases and rotor vibration meet a filter
//! tuned with the datasheet noise: it must stay on track (ATE and NEES are
//! printed for the record; the NEES shows how far real data is from the model).

#![allow(clippy::expect_used, clippy::unwrap_used)]

use agent::hybrid::{read_euroc_biases, run_robot_hybrid};
use agent::runner::{options_for, Variant};
use simulator::{Fleet, Scenario};
use std::path::PathBuf;

fn root() -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("..")
}

#[test]
fn real_v1_01_imu_with_simulated_camera_stays_on_the_flight() {
    let sc =
        Scenario::load(&root().join("sim-fleet/scenarios/v1_01_hybrid.yaml")).expect("scenario");
    let fleet = Fleet::build(&sc, 1).expect("fleet");
    let opts = options_for(&sc.estimator, &fleet, 0, Variant::IndpSlam);
    let imu = root().join("../shared/data/euroc_v1_01_micro/mav0/imu0/data.csv");
    let gt = sc.trajectory_path(0).unwrap();
    let run = run_robot_hybrid(&fleet, 0, opts, &imu, Some(&gt)).expect("hybrid run");
    let m = run.metrics();
    println!(
        "hybrid V1_01 seed 1: ATE {:.3} deg / {:.3} m, NEES ori {:.2} pos {:.2}, {} frames",
        m.ate_ori_deg.unwrap(),
        m.ate_pos_m.unwrap(),
        m.nees_ori.unwrap(),
        m.nees_pos.unwrap(),
        m.frames.unwrap()
    );
    assert!(m.frames.unwrap() > 1200, "the whole flight: {m:?}");
    assert!(m.ate_pos_m.unwrap() < 0.5, "{m:?}");
    assert!(m.ate_ori_deg.unwrap() < 3.0, "{m:?}");
}

#[test]
fn bias_columns_of_the_euroc_ground_truth_are_read() {
    let b = read_euroc_biases(&root().join("../shared/data/trajectories/V1_01_easy.csv"))
        .expect("biases");
    assert_eq!(b.len(), 2895);
    assert!((b[0].1.gyro.z - 0.0770299).abs() < 1e-9);
    assert!((b[0].1.accel.x + 0.0180115).abs() < 1e-9);
    // A TUM file has no bias columns.
    assert!(
        read_euroc_biases(&root().join("../shared/data/trajectories/V1_01_easy.txt"))
            .expect("tum")
            .is_empty()
    );
}

#[test]
fn feature_level_runs_refuse_a_scenario_that_renders_images() {
    let mut sc =
        Scenario::load(&root().join("sim-fleet/scenarios/v1_01_easy.yaml")).expect("scenario");
    sc.render.enabled = true;
    let fleet = Fleet::build(&sc, 1).expect("fleet");
    let opts = options_for(&sc.estimator, &fleet, 0, Variant::Indp);
    let err = agent::runner::run_robot(&fleet, 0, opts)
        .unwrap_err()
        .to_string();
    assert!(err.contains("image frontend"), "{err}");
}
