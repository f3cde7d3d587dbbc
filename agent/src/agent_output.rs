//! What an agent leaves in its output folder after a run:
//! `estimate.txt` / `groundtruth.txt` (TUM), `covariance.txt`, `timing.csv`,
//! `peer_events.jsonl`, `transport_stats.json` and `summary.json` (plus the MCAP
//! log written during the run).

use crate::node::NodeReport;
use crate::runner::write_run_outputs;
use common::metrics::percentile_sorted;
use common::summary::{MetricSet, RobotSummary, RunSummary};
use serde::Serialize;
use std::collections::BTreeMap;
use std::path::Path;

/// What was kept of one peer, for `transport_stats.json`.
#[derive(Clone, Debug, Serialize)]
pub struct HistoryReport {
    /// Keyframe windows held at the end.
    pub keyframes: usize,
    /// Of those, windows held whole: a frame of measurements at every clone,
    /// and the keyframe's descriptors.
    pub whole: usize,
    /// Keyframe windows stored in total.
    pub stored: u64,
    /// Keyframe windows dropped by the memory bound.
    pub dropped: u64,
    /// Bytes held at the end (history and recent data).
    pub bytes: usize,
    /// Fleet time spanned by the held keyframe windows, s.
    pub span_s: f64,
    /// Memory growth: history bytes per hour of the peer's fleet time, over
    /// every window stored (those the bound dropped too).
    pub bytes_per_peer_hour: Option<f64>,
    /// Bytes of the peer's bag-of-words keyframe database at the end (it holds
    /// the windows the history holds, and one list per vocabulary word).
    pub keyframe_db_bytes: usize,
    /// Its growth per hour of the peer's fleet time: bytes per window it holds
    /// times the windows the history stored per hour.
    pub keyframe_db_bytes_per_peer_hour: Option<f64>,
}

/// The contents of `transport_stats.json`.
#[derive(Clone, Debug, Serialize)]
pub struct TransportReport<'a> {
    /// Transport name.
    pub transport: &'a str,
    /// Traffic per kind, per peer, drops and gaps.
    pub net: &'a crate::inbox::NetStats,
    /// Messages that could not be sent.
    pub publish_errors: u64,
    /// Bytes sent per second of fleet time, per kind.
    pub bytes_per_s_by_kind: BTreeMap<String, f64>,
    /// Latency percentiles (ms): p50, p99, max.
    pub latency_ms: Option<[f64; 3]>,
    /// Peer presence at the end.
    pub peers: &'a BTreeMap<u32, crate::peer_events::PeerPresence>,
    /// Histories per peer.
    pub histories: BTreeMap<u32, HistoryReport>,
    /// Peak history bytes (all peers).
    pub peak_history_bytes: usize,
    /// Real time: largest lag behind the wall clock, s.
    pub max_lag_s: f64,
    /// Ticks done.
    pub ticks: u64,
    /// Stopped by a signal.
    pub interrupted: bool,
    /// History catch-up: requests, replays, windows recovered (`None`: off).
    pub catch_up: Option<&'a crate::history_catchup::CatchUpStats>,
    /// Bytes of this agent's archive of its own keyframe windows (what it
    /// can send again).
    pub own_archive_bytes: usize,
    /// Keyframe windows in that archive.
    pub own_archive_windows: usize,
    /// Of those, windows whole (a frame at every clone, and descriptors).
    pub own_archive_whole_windows: usize,
    /// Messages dropped by the injected outage (`faults.outage_fleet_s`).
    pub outage_dropped: u64,
    /// Messages dropped by the injected loss (`faults.loss_fraction`).
    pub loss_dropped: u64,
    /// The history store: windows read back at start, files written
    /// (`None`: no `history.store_dir`).
    pub history_store: Option<&'a crate::node::StoreStats>,
    /// The end of the run: how long it took to settle, and whether it did
    /// (`None`: stopped before).
    pub settle: Option<&'a crate::node::SettleStats>,
    /// Each peer's frames as this agent found them, oldest epoch first
    /// (`align_peer_frames`; absent when off).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub peer_frames: Option<BTreeMap<u32, Vec<PeerFrameReport>>>,
}

