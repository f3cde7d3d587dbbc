//! One agent process at work: it reads its own robot's sensors, runs its
//! estimator, tells its peers what it sees, listens to them, and keeps their
//! histories. [`run_node`] is the whole loop, one camera tick at a time:
//!
//! 1. wait for the fleet clock (lockstep barrier, or the wall clock in real time);
//! 2. hand the peers' messages of the previous ticks to their histories;
//! 3. feed this tick's IMU samples and images to the estimator, publishing each
//!    processed frame's tracks, new descriptors and, when due, a window snapshot;
//! 4. announce the tick done (heartbeat).
//!
//! At the end it says so (a `Finished` heartbeat) and keeps listening while peers
//! still run, so nothing they send is lost.

use crate::agent_log_views::PeerPose;
use crate::config::{AgentConfig, ClockMode, FaultDrop, FaultedMessage, FaultsConfig, InputSource};
use crate::estimator::{Estimator, FrameOutput};
use crate::fleet_clock::{Lockstep, Pacer, TickGrid};
use crate::history_catchup::{CatchUp, CatchUpStats, Replayer};
use crate::history_store::{Done, HistoryStore, Saved, StoreError, StoreWriter};
use crate::inbox::{DropReason, Inbox, NetStats, PeerRates};
use crate::node_images::ImageFrames;
use crate::outbox::Outbox;
use crate::peer_events::{PeerEvent, PeerEvents};
use crate::peer_history::{HistoryLimits, PeerHistory};
use crate::run_files::{RunFiles, FLUSH_PERIOD};
use crate::runner::{initial_state, options_for, record, truth_twist, RobotRun, RunError, Variant};
use crate::status_log::{Counters, StatusLog};
use crate::transport::{Received, Transport, TransportError};
use common::measurement::FeatureFrame;
use common::messages::{
    encode, AgentState, Body, Envelope, HistoryReplay, RequestRef, MAX_REPLAY_ROBOTS,
};
use simulator::{Fleet, Scenario, SimEvent};
use std::collections::{BTreeMap, VecDeque};
use std::path::Path;
use std::sync::atomic::{AtomicBool, Ordering};
use std::time::{Duration, Instant};
use thiserror::Error;

mod live;
pub use live::{run_live_node, LiveSetup};

