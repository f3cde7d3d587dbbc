//! Tests of the whole simulator on a small synthetic scenario written to a temp dir.

use crate::fleet::{Fleet, SimEvent};
use crate::scenario::{Scenario, ScenarioError};
use common::so3::exp_so3;
use common::trajectory::{write_tum, StampedPose};
use nalgebra::{Vector2, Vector3};
use std::collections::HashSet;
use std::path::Path;

/// A 30 s loop at walking speed with varying attitude, TUM format, 20 Hz.
fn write_loop(path: &Path, duration: f64) {
    let poses: Vec<StampedPose> = (0..=(duration * 20.0) as usize)
        .map(|k| {
            let t = 1000.0 + k as f64 / 20.0;
            let s = t - 1000.0;
            StampedPose {
                t,
                pos: Vector3::new(
                    3.0 * (0.25 * s).cos(),
                    3.0 * (0.25 * s).sin(),
                    1.0 + 0.2 * (0.5 * s).sin(),
                ),
                rot: exp_so3(&Vector3::new(
                    0.1 * (0.3 * s).sin(),
                    0.1 * (0.2 * s).cos(),
                    0.25 * s + 1.57,
                )),
            }
        })
        .collect();
    write_tum(path, &poses).unwrap();
}

fn scenario(dir: &Path, extra: &str) -> Scenario {
    write_loop(&dir.join("loop.txt"), 30.0);
    let text = format!(
        "name: loop\nseed: 7\nrobots:\n  - trajectory: loop.txt\n  - trajectory: loop.txt\n    start_time_s: 5.0\n{extra}"
    );
    let path = dir.join("scenario.yaml");
    std::fs::write(&path, text).unwrap();
    Scenario::load(&path).unwrap()
}

fn collect(fleet: &Fleet, robot: usize) -> Vec<String> {
    fleet
        .stream(robot)
        .unwrap()
        .map(|e| format!("{e:?}"))
        .collect()
}

#[test]
fn a_robot_stream_is_a_pure_function_of_scenario_robot_and_seed() {
    let dir = tempfile::tempdir().unwrap();
    let sc = scenario(dir.path(), "");
    let a = Fleet::build(&sc, 3).unwrap();
    let b = Fleet::build(&sc, 3).unwrap();
    let stream_a = collect(&a, 1);
    // Consuming robot 0 first does not change robot 1.
    let _ = collect(&b, 0);
    assert_eq!(stream_a, collect(&b, 1));
    assert_eq!(a.initial_calibration(1), b.initial_calibration(1));
    let c = Fleet::build(&sc, 4).unwrap();
    assert_ne!(stream_a, collect(&c, 1));
}

#[test]
fn robots_on_the_same_path_see_the_same_landmarks() {
    let dir = tempfile::tempdir().unwrap();
    let fleet = Fleet::build(&scenario(dir.path(), ""), 1).unwrap();
    let seen = |r: usize| -> HashSet<u64> {
        fleet
            .stream(r)
            .unwrap()
            .filter_map(|e| match e {
                SimEvent::Camera(c) => Some(c.landmark_ids),
                SimEvent::Imu(_) => None,
            })
            .flatten()
            .collect()
    };
    let (a, b) = (seen(0), seen(1));
    let shared = a.intersection(&b).count();
    assert!(
        shared as f64 > 0.8 * b.len() as f64,
        "{shared} of {}",
        b.len()
    );
}

