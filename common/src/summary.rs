//! The `summary.json` schema shared by the fleet runner and the agent.
//!
//! Every key is always written; unknown values are `null` (nothing is
//! skipped), so tables over many runs have the same columns. Readers accept
//! missing optional keys as `null`.

use std::path::{Path, PathBuf};

use serde::{Deserialize, Serialize};

/// One RPE row of a summary (the same fields as the metric's result).
pub type RpeEntry = crate::metrics::RpeResult;

/// The summary of one run of a scenario (one file per run).
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct RunSummary {
    /// Scenario name.
    pub scenario: String,
    /// Variant of the system (e.g. `"independent"`, `"collaborative"`), if any.
    pub variant: Option<String>,
    /// Random seed of the run.
    pub seed: u64,
    /// Transport between robots (e.g. `"udp"`, `"in-process"`), if any.
    pub transport: Option<String>,
    /// Wall-clock duration (s).
    pub wall_s: Option<f64>,
    /// Simulated / dataset duration (s).
    pub sim_s: Option<f64>,
    /// One entry per robot.
    pub robots: Vec<RobotSummary>,
    /// The mean over the robots ([`MetricSet::mean_of`]).
    pub mean: MetricSet,
}

/// The metrics of one robot of a run.
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct RobotSummary {
    /// Robot index.
    pub id: u32,
    /// Path of the robot's estimated trajectory (TUM).
    pub trajectory: String,
    /// The robot's metrics, written at the same level as `id`.
    #[serde(flatten)]
    pub metrics: MetricSet,
}

/// Accuracy, consistency and cost metrics; `None` (`null`) when unknown.
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct MetricSet {
    /// ATE orientation RMSE (degrees).
    pub ate_ori_deg: Option<f64>,
    /// ATE position RMSE (m).
    pub ate_pos_m: Option<f64>,
    /// ATE orientation RMSE after aligning the estimate to the truth by a yaw and
    /// a translation (4 DoF, the directions VIO cannot observe; fitted to the
    /// positions, `Alignment::PosYaw`), degrees: the figure single-robot VIO
    /// papers report. The fit minimizes the position error, so this can exceed
    /// the unaligned orientation ATE.
    pub ate_posyaw_ori_deg: Option<f64>,
    /// ATE position RMSE after the same alignment (m).
    pub ate_posyaw_pos_m: Option<f64>,
    /// Mean orientation NEES.
    pub nees_ori: Option<f64>,
    /// Mean position NEES.
    pub nees_pos: Option<f64>,
    /// RPE per segment length.
    pub rpe: Option<Vec<RpeEntry>>,
    /// Camera frames processed.
    pub frames: Option<u64>,
    /// Mean processing time per frame (ms).
    pub ms_per_frame_mean: Option<f64>,
    /// 95th percentile of the processing time per frame (ms).
    pub ms_per_frame_p95: Option<f64>,
    /// Bytes sent to other robots.
    pub bytes_sent: Option<u64>,
    /// Bytes received from other robots.
    pub bytes_received: Option<u64>,
    /// Bytes sent per second of fleet time.
    pub bytes_per_s_sent: Option<f64>,
    /// Messages sent to other robots.
    pub messages_sent: Option<u64>,
    /// Messages received from other robots and accepted.
    pub messages_received: Option<u64>,
    /// Received payloads dropped (malformed, foreign fleet, impostor sender).
    pub messages_dropped: Option<u64>,
    /// Times a peer vanished (died, froze or was cut off) before announcing
    /// the end of its data.
    pub peer_losses: Option<u64>,
    /// Mean one-way message latency, ms (wall clock, same host).
    pub latency_ms_mean: Option<f64>,
    /// 99th percentile of the one-way message latency, ms.
    pub latency_ms_p99: Option<f64>,
    /// Peak heap bytes of peer histories (all peers).
    pub history_bytes: Option<u64>,
    /// Inter- or intra-robot loop closures used.
    pub loop_closures: Option<u64>,
    /// Filter updates with features seen by several robots.
    pub common_feature_updates: Option<u64>,
    /// Keyframe windows this agent published: its history, as its peers
    /// store it.
    pub keyframe_windows_published: Option<u64>,
    /// Keyframe windows the other robots of the run published: what this
    /// agent would hold of its peers had it missed nothing. Only a fleet's
    /// summary knows it (`fill_peer_windows_published`); `null` in an agent's
    /// own.
    pub peer_windows_published: Option<u64>,
    /// Peers' keyframe windows this agent held at the end of its run.
    pub peer_windows_held: Option<u64>,
    /// Of those, the windows held whole: a frame at every clone, and the
    /// keyframe's descriptors.
    pub peer_windows_whole: Option<u64>,
    /// Bytes of history replays this agent sent to peers that asked for
    /// windows they had missed (history catch-up).
    pub replay_bytes_sent: Option<u64>,
    /// Peers whose world frame this agent aligned to its own from loop
    /// closures (`align_peer_frames`; `null` when off).
    pub peer_frames_aligned: Option<u64>,
    /// Root mean square yaw error of those alignments at the end, deg
    /// (simulation: against the true relative start poses).
    pub peer_frame_yaw_err_deg: Option<f64>,
    /// Root mean square translation error of those alignments at the end, m.
    pub peer_frame_pos_err_m: Option<f64>,
    /// Mean NEES (4 DoF: yaw, translation) of those alignments at the end.
    pub peer_frame_nees: Option<f64>,
    /// Fleet time from this robot's start to its first aligned peer, s.
    pub first_peer_frame_s: Option<f64>,
    /// CPU time of the run, s: an agent process's, all its threads (transport
    /// included) from the start of its run to the end; an agent on a thread of
    /// `sim-fleet`, or a standalone run (`agent run`, the independent
    /// Monte-Carlo variants), its thread's; a centralized run, its joint
    /// estimator's thread divided by the robots. It includes simulating the
    /// robots' sensors.
    pub cpu_s: Option<f64>,
    /// Mean error of the image frontend's tracks against the rendered truth,
    /// px (a run through rendered images; `null` otherwise).
    pub track_error_px: Option<f64>,
}

