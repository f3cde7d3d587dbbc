//! The MCAP file an agent writes is something Foxglove opens: two agents on
//! rendered images (in-process transport) write their logs, and robot 0's is
//! read back, schema by schema.

#![allow(clippy::expect_used, clippy::unwrap_used)]

use agent::agent_output::write_outputs;
use agent::config::AgentConfig;
use agent::node::{run_node, RobotSetup};
use agent::transport::InprocHub;
use std::collections::BTreeMap;
use std::path::Path;
use std::sync::atomic::AtomicBool;
use std::sync::Arc;

/// A 14 s loop (20 Hz, TUM), radius 2.5 m, turning with the path.
fn write_loop(path: &Path) {
    let mut text = String::from("# t x y z qx qy qz qw\n");
    for k in 0..=280 {
        let s = f64::from(k) / 20.0;
        let (x, y, z) = (
            2.5 * (0.3 * s).cos(),
            2.5 * (0.3 * s).sin(),
            1.2 + 0.2 * (0.6 * s).sin(),
        );
        let yaw = 0.3 * s + 1.57;
        text.push_str(&format!(
            "{:.3} {x:.6} {y:.6} {z:.6} 0 0 {:.9} {:.9}\n",
            50.0 + s,
            (yaw / 2.0).sin(),
            (yaw / 2.0).cos()
        ));
    }
    std::fs::write(path, text).unwrap();
}

fn config(dir: &Path, robot: u32, peer: u32) -> AgentConfig {
    let input = format!(
        "  source: simulator\n  scenario: {}\n",
        dir.join("two.yaml").display()
    );
    config_with(dir, robot, &input, &format!("[{peer}]"))
}

fn config_with(dir: &Path, robot: u32, input: &str, peers: &str) -> AgentConfig {
    let p = dir.join(format!("robot{robot}.yaml"));
    std::fs::write(
        &p,
        format!(
            "robot_id: {robot}\nfleet_id: log-{}\noutput_dir: {}\ntransport:\n  kind: inproc\ninput:\n{input}  robot_index: {robot}\nclock:\n  mode: lockstep\n  peers: {peers}\nimages:\n  mcap_every: 4\n",
            std::process::id(),
            dir.join(format!("robot{robot}")).display(),
        ),
    )
    .unwrap();
    AgentConfig::load(&p).unwrap()
}