#[test]
fn features_are_noisy_projections_of_their_landmarks_within_the_image() {
    let dir = tempfile::tempdir().unwrap();
    let fleet = Fleet::build(&scenario(dir.path(), ""), 2).unwrap();
    let calib = &fleet.true_calibrations[0];
    let (mut sum2, mut n, mut frames) = (0.0, 0usize, 0usize);
    for ev in fleet.stream(0).unwrap() {
        let SimEvent::Camera(c) = ev else { continue };
        frames += 1;
        assert!(c.frame.features.len() <= 100);
        assert!(
            c.frame.features.len() >= 60,
            "only {} features",
            c.frame.features.len()
        );
        let ids: Vec<u64> = c.frame.features.iter().map(|f| f.id).collect();
        assert_eq!(
            ids.iter().collect::<HashSet<_>>().len(),
            ids.len(),
            "duplicate track ids"
        );
        let t_c_to_g = common::so3::Se3::new(c.truth.rot, c.truth.pos).compose(&calib.t_c_to_i());
        for (f, lm) in c.frame.features.iter().zip(&c.landmark_ids) {
            let p_c = t_c_to_g
                .inverse()
                .transform_point(&fleet.world.landmarks[*lm as usize].p_in_g);
            assert!(p_c.z > 0.1 && p_c.z <= 7.0);
            let uv = calib.camera.project(&p_c).unwrap();
            let e: Vector2<f64> = f.uv - uv;
            sum2 += e.norm_squared();
            n += 2;
        }
    }
    assert!(frames > 250);
    let sigma = (sum2 / n as f64).sqrt();
    assert!((sigma - 1.0).abs() < 0.03, "pixel noise sigma {sigma}");
}

#[test]
fn imu_noise_matches_the_configured_densities() {
    let dir = tempfile::tempdir().unwrap();
    let sc = scenario(
        dir.path(),
        "sensors:\n  imu:\n    gyro_random_walk: 0.0\n    accel_random_walk: 0.0\n",
    );
    let fleet = Fleet::build(&sc, 5).unwrap();
    let truth = &fleet.truths[0];
    let g = Vector3::new(0.0, 0.0, 9.81);
    let (mut sg, mut sa, mut n) = (0.0, 0.0, 0.0);
    for ev in fleet.stream(0).unwrap() {
        let SimEvent::Imu(s) = ev else { continue };
        let st = truth.state(s.t).unwrap();
        sg += (s.gyro - st.omega).norm_squared();
        sa += (s.accel - st.rot.transpose() * (st.acc + g)).norm_squared();
        n += 3.0;
    }
    let sqrt_rate = 400f64.sqrt();
    let (gyro, accel) = ((sg / n).sqrt() / sqrt_rate, (sa / n).sqrt() / sqrt_rate);
    assert!(
        (gyro / 1.6968e-04 - 1.0).abs() < 0.02,
        "gyro density {gyro}"
    );
    assert!((accel / 2.0e-3 - 1.0).abs() < 0.02, "accel density {accel}");
}

#[test]
fn track_ids_persist_while_a_landmark_stays_in_view() {
    let dir = tempfile::tempdir().unwrap();
    let fleet = Fleet::build(&scenario(dir.path(), ""), 1).unwrap();
    let mut last: std::collections::HashMap<u64, u64> = Default::default();
    let mut continued = 0usize;
    for ev in fleet.stream(0).unwrap() {
        let SimEvent::Camera(c) = ev else { continue };
        let mut now = std::collections::HashMap::new();
        for (f, lm) in c.frame.features.iter().zip(&c.landmark_ids) {
            if let Some(&id) = last.get(lm) {
                assert_eq!(id, f.id, "a continuing track changed id");
                continued += 1;
            }
            now.insert(*lm, f.id);
        }
        last = now;
    }
    assert!(continued > 10_000);
}

#[test]
fn injected_outliers_are_marked_and_move_the_pixel() {
    let dir = tempfile::tempdir().unwrap();
    let sc = scenario(
        dir.path(),
        "world:\n  outlier_pixel_prob: 0.1\n  outlier_descriptor_prob: 0.05\n",
    );
    let fleet = Fleet::build(&sc, 1).unwrap();
    let (mut outliers, mut total) = (0usize, 0usize);
    for ev in fleet.stream(0).unwrap() {
        let SimEvent::Camera(c) = ev else { continue };
        total += c.outlier.len();
        outliers += c.outlier.iter().filter(|o| **o).count();
    }
    let rate = outliers as f64 / total as f64;
    assert!((rate - 0.145).abs() < 0.02, "outlier rate {rate}");
}