/// Where one of a peer's frames is in ours, as measured from loop closures.
#[derive(Clone, Debug, Serialize, PartialEq)]
pub struct PeerFrameReport {
    /// The frame (`StateSnapshot::frame_epoch`): a peer started again in
    /// real time sends a new one.
    pub frame_epoch: u64,
    /// Whether the frame was confirmed (its windows were used from then on).
    pub aligned: bool,
    /// When it was confirmed (fleet clock), s.
    pub aligned_at_s: Option<f64>,
    /// `ψ` of `p_ours = R_z(ψ) p_peer + t`, deg.
    pub yaw_deg: Option<f64>,
    /// `t`, m.
    pub t_m: Option<[f64; 3]>,
    /// Standard deviation of the yaw, deg.
    pub yaw_sigma_deg: Option<f64>,
    /// Root of the summed translation variances, m.
    pub t_sigma_m: Option<f64>,
    /// Loop-closure measurements taken in.
    pub measurements: u64,
    /// Measurements that disagreed with the confirmed frame (dropped).
    pub disagreements: u64,
    /// Loop closures that gave no measurement.
    pub failures: u64,
    /// Whether the agent's filter held the frame as states at the end
    /// (`cooperation.peer_frame_state_s`), or used it as a fixed alignment.
    pub in_filter: bool,
}

impl PeerFrameReport {
    /// The report of `f`, the peer's frame `frame_epoch`.
    pub fn of(frame_epoch: u64, f: &crate::cooperation::peer_frames::PeerFrame) -> Self {
        let a = f.alignment();
        Self {
            frame_epoch,
            aligned: a.is_some(),
            aligned_at_s: f.aligned_at_s,
            yaw_deg: a.map(|a| a.yaw_rad.to_degrees()),
            t_m: a.map(|a| [a.t_m.x, a.t_m.y, a.t_m.z]),
            yaw_sigma_deg: a.map(|a| a.yaw_sigma_rad().to_degrees()),
            t_sigma_m: a.map(|a| a.translation_sigma_m()),
            measurements: f.measurements,
            disagreements: f.disagreements,
            failures: f.failures,
            in_filter: f.in_filter,
        }
    }
}

/// The finite values, sorted.
fn sorted_finite(values: &[f64]) -> Vec<f64> {
    let mut v: Vec<f64> = values.iter().copied().filter(|v| v.is_finite()).collect();
    v.sort_unstable_by(f64::total_cmp);
    v
}

/// History statistics of one peer, whose keyframe database holds `db.0`
/// bytes, `db.1` per window.
pub fn history_report(h: &crate::peer_history::PeerHistory, db: (usize, f64)) -> HistoryReport {
    let first = h
        .keyframes
        .values()
        .next()
        .and_then(|k| k.snapshot.clones.first().map(|c| c.t_s));
    let last = h
        .keyframes
        .values()
        .next_back()
        .and_then(|k| k.snapshot.clones.last().map(|c| c.t_s));
    let span_s = match (first, last) {
        (Some(a), Some(b)) => (b - a).max(0.0),
        _ => 0.0,
    };
    let stored_s = h.stored_span_s();
    HistoryReport {
        keyframes: h.keyframes.len(),
        whole: h.keyframes.values().filter(|kf| kf.is_whole()).count(),
        stored: h.stored_keyframes,
        dropped: h.dropped_keyframes,
        bytes: h.bytes(),
        span_s,
        // Over everything stored: held bytes over the held span would understate
        // the growth once the bound has dropped windows out of order.
        bytes_per_peer_hour: (stored_s > 1.0).then(|| h.stored_bytes as f64 / stored_s * 3600.0),
        keyframe_db_bytes: db.0,
        keyframe_db_bytes_per_peer_hour: (stored_s > 1.0)
            .then(|| db.1 * h.stored_keyframes as f64 / stored_s * 3600.0),
    }
}

