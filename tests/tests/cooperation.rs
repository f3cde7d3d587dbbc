//! Cooperating agents as real processes: robots flying the same loop one after
//! the other share features over Zenoh and iceoryx2 and close loops on their
//! peers' histories (`dc-full-history`); the centralized baseline runs in one
//! process.
#![allow(clippy::unwrap_used)] // helpers outside #[test] functions

use integration_tests::{sim_fleet_run, write_loop_trajectory, write_loop_trajectory_from};
use serde_json::Value;
use std::path::{Path, PathBuf};

/// Three robots on one 24 s loop: the second starts 4 s after the first, the
/// third 30 s after (after the first has finished: only its history is left).
fn scenario(dir: &Path) -> PathBuf {
    write_loop_trajectory(&dir.join("loop.txt"), 24.0).unwrap();
    let p = dir.join("coop.yaml");
    std::fs::write(
        &p,
        "name: coop\nrobots:\n  - trajectory: loop.txt\n  - trajectory: loop.txt\n    start_time_s: 4.0\n  - trajectory: loop.txt\n    start_time_s: 30.0\nsensors:\n  camera:\n    max_features: 60\nestimator:\n  max_slam_features: 5\n",
    )
    .unwrap();
    p
}

/// The flags of a `dc-full-history` run over Zenoh, seed 2.
const OVER_ZENOH: [&str; 6] = [
    "--transport",
    "zenoh",
    "--variant",
    "dc-full-history",
    "--seed",
    "2",
];

fn metric(summary: &Value, robot: usize, key: &str) -> f64 {
    summary["robots"][robot][key].as_f64().unwrap_or(f64::NAN)
}

fn assert_cooperates(summary: &Value) {
    for r in 0..3 {
        let ate = metric(summary, r, "ate_pos_m");
        assert!(ate.is_finite() && ate < 0.5, "robot {r}: ATE {ate} m");
        let nees = metric(summary, r, "nees_pos");
        assert!(nees.is_finite() && nees < 10.0, "robot {r}: NEES {nees}");
    }
    // The followers used what the others saw, now and before.
    for r in 1..3 {
        let updates = metric(summary, r, "common_feature_updates");
        assert!(
            updates > 10.0,
            "robot {r}: {updates} common feature updates"
        );
    }
    let loops = metric(summary, 2, "loop_closures");
    assert!(
        loops > 5.0,
        "robot 2 closed {loops} loops on its peers' histories"
    );
}

#[test]
fn agents_over_zenoh_share_features_and_close_loops_on_peer_histories() {
    let dir = tempfile::tempdir().unwrap();
    let sc = scenario(dir.path());
    let summary = sim_fleet_run(&sc, &dir.path().join("zenoh"), &OVER_ZENOH);
    assert_cooperates(&summary);
}

#[test]
fn agents_over_iceoryx2_share_features_and_close_loops_on_peer_histories() {
    let dir = tempfile::tempdir().unwrap();
    let sc = scenario(dir.path());
    let summary = sim_fleet_run(
        &sc,
        &dir.path().join("iox"),
        &[
            "--transport",
            "iceoryx2",
            "--variant",
            "dc-full-history",
            "--seed",
            "2",
        ],
    );
    assert_cooperates(&summary);
}

/// The same fleet with three lenses (`robots[i].camera`): EuRoC cam0, TUM-VI's
/// 512x512 fisheye and a 640x480 pinhole of 2 px noise. Each agent runs its own
/// camera model and weighs its peers' measurements through theirs at their
/// noise, both carried in their windows.
#[test]
fn agents_with_different_lenses_cooperate_over_zenoh() {
    let dir = tempfile::tempdir().unwrap();
    let text = std::fs::read_to_string(scenario(dir.path())).unwrap();
    let lenses = text
        .replace(
            "    start_time_s: 4.0\n",
            "    start_time_s: 4.0\n    camera:\n      model: equidistant\n      width_px: 512\n      \
             height_px: 512\n      intrinsics_px: [190.978, 190.973, 254.932, 256.897]\n      \
             distortion: [0.0035, 0.0007, -0.0021, 0.0002]\n",
        )
        .replace(
            "    start_time_s: 30.0\n",
            "    start_time_s: 30.0\n    camera:\n      width_px: 640\n      height_px: 480\n      \
             intrinsics_px: [385.0, 385.0, 320.0, 240.0]\n      distortion: [0.0, 0.0, 0.0, 0.0]\n      \
             pixel_noise_px: 2.0\n",
        );
    assert_ne!(lenses, text);
    let sc = dir.path().join("lenses.yaml");
    std::fs::write(&sc, lenses).unwrap();
    let summary = sim_fleet_run(&sc, &dir.path().join("zenoh"), &OVER_ZENOH);
    assert_cooperates(&summary);
}