#[test]
fn unknown_keys_and_missing_files_are_clear_errors() {
    let dir = tempfile::tempdir().unwrap();
    let _ = scenario(dir.path(), "");
    let bad = dir.path().join("bad.yaml");
    std::fs::write(
        &bad,
        "name: x\nrobots:\n  - trajectory: loop.txt\nsensor: {}\n",
    )
    .unwrap();
    let e = Scenario::load(&bad).unwrap_err();
    assert!(matches!(e, ScenarioError::Parse { .. }));
    assert!(e.to_string().contains("unknown field `sensor`"), "{e}");
    std::fs::write(&bad, "name: x\nrobots:\n  - trajectory: nowhere.txt\n").unwrap();
    let e = Scenario::load(&bad).unwrap_err();
    assert!(matches!(e, ScenarioError::MissingTrajectory { .. }), "{e}");
    assert!(e.to_string().contains("nowhere.txt"));
}

#[test]
fn perturbed_calibration_differs_from_the_truth_by_the_configured_spread() {
    let dir = tempfile::tempdir().unwrap();
    let fleet = Fleet::build(&scenario(dir.path(), ""), 1).unwrap();
    let truth = &fleet.true_calibrations[0];
    let mut s2 = 0.0;
    for r in 0..2 {
        for seed in 0..200 {
            let f = Fleet {
                seed,
                ..fleet.clone()
            };
            let c = f.initial_calibration(r);
            s2 += (c.camera.intrinsics - truth.camera.intrinsics).norm_squared();
        }
    }
    let sigma = (s2 / (2.0 * 200.0 * 4.0)).sqrt();
    assert!(
        (sigma - 1.0).abs() < 0.1,
        "intrinsics perturbation sigma {sigma}"
    );
}

#[test]
fn a_sampled_start_error_has_the_prior_spread_and_the_default_is_none() {
    let dir = tempfile::tempdir().unwrap();
    let fleet = Fleet::build(&scenario(dir.path(), ""), 1).unwrap();
    assert_eq!(fleet.start_error(0), crate::perturb::StartError::default());
    let sampled = scenario(
        dir.path(),
        "estimator: {initial_error: sampled, init_sigma_ori_rad: 0.02, init_sigma_pos_m: 0.3}\n",
    );
    let fleet = Fleet::build(&sampled, 1).unwrap();
    // Its own stream: a pure function of (seed, robot), different per robot.
    assert_eq!(fleet.start_error(1), fleet.start_error(1));
    assert_ne!(fleet.start_error(0), fleet.start_error(1));
    let (mut s_rot, mut s_pos, mut n) = (0.0, 0.0, 0.0);
    for seed in 0..300 {
        let f = Fleet {
            seed,
            ..fleet.clone()
        };
        for r in 0..2 {
            let e = f.start_error(r);
            s_rot += e.rot.norm_squared();
            s_pos += e.pos.norm_squared();
            n += 3.0;
        }
    }
    let (sigma_rot, sigma_pos) = ((s_rot / n).sqrt(), (s_pos / n).sqrt());
    assert!(
        (sigma_rot / 0.02 - 1.0).abs() < 0.08,
        "orientation {sigma_rot}"
    );
    assert!((sigma_pos / 0.3 - 1.0).abs() < 0.08, "position {sigma_pos}");
}

