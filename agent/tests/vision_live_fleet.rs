//! Two fleet agents on live sensors: V1_01 and V1_02 rendered in one shared
//! room (`euroc_vicon_room1.yaml`, exported as `sim-fleet export-euroc` does),
//! each published as ROS 2 topics over Zenoh by its own `agent
//! publish-euroc`, each run by its own `agent --config` with `input.source:
//! live`, the two talking over Zenoh as a fleet does. Each starts from a
//! static start placed at its start pose in the fleet's frame; the test
//! checks that they share that frame (their estimates are on the truth
//! without alignment) and cooperate (loop closures and common-feature
//! updates on both).

#![allow(clippy::expect_used, clippy::unwrap_used)]

mod live_support;

use live_support::{agent, session_to, succeeded, wait_for};

use common::metrics::{associate, ate, nees, Alignment};
use common::trajectory::{read_covariances, read_euroc_csv, read_tum, StampedPose};
use std::path::{Path, PathBuf};
use std::process::{Child, Stdio};
use std::time::Duration;
use zenoh::Wait;

/// The heading of the IMU's `y` axis in the truth's frame, deg (EuRoC's
/// IMU has `x` up: `y` is the level one).
fn yaw_deg(p: &StampedPose) -> f64 {
    p.rot[(1, 1)].atan2(p.rot[(0, 1)]).to_degrees()
}

/// Robot `r`'s configuration: its sensors on `sensor_port`, its peer on
/// `peer_ports`, its start the truth's first pose.
fn config(r: u32, seq: &Path, out: &Path, ports: &[u16; 4], start: &StampedPose) -> String {
    let p = start.pos;
    format!(
        "robot_id: {r}
fleet_id: live-fleet-test
output_dir: {out}
status_period_s: 0
transport:
  kind: zenoh
  zenoh:
    config: loopback
    listen: [tcp/127.0.0.1:{me}]
    connect: [tcp/127.0.0.1:{peer}]
input:
  source: live
  live:
    calibration: {seq}
    zenoh:
      config: loopback
      listen: [tcp/127.0.0.1:{sensors}]
    imu_key: robot{r}/imu0
    image_key: robot{r}/cam0/image_raw
    pose_key: robot{r}/vio/pose
    odom_key: robot{r}/vio/odom
    start:
      position_m: [{}, {}, {}]
      yaw_deg: {}
      heading_axis: y
    idle_timeout_s: 3
estimator:
  variant: dc-full-history
clock:
  mode: realtime
  peers: [{other}]
",
        p.x,
        p.y,
        p.z,
        yaw_deg(start),
        out = out.display(),
        seq = seq.display(),
        me = ports[r as usize],
        peer = ports[1 - r as usize],
        sensors = ports[2 + r as usize],
        other = 1 - r,
    )
}

/// The last gyro reading at or before `t_s` of an exported sequence's
/// `imu0/data.csv`.
fn gyro_reading_at(seq: &Path, t_s: f64) -> nalgebra::Vector3<f64> {
    let text = std::fs::read_to_string(seq.join("mav0/imu0/data.csv")).expect("imu0");
    let t_ns = (t_s * 1e9).round() as i64 + 1_000;
    let mut last = None;
    for line in text.lines().filter(|l| !l.starts_with('#')) {
        let v: Vec<f64> = line
            .split(',')
            .map(|x| x.trim().parse().expect("number"))
            .collect();
        if v[0] as i64 > t_ns {
            break;
        }
        last = Some(nalgebra::Vector3::new(v[1], v[2], v[3]));
    }
    last.expect("a reading before the estimate")
}