/// Why a summary could not be written or read.
#[derive(Debug, thiserror::Error)]
pub enum SummaryError {
    /// The file could not be created, written or read.
    #[error("cannot access {}", path.display())]
    Io {
        /// The file.
        path: PathBuf,
        /// The I/O error.
        #[source]
        source: std::io::Error,
    },
    /// The content is not a valid summary (or could not be serialized).
    #[error("invalid summary JSON in {}", path.display())]
    Json {
        /// The file.
        path: PathBuf,
        /// The JSON error (with line and column when reading).
        #[source]
        source: serde_json::Error,
    },
}

impl RunSummary {
    /// Writes the summary as pretty-printed JSON.
    pub fn write_json(&self, path: impl AsRef<Path>) -> Result<(), SummaryError> {
        let path = path.as_ref();
        let text = serde_json::to_string_pretty(self).map_err(|source| SummaryError::Json {
            path: path.to_path_buf(),
            source,
        })?;
        std::fs::write(path, text + "\n").map_err(|source| SummaryError::Io {
            path: path.to_path_buf(),
            source,
        })
    }

    /// Reads a summary written by [`RunSummary::write_json`].
    pub fn read_json(path: impl AsRef<Path>) -> Result<Self, SummaryError> {
        let path = path.as_ref();
        let text = std::fs::read_to_string(path).map_err(|source| SummaryError::Io {
            path: path.to_path_buf(),
            source,
        })?;
        serde_json::from_str(&text).map_err(|source| SummaryError::Json {
            path: path.to_path_buf(),
            source,
        })
    }
}