#[test]
fn measurements_survive_an_mcap_round_trip() {
    let dir = tempfile::tempdir().unwrap();
    let fleet = Fleet::build(&scenario(dir.path(), ""), 1).unwrap();
    let path = dir.path().join("r0.mcap");
    let events: Vec<SimEvent> = fleet.stream(0).unwrap().take(3000).collect();
    let n = crate::mcap_io::write_stream(&path, events.clone()).unwrap();
    let back = crate::mcap_io::read_stream(&path).unwrap();
    assert_eq!(back.len(), events.len());
    let frames = events
        .iter()
        .filter(|e| matches!(e, SimEvent::Camera(_)))
        .count();
    assert_eq!(n as usize, events.len() + frames);
    for (a, b) in events.iter().zip(&back) {
        match (a, b) {
            (SimEvent::Imu(x), SimEvent::Imu(y)) => assert_eq!(x, y),
            (SimEvent::Camera(x), SimEvent::Camera(y)) => {
                assert_eq!(x.frame, y.frame);
                assert_eq!(x.landmark_ids, y.landmark_ids);
                assert!((x.truth.pos - y.truth.pos).norm() < 1e-12);
                assert!((x.truth.rot - y.truth.rot).norm() < 1e-12);
            }
            _ => panic!("event kinds differ"),
        }
    }
}

#[test]
fn a_truncated_mcap_file_is_an_error_not_a_panic() {
    let dir = tempfile::tempdir().unwrap();
    let fleet = Fleet::build(&scenario(dir.path(), ""), 1).unwrap();
    let path = dir.path().join("r0.mcap");
    crate::mcap_io::write_stream(&path, fleet.stream(0).unwrap().take(500)).unwrap();
    let bytes = std::fs::read(&path).unwrap();
    std::fs::write(&path, &bytes[..bytes.len() / 2]).unwrap();
    assert!(crate::mcap_io::read_stream(&path).is_err());
}

#[test]
fn every_example_scenario_loads() {
    fn visit(dir: &Path, found: &mut Vec<std::path::PathBuf>) {
        for entry in std::fs::read_dir(dir).unwrap() {
            let p = entry.unwrap().path();
            if p.is_dir() {
                visit(&p, found);
            } else if p.extension().is_some_and(|e| e == "yaml") {
                found.push(p);
            }
        }
    }
    let mut found = Vec::new();
    visit(
        &Path::new(env!("CARGO_MANIFEST_DIR")).join("../scenarios"),
        &mut found,
    );
    assert!(found.len() >= 6);
    for p in found {
        Scenario::load(&p).unwrap_or_else(|e| panic!("{}: {e}", p.display()));
    }
}

#[test]
fn a_noise_free_camera_needs_the_filter_pixel_sigma_set_explicitly() {
    let dir = tempfile::tempdir().unwrap();
    let _ = scenario(dir.path(), "");
    let bad = dir.path().join("noise_free.yaml");
    let base = "name: x\nrobots:\n  - trajectory: loop.txt\nsensors:\n  camera:\n    pixel_noise_px: 0.0\n";
    std::fs::write(&bad, base).unwrap();
    let e = Scenario::load(&bad).unwrap_err();
    assert!(matches!(e, ScenarioError::Invalid { .. }), "{e}");
    assert!(e.to_string().contains("estimator.pixel_sigma_px"), "{e}");
    std::fs::write(&bad, format!("{base}estimator:\n  pixel_sigma_px: 1.0\n")).unwrap();
    let s = Scenario::load(&bad).unwrap();
    assert_eq!(s.estimator.filter_pixel_sigma_px(0.0), 1.0);
    std::fs::write(&bad, base.replace("0.0", "-1.0")).unwrap();
    let e = Scenario::load(&bad).unwrap_err();
    assert!(
        e.to_string().contains("pixel_noise_px must be at least 0"),
        "{e}"
    );
}