#[test]
fn an_agent_on_images_writes_foxglove_schemas_a_reader_counts_back() {
    let dir = tempfile::tempdir().unwrap();
    write_loop(&dir.path().join("loop.txt"));
    std::fs::write(
        dir.path().join("two.yaml"),
        "name: two\nrobots:\n  - trajectory: loop.txt\n  - trajectory: loop.txt\n    start_time_s: 1.0\nrender:\n  enabled: true\nestimator:\n  start_after_motion_m: 0.5\n",
    )
    .unwrap();
    let hub = InprocHub::new();
    let stop = Arc::new(AtomicBool::new(false));
    let handles: Vec<_> = [(0u32, 1u32), (1, 0)]
        .into_iter()
        .map(|(me, peer)| {
            let cfg = config(dir.path(), me, peer);
            let transport = agent::transport::open(&cfg.transport_settings(), Some(&hub)).unwrap();
            let stop = Arc::clone(&stop);
            std::thread::spawn(move || {
                let setup = RobotSetup::load(&cfg).unwrap();
                let report = run_node(&cfg, &setup, transport, &stop, |_| {}).unwrap();
                write_outputs(&report, cfg.robot_id, "inproc", &cfg.output_dir).unwrap();
                report.run.frames.len()
            })
        })
        .collect();
    let frames: Vec<usize> = handles.into_iter().map(|h| h.join().unwrap()).collect();
    assert!(frames[0] > 80, "{frames:?}");

    let bytes = std::fs::read(dir.path().join("robot0/agent.mcap")).unwrap();
    let mut by_schema: BTreeMap<String, usize> = BTreeMap::new();
    let mut by_topic: BTreeMap<String, usize> = BTreeMap::new();
    let mut peer_in_scene = false;
    let mut image_size = None;
    for m in mcap::MessageStream::new(&bytes).unwrap() {
        let m = m.unwrap();
        let schema = m.channel.schema.as_ref().unwrap();
        assert_eq!(schema.encoding, "jsonschema");
        assert_eq!(m.channel.message_encoding, "json");
        let v: serde_json::Value = serde_json::from_slice(&m.data).unwrap();
        *by_schema.entry(schema.name.clone()).or_default() += 1;
        *by_topic.entry(m.channel.topic.clone()).or_default() += 1;
        match schema.name.as_str() {
            "foxglove.SceneUpdate" => {
                peer_in_scene |= v["entities"]
                    .as_array()
                    .unwrap()
                    .iter()
                    .any(|e| e["id"] == "peer_1");
            }
            "foxglove.CompressedImage" if image_size.is_none() => {
                assert_eq!(v["format"], "png");
                let png = common::base64::decode(v["data"].as_str().unwrap()).unwrap();
                let img = common::image::GrayImage::from_png(&png).unwrap();
                image_size = Some((img.width(), img.height()));
            }
            "foxglove.ImageAnnotations" => {
                let n = v["points"][0]["points"].as_array().unwrap().len();
                assert!(n > 100, "{n} tracked features drawn");
            }
            "fleet.BodyTwist" => {
                let sigma = v["sigma"].as_array().unwrap();
                let estimated = m.channel.topic == "/estimate/twist";
                assert_eq!(sigma.len(), if estimated { 6 } else { 0 });
                assert!(v["linear_mps"]["x"].is_f64() && v["angular_radps"]["z"].is_f64());
            }
            _ => {}
        }
    }
    println!("{by_topic:?}");
    let f = frames[0];
    assert_eq!(by_topic["/estimate"], f);
    assert_eq!(by_topic["/groundtruth"], f);
    assert_eq!(by_schema["fleet.PoseCovariance"], f);
    assert_eq!(by_topic["/estimate/twist"], f);
    assert_eq!(by_topic["/groundtruth/twist"], f);
    // Every 10 frames (a short run), and once more at the end.
    assert_eq!(by_topic["/estimate/path"], f.div_ceil(10) + 1);
    assert_eq!(by_topic["/groundtruth/path"], f.div_ceil(10) + 1);
    assert_eq!(by_schema["foxglove.SceneUpdate"], f.div_ceil(10));
    let images = by_schema["foxglove.CompressedImage"];
    assert!(images >= f / 4, "{images} images for {f} frames");
    assert_eq!(by_schema["foxglove.ImageAnnotations"], images);
    assert!(by_schema["foxglove.Log"] >= 1, "peer events");
    assert!(by_topic.keys().any(|t| t.starts_with("/peers/1/")));
    assert!(peer_in_scene, "the peer's pose is in the scene");
    assert_eq!(image_size, Some((752, 480)));
}

#[test]
fn an_agent_replays_a_rendered_recording_through_its_frontend() {
    let dir = tempfile::tempdir().unwrap();
    write_loop(&dir.path().join("loop.txt"));
    let scenario = dir.path().join("one.yaml");
    std::fs::write(
        &scenario,
        "name: one\nrobots:\n  - trajectory: loop.txt\nrender:\n  enabled: true\nestimator:\n  start_after_motion_m: 0.5\n",
    )
    .unwrap();
    let sc = simulator::Scenario::load(&scenario).unwrap();
    let fleet = simulator::Fleet::build(&sc, 3).unwrap();
    let recording = dir.path().join("rec.mcap");
    simulator::mcap_io::write_stream(&recording, fleet.stream(0).unwrap()).unwrap();
    let input = format!(
        "  source: mcap\n  scenario: {}\n  seed: 3\n  mcap: {}\n",
        scenario.display(),
        recording.display()
    );
    let cfg = config_with(dir.path(), 0, &input, "[]");
    let hub = InprocHub::new();
    let transport = agent::transport::open(&cfg.transport_settings(), Some(&hub)).unwrap();
    let setup = RobotSetup::load(&cfg).unwrap();
    let report = run_node(&cfg, &setup, transport, &AtomicBool::new(false), |_| {}).unwrap();
    let m = agent::agent_output::metrics_of(&report);
    println!(
        "replayed rendered recording: {} frames, ATE {:?} m",
        report.run.frames.len(),
        m.ate_pos_m
    );
    assert!(report.run.frames.len() > 80);
    assert!(m.ate_pos_m.unwrap() < 0.3, "{m:?}");
}