#[test]
fn two_agents_on_live_sensors_share_the_fleet_frame_and_cooperate() {
    let dir = tempfile::tempdir().expect("tempdir");
    let scenario_path = PathBuf::from(env!("CARGO_MANIFEST_DIR"))
        .join("../sim-fleet/scenarios/euroc_vicon_room1.yaml");
    let mut scenario = simulator::Scenario::load(&scenario_path).expect("scenario");
    scenario.render.enabled = true;
    let fleet = simulator::Fleet::build(&scenario, 1).expect("fleet");
    let ports: [u16; 4] = common::loopback_ports::free_loopback_ports(4)
        .expect("ports")
        .try_into()
        .expect("four");
    let mut agents = Vec::new();
    let mut seqs = Vec::new();
    for r in 0..2u32 {
        let seq = dir.path().join(format!("seq{r}"));
        let t_end = fleet.truths[r as usize].start_time() + 20.0;
        let n = simulator::euroc_export::export_euroc(&fleet, r as usize, t_end, &seq, "test")
            .expect("export");
        assert_eq!(n.images, 201);
        let gt = read_euroc_csv(seq.join("mav0/state_groundtruth_estimate0/data.csv")).expect("gt");
        let out = dir.path().join(format!("out{r}"));
        let cfg = dir.path().join(format!("robot{r}.yaml"));
        std::fs::write(&cfg, config(r, &seq, &out, &ports, &gt[0])).expect("config");
        let child = agent()
            .arg("--config")
            .arg(&cfg)
            .stdout(Stdio::piped())
            .stderr(Stdio::piped())
            .spawn()
            .expect("agent");
        agents.push((child, out));
        seqs.push((seq, gt));
    }
    // Robot 0's poses as a ROS 2 node would take them.
    let listener = session_to(ports[2]);
    let poses = listener
        .declare_subscriber("robot0/vio/pose")
        .with(zenoh::handlers::FifoChannel::new(10_000))
        .wait()
        .expect("subscriber");
    let odometry = listener
        .declare_subscriber("robot0/vio/odom")
        .with(zenoh::handlers::FifoChannel::new(10_000))
        .wait()
        .expect("subscriber");
    let publishers: Vec<Child> = (0..2)
        .map(|r| {
            agent()
                .arg("publish-euroc")
                .arg("--euroc")
                .arg(&seqs[r].0)
                .args([
                    "--listen",
                    "tcp/127.0.0.1:0",
                    "--connect",
                    &format!("tcp/127.0.0.1:{}", ports[2 + r]),
                    "--imu-key",
                    &format!("robot{r}/imu0"),
                    "--image-key",
                    &format!("robot{r}/cam0/image_raw"),
                    "--speed",
                    "2",
                ])
                .stdout(Stdio::piped())
                .stderr(Stdio::piped())
                .spawn()
                .expect("publish-euroc")
        })
        .collect();
    for p in publishers {
        succeeded("publish-euroc", &wait_for(p, Duration::from_secs(120)));
    }
    for (r, (child, out)) in agents.into_iter().enumerate() {
        let stdout = succeeded("agent", &wait_for(child, Duration::from_secs(120)));
        println!("robot {r}: {stdout}");
        assert!(
            stdout.contains("sensors: IMU 8001 received, 0 undecodable")
                && stdout.contains("images 201 received, 0 undecodable"),
            "{stdout}"
        );
        let est = read_tum(out.join("estimate.txt")).expect("estimates");
        let covs = read_covariances(out.join("covariance.txt")).expect("covariances");
        assert!(est.len() > 150, "{} estimates", est.len());
        assert!(!out.join("groundtruth.txt").exists());
        // Without alignment: the start pose put the estimate in the fleet's frame.
        let pairs = associate(&est, &seqs[r].1, common::metrics::DEFAULT_MAX_DT_S);
        assert_eq!(pairs.len(), est.len());
        let a = ate(&pairs, Alignment::None);
        let n = nees(&pairs, &covs);
        let (n_ori, n_pos) = (n.ori_mean.expect("nees"), n.pos_mean.expect("nees"));
        println!(
            "robot {r}: ATE {:.3} deg / {:.4} m, NEES {n_ori:.2} / {n_pos:.2}",
            a.ori_deg, a.pos_m
        );
        assert!(a.ori_deg < 0.5 && a.pos_m < 0.05, "robot {r}: ATE {a:?}");
        assert!(
            n_ori < 6.0 && n_pos < 6.0,
            "robot {r}: NEES {n_ori} / {n_pos}"
        );
        let summary: serde_json::Value =
            serde_json::from_slice(&std::fs::read(out.join("summary.json")).expect("summary"))
                .expect("json");
        let m = &summary["robots"][0];
        let closures = m["loop_closures"].as_u64().unwrap_or(0);
        let common = m["common_feature_updates"].as_u64().unwrap_or(0);
        println!("robot {r}: {closures} loop closures, {common} common-feature updates");
        assert!(
            closures > 0 && common > 0,
            "robot {r} did not cooperate: {m}"
        );
    }
    // The last published pose is the fleet-frame estimate, on the truth.
    let received: Vec<_> = poses
        .drain()
        .map(|s| common::ros_cdr::decode_pose(&s.payload().to_bytes()).expect("a pose"))
        .collect();
    let last = received.last().expect("poses published");
    assert_eq!(last.header.frame_id, "fleet_world");
    let truth = common::trajectory::interpolate_pose(&seqs[0].1, last.pose.t).expect("covered");
    assert!(
        (last.pose.pos - truth.pos).norm() < 0.1,
        "{:?} vs {:?}",
        last.pose.pos,
        truth.pos
    );
    // Each pose went out as an odometry too. Its velocity is the body's, which
    // the truth gives by central differences (the exported truth is at the
    // image rate: a mean over 0.1 s). Its angular rate is the gyro's reading
    // at that time less the estimated bias: the simulator's bias is near 0, so
    // the reading itself is the check (the truth's mean over 0.1 s is not: the
    // rate about z falls from 0.14 to 0 rad/s within 0.1 s around 11.05 s).
    let odoms: Vec<_> = odometry
        .drain()
        .map(|s| common::ros_cdr::decode_odometry(&s.payload().to_bytes()).expect("an odometry"))
        .collect();
    assert_eq!(odoms.len(), received.len());
    let mid = odoms.len() / 2;
    let odom = &odoms[mid];
    assert_eq!(
        (odom.child_frame_id.as_str(), odom.pose.t),
        ("imu", received[mid].pose.t)
    );
    let h = 0.05;
    let at = |t: f64| common::trajectory::interpolate_pose(&seqs[0].1, t).expect("covered");
    let (before, now, after) = (at(odom.pose.t - h), at(odom.pose.t), at(odom.pose.t + h));
    let v_body = now.rot.transpose() * (after.pos - before.pos) / (2.0 * h);
    let reading = gyro_reading_at(&seqs[0].0, odom.pose.t);
    let tw = &odom.twist;
    println!(
        "twist at {:.4} s: {:?} vs truth {:?}; {:?} vs the gyro's {:?}; sigmas {:?}",
        odom.pose.t,
        tw.linear,
        v_body,
        tw.angular,
        reading,
        (0..6)
            .map(|i| tw.covariance[7 * i].sqrt())
            .collect::<Vec<_>>()
    );
    assert!(
        (tw.linear - v_body).norm() < 0.05,
        "{:?} vs {:?}",
        tw.linear,
        v_body
    );
    assert!(
        (tw.angular - reading).norm() < 0.02,
        "{:?} vs {:?}",
        tw.angular,
        reading
    );
    listener.close().wait().expect("close");
}