/// The same fleet, each robot in its own frame (`start_frame: own`): no robot
/// knows where the others started, and each finds their frames from its loop
/// closures to their keyframe windows before it uses them.
#[test]
fn agents_in_their_own_frames_align_their_peers_from_loop_closures_over_zenoh() {
    let dir = tempfile::tempdir().unwrap();
    let sc = scenario(dir.path());
    let text = std::fs::read_to_string(&sc).unwrap();
    std::fs::write(&sc, text + "  start_frame: own\n").unwrap();
    let out = dir.path().join("own");
    let summary = sim_fleet_run(&sc, &out, &OVER_ZENOH);
    // Robot 1 flies 4 s behind robot 0, over its places; robot 2 after both.
    for (r, peers) in [(1, 1.0), (2, 2.0)] {
        assert_eq!(
            metric(&summary, r, "peer_frames_aligned"),
            peers,
            "robot {r}"
        );
        let yaw = metric(&summary, r, "peer_frame_yaw_err_deg");
        let pos = metric(&summary, r, "peer_frame_pos_err_m");
        assert!(yaw < 1.0 && pos < 0.2, "robot {r}: {yaw} deg, {pos} m off");
        let updates = metric(&summary, r, "common_feature_updates");
        assert!(
            updates > 10.0,
            "robot {r}: {updates} common feature updates"
        );
    }
    for r in 0..3 {
        let ate = metric(&summary, r, "ate_pos_m");
        assert!(ate.is_finite() && ate < 0.5, "robot {r}: ATE {ate} m");
    }
    // Each agent says where it found each peer, with how sure it is.
    let stats = integration_tests::read_json(&out.join("robot2/transport_stats.json"));
    for peer in ["0", "1"] {
        // One frame per peer (none started again), named 1 in lockstep.
        let frames = stats["peer_frames"][peer].as_array().unwrap();
        assert_eq!(frames.len(), 1, "{frames:?}");
        let f = &frames[0];
        assert_eq!(f["frame_epoch"].as_u64(), Some(1), "{f}");
        assert_eq!(f["aligned"], Value::Bool(true), "{f}");
        let sigma = f["yaw_sigma_deg"].as_f64().unwrap_or(f64::NAN);
        assert!(sigma > 0.0 && sigma < 2.0, "{f}");
        assert!(f["measurements"].as_u64().unwrap_or(0) >= 2, "{f}");
    }
}

/// A robot in its own frame killed and started again in real time comes
/// back in a new frame (a new `frame_epoch`) that no peer knows: the
/// followers, holding its first frame in their filters, find the new one from
/// their loop closures to the windows it makes after the restart, and both
/// frames place it right (its frame is its trajectory's start either way).
#[test]
fn a_restarted_robot_in_its_own_frame_is_found_again_by_peers_holding_its_old_frame() {
    use integration_tests::fleet::{configs, kill_and_restart, start_agents, wait, wait_for_poses};
    use std::time::Duration;
    let dir = tempfile::tempdir().unwrap();
    write_loop_trajectory(&dir.path().join("loop.txt"), 24.0).unwrap();
    let sc = dir.path().join("restart.yaml");
    std::fs::write(
        &sc,
        "name: restart\nrobots:\n  - trajectory: loop.txt\n  - trajectory: loop.txt\n    start_time_s: 3.0\n  - trajectory: loop.txt\n    start_time_s: 6.0\nsensors:\n  camera:\n    max_features: 60\nestimator:\n  max_slam_features: 5\n  start_frame: own\n",
    )
    .unwrap();
    let out = dir.path().join("run");
    // Real time at 4x: the leader is killed 8-12 s into its flight (it has
    // sent keyframe windows of its first frame by then) and back about 4 s
    // later, over the places its followers reach next.
    let cfgs = configs(
        &sc,
        &out,
        &[
            "--transport",
            "zenoh",
            "--variant",
            "dc-full-history",
            "--realtime",
            "4",
        ],
    );
    let mut agents = start_agents(&cfgs, &out);
    let flew = wait_for_poses(
        &out.join("robot0/estimate.txt"),
        80,
        Duration::from_secs(60),
    );
    assert!(flew, "robot 0 did not fly 8 s");
    let mut restarted = kill_and_restart(
        &mut agents[0],
        &cfgs[0],
        &out.join("robot0-again.log"),
        Duration::ZERO,
        Duration::from_millis(1000),
    );
    for (i, a) in agents.iter_mut().enumerate().skip(1) {
        assert!(wait(a, Duration::from_secs(120)), "robot {i} failed");
    }
    assert!(
        wait(&mut restarted, Duration::from_secs(120)),
        "restarted robot failed"
    );
    for r in 1..3 {
        let st = stats(&out, r);
        let frames = st["peer_frames"]["0"].as_array().unwrap();
        let aligned: Vec<&Value> = frames.iter().filter(|f| f["aligned"] == true).collect();
        assert_eq!(aligned.len(), 2, "robot {r}: {frames:?}");
        assert_ne!(aligned[0]["frame_epoch"], aligned[1]["frame_epoch"]);
        // Every robot flies the loop from its start, so every frame is the
        // same: each alignment should be the identity. Weights chosen per
        // update (the default): both are held in the filter to the end.
        for f in aligned {
            assert_eq!(f["in_filter"], true, "robot {r}: {f}");
            let yaw = f["yaw_deg"].as_f64().unwrap_or(f64::NAN);
            let t: Vec<f64> = (0..3)
                .map(|k| f["t_m"][k].as_f64().unwrap_or(f64::NAN))
                .collect();
            assert!(yaw.abs() < 2.0, "robot {r}: {f}");
            assert!(t.iter().all(|x| x.abs() < 0.25), "robot {r}: {f}");
        }
        let s = integration_tests::read_json(&out.join(format!("robot{r}/summary.json")));
        let ate = s["robots"][0]["ate_pos_m"].as_f64().unwrap_or(f64::NAN);
        assert!(ate.is_finite() && ate < 0.5, "robot {r}: ATE {ate} m");
    }
}