#[test]
fn estimator_settings_that_cannot_run_are_named_at_load() {
    let dir = tempfile::tempdir().unwrap();
    let _ = scenario(dir.path(), "");
    let bad = dir.path().join("bad_estimator.yaml");
    let load = |estimator: &str| {
        std::fs::write(
            &bad,
            format!("name: x\nrobots:\n  - trajectory: loop.txt\nestimator: {estimator}\n"),
        )
        .unwrap();
        Scenario::load(&bad).map(|_| ()).map_err(|e| e.to_string())
    };
    assert!(load("{}").is_ok());
    assert!(load("{ init_sigma_ori_rad: 0.0 }").is_ok());
    let e = load("{ max_clones: 0 }").unwrap_err();
    assert!(e.contains("estimator.max_clones"), "{e}");
    let e = load("{ init_sigma_pos_m: -0.05 }").unwrap_err();
    assert!(e.contains("estimator.init_sigma_pos_m"), "{e}");
    let e = load("{ slam_delay_s: .nan }").unwrap_err();
    assert!(e.contains("estimator.slam_delay_s"), "{e}");
    let e = load("{ min_clones_to_update: 0 }").unwrap_err();
    assert!(e.contains("min_clones_to_update"), "{e}");
    let e = load("{ cooperation: { ci_peer_weight: 0.0 } }").unwrap_err();
    assert!(e.contains("estimator.cooperation.ci_peer_weight"), "{e}");
    let e = load("{ cooperation: { constraint_sigma_m: 0.0 } }").unwrap_err();
    assert!(
        e.contains("estimator.cooperation.constraint_sigma_m"),
        "{e}"
    );
}

#[test]
fn a_robot_flying_laps_retraces_its_path_continuously() {
    let dir = tempfile::tempdir().unwrap();
    let one = Fleet::build(&scenario(dir.path(), ""), 1).unwrap();
    let text = "name: loop\nseed: 7\nrobots:\n  - trajectory: loop.txt\n    laps: 3\n";
    let path = dir.path().join("laps.yaml");
    std::fs::write(&path, text).unwrap();
    let three = Fleet::build(&Scenario::load(&path).unwrap(), 1).unwrap();
    let (a, b) = (&one.truths[0], &three.truths[0]);
    let lap = a.end_time() - a.start_time();
    assert!((b.start_time() - a.start_time()).abs() < 1e-9);
    let laps3 = b.end_time() - b.start_time();
    assert!((laps3 - 3.0 * lap).abs() < 0.5, "{laps3} for laps of {lap}");
    // The robot stops at the turn (the recording's end) and flies back: a
    // second later it is where it was a second before the turn.
    let at = |t: &crate::truth::RobotTruth, s: f64| t.state(s).unwrap().pos;
    let turn = (0..=400)
        .map(|k| a.end_time() - 1.0 + 0.005 * f64::from(k))
        .min_by(|x, y| {
            let v = |s: f64| b.state(s).unwrap().vel.norm();
            v(*x).total_cmp(&v(*y))
        })
        .unwrap();
    assert!(b.state(turn).unwrap().vel.norm() < 0.05);
    let mid = a.start_time() + 0.5 * lap;
    assert!((at(b, 2.0 * turn - mid) - at(a, mid)).norm() < 0.02);
    assert!((at(b, turn + 1.0) - at(a, turn - 1.0)).norm() < 0.02);
    // Continuous through the turn (the spline is C2): velocity changes by at
    // most the turn's deceleration from one 10 ms step to the next. This loop
    // ends at full speed, so the turn is a hard stop (a recording that ends
    // slow, as EuRoC's V1 flights do, turns gently).
    let mut prev = b.state(turn - 1.0).unwrap().vel;
    for k in 1..=200 {
        let v = b.state(turn - 1.0 + 0.01 * f64::from(k)).unwrap().vel;
        assert!((v - prev).norm() < 0.3, "at {k}: {v:?} after {prev:?}");
        prev = v;
    }
}