/// A live agent whose calibration is missing stops at once and names it;
/// one whose sensors never speak stops after `wait_s` and says on which keys
/// it listened.
#[test]
fn a_live_agent_without_calibration_or_sensors_stops_with_the_reason() {
    let dir = tempfile::tempdir().expect("tempdir");
    let ports: [u16; 4] = common::loopback_ports::free_loopback_ports(4)
        .expect("ports")
        .try_into()
        .expect("four");
    let start = StampedPose {
        t: 0.0,
        rot: nalgebra::Matrix3::identity(),
        pos: nalgebra::Vector3::zeros(),
    };
    let run = |calibration: &Path, extra: &str| {
        let cfg = dir.path().join("robot0.yaml");
        let text = config(0, calibration, &dir.path().join("out"), &ports, &start)
            .replace(
                "idle_timeout_s: 3",
                &format!("idle_timeout_s: 3\n    {extra}"),
            )
            .replace("peers: [1]", "peers: []");
        std::fs::write(&cfg, text).expect("config");
        let child = agent()
            .arg("--config")
            .arg(&cfg)
            .stdout(Stdio::piped())
            .stderr(Stdio::piped())
            .spawn()
            .expect("agent");
        let out = wait_for(child, Duration::from_secs(60));
        assert!(!out.status.success());
        String::from_utf8_lossy(&out.stderr).into_owned()
    };
    let missing = dir.path().join("no-such-calibration");
    let err = run(&missing, "");
    assert!(
        err.contains("calibration") && err.contains("no-such-calibration"),
        "{err}"
    );
    // A real calibration, and nobody publishing.
    let seq = PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("../../shared/data/euroc_v1_01_micro");
    let err = run(&seq, "wait_s: 1");
    assert!(
        err.contains("no sensor message decoded on robot0/imu0 or robot0/cam0/image_raw"),
        "{err}"
    );
}