#[test]
fn the_centralized_estimator_runs_the_fleet_in_one_process() {
    let dir = tempfile::tempdir().unwrap();
    let sc = scenario(dir.path());
    let out = dir.path().join("ce");
    let summary = sim_fleet_run(&sc, &out, &["--variant", "ce-cmsckf-cslam", "--seed", "2"]);
    for r in 0..3 {
        let ate = metric(&summary, r, "ate_pos_m");
        assert!(ate.is_finite() && ate < 0.5, "robot {r}: ATE {ate} m");
        assert!(out.join(format!("robot{r}/estimate.txt")).is_file());
    }
}

/// Two robots on opposite sides of one circle, each estimating its camera
/// intrinsics online, fuse the peer's measurements of their SLAM features with
/// the peer's intrinsics as a CI participant. With the measurement's Jacobians
/// taken at the measured point instead of the predicted one, the noise biased
/// every update toward longer focal lengths, and both robots' focal lengths ran
/// away together (this run, seeds 1-2: orientation NEES 19-28, 0.31-0.40 deg;
/// now, seed 1: 0.96 and 1.61, 0.08 deg with the fixed peer weight 0.005; 1.13
/// and 2.13, 0.08 deg with the weights chosen per update, the default, named
/// here).
#[test]
fn robots_that_fuse_their_peers_intrinsics_keep_their_focal_lengths() {
    let dir = tempfile::tempdir().unwrap();
    write_loop_trajectory_from(&dir.path().join("a.txt"), 40.0, 0.0).unwrap();
    write_loop_trajectory_from(&dir.path().join("b.txt"), 40.0, std::f64::consts::PI).unwrap();
    let sc = dir.path().join("opposite.yaml");
    std::fs::write(
        &sc,
        "name: opposite\nrobots:\n  - trajectory: a.txt\n  - trajectory: b.txt\nsensors:\n  calibration_perturbation:\n    enabled: false\nestimator:\n  init_sigma_pos_m: 0.001\n  init_sigma_ori_rad: 0.001\n  calib_extrinsics: false\n  calib_time_offset: false\n  cooperation:\n    ci_weighting: min_pose_trace\n",
    )
    .unwrap();
    let summary = sim_fleet_run(
        &sc,
        &dir.path().join("out"),
        &["--variant", "dc-cmsckf-cslam", "--seed", "1"],
    );
    for r in 0..2 {
        let updates = metric(&summary, r, "common_feature_updates");
        assert!(
            updates > 100.0,
            "robot {r}: {updates} common feature updates"
        );
        let nees = metric(&summary, r, "nees_ori");
        assert!(
            nees.is_finite() && nees < 6.0,
            "robot {r}: orientation NEES {nees}"
        );
        let ate = metric(&summary, r, "ate_ori_deg");
        assert!(ate.is_finite() && ate < 0.2, "robot {r}: ATE {ate} deg");
    }
}

/// `transport_stats.json` of robot `r` of the run in `out`.
fn stats(out: &Path, r: usize) -> Value {
    integration_tests::read_json(&out.join(format!("robot{r}/transport_stats.json")))
}

/// Keyframe windows robot `r` holds of robot `p`.
fn held(out: &Path, r: usize, p: usize) -> u64 {
    stats(out, r)["histories"][p.to_string()]["keyframes"]
        .as_u64()
        .unwrap_or(0)
}