#[test]
fn robots_in_their_own_frames_start_at_their_origins_and_keep_their_motion() {
    let dir = tempfile::tempdir().unwrap();
    let shared = Fleet::build(&scenario(dir.path(), ""), 1).unwrap();
    let own = Fleet::build(&scenario(dir.path(), "estimator:\n  start_frame: own\n"), 1).unwrap();
    for r in 0..2 {
        assert_eq!(shared.robot_frame(r).unwrap().trans, Vector3::zeros());
        let start = own.estimator_start_time(r).unwrap();
        let truth = own.agent_truth(r).unwrap();
        let s = truth.state(start).unwrap();
        assert!(s.pos.norm() < 1e-9, "robot {r} starts at {:?}", s.pos);
        // Yawed so that its most horizontal IMU axis points along x; the
        // frame keeps gravity: roll and pitch are the world's.
        let axis = s
            .rot
            .column_iter()
            .min_by(|a, b| a.z.abs().total_cmp(&b.z.abs()))
            .unwrap()
            .into_owned();
        assert!(axis.y.abs() < 1e-9 && axis.x > 0.0, "{axis:?}");
        let world = own.truths[r].state(start + 3.0).unwrap();
        let mine = truth.state(start + 3.0).unwrap();
        assert!((world.rot.row(2) - mine.rot.row(2)).norm() < 1e-9);
        assert!((world.vel.z - mine.vel.z).abs() < 1e-9);
        assert!((world.vel.norm() - mine.vel.norm()).abs() < 1e-9);
    }
    // Robot 1's frame in robot 0's carries robot 1's points onto robot 0's.
    let f = own.frame_between(0, 1).unwrap();
    let t = own.estimator_start_time(1).unwrap() + 2.0;
    let (a, b) = (own.agent_truth(0).unwrap(), own.agent_truth(1).unwrap());
    let (p0, p1) = (
        own.robot_frame(0)
            .unwrap()
            .transform_point(&own.truths[1].state(t).unwrap().pos),
        b.state(t).unwrap().pos,
    );
    assert!((f.transform_point(&p1) - p0).norm() < 1e-9);
    assert!(a.state(t).is_some());
    assert!(f.rot[(2, 2)] > 1.0 - 1e-12, "a yaw only");
}

/// A two-robot loop whose robot 1 has TUM-VI's 512x512 fisheye instead of
/// the fleet's EuRoC cam0, written into the robot list (`robots[1].camera`).
fn mixed_lens_scenario(dir: &Path, extra: &str) -> Result<Scenario, ScenarioError> {
    write_loop(&dir.join("loop.txt"), 30.0);
    let text = format!(
        "name: mixed\nseed: 7\nrobots:\n  - trajectory: loop.txt\n  - trajectory: loop.txt\n    \
         start_time_s: 5.0\n    camera:\n      model: equidistant\n      width_px: 512\n      \
         height_px: 512\n      intrinsics_px: [190.978, 190.973, 254.932, 256.897]\n      \
         distortion: [0.0035, 0.0007, -0.0021, 0.0002]\n      pixel_noise_px: 0.5\n{extra}"
    );
    let path = dir.join("mixed.yaml");
    std::fs::write(&path, text).unwrap();
    Scenario::load(&path)
}

#[test]
fn a_robot_with_its_own_lens_sees_the_world_through_it() {
    let dir = tempfile::tempdir().unwrap();
    let sc =
        mixed_lens_scenario(dir.path(), "sensors:\n  camera:\n    max_features: 80\n").unwrap();
    assert!(!sc.one_camera());
    // Keys it does not give are the fleet camera's.
    let (fleet_cam, own) = (sc.camera(0), sc.camera(1));
    assert_eq!(own.max_features, 80);
    assert_eq!(own.t_imu_cam, fleet_cam.t_imu_cam);
    assert_eq!(own.model, common::camera::Distortion::Equidistant);
    assert_eq!(sc.sensors_of(1).camera.pixel_noise_px, 0.5);
    let fleet = Fleet::build(&sc, 2).unwrap();
    let calib = fleet.true_calibration(1).unwrap();
    assert_eq!((calib.camera.width, calib.camera.height), (512, 512));
    assert_eq!(fleet.true_calibration(0).unwrap().camera.width, 752);
    assert_eq!(fleet.initial_calibration(1).camera.width, 512);
    // Its features are its fisheye's projections of the shared landmarks,
    // with its own pixel noise.
    let (mut sum2, mut n) = (0.0, 0usize);
    for ev in fleet.stream(1).unwrap() {
        let SimEvent::Camera(c) = ev else { continue };
        assert!(c.frame.features.len() <= 80);
        let t_c_to_g = common::so3::Se3::new(c.truth.rot, c.truth.pos).compose(&calib.t_c_to_i());
        for (f, lm) in c.frame.features.iter().zip(&c.landmark_ids) {
            let p_c = t_c_to_g
                .inverse()
                .transform_point(&fleet.world.landmarks[*lm as usize].p_in_g);
            let uv = calib.camera.project(&p_c).unwrap();
            assert!(uv.x >= -3.0 && uv.x < 515.0 && uv.y >= -3.0 && uv.y < 515.0);
            sum2 += (f.uv - uv).norm_squared();
            n += 2;
        }
    }
    let sigma = (sum2 / n as f64).sqrt();
    assert!(
        n > 10_000 && (sigma - 0.5).abs() < 0.02,
        "{n} rows, sigma {sigma}"
    );
    let uniform = scenario(dir.path(), "");
    assert!(uniform.one_camera());
    assert_eq!(uniform.camera(1).width_px, 752);
}

