//! Live sensors: the EuRoC V1_01 micro sequence published as ROS 2 topics
//! over Zenoh by one process (`agent publish-euroc`, CDR as
//! `zenoh-bridge-ros2dds` carries it) and run live by another (`agent live`).
//! Undecodable payloads on the sensors' keys are counted and the run goes on;
//! the live run's estimates are the file replay's, bit for bit.

#![allow(clippy::expect_used, clippy::unwrap_used)]

mod live_support;

use live_support::{agent, session_to, succeeded, wait_for};

use std::path::{Path, PathBuf};
use std::process::{Child, Stdio};
use std::time::{Duration, Instant};
use zenoh::Wait;

fn data(rel: &str) -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR"))
        .join("../../shared/data")
        .join(rel)
}

/// Sends payloads that are not the topics' messages on both keys, once the
/// live agent subscribes to them.
fn send_garbage(port: u16, imu_key: &str, image_key: &str) {
    let session = session_to(port);
    for key in [imu_key, image_key] {
        let publisher = session
            .declare_publisher(key.to_owned())
            .wait()
            .expect("publisher");
        let start = Instant::now();
        while !publisher
            .matching_status()
            .wait()
            .expect("status")
            .matching()
        {
            assert!(
                start.elapsed() < Duration::from_secs(30),
                "no subscriber on {key}"
            );
            std::thread::sleep(Duration::from_millis(50));
        }
        // An XCDR2 header, then a truncated little-endian message.
        publisher
            .put(vec![0x00, 0x07, 0, 0, 1, 2])
            .wait()
            .expect("put");
        publisher
            .put(vec![0x00, 0x01, 0, 0, 1, 2, 3])
            .wait()
            .expect("put");
    }
    std::thread::sleep(Duration::from_millis(300));
    session.close().wait().expect("close");
}

/// Runs `agent dataset` on `seq` into `file_out` and checks that the live run
/// in `live_out` wrote the same estimates, covariances and ground truth.
fn assert_live_is_the_replay(seq: &Path, gt: &Path, live_out: &Path, file_out: &Path) {
    let file = agent()
        .arg("dataset")
        .arg("--euroc")
        .arg(seq)
        .arg("--groundtruth")
        .arg(gt)
        .arg("--out")
        .arg(file_out)
        .output()
        .expect("agent dataset");
    succeeded("agent dataset", &file);
    for f in ["estimate.txt", "covariance.txt", "groundtruth.txt"] {
        assert_eq!(read(live_out, f), read(file_out, f), "{f} differs");
    }
}

fn read(dir: &Path, file: &str) -> Vec<u8> {
    std::fs::read(dir.join(file)).expect("output")
}

/// Starts `agent live` on `sensors`, listening on `listen`, with `extra` arguments.
fn spawn_live(sensors: &Path, gt: &Path, listen: &str, out: &Path, extra: &[&str]) -> Child {
    agent()
        .arg("live")
        .arg("--sensors")
        .arg(sensors)
        .arg("--groundtruth")
        .arg(gt)
        .args(["--listen", listen, "--idle-timeout-s", "3"])
        .args(extra)
        .arg("--out")
        .arg(out)
        .stdout(Stdio::piped())
        .stderr(Stdio::piped())
        .spawn()
        .expect("agent live")
}