/// Of those, the windows held whole (a frame at every clone, descriptors).
fn held_whole(out: &Path, r: usize, p: usize) -> u64 {
    stats(out, r)["histories"][p.to_string()]["whole"]
        .as_u64()
        .unwrap_or(0)
}

/// A link outage over fleet seconds 4-20 (every data message sent in it is
/// lost; lockstep heartbeats pass) costs the third robot most of the others'
/// flights. With history catch-up every agent gets the missed keyframe windows
/// back from their authors once the link returns, and ends with the whole
/// history of every peer; without it the windows of the outage stay lost.
#[test]
fn after_a_link_outage_agents_catch_up_on_their_peers_histories_over_zenoh() {
    let dir = tempfile::tempdir().unwrap();
    let sc = scenario(dir.path());
    let common = [&OVER_ZENOH[..], &["--link-outage", "4:20"]].concat();
    let on = dir.path().join("catch-up");
    let summary = sim_fleet_run(&sc, &on, &common);
    assert_cooperates(&summary);
    let off = dir.path().join("no-catch-up");
    sim_fleet_run(&sc, &off, &[&common[..], &["--no-catch-up"]].concat());
    for r in 0..3 {
        let s = stats(&on, r);
        assert!(s["outage_dropped"].as_u64().unwrap_or(0) > 100, "{s}");
        for p in (0..3).filter(|p| *p != r) {
            let whole = stats(&on, p)["own_archive_windows"].as_u64().unwrap_or(0);
            assert!(whole > 15, "robot {p} made {whole} windows");
            assert_eq!(
                held(&on, r, p),
                whole,
                "robot {r} holds {} of robot {p}'s {whole} windows after catching up",
                held(&on, r, p)
            );
        }
        let c = &s["catch_up"];
        assert!(c["windows_stored"].as_u64().unwrap_or(0) > 10, "{c}");
    }
    // Without catch-up the outage's windows stay lost.
    let lost = held(&off, 2, 0);
    let whole = stats(&on, 0)["own_archive_windows"].as_u64().unwrap_or(0);
    assert!(
        lost + 10 < whole,
        "without catch-up robot 2 holds {lost} of robot 0's {whole} windows"
    );
    assert_eq!(stats(&off, 2)["catch_up"], Value::Null);
}

/// On a link that loses 30 % of the messages (each agent its own draws; the
/// lockstep heartbeats pass), nearly every keyframe window arrives short of a
/// frame, its descriptors or its snapshot. Catch-up asks again for the gaps,
/// and for the windows an answer listed but whose replays were lost too; a
/// window held short of a frame or its descriptors gets only those back. The
/// last losses of a flight show no gap: once every robot's data have ended,
/// each agent asks its peers once more and leaves when all have settled. So
/// every agent ends holding every window of every peer, whole.
#[test]
fn on_a_lossy_link_agents_still_end_with_their_peers_whole_histories_over_zenoh() {
    let dir = tempfile::tempdir().unwrap();
    let sc = scenario(dir.path());
    let out = dir.path().join("lossy");
    let summary = sim_fleet_run(
        &sc,
        &out,
        &[&OVER_ZENOH[..], &["--link-loss", "0.3"]].concat(),
    );
    assert_cooperates(&summary);
    let (mut reasked, mut parts) = (0, 0);
    for r in 0..3 {
        let s = stats(&out, r);
        assert!(s["loss_dropped"].as_u64().unwrap_or(0) > 100, "{s}");
        let c = &s["catch_up"];
        let completed = c["windows_completed"].as_u64().unwrap_or(0);
        let by_parts = c["parts_stored"].as_u64().unwrap_or(0);
        assert!(completed + by_parts > 5, "{c}");
        reasked += c["windows_reasked"].as_u64().unwrap_or(0);
        parts += by_parts;
        assert_eq!(
            s["settle"]["complete"],
            Value::Bool(true),
            "{}",
            s["settle"]
        );
        for p in (0..3).filter(|p| *p != r) {
            let made = stats(&out, p);
            let windows = made["own_archive_windows"].as_u64().unwrap_or(0);
            let whole = made["own_archive_whole_windows"].as_u64().unwrap_or(0);
            assert!(whole > 15, "robot {p} made {whole} whole windows");
            let held = held(&out, r, p);
            assert_eq!(
                held, windows,
                "robot {r} holds {held} of robot {p}'s {windows} windows"
            );
            let held_whole = held_whole(&out, r, p);
            assert_eq!(
                held_whole, whole,
                "robot {r} holds {held_whole} of robot {p}'s {whole} whole windows whole"
            );
        }
    }
    assert!(reasked > 0, "no lost replay was asked for again");
    assert!(parts > 0, "no window was completed by a part");
}