#[test]
fn a_robot_camera_at_another_rate_or_out_of_range_is_refused_by_name() {
    let dir = tempfile::tempdir().unwrap();
    let e = mixed_lens_scenario(dir.path(), "")
        .map(|_| ())
        .and_then(|()| {
            let text = std::fs::read_to_string(dir.path().join("mixed.yaml")).unwrap();
            let path = dir.path().join("rate.yaml");
            std::fs::write(&path, text.replace("pixel_noise_px: 0.5", "rate_hz: 20")).unwrap();
            Scenario::load(&path).map(|_| ())
        })
        .unwrap_err();
    assert!(
        e.to_string()
            .contains("robots[1].camera.rate_hz must be the fleet's"),
        "{e}"
    );
    let text = std::fs::read_to_string(dir.path().join("mixed.yaml")).unwrap();
    let path = dir.path().join("noise.yaml");
    std::fs::write(
        &path,
        text.replace("pixel_noise_px: 0.5", "pixel_noise_px: -1"),
    )
    .unwrap();
    let e = Scenario::load(&path).unwrap_err();
    assert!(
        e.to_string()
            .contains("robots[1].camera.pixel_noise_px must be at least 0"),
        "{e}"
    );
    std::fs::write(&path, text.replace("pixel_noise_px: 0.5", "lens: big")).unwrap();
    let e = Scenario::load(&path).unwrap_err();
    assert!(e.to_string().contains("unknown field `lens`"), "{e}");
}

#[test]
fn a_rendered_fleet_shows_each_robot_the_one_room_through_its_own_lens() {
    let dir = tempfile::tempdir().unwrap();
    let sc = mixed_lens_scenario(dir.path(), "render:\n  enabled: true\n").unwrap();
    let fleet = Fleet::build(&sc, 3).unwrap();
    let (r0, r1) = (fleet.renderer(0).unwrap(), fleet.renderer(1).unwrap());
    assert_eq!(r0.room(), r1.room());
    let image = |robot: usize| {
        fleet
            .stream(robot)
            .unwrap()
            .find_map(|e| match e {
                SimEvent::Camera(c) => c.image.clone(),
                SimEvent::Imu(_) => None,
            })
            .unwrap()
    };
    assert_eq!((image(0).width(), image(0).height()), (752, 480));
    assert_eq!((image(1).width(), image(1).height()), (512, 512));
    // The same pose looks at the same room point through either lens: the
    // optical axis hits one spot whatever the lens.
    let t = fleet.truths[0].start_time() + 10.0;
    let pose = crate::world::camera_pose(&fleet.truths[0], &fleet.true_calibrations[0], t).unwrap();
    let centre = |robot: usize| {
        let cam = &fleet.true_calibrations[robot].camera;
        let uv = cam.distort(&Vector2::zeros());
        fleet.renderer(robot).unwrap().raycast(&pose, &uv).unwrap()
    };
    assert!((centre(0) - centre(1)).norm() < 1e-9);
}