impl MetricSet {
    /// The field-wise mean over `sets`, each field over the sets that have it
    /// (`None` if none has it). Counters are rounded to the nearest integer.
    /// RPE rows are matched by segment length: statistics are averaged over
    /// the sets that have them (so medians become means of medians) and
    /// counts are summed.
    pub fn mean_of(sets: &[MetricSet]) -> MetricSet {
        let f = |get: fn(&MetricSet) -> Option<f64>| mean(sets.iter().filter_map(get));
        let u = |get: fn(&MetricSet) -> Option<u64>| {
            mean(sets.iter().filter_map(get).map(|v| v as f64)).map(|m| m.round() as u64)
        };
        MetricSet {
            ate_ori_deg: f(|s| s.ate_ori_deg),
            ate_pos_m: f(|s| s.ate_pos_m),
            ate_posyaw_ori_deg: f(|s| s.ate_posyaw_ori_deg),
            ate_posyaw_pos_m: f(|s| s.ate_posyaw_pos_m),
            nees_ori: f(|s| s.nees_ori),
            nees_pos: f(|s| s.nees_pos),
            rpe: mean_rpe(sets),
            frames: u(|s| s.frames),
            ms_per_frame_mean: f(|s| s.ms_per_frame_mean),
            ms_per_frame_p95: f(|s| s.ms_per_frame_p95),
            bytes_sent: u(|s| s.bytes_sent),
            bytes_received: u(|s| s.bytes_received),
            bytes_per_s_sent: f(|s| s.bytes_per_s_sent),
            messages_sent: u(|s| s.messages_sent),
            messages_received: u(|s| s.messages_received),
            messages_dropped: u(|s| s.messages_dropped),
            peer_losses: u(|s| s.peer_losses),
            latency_ms_mean: f(|s| s.latency_ms_mean),
            latency_ms_p99: f(|s| s.latency_ms_p99),
            history_bytes: u(|s| s.history_bytes),
            loop_closures: u(|s| s.loop_closures),
            common_feature_updates: u(|s| s.common_feature_updates),
            keyframe_windows_published: u(|s| s.keyframe_windows_published),
            peer_windows_published: u(|s| s.peer_windows_published),
            peer_windows_held: u(|s| s.peer_windows_held),
            peer_windows_whole: u(|s| s.peer_windows_whole),
            replay_bytes_sent: u(|s| s.replay_bytes_sent),
            peer_frames_aligned: u(|s| s.peer_frames_aligned),
            peer_frame_yaw_err_deg: f(|s| s.peer_frame_yaw_err_deg),
            peer_frame_pos_err_m: f(|s| s.peer_frame_pos_err_m),
            peer_frame_nees: f(|s| s.peer_frame_nees),
            first_peer_frame_s: f(|s| s.first_peer_frame_s),
            cpu_s: f(|s| s.cpu_s),
            track_error_px: f(|s| s.track_error_px),
        }
    }
}

/// Fills in each robot's `peer_windows_published`: the keyframe windows the
/// other robots of `sets` (one robot each, every robot of a fleet run)
/// published. Left `None` for all when a robot's own count is unknown, since
/// the others' sums would then be short.
pub fn fill_peer_windows_published<'a>(sets: impl IntoIterator<Item = &'a mut MetricSet>) {
    let mut sets: Vec<&mut MetricSet> = sets.into_iter().collect();
    let total: Option<u64> = sets.iter().map(|m| m.keyframe_windows_published).sum();
    for m in &mut sets {
        m.peer_windows_published = total
            .zip(m.keyframe_windows_published)
            .map(|(t, own)| t - own);
    }
}

/// The mean of the values, `None` for none.
fn mean(values: impl Iterator<Item = f64>) -> Option<f64> {
    let (sum, n) = values.fold((0.0, 0usize), |(s, n), v| (s + v, n + 1));
    (n > 0).then(|| sum / n as f64)
}

/// RPE rows averaged by segment length, in order of first appearance.
fn mean_rpe(sets: &[MetricSet]) -> Option<Vec<RpeEntry>> {
    let rows: Vec<&RpeEntry> = sets
        .iter()
        .filter_map(|s| s.rpe.as_ref())
        .flatten()
        .collect();
    if sets.iter().all(|s| s.rpe.is_none()) {
        return None;
    }
    let mut segments: Vec<f64> = Vec::new();
    for r in &rows {
        if !segments.iter().any(|s| same_segment(*s, r.segment_m)) {
            segments.push(r.segment_m);
        }
    }
    let out = segments
        .into_iter()
        .map(|segment_m| {
            let group: Vec<&&RpeEntry> = rows
                .iter()
                .filter(|r| same_segment(r.segment_m, segment_m))
                .collect();
            let avg = |get: fn(&RpeEntry) -> Option<f64>| mean(group.iter().filter_map(|r| get(r)));
            RpeEntry {
                segment_m,
                ori_deg_mean: avg(|r| r.ori_deg_mean),
                pos_m_mean: avg(|r| r.pos_m_mean),
                ori_deg_median: avg(|r| r.ori_deg_median),
                pos_m_median: avg(|r| r.pos_m_median),
                count: group.iter().map(|r| r.count).sum(),
            }
        })
        .collect();
    Some(out)
}

/// Segment lengths equal up to rounding.
fn same_segment(a: f64, b: f64) -> bool {
    (a - b).abs() <= 1e-9 * a.abs().max(1.0)
}

#[cfg(test)]
mod tests;
