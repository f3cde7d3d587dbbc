use super::*;

fn rpe_row(segment_m: f64, pos: Option<f64>, count: usize) -> RpeEntry {
    RpeEntry {
        segment_m,
        ori_deg_mean: pos.map(|p| p * 10.0),
        pos_m_mean: pos,
        ori_deg_median: None,
        pos_m_median: pos,
        count,
    }
}

const METRIC_KEYS: [&str; 31] = [
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
    "bytes_per_s_sent",
    "messages_sent",
    "messages_received",
    "messages_dropped",
    "peer_losses",
    "latency_ms_mean",
    "latency_ms_p99",
    "history_bytes",
    "loop_closures",
    "common_feature_updates",
    "keyframe_windows_published",
    "peer_windows_published",
    "peer_windows_held",
    "peer_windows_whole",
    "replay_bytes_sent",
    "peer_frames_aligned",
    "peer_frame_yaw_err_deg",
    "peer_frame_pos_err_m",
    "peer_frame_nees",
    "first_peer_frame_s",
    "cpu_s",
];

#[test]
fn serialization_writes_every_key_with_null_when_unknown() {
    let summary = RunSummary {
        scenario: "two_robots".into(),
        seed: 3,
        robots: vec![RobotSummary {
            id: 0,
            trajectory: "robot0.txt".into(),
            metrics: MetricSet {
                ate_pos_m: Some(0.25),
                ..MetricSet::default()
            },
        }],
        ..RunSummary::default()
    };
    let value = serde_json::to_value(&summary).unwrap();
    let top = value.as_object().unwrap();
    for key in [
        "scenario",
        "variant",
        "seed",
        "transport",
        "wall_s",
        "sim_s",
        "robots",
        "mean",
    ] {
        assert!(top.contains_key(key), "missing {key}");
    }
    assert!(top["variant"].is_null() && top["wall_s"].is_null());
    let robot = top["robots"][0].as_object().unwrap();
    let mean = top["mean"].as_object().unwrap();
    for key in METRIC_KEYS {
        assert!(robot.contains_key(key), "robot misses {key}");
        assert!(mean.contains_key(key), "mean misses {key}");
        assert!(mean[key].is_null());
    }
    assert_eq!(robot["id"], 0);
    assert_eq!(robot["ate_pos_m"], 0.25);
    assert!(robot["nees_ori"].is_null());
}

#[test]
fn a_written_summary_reads_back_equal() {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("summary.json");
    let metrics = MetricSet {
        ate_ori_deg: Some(1.5),
        rpe: Some(vec![rpe_row(8.0, Some(0.1), 3), rpe_row(16.0, None, 0)]),
        frames: Some(1200),
        ..MetricSet::default()
    };
    let summary = RunSummary {
        scenario: "s".into(),
        variant: Some("collaborative".into()),
        seed: u64::MAX,
        transport: Some("udp".into()),
        wall_s: Some(12.5),
        sim_s: Some(60.0),
        robots: vec![RobotSummary {
            id: 2,
            trajectory: "r2.txt".into(),
            metrics: metrics.clone(),
        }],
        mean: metrics,
    };
    summary.write_json(&path).unwrap();
    assert_eq!(RunSummary::read_json(&path).unwrap(), summary);
}

#[test]
fn reading_a_bad_or_missing_file_names_it() {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("broken.json");
    std::fs::write(&path, "{\"scenario\": 1}").unwrap();
    let err = RunSummary::read_json(&path).unwrap_err();
    assert!(matches!(err, SummaryError::Json { .. }));
    assert!(err.to_string().contains("broken.json"));
    let missing = RunSummary::read_json(dir.path().join("none.json")).unwrap_err();
    assert!(matches!(missing, SummaryError::Io { .. }));
}

#[test]
fn the_mean_averages_each_field_over_the_robots_that_have_it() {
    let a = MetricSet {
        ate_pos_m: Some(1.0),
        nees_ori: Some(3.0),
        frames: Some(10),
        rpe: Some(vec![rpe_row(8.0, Some(0.2), 5), rpe_row(16.0, None, 0)]),
        ..MetricSet::default()
    };
    let b = MetricSet {
        ate_pos_m: Some(2.0),
        frames: Some(13),
        rpe: Some(vec![
            rpe_row(8.0, Some(0.4), 7),
            rpe_row(16.0, Some(1.0), 2),
        ]),
        ..MetricSet::default()
    };
    let c = MetricSet::default();
    let m = MetricSet::mean_of(&[a, b, c]);
    assert_eq!(m.ate_pos_m, Some(1.5));
    assert_eq!(m.nees_ori, Some(3.0));
    assert_eq!(m.nees_pos, None);
    assert_eq!(m.frames, Some(12));
    assert_eq!(m.bytes_sent, None);
    let rpe = m.rpe.unwrap();
    assert_eq!(rpe.len(), 2);
    assert_eq!(rpe[0].segment_m, 8.0);
    assert!((rpe[0].pos_m_mean.unwrap() - 0.3).abs() < 1e-15);
    assert_eq!(rpe[0].count, 12);
    assert_eq!(rpe[0].ori_deg_median, None);
    assert_eq!(rpe[1].pos_m_mean, Some(1.0));
    assert_eq!(rpe[1].count, 2);
    assert_eq!(MetricSet::mean_of(&[]), MetricSet::default());
}

#[test]
fn each_robot_is_owed_the_windows_the_others_published() {
    let with = |n: Option<u64>| MetricSet {
        keyframe_windows_published: n,
        ..MetricSet::default()
    };
    let mut sets = [with(Some(123)), with(Some(71)), with(Some(88))];
    fill_peer_windows_published(sets.iter_mut());
    let owed: Vec<_> = sets.iter().map(|m| m.peer_windows_published).collect();
    assert_eq!(owed, [Some(159), Some(211), Some(194)]);

    // One robot's count unknown (its summary is missing): nobody's sum is known.
    let mut sets = [with(Some(123)), with(None), with(Some(88))];
    fill_peer_windows_published(sets.iter_mut());
    assert!(sets.iter().all(|m| m.peer_windows_published.is_none()));
}