#[test]
fn a_sequence_published_over_zenoh_runs_live_as_it_runs_from_files() {
    let micro = data("euroc_v1_01_micro");
    let gt = data("trajectories/V1_01_easy.csv");
    let dir = tempfile::tempdir().expect("tempdir");
    let (live_out, file_out) = (dir.path().join("live"), dir.path().join("file"));
    let port = common::loopback_ports::free_loopback_ports(1).expect("port")[0];
    let (imu_key, image_key) = ("robot7/imu0", "robot7/cam0/image_raw");
    let listen = format!("tcp/127.0.0.1:{port}");
    let keys = ["--imu-key", imu_key, "--image-key", image_key];
    let pose = [
        "--pose-key",
        "robot7/vio/pose",
        "--odom-key",
        "robot7/vio/odom",
        "--body-frame",
        "robot7/imu",
    ];
    let live = spawn_live(
        &micro,
        &gt,
        &listen,
        &live_out,
        &[&keys[..], &pose].concat(),
    );
    send_garbage(port, imu_key, image_key);
    let listener = session_to(port);
    let poses = listener
        .declare_subscriber("robot7/vio/pose")
        .with(zenoh::handlers::FifoChannel::new(10_000))
        .wait()
        .expect("subscriber");
    let odometry = listener
        .declare_subscriber("robot7/vio/odom")
        .with(zenoh::handlers::FifoChannel::new(10_000))
        .wait()
        .expect("subscriber");
    let publish = agent()
        .arg("publish-euroc")
        .arg("--euroc")
        .arg(&micro)
        .args(["--listen", "tcp/127.0.0.1:0", "--connect", &listen])
        .args([
            "--imu-key",
            imu_key,
            "--image-key",
            image_key,
            "--speed",
            "2",
        ])
        .output()
        .expect("agent publish-euroc");
    let published = succeeded("publish-euroc", &publish);
    assert!(
        published.contains("published 941 IMU messages") && published.contains("and 95 images"),
        "{published}"
    );
    let live = succeeded("agent live", &wait_for(live, Duration::from_secs(120)));
    println!("{live}");
    assert!(
        live.contains(
            "sensors: IMU 941 received, 2 undecodable, 0 dropped; images 95 received, 2 undecodable, 0 dropped"
        ),
        "{live}"
    );
    let tilt: f64 = live
        .split("tilt error vs ground truth ")
        .nth(1)
        .and_then(|r| r.split(' ').next())
        .and_then(|v| v.parse().ok())
        .expect("the static start succeeded");
    assert!(tilt < 1.0, "tilt error at the start {tilt} deg");
    // Every estimate went out as a pose, and the last is the last estimate.
    let received: Vec<_> = poses
        .drain()
        .map(|s| common::ros_cdr::decode_pose(&s.payload().to_bytes()).expect("a pose"))
        .collect();
    let estimates = common::trajectory::read_tum(live_out.join("estimate.txt")).expect("estimates");
    assert!(
        live.contains(&format!("poses: {} published", estimates.len())),
        "{live}"
    );
    assert_eq!(received.len(), estimates.len());
    let (last, sent) = (
        estimates.last().expect("one"),
        received.last().expect("one"),
    );
    assert_eq!(sent.header.frame_id, "vio_world");
    assert!((sent.pose.t - last.t).abs() < 1e-6);
    assert!((sent.pose.pos - last.pos).norm() < 1e-6);
    assert!((sent.pose.rot - last.rot).norm() < 1e-6);
    assert!(sent.covariance[0] > 0.0 && sent.covariance[35] > 0.0);
    // And as an odometry: the same pose, and the twist of a drone that stands
    // on the floor with its rotors running (the sequence ends before take-off).
    let odoms: Vec<_> = odometry
        .drain()
        .map(|s| common::ros_cdr::decode_odometry(&s.payload().to_bytes()).expect("an odometry"))
        .collect();
    assert_eq!(odoms.len(), estimates.len());
    assert!(
        live.contains(&format!("odometry: {} published", estimates.len())),
        "{live}"
    );
    let odom = odoms.last().expect("one");
    assert_eq!(odom.header.frame_id, "vio_world");
    assert_eq!(odom.child_frame_id, "robot7/imu");
    assert_eq!((odom.pose.t, odom.pose.pos), (sent.pose.t, sent.pose.pos));
    assert_eq!(odom.pose_covariance, sent.covariance);
    let tw = &odom.twist;
    println!(
        "last twist {:?} {:?}, variances {:?}",
        tw.linear,
        tw.angular,
        (0..6).map(|i| tw.covariance[7 * i]).collect::<Vec<_>>()
    );
    for i in 0..6 {
        let var = tw.covariance[7 * i];
        assert!(var > 0.0 && var.is_finite(), "twist variance {i}: {var}");
    }
    assert!(tw.linear.norm() < 0.05, "{:?}", tw.linear);
    assert!(tw.angular.norm() < 0.1, "{:?}", tw.angular);
    listener.close().wait().expect("close");

    assert_live_is_the_replay(&micro, &gt, &live_out, &file_out);
    assert!(read(&live_out, "estimate.txt").len() > 1000);
}

/// A moving robot: 20 s of V1_01 rendered (`simulator::euroc_export`, as
/// `sim-fleet export-euroc` writes it), from its still start through its first
/// turns, live at twice real time. The live run is the file replay, bit for
/// bit, and it is on the truth. (At four times real time, 25 ms per image, the
/// agent dropped images when the other test of this file and a build shared
/// the two cores.)
#[test]
fn a_rendered_flight_runs_live_on_the_truth_as_it_runs_from_files() {
    let dir = tempfile::tempdir().expect("tempdir");
    let seq = dir.path().join("v1_01_rendered");
    let scenario_path =
        PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("../sim-fleet/scenarios/v1_01_easy.yaml");
    let mut scenario = simulator::Scenario::load(&scenario_path).expect("scenario");
    scenario.render.enabled = true;
    let fleet = simulator::Fleet::build(&scenario, 1).expect("fleet");
    let t_end = fleet.truths[0].start_time() + 20.0;
    let n = simulator::euroc_export::export_euroc(&fleet, 0, t_end, &seq, "test").expect("export");
    assert_eq!(n.images, 201);
    let gt = seq.join("mav0/state_groundtruth_estimate0/data.csv");
    let (live_out, file_out) = (dir.path().join("live"), dir.path().join("file"));
    let port = common::loopback_ports::free_loopback_ports(1).expect("port")[0];
    let listen = format!("tcp/127.0.0.1:{port}");
    let live = spawn_live(&seq, &gt, &listen, &live_out, &["--pose-key", "none"]);
    let publish = agent()
        .arg("publish-euroc")
        .arg("--euroc")
        .arg(&seq)
        .args([
            "--listen",
            "tcp/127.0.0.1:0",
            "--connect",
            &listen,
            "--speed",
            "2",
        ])
        .output()
        .expect("agent publish-euroc");
    succeeded("publish-euroc", &publish);
    let live = succeeded("agent live", &wait_for(live, Duration::from_secs(120)));
    println!("{live}");
    assert!(
        live.contains("images 201 received, 0 undecodable, 0 dropped"),
        "{live}"
    );
    assert_live_is_the_replay(&seq, &gt, &live_out, &file_out);
    let summary: serde_json::Value =
        serde_json::from_slice(&read(&live_out, "summary.json")).expect("summary");
    let m = &summary["robots"][0];
    let get = |k: &str| m[k].as_f64().unwrap_or(f64::NAN);
    println!("{m}");
    assert!(get("ate_ori_deg") < 0.5, "{m}");
    assert!(get("ate_pos_m") < 0.05, "{m}");
    assert!(get("nees_ori") < 6.0 && get("nees_pos") < 6.0, "{m}");
    assert!(live.contains("tilt error vs ground truth 0."), "{live}");
}
