//! `sim-fleet simulate` and `sim-fleet eval` as a user runs them.

use integration_tests::{bin, read_json, write_loop_trajectory};
use std::process::Command;

#[test]
fn simulate_writes_measurements_ground_truth_and_a_summary_with_null_unknowns() {
    let dir = tempfile::tempdir().unwrap();
    write_loop_trajectory(&dir.path().join("loop.txt"), 30.0).unwrap();
    let scenario = dir.path().join("two.yaml");
    std::fs::write(
        &scenario,
        "name: two\nrobots:\n  - trajectory: loop.txt\n  - trajectory: loop.txt\n    start_time_s: 3.0\n",
    )
    .unwrap();
    let out = dir.path().join("out");
    let status = Command::new(bin("sim-fleet"))
        .args([
            "simulate",
            scenario.to_str().unwrap(),
            "--seed",
            "2",
            "--out",
            out.to_str().unwrap(),
        ])
        .status()
        .unwrap();
    assert!(status.success());
    for r in ["robot0", "robot1"] {
        assert!(out.join(r).join("measurements.mcap").is_file());
        assert!(out.join(r).join("groundtruth.txt").is_file());
    }
    let summary = read_json(&out.join("summary.json"));
    assert_eq!(summary["scenario"], "two");
    assert_eq!(summary["seed"], 2);
    for key in ["variant", "transport", "wall_s", "sim_s", "mean", "robots"] {
        assert!(summary.get(key).is_some(), "missing {key}");
    }
    let robot = &summary["robots"][1];
    for key in [
        "id",
        "trajectory",
        "ate_ori_deg",
        "ate_pos_m",
        "nees_ori",
        "nees_pos",
        "rpe",
        "frames",
        "ms_per_frame_mean",
        "ms_per_frame_p95",
        "bytes_sent",
        "bytes_received",
        "loop_closures",
        "common_feature_updates",
    ] {
        assert!(robot.get(key).is_some(), "robot summary misses {key}");
    }
    assert!(
        robot["ate_pos_m"].is_null(),
        "no estimator yet: ATE must be null"
    );
    assert!(robot["frames"].as_u64().unwrap() > 200);

    // The ground truth evaluated against itself: zero error, JSON keys present.
    let gt = out.join("robot0").join("groundtruth.txt");
    let output = Command::new(bin("sim-fleet"))
        .args([
            "eval",
            "--gt",
            gt.to_str().unwrap(),
            "--est",
            gt.to_str().unwrap(),
            "--json",
            "--no-plots",
        ])
        .output()
        .unwrap();
    assert!(
        output.status.success(),
        "{}",
        String::from_utf8_lossy(&output.stderr)
    );
    let report: serde_json::Value = serde_json::from_slice(&output.stdout).unwrap();
    assert!(report["ate_pos_m"].as_f64().unwrap() < 1e-9);
    assert!(report["nees_ori"].is_null());
    assert!(report["rpe"].is_array());
}

#[test]
fn eval_scores_a_runs_velocity_and_biases_and_plots_their_errors() {
    let dir = tempfile::tempdir().unwrap();
    write_loop_trajectory(&dir.path().join("loop.txt"), 20.0).unwrap();
    let scenario = dir.path().join("loop.yaml");
    std::fs::write(&scenario, "name: loop\nrobots:\n  - trajectory: loop.txt\n").unwrap();
    let out = dir.path().join("run");
    let status = Command::new(bin("agent"))
        .arg("run")
        .arg("--scenario")
        .arg(&scenario)
        .arg("--out")
        .arg(&out)
        .output()
        .unwrap();
    assert!(status.status.success(), "{status:?}");
    let plots = dir.path().join("plots");
    let output = Command::new(bin("sim-fleet"))
        .arg("eval")
        .arg("--gt")
        .arg(out.join("groundtruth.txt"))
        .arg("--est")
        .arg(out.join("estimate.txt"))
        .arg("--cov")
        .arg(out.join("covariance.txt"))
        .arg("--imu-state")
        .arg(out.join("imu_state.txt"))
        .arg("--plots-dir")
        .arg(&plots)
        .arg("--json")
        .output()
        .unwrap();
    assert!(
        output.status.success(),
        "{}",
        String::from_utf8_lossy(&output.stderr)
    );
    let report: serde_json::Value = serde_json::from_slice(&output.stdout).unwrap();
    let imu = &report["imu_state"];
    assert!(imu["records"].as_u64().unwrap_or(0) > 100, "{imu}");
    let vel = imu["vel_rmse_mps"].as_f64().unwrap();
    assert!(vel > 0.0 && vel < 0.1, "{imu}");
    for key in ["nees_vel", "nees_bias_gyro", "nees_bias_accel"] {
        let nees = imu[key].as_f64().unwrap();
        assert!(nees > 0.1 && nees < 20.0, "{key}: {imu}");
    }
    for file in [
        "error_vel.svg",
        "error_bias_gyro.svg",
        "error_bias_accel.svg",
    ] {
        assert!(plots.join(file).is_file(), "{file}");
    }
}

#[test]
fn a_scenario_with_an_unknown_key_fails_with_a_message_naming_it() {
    let dir = tempfile::tempdir().unwrap();
    write_loop_trajectory(&dir.path().join("loop.txt"), 10.0).unwrap();
    let scenario = dir.path().join("bad.yaml");
    std::fs::write(
        &scenario,
        "name: bad\nrobots:\n  - trajectory: loop.txt\n    speed: 3\n",
    )
    .unwrap();
    let output = Command::new(bin("sim-fleet"))
        .args([
            "simulate",
            scenario.to_str().unwrap(),
            "--out",
            dir.path().join("o").to_str().unwrap(),
        ])
        .output()
        .unwrap();
    assert!(!output.status.success());
    let err = String::from_utf8_lossy(&output.stderr);
    assert!(err.contains("unknown field `speed`"), "{err}");
}

#[test]
fn agent_prints_its_version_and_help() {
    let out = Command::new(bin("agent"))
        .arg("--version")
        .output()
        .unwrap();
    assert!(out.status.success());
    assert!(String::from_utf8_lossy(&out.stdout).starts_with("agent "));
    let out = Command::new(bin("agent")).arg("--help").output().unwrap();
    assert!(out.status.success());
}