/// Writes every output of `report` into `dir`; `transport` names the transport.
pub fn write_outputs(
    report: &NodeReport,
    robot_id: u32,
    transport: &str,
    dir: &Path,
) -> std::io::Result<()> {
    if report.run_files_in.as_deref() != Some(dir) {
        write_run_outputs(&report.run, dir)?;
    }
    let mut events = std::io::BufWriter::new(std::fs::File::create(dir.join("peer_events.jsonl"))?);
    report.peers.write_jsonl(&mut events)?;
    std::io::Write::flush(&mut events)?;

    let lat = sorted_finite(&report.latencies_ms);
    let latency_ms = match (percentile_sorted(&lat, 0.5), percentile_sorted(&lat, 0.99)) {
        (Some(p50), Some(p99)) => Some([p50, p99, lat.last().copied().unwrap_or(p99)]),
        _ => None,
    };
    let fleet_s = report.fleet_s.max(1e-9);
    let transport_report = TransportReport {
        transport,
        net: &report.net,
        publish_errors: report.publish_errors,
        bytes_per_s_by_kind: report
            .net
            .kinds
            .iter()
            .map(|(k, c)| (k.as_str().to_string(), c.sent_bytes as f64 / fleet_s))
            .collect(),
        latency_ms,
        peers: &report.peers.peers,
        histories: report
            .histories
            .iter()
            .map(|(p, h)| {
                let db = report.keyframe_db_bytes.get(p).copied().unwrap_or_default();
                (*p, history_report(h, db))
            })
            .collect(),
        peak_history_bytes: report.peak_history_bytes,
        max_lag_s: report.max_lag_s,
        ticks: report.ticks,
        interrupted: report.interrupted,
        catch_up: report.catch_up.as_ref(),
        own_archive_bytes: report.own_archive_bytes,
        own_archive_windows: report.own_archive_windows,
        own_archive_whole_windows: report.own_archive_whole_windows,
        outage_dropped: report.outage_dropped,
        loss_dropped: report.loss_dropped,
        history_store: report.store.as_ref(),
        settle: report.settle.as_ref(),
        peer_frames: report.peer_frames.as_ref().map(|frames| {
            frames
                .iter()
                .map(|(p, epochs)| {
                    let each = epochs.iter().map(|(e, f)| PeerFrameReport::of(*e, f));
                    (*p, each.collect())
                })
                .collect()
        }),
    };
    let json = serde_json::to_string_pretty(&transport_report).map_err(std::io::Error::other)?;
    std::fs::write(dir.join("transport_stats.json"), json)?;

    let metrics = metrics_of(report);
    let summary = RunSummary {
        scenario: report.scenario.clone(),
        variant: Some(report.variant.clone()),
        seed: report.seed,
        transport: Some(transport.to_string()),
        wall_s: Some(report.wall_s),
        sim_s: Some(report.fleet_s),
        mean: MetricSet::mean_of(std::slice::from_ref(&metrics)),
        robots: vec![RobotSummary {
            id: robot_id,
            trajectory: report.robot_name.clone(),
            metrics,
        }],
    };
    summary
        .write_json(dir.join("summary.json"))
        .map_err(|e| std::io::Error::other(e.to_string()))
}

/// The robot's metrics: the estimator's, plus traffic and peers.
pub fn metrics_of(report: &NodeReport) -> MetricSet {
    let mut m = report.run.metrics();
    let net = &report.net;
    m.bytes_sent = Some(net.bytes_sent());
    m.bytes_received = Some(net.bytes_received());
    m.bytes_per_s_sent = (report.fleet_s > 0.0).then(|| net.bytes_sent() as f64 / report.fleet_s);
    m.messages_sent = Some(net.kinds.values().map(|k| k.sent).sum());
    m.messages_received = Some(net.kinds.values().map(|k| k.received).sum());
    m.messages_dropped = Some(net.dropped.values().sum());
    m.peer_losses = Some(
        report
            .peers
            .peers
            .values()
            .map(|p| u64::from(p.losses))
            .sum(),
    );
    let lat = sorted_finite(&report.latencies_ms);
    m.latency_ms_mean = (!lat.is_empty()).then(|| lat.iter().sum::<f64>() / lat.len() as f64);
    m.latency_ms_p99 = percentile_sorted(&lat, 0.99);
    m.history_bytes = Some(report.peak_history_bytes as u64);
    m.keyframe_windows_published = Some(report.keyframe_windows_published);
    let held = report.histories.values().flat_map(|h| h.keyframes.values());
    let (held, whole) = held.fold((0, 0), |(n, w), kf| (n + 1, w + u64::from(kf.is_whole())));
    m.peer_windows_held = Some(held);
    m.peer_windows_whole = Some(whole);
    // Without catch-up nothing is replayed.
    m.replay_bytes_sent = Some(report.catch_up.as_ref().map_or(0, |c| c.replay_bytes));
    m.cpu_s = report.cpu_s;
    if let Some(frames) = &report.peer_frames {
        let s = crate::cooperation::peer_frames::score(frames, |p| {
            report.true_peer_frames.get(&p).copied()
        });
        m.peer_frames_aligned = Some(s.aligned);
        m.peer_frame_yaw_err_deg = s.yaw_err_deg;
        m.peer_frame_pos_err_m = s.pos_err_m;
        m.peer_frame_nees = s.nees;
        let start = report
            .estimator_start_s
            .or_else(|| report.run.estimate.first().map(|p| p.t));
        m.first_peer_frame_s = s.first_aligned_at_s.zip(start).map(|(a, b)| a - b);
    }
    m
}