/// Why an agent could not run.
#[derive(Debug, Error)]
pub enum NodeError {
    /// The scenario could not be loaded.
    #[error(transparent)]
    Scenario(#[from] simulator::scenario::ScenarioError),
    /// The simulation failed.
    #[error(transparent)]
    Sim(#[from] simulator::SimError),
    /// Replay file error.
    #[error(transparent)]
    Replay(#[from] simulator::mcap_io::McapIoError),
    /// Estimator set-up error.
    #[error(transparent)]
    Run(#[from] RunError),
    /// The vocabulary file could not be loaded.
    #[error(transparent)]
    Vocabulary(#[from] vocabulary::VocabIoError),
    /// The transport failed beyond recovery.
    #[error(transparent)]
    Transport(#[from] TransportError),
    /// Camera images could not be turned into features.
    #[error("camera images: {0}")]
    Images(String),
    /// The history store (`history.store_dir`) could not be opened.
    #[error("history store: {0}")]
    Store(#[from] crate::history_store::StoreError),
    /// Live sensors could not be read (`input.source: live`).
    #[error("live sensors: {0}")]
    Live(#[from] crate::ros_input::LiveError),
    /// The live sensors' calibration could not be read.
    #[error("calibration: {0}")]
    Calibration(#[from] crate::dataset::DatasetError),
}

/// Progress of a run, for the launcher's display.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Progress {
    /// Ticks done.
    pub tick: u64,
    /// Ticks in the run.
    pub ticks_total: u64,
    /// Camera frames processed by the estimator.
    pub frames: u64,
    /// Real time: how far behind the wall clock the agent is, s.
    pub lag_s: f64,
}

/// Everything a finished run knows.
#[derive(Debug, Default)]
pub struct NodeReport {
    /// The estimate, truth, covariances and per-frame outputs.
    pub run: RobotRun,
    /// The folder that holds `run`'s text files whole, written as the run
    /// went ([`RunFiles`]); [`crate::agent_output::write_outputs`] writes them
    /// into any other.
    pub run_files_in: Option<std::path::PathBuf>,
    /// Traffic statistics.
    pub net: NetStats,
    /// Peer presence and its event log.
    pub peers: PeerEvents,
    /// What was kept of each peer.
    pub histories: BTreeMap<u32, PeerHistory>,
    /// Largest total history bytes seen.
    pub peak_history_bytes: usize,
    /// Each peer's keyframe database at the end: bytes, and bytes per window.
    pub keyframe_db_bytes: BTreeMap<u32, (usize, f64)>,
    /// Each peer's frames (by epoch) as aligned to ours (`align_peer_frames`;
    /// `None` off).
    pub peer_frames:
        Option<BTreeMap<u32, BTreeMap<u64, crate::cooperation::peer_frames::PeerFrame>>>,
    /// Where each peer's frame truly is in ours, `(yaw rad, translation m)`
    /// (simulation).
    pub true_peer_frames: BTreeMap<u32, (f64, nalgebra::Vector3<f64>)>,
    /// When our estimator started (fleet clock), s (simulation; else the
    /// first estimate's time stands in).
    pub estimator_start_s: Option<f64>,
    /// Ticks done.
    pub ticks: u64,
    /// Fleet time covered, s.
    pub fleet_s: f64,
    /// Wall time, s.
    pub wall_s: f64,
    /// CPU time of the node's thread over the run, s (the agent binary
    /// replaces it with its whole process's: the transport's threads too).
    pub cpu_s: Option<f64>,
    /// Stopped by a signal before the end of the data.
    pub interrupted: bool,
    /// Publish errors (the message was not sent; the run went on).
    pub publish_errors: u64,
    /// Largest lag behind the wall clock in real-time mode, s.
    pub max_lag_s: f64,
    /// One-way latencies of received messages, ms (same-host wall clocks); the
    /// first [`MAX_LATENCY_SAMPLES`].
    pub latencies_ms: Vec<f64>,
    /// Scenario name.
    pub scenario: String,
    /// Seed.
    pub seed: u64,
    /// Estimator variant.
    pub variant: String,
    /// Robot name (trajectory).
    pub robot_name: String,
    /// History catch-up counters, asking and answering (`None`: switched off).
    pub catch_up: Option<CatchUpStats>,
    /// Keyframe windows handed to the transport (a window whose sending
    /// failed still counts: peers can ask for it again).
    pub keyframe_windows_published: u64,
    /// Bytes of this agent's archive of its own keyframe windows.
    pub own_archive_bytes: usize,
    /// Keyframe windows in that archive (what peers hold of this agent when
    /// they missed nothing).
    pub own_archive_windows: usize,
    /// Of those, windows whole (a frame at every clone, and descriptors).
    pub own_archive_whole_windows: usize,
    /// Messages dropped by the injected outage (`faults.outage_fleet_s`).
    /// They are dropped after decoding, so `net` counts them as received
    /// (its sequence numbers then show no gap for them).
    pub outage_dropped: u64,
    /// Messages dropped by the injected loss (`faults.loss_fraction`), counted
    /// as `outage_dropped` is.
    pub loss_dropped: u64,
    /// The history store (`history.store_dir`), if one is used.
    pub store: Option<StoreStats>,
    /// How the end of the run settled (`None`: it was stopped first).
    pub settle: Option<SettleStats>,
    /// Live sensors: what arrived, was undecodable or dropped, per sensor.
    pub sensors: Option<String>,
}

/// How the end of a run settled: once every peer's data had ended, the agent
/// asked each once more for the windows it lacked or held short, and left
/// when it and every peer were done (or at `clock.settle_timeout_s`).
#[derive(Clone, Copy, Debug, Default, serde::Serialize)]
pub struct SettleStats {
    /// Wall seconds from every peer's data end to leaving.
    pub wall_s: f64,
    /// Whether it left with its own catch-up done and every peer settled
    /// (false: the timeout came first).
    pub complete: bool,
}

/// Fleet seconds per wall second after the data end of a lockstep run.
const LOCKSTEP_LINGER_RATE: f64 = 10.0;

/// Seconds between repeats of a `Settled` heartbeat (one may be lost).
const SETTLED_REPEAT_S: f64 = 0.5;

/// The settling at the end of a run, once every peer's data have ended.
struct Settling {
    started: Instant,
    deadline: Instant,
    /// When `Settled` was last announced.
    announced: Option<Instant>,
}

/// The history store of a node, its writer thread and its period.
#[derive(Debug)]
struct Store {
    store: HistoryStore,
    writer: Option<StoreWriter>,
    period_s: f64,
    last_s: f64,
}

/// Takes a finished write into the stats; a failed one makes the store write
/// that file whole next time.
fn settle(store: &mut HistoryStore, stats: &mut StoreStats, done: Done) {
    stats.write_wall_s += done.wall_s;
    if done.result.is_ok() {
        store.succeeded(done.robot);
    }
    match done.result {
        Ok(Saved::Unchanged) => {}
        Ok(Saved::Appended(bytes)) => {
            stats.writes += 1;
            stats.bytes_written += bytes;
        }
        Ok(Saved::Rewritten(bytes)) => {
            stats.writes += 1;
            stats.rewrites += 1;
            stats.bytes_written += bytes;
        }
        Err(e) => {
            store.failed_job(done.robot, done.planned_after);
            stats.write_errors += 1;
            warn_store(stats, &e);
        }
    }
}

/// Logs a store error, the first few only.
fn warn_store(stats: &StoreStats, e: &StoreError) {
    if stats.write_errors <= 5 {
        tracing::warn!("history store: {e}");
    }
}

/// What the history store did in a run.
#[derive(Clone, Debug, Default, serde::Serialize)]
pub struct StoreStats {
    /// Keyframe windows read back at start, per robot (ours included).
    pub restored_windows: BTreeMap<u32, usize>,
    /// Files (or their tails) that could not be read, and why.
    pub unreadable: Vec<String>,
    /// Writes to history files: appends and rewrites.
    pub writes: u64,
    /// Of those, files written whole (the first write of a file, and
    /// compactions).
    pub rewrites: u64,
    /// Bytes written, appends and rewrites.
    pub bytes_written: u64,
    /// Wall time of the file writes, s (on the writer thread).
    pub write_wall_s: f64,
    /// Wall time the agent's thread spent on the store's writes, s:
    /// encoding the records and queueing them.
    pub agent_thread_s: f64,
    /// Most bytes queued for the writer thread at once.
    pub queued_bytes_peak: u64,
    /// Histories whose write was put off to a later period because the
    /// writer thread had [`crate::history_store::MAX_QUEUED_BYTES`] queued (a
    /// disk slower than the histories grow).
    pub writes_deferred: u64,
    /// Writes that failed (each logged; the run goes on).
    pub write_errors: u64,
}

/// The robot this agent is: its simulated (or recorded) sensors and its
/// estimator settings.
pub struct RobotSetup {
    /// The fleet (truth, world) of the scenario.
    pub fleet: Fleet,
    /// Robot index in the scenario.
    pub robot: usize,
    /// Estimator variant.
    pub variant: Variant,
    /// The fleet's camera tick grid.
    pub grid: TickGrid,
    /// Ticks until the robot's data end.
    pub ticks_total: u64,
    /// Ticks until the last robot's data end (simulated fleets; a recording
    /// knows only its own robot): in lockstep an agent whose data have ended
    /// keeps ticking with its peers, so that what it still sends them
    /// (answers to history catch-up requests) lands on the fleet clock.
    pub fleet_ticks_total: u64,
    /// Recorded events (MCAP replay), if any.
    recorded: Option<Vec<SimEvent>>,
}

impl RobotSetup {
    /// Loads the scenario and, for a replay, the recording.
    pub fn load(cfg: &AgentConfig) -> Result<Self, NodeError> {
        let scenario = Scenario::load(&cfg.input.scenario)?;
        let seed = cfg.input.seed.unwrap_or(scenario.seed);
        let fleet = Fleet::build(&scenario, seed)?;
        let robot = cfg.robot_index();
        let truth = fleet
            .truths
            .get(robot)
            .ok_or(simulator::SimError::NoSuchRobot(robot))?;
        let variant: Variant = cfg.estimator.variant.parse()?;
        let t0_s = fleet
            .truths
            .iter()
            .map(|t| t.start_time())
            .fold(f64::INFINITY, f64::min);
        let dt_s = 1.0 / fleet.scenario.sensors.camera.rate_hz;
        let grid = TickGrid { t0_s, dt_s };
        let recorded = match (cfg.input.source, &cfg.input.mcap) {
            (InputSource::Mcap, Some(path)) => Some(simulator::mcap_io::read_stream(path)?),
            _ => None,
        };
        let t_end = match &recorded {
            Some(events) => events.last().map_or(t0_s, event_time),
            None => truth.end_time(),
        };
        Ok(Self {
            ticks_total: grid.ticks_until(t_end),
            fleet_ticks_total: match &recorded {
                Some(_) => grid.ticks_until(t_end),
                None => grid.ticks_until(
                    fleet
                        .truths
                        .iter()
                        .map(|t| t.end_time())
                        .fold(t_end, f64::max),
                ),
            },
            fleet,
            robot,
            variant,
            grid,
            recorded,
        })
    }

    fn events(&self) -> Result<Box<dyn Iterator<Item = SimEvent> + '_>, NodeError> {
        Ok(match &self.recorded {
            Some(events) => Box::new(events.iter().cloned()),
            None => Box::new(self.fleet.stream(self.robot)?),
        })
    }
}

fn event_time(e: &SimEvent) -> f64 {
    match e {
        SimEvent::Imu(s) => s.t,
        SimEvent::Camera(c) => c.frame.t,
    }
}

/// Latency samples kept for the summary (8 MiB): a flooding peer must not grow
/// them without bound.
pub const MAX_LATENCY_SAMPLES: usize = 1 << 20;

/// Messages taken in one [`Node::drain`]: a peer sending faster than the agent
/// decodes must not keep it from its own frames.
const MAX_DRAIN: usize = 256;

/// The agent's moving parts during a run.
struct Node {
    transport: Box<dyn Transport>,
    inbox: Inbox,
    outbox: Outbox,
    lockstep: Lockstep,
    /// Accepted messages waiting for the fleet clock, with their encoded size.
    pending: Vec<(Envelope, usize)>,
    /// Encoded bytes in `pending`, per admitted peer (bounded by `limits.max_bytes`).
    pending_bytes: BTreeMap<u32, usize>,
    /// Received bytes per admitted peer and second.
    rates: PeerRates,
    limits: HistoryLimits,
    report: NodeReport,
    started: Instant,
    fleet_t: Option<f64>,
    log: Option<crate::agent_log::AgentLog>,
    /// Frames recorded when the paths were last logged.
    path_logged_at: Option<usize>,
    /// Peers' newest camera poses, for the logged scene.
    peer_poses: BTreeMap<u32, PeerPose>,
    /// History catch-up, asking and answering (`None`: switched off).
    catch_up: Option<(CatchUp, Replayer)>,
    /// With catch-up off: requests addressed to us since the last answer.
    /// We keep no archive, so the answer says we found nothing; unanswered,
    /// peers would ask again every `catch_up_retry_s` for good.
    unanswerable: Vec<RequestRef>,
    /// Histories kept on disk (`None`: memory only), the fleet seconds
    /// between writes and the time of the last.
    store: Option<Store>,
    faults: FaultsConfig,
    /// This agent's robot id (the receiver in the fault draws).
    robot_id: u32,
    lockstep_mode: bool,
    /// Newest send time of any peer message accepted, s: the fleet clock as
    /// the peers see it, which goes on after our own data end.
    peer_clock_s: f64,
}

impl Node {
    fn wall_s(&self) -> f64 {
        self.started.elapsed().as_secs_f64()
    }

    /// The counters of a status line ([`StatusLog`]).
    fn counters(&self, lag_s: f64) -> Counters {
        let r = &self.report;
        Counters {
            wall_s: self.wall_s(),
            fleet_s: self.fleet_t,
            frames: r.run.frames.len(),
            peers_alive: r.peers.alive().len(),
            windows: r.histories.values().map(|h| h.keyframes.len()).sum(),
            history_bytes: r.histories.values().map(PeerHistory::bytes).sum(),
            sent_bytes: r.net.bytes_sent(),
            received_bytes: r.net.bytes_received(),
            dropped: r.net.dropped.values().sum(),
            rejected: r.run.rejected.len(),
            lag_s,
            latency_samples: r.latencies_ms.len(),
        }
    }

    fn note(&mut self, e: Option<PeerEvent>) {
        let Some(e) = e else { return };
        tracing::info!(peer = e.peer, event = e.event, "peer event");
        if let Some(log) = self.log.as_mut() {
            let t = e.fleet_t_s.unwrap_or(0.0);
            let _ = log.log(t, 2, "peers", &format!("robot {} {}", e.peer, e.event));
        }
    }

    /// Publishes `envelopes`; a failure is counted and logged, never fatal.
    fn publish(&mut self, envelopes: Vec<Envelope>) {
        for env in envelopes {
            if matches!(&env.body, Body::Snapshot(s) if s.keyframe) {
                self.report.keyframe_windows_published += 1;
            }
            if let Some((_, replayer)) = self.catch_up.as_mut() {
                replayer.published(&env.body);
            }
            self.publish_one(env);
        }
    }

    /// Publishes one envelope; returns its encoded size (0 if it was not sent).
    fn publish_one(&mut self, mut env: Envelope) -> usize {
        env.sent_wall_ns = wall_ns();
        let kind = env.kind();
        let bytes = match encode(&env) {
            Ok(b) => b,
            Err(e) => {
                tracing::warn!("not sending {kind:?}: {e}");
                self.report.publish_errors += 1;
                return 0;
            }
        };
        match self.transport.publish(kind, &bytes) {
            Ok(()) => {
                self.report.net.sent(kind, bytes.len());
                bytes.len()
            }
            Err(e) => {
                self.report.publish_errors += 1;
                if self.report.publish_errors <= 10 {
                    tracing::warn!("{e}");
                }
                0
            }
        }
    }

    /// End of our newest keyframe window, as peers would store it (`None`
    /// before the first, or with catch-up off: peers then cannot tell).
    fn newest_window_end_s(&self) -> Option<f64> {
        let (_, replayer) = self.catch_up.as_ref()?;
        replayer.archive().stored_span.map(|(_, end)| end)
    }

    /// Starts settling: every peer in `alive` is asked once more for the
    /// windows we lack or hold short (the last losses of a run leave no later
    /// message to show a gap).
    fn start_settling(&mut self, alive: &[u32], timeout: Duration) -> Settling {
        if let Some((asking, _)) = self.catch_up.as_mut() {
            for &peer in alive {
                asking.sweep(peer);
            }
        }
        let started = Instant::now();
        Settling {
            started,
            deadline: started + timeout,
            announced: None,
        }
    }

    /// One step of settling: announces `Settled` once our catch-up has
    /// nothing asked or queued (and again every [`SETTLED_REPEAT_S`]);
    /// returns whether to leave: we and every peer in `alive` settled (we
    /// stay for theirs, to answer their requests), or the deadline passed.
    /// Without catch-up there is nothing to ask or answer: it leaves at once.
    fn settle(
        &mut self,
        s: &mut Settling,
        alive: &[u32],
        t_last: f64,
        last_tick: Option<u64>,
    ) -> bool {
        let idle = self
            .catch_up
            .as_ref()
            .is_none_or(|(asking, replayer)| asking.idle() && replayer.idle());
        if idle
            && s.announced
                .is_none_or(|t| t.elapsed().as_secs_f64() >= SETTLED_REPEAT_S)
        {
            let hb = self.outbox.heartbeat(
                t_last,
                AgentState::Settled,
                self.report.run.frames.len() as u64,
                last_tick,
                self.newest_window_end_s(),
            );
            self.publish(vec![hb]);
            s.announced = Some(Instant::now());
        }
        let peers_settled = alive
            .iter()
            .all(|p| self.report.peers.peers.get(p).is_some_and(|st| st.settled));
        let complete = idle && (peers_settled || self.catch_up.is_none());
        let leave = complete || Instant::now() >= s.deadline;
        if leave {
            self.report.settle = Some(SettleStats {
                wall_s: s.started.elapsed().as_secs_f64(),
                complete,
            });
        }
        leave
    }

    /// Reads the histories kept in `dir` (ours into the catch-up archive,
    /// the peers' into their histories), and keeps them there from now on.
    fn restore(
        &mut self,
        dir: &Path,
        (fleet_id, mission): (&str, &str),
        period_s: f64,
        max_peers: usize,
    ) -> Result<(), NodeError> {
        let mut store = HistoryStore::open(dir, fleet_id, mission)?;
        let loaded = store.load(&self.limits)?;
        let mut stats = StoreStats::default();
        for u in loaded.unreadable {
            let why = format!("{}: {}", u.path.display(), u.why);
            tracing::warn!("history store: {why}");
            stats.unreadable.push(why);
        }
        for (robot, history) in loaded.histories {
            let windows = history.keyframes.len();
            if robot == self.robot_id {
                // Our own windows serve peers' requests; without catch-up
                // there is nobody to serve.
                match self.catch_up.as_mut() {
                    Some((_, replayer)) => replayer.restore(history),
                    None => continue,
                }
            } else {
                if !self.report.histories.contains_key(&robot)
                    && self.report.histories.len() >= max_peers
                {
                    tracing::warn!(robot, "history store: no room for another peer");
                    continue;
                }
                if let Some((asking, _)) = self.catch_up.as_mut() {
                    asking.restored(robot, &history);
                }
                self.report.histories.insert(robot, history);
            }
            tracing::info!(robot, windows, "history store: read back");
            stats.restored_windows.insert(robot, windows);
        }
        self.report.store = Some(stats);
        // Without a writer thread (none could be started) the agent's
        // thread writes, as it must then.
        let writer = StoreWriter::spawn()
            .map_err(|e| tracing::warn!("history store: no writer thread ({e}); writing inline"))
            .ok();
        self.store = Some(Store {
            store,
            writer,
            period_s,
            last_s: f64::NEG_INFINITY,
        });
        Ok(())
    }

    /// Writes the histories that changed, if `store_period_s` passed since
    /// the last write (`last`: now, whatever the period, and waits for the
    /// writes to end). The records are encoded on this thread; the writer
    /// thread does the file work.
    fn store_histories(&mut self, now_s: f64, last: bool) {
        let Some(st) = self.store.as_mut() else {
            return;
        };
        let stats = self.report.store.get_or_insert_with(StoreStats::default);
        if let Some(w) = st.writer.as_ref() {
            for done in w.finished() {
                settle(&mut st.store, stats, done);
            }
        }
        if !last && now_s - st.last_s < st.period_s {
            return;
        }
        st.last_s = now_s;
        let started = Instant::now();
        if last {
            st.store.retry_now();
        }
        let own = self
            .catch_up
            .as_ref()
            .map(|(_, r)| (self.robot_id, r.archive()));
        let peers = self.report.histories.iter().map(|(&r, h)| (r, h));
        for (robot, history) in peers.chain(own) {
            if !last && st.writer.as_ref().is_some_and(StoreWriter::busy) {
                // The disk is behind: this history waits for a later period.
                stats.writes_deferred += 1;
                continue;
            }
            let job = match st.store.plan(robot, history) {
                Ok(Some(job)) => job,
                Ok(None) => continue,
                Err(e) => {
                    stats.write_errors += 1;
                    warn_store(stats, &e);
                    continue;
                }
            };
            let job = match st.writer.as_ref() {
                Some(w) => {
                    let queued = (w.queued_bytes() + job.len()) as u64;
                    match w.submit(job) {
                        Ok(()) => {
                            stats.queued_bytes_peak = stats.queued_bytes_peak.max(queued);
                            continue;
                        }
                        Err(job) => {
                            tracing::warn!(
                                "history store: the writer thread is gone; writing inline"
                            );
                            st.writer = None;
                            job
                        }
                    }
                }
                None => job,
            };
            let t = Instant::now();
            let result = job.run();
            let done = Done {
                robot,
                planned_after: job.planned_after(),
                result,
                wall_s: t.elapsed().as_secs_f64(),
            };
            settle(&mut st.store, stats, done);
        }
        stats.agent_thread_s += started.elapsed().as_secs_f64();
        if last {
            if let Some(w) = st.writer.take() {
                for done in w.finish() {
                    settle(&mut st.store, stats, done);
                }
            }
        }
    }

    /// History catch-up at fleet time `now_s`: the requests due, then the
    /// replays the budget allows.
    fn catch_up(&mut self, now_s: f64) {
        let Some((asking, replayer)) = self.catch_up.as_mut() else {
            if !self.unanswerable.is_empty() {
                let completes = std::mem::take(&mut self.unanswerable);
                let nothing = Body::HistoryReplay(Box::new(HistoryReplay {
                    for_robots: Vec::new(),
                    window: None,
                    part: None,
                    completes,
                    answered: Vec::new(),
                }));
                let env = self.outbox.catch_up(now_s, nothing);
                self.publish_one(env);
            }
            return;
        };
        let requests = asking.requests(now_s, &self.report.histories);
        replayer.refill(now_s);
        for r in requests {
            let env = self.outbox.catch_up(now_s, Body::HistoryRequest(r));
            self.publish_one(env);
        }
        while let Some(replay) = self.catch_up.as_mut().and_then(|(_, r)| r.next_replay()) {
            let carried = (replay.window.is_some(), replay.part.is_some());
            let env = self
                .outbox
                .catch_up(now_s, Body::HistoryReplay(Box::new(replay)));
            // A replay that could not be sent still costs its turn: the
            // budget must not let a failing publish spin.
            let bytes = self.publish_one(env);
            if let Some((_, r)) = self.catch_up.as_mut() {
                r.sent(carried, bytes.max(1));
            }
        }
    }

    /// Receives for at most `timeout` (one message, or none), and applies
    /// presence changes.
    fn pump(&mut self, timeout: Duration) -> bool {
        let events = self.transport.presence();
        if events
            .iter()
            .any(|e| matches!(e, crate::transport::PresenceEvent::Vanished(_)))
        {
            // A peer's last messages (its final heartbeat) may still wait behind
            // the news of its departure: read them first, so that a peer that
            // finished is seen leaving, not lost and back.
            for _ in 0..MAX_DRAIN {
                if !self.receive_one(Duration::ZERO) {
                    break;
                }
            }
        }
        for ev in events {
            let e = self.report.peers.presence(ev, self.wall_s(), self.fleet_t);
            if let (Some(e), Some((asking, _))) = (e.as_ref(), self.catch_up.as_mut()) {
                match e.event {
                    "reappeared" => asking.reappeared(e.peer, self.report.histories.get(&e.peer)),
                    "vanished" | "left" => asking.vanished(e.peer),
                    _ => {}
                }
            }
            self.note(e);
            if let crate::transport::PresenceEvent::Vanished(p) = ev {
                if self.lockstep.release(p) {
                    self.report
                        .peers
                        .push(p, "released", self.wall_s(), self.fleet_t);
                    tracing::info!(peer = p, "gone: no longer waiting for it");
                }
            }
        }
        self.receive_one(timeout)
    }

    /// Receives for at most `timeout` (one message, or none).
    fn receive_one(&mut self, timeout: Duration) -> bool {
        let msg = match self.transport.receive(timeout) {
            Ok(Some(m)) => m,
            Ok(None) => return false,
            Err(e) => {
                tracing::warn!("{e}");
                return false;
            }
        };
        let size = msg.bytes.len();
        let accepted = match self.refusal(&msg) {
            Some((reason, why)) => {
                self.report.net.drop(reason, why);
                None
            }
            None => self.inbox.accept(&msg, &mut self.report.net),
        };
        let Some(env) = accepted else {
            if let Some(why) = self.report.net.drop_samples.last() {
                if self.report.net.dropped.values().sum::<u64>() <= 20 {
                    tracing::warn!("dropped: {why}");
                }
            }
            return true;
        };
        let faulted = FaultedMessage {
            kind: env.kind(),
            sender: env.robot_id,
            seq: env.seq,
            stamp_s: env.stamp_s,
        };
        match self
            .faults
            .drops(faulted, self.robot_id, self.lockstep_mode)
        {
            Some(FaultDrop::Outage) => {
                self.report.outage_dropped += 1;
                return true;
            }
            Some(FaultDrop::Loss) => {
                self.report.loss_dropped += 1;
                return true;
            }
            None => {}
        }
        self.peer_clock_s = self.peer_clock_s.max(env.stamp_s);
        let peer = env.robot_id;
        *self.pending_bytes.entry(peer).or_default() += size;
        let now = self.wall_s();
        if self.report.latencies_ms.len() < MAX_LATENCY_SAMPLES {
            if let Some(ms) = latency_ms(&env) {
                self.report.latencies_ms.push(ms);
            }
        }
        let e = self.report.peers.heard(peer, now, self.fleet_t);
        self.note(e);
        self.lockstep.heard(peer, now);
        if let Body::Heartbeat(hb) = &env.body {
            let settled = hb.state == AgentState::Settled;
            let finished = settled || hb.state == AgentState::Finished;
            self.lockstep
                .progress(peer, hb.last_frame_index, finished, now);
            let known = self.report.peers.peers.get(&peer).copied();
            // A lost `Finished` heartbeat: the `Settled` one says it too.
            if finished && !known.is_some_and(|p| p.finished) {
                let e = self.report.peers.push(peer, "finished", now, self.fleet_t);
                self.note(Some(e));
            }
            if settled && !known.is_some_and(|p| p.settled) {
                let e = self.report.peers.push(peer, "settled", now, self.fleet_t);
                self.note(Some(e));
            }
        }
        self.pending.push((env, size));
        true
    }

    /// Why `msg` is dropped before it costs a decode, if it is: a robot id
    /// beyond the peer limit, a peer beyond its rate, or one whose messages
    /// waiting for the fleet clock fill its memory bound.
    fn refusal(&mut self, msg: &Received) -> Option<(DropReason, String)> {
        let (peer, kind, size) = (msg.from_robot, msg.kind, msg.bytes.len());
        if !self.inbox.has_room_for(peer) {
            let why = format!("{kind:?} from robot {peer}: no room for another peer");
            return Some((DropReason::TooManyPeers, why));
        }
        // Only admitted peers have a backlog entry, and a rate budget.
        let backlog = self.pending_bytes.get(&peer).copied();
        if backlog.is_some() && !self.rates.admit(peer, size, self.wall_s()) {
            let why = format!("{kind:?} from robot {peer}: beyond its receive rate");
            return Some((DropReason::RateLimit, why));
        }
        let backlog = backlog.unwrap_or(0);
        if backlog + size > self.limits.max_bytes {
            let why = format!(
                "{kind:?} from robot {peer}: {backlog} bytes already wait for the fleet clock"
            );
            return Some((DropReason::Backlog, why));
        }
        None
    }

    /// Waits for the expected peers (their presence means their subscribers
    /// exist), at most `clock.start_timeout_s`: the ones still missing are
    /// not waited for.
    fn wait_for_peers(&mut self, cfg: &AgentConfig, stop: &AtomicBool) {
        let deadline = Instant::now() + Duration::from_secs_f64(cfg.clock.start_timeout_s);
        loop {
            let alive = self.report.peers.alive();
            let missing: Vec<u32> = cfg
                .clock
                .peers
                .iter()
                .filter(|p| !alive.contains(p))
                .copied()
                .collect();
            if missing.is_empty() || Instant::now() >= deadline || Self::stopping(stop) {
                if !missing.is_empty() {
                    tracing::warn!(?missing, "starting without these peers");
                    for p in missing {
                        self.lockstep.release(p);
                    }
                }
                break;
            }
            self.pump(Duration::from_millis(20));
        }
        let now = self.wall_s();
        for p in &cfg.clock.peers {
            self.lockstep.heard(*p, now);
        }
    }

    /// Takes the estimator's new estimates, one per queued frame: the
    /// frame's tracks go out with, when due, a window snapshot, and the
    /// estimate is logged and recorded (with `truth` at its time, when it
    /// is known). Returns the estimates recorded.
    fn take_estimates(
        &mut self,
        est: &mut Estimator,
        queued: &mut VecDeque<(u64, FeatureFrame)>,
        truth: Option<&simulator::truth::RobotTruth>,
        mut run_files: Option<&mut RunFiles>,
    ) -> usize {
        let mut recorded = 0;
        for out in est.poll_with(&self.report.histories) {
            let Some((index, frame)) = queued.pop_front() else {
                break;
            };
            let mut envs = self.outbox.tracks(index, &frame, est.calibration());
            match out {
                Ok(o) => {
                    let clones = est.state().map(|s| &s.clones);
                    let oldest = clones.and_then(|c| c.values().next().map(|c| c.t_cam));
                    let full = clones.is_some_and(|c| c.len() >= est.options().max_clones);
                    if let Some(plan) = self.outbox.snapshot_due(index, frame.t, oldest, full) {
                        if let Some(w) = est.camera_window(plan.landmarks) {
                            envs.extend(self.outbox.snapshot(index, &frame, plan, &w));
                        }
                    }
                    log_estimate(self, &o, truth, est);
                    let before = self.report.run.estimate.len();
                    match truth {
                        Some(truth) => record(&mut self.report.run, truth, o),
                        None => self.report.run.record_without_truth(o),
                    }
                    recorded += self.report.run.estimate.len() - before;
                    if let Some(f) = run_files.as_deref_mut() {
                        f.append(&self.report.run);
                    }
                }
                Err(e) => self.report.run.rejected.push(e.to_string()),
            }
            self.publish(envs);
        }
        recorded
    }

    /// Receives what is already there, up to [`MAX_DRAIN`] messages.
    fn drain(&mut self) {
        for _ in 0..MAX_DRAIN {
            if !self.pump(Duration::ZERO) {
                break;
            }
        }
    }

    /// Moves pending messages stamped up to `until_s` into the peers' histories,
    /// in a deterministic order.
    fn deliver(&mut self, until_s: f64) {
        let (now, later): (Vec<_>, Vec<_>) = std::mem::take(&mut self.pending)
            .into_iter()
            .partition(|(e, _)| e.stamp_s <= until_s);
        self.pending = later;
        let mut now: Vec<Envelope> = now
            .into_iter()
            .map(|(env, size)| {
                if let Some(b) = self.pending_bytes.get_mut(&env.robot_id) {
                    *b = b.saturating_sub(size);
                }
                env
            })
            .collect();
        now.sort_by(|a, b| {
            a.stamp_s
                .total_cmp(&b.stamp_s)
                .then(a.robot_id.cmp(&b.robot_id))
                .then(a.kind().cmp(&b.kind()))
                .then(a.seq.cmp(&b.seq))
        });
        let mut moved: BTreeMap<u32, f64> = BTreeMap::new();
        // The fleet time of this delivery: after our own data end (lingering)
        // the peers' clock goes on.
        let now_s = if until_s.is_finite() {
            until_s
        } else {
            self.fleet_t.unwrap_or(0.0).max(self.peer_clock_s)
        };
        for env in now {
            let h = self.report.histories.entry(env.robot_id).or_default();
            if let Some((asking, _)) = self.catch_up.as_mut() {
                asking.delivered(&env, h);
            }
            match env.body {
                Body::Tracks(t) => h.add_tracks(t, &self.limits),
                Body::Descriptors(d) => h.add_descriptors(d, &self.limits),
                Body::Snapshot(s) => {
                    if let Some(c) = s.clones.last() {
                        let pose = PeerPose {
                            robot: env.robot_id,
                            rot: c.rot_c_to_g(),
                            pos: c.p_c_in_g(),
                        };
                        self.peer_poses.insert(env.robot_id, pose);
                        moved.insert(env.robot_id, c.t_s);
                    }
                    h.add_snapshot(s, &self.limits);
                }
                Body::Heartbeat(_) => {}
                Body::HistoryRequest(r) => match self.catch_up.as_mut() {
                    Some((_, replayer)) => replayer.request(env.robot_id, &r),
                    None if r.to_robot == self.robot_id
                        && env.robot_id != self.robot_id
                        && self.unanswerable.len() < MAX_REPLAY_ROBOTS =>
                    {
                        self.unanswerable.push(RequestRef {
                            robot: env.robot_id,
                            request_id: r.request_id,
                        });
                    }
                    None => {}
                },
                Body::HistoryReplay(r) => {
                    if let Some((asking, _)) = self.catch_up.as_mut() {
                        asking.accept(env.robot_id, *r, now_s, h, &self.limits);
                    }
                }
            }
        }
        // One logged pose per peer and delivery (a tick): a peer that floods
        // snapshots must not grow the log with them.
        if let Some(log) = self.log.as_mut() {
            for (peer, t_s) in moved {
                if let Some(pose) = self.peer_poses.get(&peer) {
                    let topic = format!("/peers/{peer}/camera");
                    let _ = log.pose(&topic, "world", t_s, &pose.rot, &pose.pos);
                }
            }
        }
        let total: usize = self.report.histories.values().map(|h| h.bytes()).sum();
        self.report.peak_history_bytes = self.report.peak_history_bytes.max(total);
    }

    fn stopping(stop: &AtomicBool) -> bool {
        stop.load(Ordering::Relaxed)
    }
}

/// The world frame our snapshots are in (`StateSnapshot::frame_epoch`): 0,
/// the fleet's, unless the robots are in frames of their own
/// (`align_peer_frames`). Then 1 in lockstep, whose runs replay the same
/// data from the same start pose whenever they start; and in real time the
/// start's wall-clock time, since a robot started again (live sensors)
/// stands wherever it was, and its new frame must not be taken for the old.
fn frame_epoch(align_peer_frames: bool, mode: ClockMode) -> u64 {
    if !align_peer_frames {
        return 0;
    }
    match mode {
        ClockMode::Lockstep => 1,
        ClockMode::Realtime => std::time::SystemTime::now()
            .duration_since(std::time::UNIX_EPOCH)
            .map_or(2, |d| u64::try_from(d.as_nanos()).unwrap_or(u64::MAX))
            .max(2),
    }
}

/// What a run is, for its report and its history store.
struct RunHeader {
    scenario: String,
    seed: u64,
    variant: Variant,
    robot_name: String,
    /// The mission the stored histories belong to (a store of another is
    /// set aside).
    mission: String,
    /// A truth is known (simulation): `groundtruth.txt` is written.
    with_truth: bool,
}

impl Node {
    /// The agent's moving parts for `cfg`, an earlier unfinished run set
    /// aside, the stored histories restored, the vocabulary given to `est`
    /// when it uses historical features; and the run's text files, written
    /// as it goes (`None` if they cannot be: the outputs are then written at
    /// the end).
    fn open(
        cfg: &AgentConfig,
        header: &RunHeader,
        transport: Box<dyn Transport>,
        est: &mut Estimator,
    ) -> Result<(Node, Option<RunFiles>), NodeError> {
        if est.options().cooperation.historical {
            let voc = match &cfg.estimator.vocabulary {
                Some(path) => Some(std::sync::Arc::new(vocabulary::Vocabulary::load(path)?)),
                None => crate::cooperation::builtin_vocabulary(),
            };
            est.set_vocabulary(voc);
        }
        // A run of this robot that never finished (it lost power) is kept aside.
        match crate::run_files::set_aside_unfinished(&cfg.output_dir) {
            Ok(Some(aside)) => tracing::warn!(
                "an earlier run here did not finish: its files are kept in {}",
                aside.display()
            ),
            Ok(None) => {}
            Err(e) => tracing::warn!("readying {}: {e}", cfg.output_dir.display()),
        }
        let log = if cfg.mcap_log {
            std::fs::create_dir_all(&cfg.output_dir).ok();
            match crate::agent_log::AgentLog::create(&cfg.output_dir.join("agent.mcap")) {
                Ok(l) => Some(l),
                Err(e) => {
                    tracing::warn!("no MCAP log: {e}");
                    None
                }
            }
        } else {
            None
        };
        // The text outputs as the run goes: a robot killed hard keeps its poses.
        let run_files = match RunFiles::create(&cfg.output_dir, header.with_truth, FLUSH_PERIOD) {
            Ok(f) => Some(f),
            Err(e) => {
                tracing::warn!(
                    "cannot write {} as the run goes ({e}): the outputs are written at the end",
                    cfg.output_dir.display()
                );
                None
            }
        };
        let mut node = Node {
            transport,
            inbox: Inbox::new(&cfg.fleet_id, cfg.robot_id, cfg.history.max_peers),
            outbox: Outbox::new(
                &cfg.fleet_id,
                cfg.robot_id,
                cfg.publish.clone(),
                frame_epoch(est.options().cooperation.align_peer_frames, cfg.clock.mode),
                est.options().pixel_sigma_px,
            ),
            lockstep: Lockstep::new(&cfg.clock.peers, 0.0),
            pending: Vec::new(),
            pending_bytes: BTreeMap::new(),
            rates: PeerRates::new(cfg.history.max_peer_mib_per_s * 1024.0 * 1024.0),
            limits: HistoryLimits {
                max_bytes: (cfg.history.max_mib_per_peer * 1024.0 * 1024.0) as usize,
                recent_s: cfg.history.recent_tracks_s,
                retention: cfg.history.retention,
            },
            report: NodeReport {
                scenario: header.scenario.clone(),
                seed: header.seed,
                variant: header.variant.name().to_string(),
                robot_name: header.robot_name.clone(),
                run: RobotRun {
                    without_truth: !header.with_truth,
                    ..RobotRun::default()
                },
                ..NodeReport::default()
            },
            started: Instant::now(),
            fleet_t: None,
            log,
            path_logged_at: None,
            peer_poses: BTreeMap::new(),
            catch_up: None,
            unanswerable: Vec::new(),
            store: None,
            faults: cfg.faults.for_run(header.seed),
            robot_id: cfg.robot_id,
            lockstep_mode: cfg.clock.mode == ClockMode::Lockstep,
            peer_clock_s: f64::NEG_INFINITY,
        };
        if cfg.history.catch_up {
            node.catch_up = Some((
                CatchUp::new(cfg.robot_id, cfg.history.catch_up_retry_s),
                Replayer::new(
                    cfg.robot_id,
                    node.limits,
                    cfg.history.replay_kib_per_s * 1024.0,
                ),
            ));
        }
        if let Some(dir) = &cfg.history.store_dir {
            node.restore(
                dir,
                (&cfg.fleet_id, &header.mission),
                cfg.history.store_period_s,
                cfg.history.max_peers,
            )?;
        }
        Ok((node, run_files))
    }
}

fn wall_ns() -> u64 {
    std::time::SystemTime::now()
        .duration_since(std::time::UNIX_EPOCH)
        .map_or(0, |d| d.as_nanos() as u64)
}

/// One-way latency from the envelope's wall-clock send time (same host).
fn latency_ms(env: &Envelope) -> Option<f64> {
    let sent = env.sent_wall_ns;
    if sent == 0 {
        return None;
    }
    Some(wall_ns().saturating_sub(sent) as f64 * 1e-6)
}

/// Runs the agent until its data end (or `stop` is set), then lingers while
/// peers still run. Outputs are returned, not written (see
/// [`crate::agent_output`]).
pub fn run_node(
    cfg: &AgentConfig,
    setup: &RobotSetup,
    transport: Box<dyn Transport>,
    stop: &AtomicBool,
    mut progress: impl FnMut(Progress),
) -> Result<NodeReport, NodeError> {
    let cpu_start = cpu_time::ThreadTime::try_now().ok();
    let fleet = &setup.fleet;
    let robot = setup.robot;
    let truth = &fleet
        .agent_truth(robot)
        .ok_or(simulator::SimError::NoSuchRobot(robot))?;
    let spec = &fleet.scenario.estimator;
    let start_t = fleet
        .estimator_start_time(robot)
        .ok_or(simulator::SimError::NoSuchRobot(robot))?;
    let mut opts = options_for(spec, fleet, robot, setup.variant);
    cfg.estimator.apply(&mut opts);
    // E.g. robots in their own frames with a variant that closes no loops:
    // it could never find its peers' frames.
    opts.validate().map_err(RunError::Options)?;
    let mut est = Estimator::new(opts, fleet.initial_calibration(robot));
    let header = RunHeader {
        scenario: fleet.scenario.name.clone(),
        seed: fleet.seed,
        variant: setup.variant,
        robot_name: fleet.scenario.robot_name(robot),
        // The fleet's mission: every robot runs the same scenario and seed.
        mission: format!("{}, seed {}", fleet.scenario.name, fleet.seed),
        with_truth: true,
    };
    let (mut node, mut run_files) = Node::open(cfg, &header, transport, &mut est)?;
    let mut images: Option<ImageFrames> = None;
    let mut status = StatusLog::new(cfg.status_period_s);

    node.wait_for_peers(cfg, stop);

    let grid = setup.grid;
    let pacer = Pacer::new(grid.end_of(0), cfg.clock.realtime_rate);
    let mut events = setup.events()?.peekable();
    let mut queued: VecDeque<(u64, FeatureFrame)> = VecDeque::new();
    let mut frames_seen = 0u64;
    let mut initialized = false;
    let mut last_heartbeat = Instant::now();
    let mut tick = 0u64;
    // In lockstep with peers, tick on to the last robot's end (see
    // `RobotSetup::fleet_ticks_total`); past our own end there are no data.
    let ticks_end = match cfg.clock.mode {
        ClockMode::Lockstep if !cfg.clock.peers.is_empty() => {
            setup.fleet_ticks_total.max(setup.ticks_total)
        }
        _ => setup.ticks_total,
    };
    while tick < ticks_end {
        if Node::stopping(stop) {
            node.report.interrupted = true;
            break;
        }
        // 1. The fleet clock.
        match cfg.clock.mode {
            ClockMode::Lockstep if tick > 0 => {
                let mut next_note = node.wall_s() + 5.0;
                loop {
                    let waiting = node.lockstep.waiting_for(tick - 1);
                    if waiting.is_empty() || Node::stopping(stop) {
                        break;
                    }
                    node.pump(Duration::from_millis(20));
                    let now = node.wall_s();
                    if now > next_note {
                        tracing::info!(tick, ?waiting, "waiting for peers");
                        next_note = now + 5.0;
                    }
                    for p in
                        node.lockstep
                            .release_silent(tick - 1, now, cfg.clock.barrier_timeout_s)
                    {
                        tracing::warn!(peer = p, "silent for too long: no longer waiting for it");
                        let e = node.report.peers.push(p, "silent", now, node.fleet_t);
                        node.note(Some(e));
                    }
                }
                node.drain();
                // 2. Everything the peers sent up to the previous tick.
                node.deliver(grid.end_of(tick - 1));
            }
            ClockMode::Lockstep => {}
            ClockMode::Realtime => {
                let due = pacer.due(grid.end_of(tick));
                while Instant::now() < due && !Node::stopping(stop) {
                    let left = due.saturating_duration_since(Instant::now());
                    node.pump(left.min(Duration::from_millis(20)));
                }
                node.drain();
                node.deliver(f64::INFINITY);
                node.report.max_lag_s = node.report.max_lag_s.max(pacer.lag_s(grid.end_of(tick)));
            }
        }
        let t_end = grid.end_of(tick);
        node.fleet_t = Some(t_end);

        // 3. This tick's sensor data.
        while let Some(ev) = events.next_if(|e| event_time(e) <= t_end) {
            match ev {
                SimEvent::Imu(s) => {
                    if let Err(e) = est.feed_imu(s) {
                        node.report.run.rejected.push(e.to_string());
                    }
                }
                SimEvent::Camera(mut c) => {
                    if c.image.is_some() {
                        let imgs = match images.as_mut() {
                            Some(i) => i,
                            None => images.insert(
                                ImageFrames::new(
                                    &cfg.images.frontend,
                                    fleet.initial_calibration(robot).camera,
                                    cfg.images.mcap_every,
                                )
                                .map_err(NodeError::Images)?,
                            ),
                        };
                        imgs.apply(&mut c, node.log.as_mut())
                            .map_err(NodeError::Images)?;
                    }
                    let index = frames_seen;
                    frames_seen += 1;
                    if c.truth.t.is_finite() {
                        node.report.run.note_true_biases(c.truth.t, c.truth.biases);
                    }
                    if !initialized {
                        if c.truth.t.is_finite() && c.truth.t >= start_t {
                            est.initialize(&initial_state(fleet, robot, &c.truth));
                            initialized = true;
                        }
                        let env = node.outbox.tracks(index, &c.frame, est.calibration());
                        node.publish(env);
                        continue;
                    }
                    match est.feed_frame(c.frame.clone()) {
                        Ok(()) => queued.push_back((index, c.frame)),
                        Err(e) => node.report.run.rejected.push(e.to_string()),
                    }
                }
            }
            node.take_estimates(&mut est, &mut queued, Some(truth), run_files.as_mut());
        }

        // 4. Tick done: history catch-up first, so that a peer that has our
        // heartbeat of this tick has our requests and replays of it too (the
        // lockstep clock keeps them deterministic).
        node.catch_up(t_end);
        node.store_histories(t_end, false);
        let beat = match cfg.clock.mode {
            ClockMode::Lockstep => true,
            ClockMode::Realtime => {
                last_heartbeat.elapsed().as_secs_f64() >= cfg.publish.heartbeat_period_s
            }
        };
        if beat {
            last_heartbeat = Instant::now();
            let hb = node.outbox.heartbeat(
                t_end,
                AgentState::Running,
                node.report.run.frames.len() as u64,
                Some(tick),
                node.newest_window_end_s(),
            );
            node.publish(vec![hb]);
        }
        tick += 1;
        node.report.ticks = tick;
        if let Some(s) = status.as_mut() {
            let lag_s = if cfg.clock.mode == ClockMode::Realtime {
                pacer.lag_s(t_end)
            } else {
                0.0
            };
            let frames = &node.report.run.frames;
            if let Some(line) = s.due(
                node.wall_s(),
                || node.counters(lag_s),
                |k| frames.get(k).map_or(0.0, |f| f.timing.cpu_ms),
                &node.report.latencies_ms,
            ) {
                tracing::info!(robot = cfg.robot_id, "status: {line}");
            }
        }
        if tick % 10 == 0 || tick == ticks_end {
            progress(Progress {
                tick,
                ticks_total: ticks_end,
                frames: node.report.run.frames.len() as u64,
                lag_s: if cfg.clock.mode == ClockMode::Realtime {
                    pacer.lag_s(t_end)
                } else {
                    0.0
                },
            });
        }
    }

    let t_last = node.fleet_t.unwrap_or(grid.t0_s);
    // Our own span: the ticks past our data end (lockstep) only kept time.
    let own_end = grid.end_of(setup.ticks_total.saturating_sub(1));
    let end = RunEnd {
        t_last,
        last_tick: tick.checked_sub(1),
        data_unfinished: tick < setup.ticks_total,
        fleet_s: t_last.min(own_end) - grid.t0_s,
    };
    let mut report = node.finish(cfg, &est, run_files, stop, &end, cpu_start.as_ref());
    report.estimator_start_s = Some(start_t);
    // The truth of the peers' frames in ours (robot ids are fleet indices).
    report.true_peer_frames = (0..fleet.robot_count())
        .filter(|r| *r != robot)
        .filter_map(|r| {
            let f = fleet.frame_between(robot, r)?;
            Some((
                u32::try_from(r).ok()?,
                (f.rot[(1, 0)].atan2(f.rot[(0, 0)]), f.trans),
            ))
        })
        .collect();
    Ok(report)
}

/// How the main loop of a run ended.
struct RunEnd {
    /// The fleet time reached, s.
    t_last: f64,
    /// The last tick done, if any.
    last_tick: Option<u64>,
    /// Our data had not all been processed.
    data_unfinished: bool,
    /// Fleet time our own data covered, s.
    fleet_s: f64,
}

impl Node {
    /// The end of a run: says so (a `Finished` heartbeat), keeps listening
    /// while peers still run, settles once none does, and completes the
    /// report.
    fn finish(
        mut self,
        cfg: &AgentConfig,
        est: &Estimator,
        run_files: Option<RunFiles>,
        stop: &AtomicBool,
        end: &RunEnd,
        cpu_start: Option<&cpu_time::ThreadTime>,
    ) -> NodeReport {
        // The end: say so, then keep listening while peers still run, and settle
        // once none does.
        let t_last = end.t_last;
        let hb = self.outbox.heartbeat(
            t_last,
            AgentState::Finished,
            self.report.run.frames.len() as u64,
            end.last_tick,
            self.newest_window_end_s(),
        );
        self.publish(vec![hb]);
        let linger_start = Instant::now();
        let linger_until = linger_start + Duration::from_secs_f64(cfg.clock.linger_timeout_s);
        // Fleet seconds per wall second from here on. In lockstep nothing paces
        // the clock once the data have ended, and the catch-up timers (a request
        // is sent again after `history.catch_up_retry_s` of fleet time) would
        // otherwise wait seconds of wall time for a reply that takes
        // milliseconds: on a lossy link, settling timed out in 18 of 60 runs.
        let rate = match cfg.clock.mode {
            ClockMode::Realtime => cfg.clock.realtime_rate,
            ClockMode::Lockstep => LOCKSTEP_LINGER_RATE,
        };
        let mut settling: Option<Settling> = None;
        while !Self::stopping(stop) && Instant::now() < linger_until {
            let alive = self.report.peers.alive();
            let running = alive
                .iter()
                .any(|p| !self.report.peers.peers.get(p).is_some_and(|s| s.finished));
            if !running {
                // Every peer's data have ended: settle before leaving.
                let timeout = Duration::from_secs_f64(cfg.clock.settle_timeout_s);
                let s = match settling.as_mut() {
                    Some(s) => s,
                    None => settling.insert(self.start_settling(&alive, timeout)),
                };
                if self.settle(s, &alive, t_last, end.last_tick) {
                    break;
                }
            }
            self.pump(Duration::from_millis(20));
            // Peers still running may ask for our windows (after an outage): our
            // data are done, not our archive.
            self.deliver(f64::INFINITY);
            let own = t_last + linger_start.elapsed().as_secs_f64() * rate;
            self.catch_up(own.max(self.peer_clock_s));
        }
        self.drain();
        self.deliver(f64::INFINITY);
        self.store_histories(f64::INFINITY, true);
        if Self::stopping(stop) {
            self.report.interrupted = self.report.interrupted || end.data_unfinished;
        }
        self.report.fleet_s = end.fleet_s;
        self.report.run.cooperation = est.cooperation().map(|c| c.stats);
        self.report.keyframe_db_bytes = est
            .cooperation()
            .map(|c| c.keyframe_db_bytes())
            .unwrap_or_default();
        self.report.peer_frames = est
            .cooperation()
            .filter(|c| c.aligns_peer_frames())
            .map(|c| c.peer_frames());
        if let Some((asking, replayer)) = self.catch_up.as_ref() {
            let (a, r) = (&asking.stats, &replayer.stats);
            self.report.catch_up = Some(CatchUpStats {
                requests_answered: r.requests_answered,
                windows_replayed: r.windows_replayed,
                parts_replayed: r.parts_replayed,
                replay_bytes: r.replay_bytes,
                ..a.clone()
            });
            self.report.own_archive_bytes = replayer.archive().bytes();
            self.report.own_archive_windows = replayer.archive().keyframes.len();
            self.report.own_archive_whole_windows = replayer
                .archive()
                .keyframes
                .values()
                .filter(|kf| kf.is_whole())
                .count();
        }
        if let Some(f) = run_files {
            match f.finish(&self.report.run) {
                Ok(()) => self.report.run_files_in = Some(cfg.output_dir.clone()),
                Err(e) => tracing::warn!("{}: {e}", cfg.output_dir.display()),
            }
            if let Err(e) = crate::runner::write_imu_states(&self.report.run, &cfg.output_dir) {
                tracing::warn!("{}: {e}", cfg.output_dir.display());
            }
        }
        self.report.wall_s = self.wall_s();
        self.report.cpu_s = crate::runner::thread_cpu_s(cpu_start);
        if let Some(mut log) = self.log.take() {
            // The whole paths once more, so the log ends with them.
            if let Some(last) = self.report.run.estimate.last() {
                log_paths(&mut log, &self.report.run, last.t);
            }
            if let Err(e) = log.finish() {
                tracing::warn!("MCAP log: {e}");
            }
        }
        if let Err(e) = self.transport.close(Duration::from_secs(2)) {
            tracing::warn!("closing the transport: {e}");
        }
        self.report
    }
}

/// Frames between two logged scenes, and the fewest between two logged paths.
const SCENE_EVERY_FRAMES: usize = 10;
/// Most poses in one logged path.
const MAX_PATH_POSES: usize = 2000;
/// A path is logged again once the run has grown by this fraction of its frames
/// (at least [`SCENE_EVERY_FRAMES`]): every path repeats up to
/// [`MAX_PATH_POSES`] poses, and logged every second the two paths were 98 % of
/// an hour's log (2.6 GB of JSON per robot, 622 MB compressed). Runs under
/// 2 000 frames are unchanged; after an hour a path is at most 18 s behind.
const PATH_GROWTH: usize = 200;

/// Whether the paths are due with `frames` recorded, the last logged at
/// `last` frames (`None`: never).
fn path_due(frames: usize, last: Option<usize>) -> bool {
    last.is_none_or(|l| frames >= l + SCENE_EVERY_FRAMES.max(frames / PATH_GROWTH))
}

/// The estimated and true paths so far, at time `t`.
fn log_paths(log: &mut crate::agent_log::AgentLog, run: &RobotRun, t: f64) {
    let _ = log.path("/estimate/path", t, &run.estimate, MAX_PATH_POSES);
    let _ = log.path("/groundtruth/path", t, &run.truth, MAX_PATH_POSES);
}

fn log_estimate(
    node: &mut Node,
    o: &FrameOutput,
    truth: Option<&simulator::truth::RobotTruth>,
    est: &Estimator,
) {
    let Some(log) = node.log.as_mut() else {
        return;
    };
    let _ = log.pose("/estimate", "world", o.t(), &o.rot, &o.pos);
    let _ = log.covariance(o.t(), &o.cov_ori, &o.cov_pos);
    let _ = log.twist("/estimate/twist", &o.twist.stamped(o.t()), true);
    if let Some(gt) = truth.and_then(|truth| truth.spline.pose(o.t())) {
        let _ = log.pose("/groundtruth", "world", o.t(), &gt.rot, &gt.trans);
    }
    if let Some(gt) = truth.and_then(|truth| truth.spline.state(o.t())) {
        let _ = log.twist("/groundtruth/twist", &truth_twist(o.t(), &gt), false);
    }
    let run = &node.report.run;
    let frames = run.frames.len();
    if path_due(frames, node.path_logged_at) {
        log_paths(log, run, o.t());
        node.path_logged_at = Some(frames);
    }
    if frames % SCENE_EVERY_FRAMES == 0 {
        let landmarks: Vec<nalgebra::Vector3<f64>> = est
            .camera_window(true)
            .map(|w| w.landmarks.iter().map(|l| l.pos).collect())
            .unwrap_or_default();
        let peers: Vec<PeerPose> = node.peer_poses.values().copied().collect();
        let _ = log.scene(o.t(), &landmarks, &peers);
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_frame_of_our_own_is_named_by_the_start_that_could_not_keep_the_old() {
        // One fleet frame, whatever the clock.
        assert_eq!(frame_epoch(false, ClockMode::Lockstep), 0);
        assert_eq!(frame_epoch(false, ClockMode::Realtime), 0);
        // Lockstep starts replay the same start pose: the same frame, so
        // two runs stay bit for bit the same.
        assert_eq!(frame_epoch(true, ClockMode::Lockstep), 1);
        // A start in real time names a frame no other start names.
        let a = frame_epoch(true, ClockMode::Realtime);
        std::thread::sleep(Duration::from_millis(2));
        let b = frame_epoch(true, ClockMode::Realtime);
        assert!(a > 1 && b > a, "{a} then {b}");
    }

    /// Frames at which the paths are logged over a run of `frames` frames.
    fn logged(frames: usize) -> Vec<usize> {
        let mut last = None;
        (0..frames)
            .filter(|&k| {
                let due = path_due(k, last);
                if due {
                    last = Some(k);
                }
                due
            })
            .collect()
    }

    #[test]
    fn paths_are_logged_every_ten_frames_then_as_the_run_grows_by_half_a_percent() {
        // A run under 2 000 frames: every 10 frames, from the first.
        let short = logged(1500);
        assert_eq!(short, (0..1500).step_by(10).collect::<Vec<_>>());
        // An hour at 10 Hz: far fewer, each at most 0.5 % of the run after the last.
        let hour = logged(36_000);
        assert!(hour.len() < 800, "{} paths", hour.len());
        for w in hour.windows(2) {
            let gap = w[1] - w[0];
            assert!(gap >= 10 && gap <= 10.max(w[1] / 200), "{w:?}");
        }
        assert!(36_000 - hour[hour.len() - 1] <= 180);
    }
}
