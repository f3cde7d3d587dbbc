//! A fleet agent on its robot's own sensors, live (`input.source: live`):
//! the loop of [`run_node`](super::run_node) driven by the IMU samples and
//! images as they arrive over Zenoh ([`crate::ros_input`]) instead of a tick
//! grid. The fleet clock is the sensors' clock (the robots' clocks kept
//! together, by PTP or chrony); the estimator starts with the static
//! initializer, placed at the configured start pose in the fleet's frame, so
//! that what peers send and what it estimates share one frame.
//!
//! [`run_live_node`] is the whole loop, one sensor event at a time:
//!
//! 1. take the peers' messages that arrived into their histories;
//! 2. feed the event to the estimator (an image through the frontend first;
//!    until the static start succeeds, its tracks only go to the peers);
//! 3. take the new estimates: publish each frame's tracks and, when due, a
//!    window snapshot; record the estimate and publish it as a ROS pose;
//! 4. history catch-up, the history store and the heartbeat on their periods.

use super::{event_time, Node, NodeError, NodeReport, Progress, RunEnd, RunHeader};
use crate::config::{AgentConfig, LiveInputConfig};
use crate::dataset::{mav0_root, SensorSetup};
use crate::estimator::static_init::{static_start_sigmas, StaticInitOptions};
use crate::estimator::{Estimator, InitialState};
use crate::node_images::ImageFrames;
use crate::ros_input::{EstimateLatency, LiveError, LiveLimits, LiveSensors, SensorKeys};
use crate::runner::Variant;
use crate::status_log::StatusLog;
use common::calibration::CameraCalibration;
use common::estimator_options::EstimatorOptions;
use common::measurement::FeatureFrame;
use common::messages::AgentState;
use nalgebra::Vector3;
use simulator::SimEvent;
use std::collections::VecDeque;
use std::sync::atomic::AtomicBool;
use std::sync::mpsc::{sync_channel, RecvTimeoutError};
use std::sync::Arc;
use std::time::{Duration, Instant};

/// Sensor events between the reading thread and the loop: a few seconds of
/// a 200 Hz IMU. When the loop falls behind, the reader waits and the
/// sensors' own bounded queues drop (and count) what does not fit.
const EVENT_QUEUE: usize = 1024;

/// Wall time between two notes that the static start is still waiting.
const START_NOTE_PERIOD: Duration = Duration::from_secs(5);

/// Wall time between two rounds of catch-up, history store, heartbeat and
/// status checks.
const HOUSEKEEPING_PERIOD: Duration = Duration::from_millis(50);

/// Longest wait for a sensor event before the loop looks at its peers, ms.
const POLL_MS: u64 = 5;

/// The robot this agent is, on live sensors: its calibration and its
/// estimator's settings.
#[derive(Clone, Debug)]
pub struct LiveSetup {
    /// The camera's (and the IMU's) calibration.
    pub calibration: CameraCalibration,
    /// The estimator's settings: the defaults, the IMU noise of the
    /// calibration, the variant, then the configuration's `estimator:` keys.
    pub opts: EstimatorOptions,
    /// Estimator variant.
    pub variant: Variant,
    /// The `input.live` block.
    pub live: LiveInputConfig,
}

impl LiveSetup {
    /// Reads the calibration `cfg.input.live` names and sets the estimator up.
    pub fn load(cfg: &AgentConfig) -> Result<Self, NodeError> {
        let live = cfg
            .input
            .live
            .clone()
            .ok_or_else(|| LiveError::Setting("input.live is not set".into()))?;
        let sensors = SensorSetup::load(&mav0_root(&live.calibration))?;
        let variant: Variant = cfg.estimator.variant.parse()?;
        if variant.centralized() {
            return Err(LiveError::Setting(format!(
                "variant `{}` runs in one process over the whole fleet, not in an agent",
                variant.name()
            ))
            .into());
        }
        let mut opts = EstimatorOptions::for_tracked_images();
        if let Some(n) = sensors.imu_noise {
            n.apply(&mut opts);
        }
        variant.apply(&mut opts);
        cfg.estimator.apply(&mut opts);
        opts.validate()
            .map_err(|e| LiveError::Setting(format!("estimator settings: {e}")))?;
        Ok(Self {
            calibration: sensors.calibration,
            opts,
            variant,
            live,
        })
    }

    /// The prior of the placed static start: the static initializer's,
    /// with the start pose's standard deviations.
    fn start_sigmas(&self) -> InitialState {
        InitialState {
            sigma_ori_rad: self.live.start.sigma_ori_deg.to_radians(),
            sigma_yaw_rad: self.live.start.sigma_yaw_deg.map(f64::to_radians),
            sigma_pos_m: self.live.start.sigma_pos_m,
            ..static_start_sigmas()
        }
    }
}

/// Where and how the static start puts the robot in the fleet's frame.
struct Placement {
    init: StaticInitOptions,
    sigmas: InitialState,
    /// The IMU axis whose heading is given (unit, IMU frame).
    axis_i: Vector3<f64>,
    yaw_rad: f64,
    pos: Vector3<f64>,
}

/// The robot's own side of the loop: its filter and frontend, and the
/// frames waiting for their estimates.
struct Robot<'a> {
    cfg: &'a AgentConfig,
    setup: &'a LiveSetup,
    est: Estimator,
    images: Option<ImageFrames>,
    queued: VecDeque<(u64, FeatureFrame)>,
    frames_seen: u64,
    /// The start still to make (`None` once the filter runs).
    start: Option<Placement>,
    /// When the wait for a static start was last noted.
    waiting_noted: Instant,
}

impl Robot<'_> {
    /// One sensor event into the filter: an IMU sample, or an image through
    /// the frontend. A sample the filter refuses (NaN, time going back) and
    /// an image the frontend cannot take lose themselves, not the run.
    fn event(&mut self, node: &mut Node, ev: SimEvent) -> Result<(), NodeError> {
        match ev {
            SimEvent::Imu(s) => {
                if let Err(e) = self.est.feed_imu(s) {
                    node.report.run.rejected.push(e.to_string());
                }
            }
            SimEvent::Camera(mut c) => {
                let images = match self.images.as_mut() {
                    Some(i) => i,
                    None => self.images.insert(
                        ImageFrames::new(
                            &self.cfg.images.frontend,
                            self.setup.calibration.camera.clone(),
                            self.cfg.images.mcap_every,
                        )
                        .map_err(NodeError::Images)?,
                    ),
                };
                if let Err(e) = images.apply(&mut c, node.log.as_mut()) {
                    let why = format!("image at t={:.6} s: {e}", c.frame.t);
                    node.report.run.rejected.push(why);
                    return Ok(());
                }
                let index = self.frames_seen;
                self.frames_seen += 1;
                if self.start.is_some() {
                    // Before the start the tracks only go to the peers.
                    self.try_start();
                    let env = node.outbox.tracks(index, &c.frame, self.est.calibration());
                    node.publish(env);
                } else {
                    match self.est.feed_frame(c.frame.clone()) {
                        Ok(()) => self.queued.push_back((index, c.frame)),
                        Err(e) => node.report.run.rejected.push(e.to_string()),
                    }
                }
            }
        }
        Ok(())
    }

    /// Starts the filter if the IMU up to this image stood still, placed in
    /// the fleet's frame; says every few seconds why it cannot yet (a robot
    /// that never stands still never starts).
    fn try_start(&mut self) {
        let Some(p) = self.start.as_ref() else {
            return;
        };
        match (self.est).initialize_static_at(&p.init, &p.sigmas, &p.axis_i, p.yaw_rad, p.pos) {
            Ok(res) => {
                let s = &self.setup.live.start;
                tracing::info!(
                    robot = self.cfg.robot_id,
                    t = res.t,
                    "static start, placed at {:?} m, IMU {} heading {} deg",
                    s.position_m,
                    s.heading_axis,
                    s.yaw_deg
                );
                self.start = None;
            }
            Err(e) if self.waiting_noted.elapsed() >= START_NOTE_PERIOD => {
                self.waiting_noted = Instant::now();
                tracing::warn!(
                    robot = self.cfg.robot_id,
                    "no static start yet (keep the robot still): {e}"
                );
            }
            Err(_) => {}
        }
    }
}

/// Runs the agent on live sensors until they stop (`input.live.idle_timeout_s`),
/// the time is up (`max_duration_s`) or `stop` is set, then lingers while peers
/// still run, as [`run_node`](super::run_node) does. Outputs are returned, not
/// written ([`crate::agent_output`]); the run's text files are written as it
/// goes.
pub fn run_live_node(
    cfg: &AgentConfig,
    setup: &LiveSetup,
    transport: Box<dyn crate::transport::Transport>,
    stop: &Arc<AtomicBool>,
    mut progress: impl FnMut(Progress),
) -> Result<NodeReport, NodeError> {
    let cpu_start = cpu_time::ThreadTime::try_now().ok();
    let live = &setup.live;
    let start = &live.start;
    let mut robot = Robot {
        cfg,
        setup,
        est: Estimator::new(setup.opts.clone(), setup.calibration.clone()),
        images: None,
        queued: VecDeque::new(),
        frames_seen: 0,
        start: Some(Placement {
            init: StaticInitOptions::default(),
            sigmas: setup.start_sigmas(),
            axis_i: start.heading_axis_i().map_err(LiveError::Setting)?,
            yaw_rad: start.yaw_deg.to_radians(),
            pos: Vector3::from(start.position_m),
        }),
        waiting_noted: Instant::now(),
    };
    let header = RunHeader {
        scenario: "live".into(),
        seed: cfg.input.seed.unwrap_or(0),
        variant: setup.variant,
        robot_name: format!("robot{}", cfg.robot_id),
        mission: format!("live, fleet {}", cfg.fleet_id),
        with_truth: false,
    };
    let keys = SensorKeys {
        imu: live.imu_key.clone(),
        image: live.image_key.clone(),
    };
    // A bad sensor setting must stop the agent before it starts...
    crate::transport::zenoh::load_config(&live.zenoh)
        .map_err(|e| LiveError::Zenoh(format!("input.live.zenoh: {e}")))?;
    let (mut node, mut run_files) = Node::open(cfg, &header, transport, &mut robot.est)?;
    node.wait_for_peers(cfg, stop);
    // ...but the sensors are heard only once the peers are: samples queued
    // while waiting for them would be stale, and the queues' bounds would drop
    // them as if the agent were behind.
    let sensors = LiveSensors::open(&live.zenoh, &keys)?;
    let counts = sensors.counts();
    let mut poses = match &live.pose_key {
        Some(key) => Some(sensors.pose_publisher(key, &live.world_frame)?),
        None => None,
    };
    let mut odometry = match &live.odom_key {
        Some(key) => Some(sensors.odometry_publisher(key, &live.world_frame, &live.body_frame)?),
        None => None,
    };
    tracing::info!(
        robot = cfg.robot_id,
        "{}: listening for {} (IMU) and {} (camera)",
        setup.variant.name(),
        keys.imu,
        keys.image
    );

    let limits = LiveLimits {
        wait_first: Duration::from_secs_f64(live.wait_s),
        idle: Duration::from_secs_f64(live.idle_timeout_s),
        max_duration: live.max_duration_s.map(Duration::from_secs_f64),
    };
    let mut events = sensors.events(Arc::clone(stop), limits);
    let mut latency = EstimateLatency::new(events.arrivals());
    let (tx, rx) = sync_channel(EVENT_QUEUE);
    // The sensors' iterator blocks; the loop must also hear its peers.
    let reader = std::thread::Builder::new()
        .name(format!("robot{}-sensors", cfg.robot_id))
        .spawn(move || {
            for ev in events.by_ref() {
                if tx.send(ev).is_err() {
                    break;
                }
            }
            events
        })
        .map_err(|e| LiveError::Setting(format!("starting the sensor reader: {e}")))?;

    let mut status = StatusLog::new(cfg.status_period_s);
    let mut t_first: Option<f64> = None;
    let mut last_heartbeat = Instant::now();
    let mut last_housekeeping = Instant::now();
    loop {
        if Node::stopping(stop) {
            node.report.interrupted = true;
            break;
        }
        let ev = match rx.recv_timeout(Duration::from_millis(POLL_MS)) {
            Ok(ev) => Some(ev),
            Err(RecvTimeoutError::Timeout) => None,
            Err(RecvTimeoutError::Disconnected) => break,
        };
        // 1. What the peers sent: on the sensors' clock there is no barrier.
        node.drain();
        node.deliver(f64::INFINITY);
        match ev {
            Some(Ok(ev)) => {
                let t = event_time(&ev);
                t_first.get_or_insert(t);
                node.fleet_t = Some(node.fleet_t.map_or(t, |f| f.max(t)));
                // 2. The event.
                robot.event(&mut node, ev)?;
                // 3. The new estimates, out as ROS poses too.
                let n = node.take_estimates(
                    &mut robot.est,
                    &mut robot.queued,
                    None,
                    run_files.as_mut(),
                );
                let run = &node.report.run;
                if let (true, Some(pose), Some(cov), Some(twist)) = (
                    n > 0,
                    run.estimate.last(),
                    run.covariance.last(),
                    run.last_twist.as_ref(),
                ) {
                    for p in [poses.as_mut(), odometry.as_mut()].into_iter().flatten() {
                        p.publish(pose, cov, twist);
                    }
                    latency.estimated(pose.t);
                }
            }
            Some(Err(why)) => node.report.run.rejected.push(why),
            None => {}
        }
        // 4. Housekeeping on the fleet clock, as often as the simulated loop's
        // camera ticks: not after each of the IMU's 200-400 samples a second.
        let Some(now_s) = node.fleet_t else {
            continue;
        };
        if last_housekeeping.elapsed() < HOUSEKEEPING_PERIOD {
            continue;
        }
        last_housekeeping = Instant::now();
        node.catch_up(now_s);
        node.store_histories(now_s, false);
        node.report.ticks = robot.frames_seen;
        if last_heartbeat.elapsed().as_secs_f64() >= cfg.publish.heartbeat_period_s {
            last_heartbeat = Instant::now();
            let hb = node.outbox.heartbeat(
                now_s,
                AgentState::Running,
                node.report.run.frames.len() as u64,
                robot.frames_seen.checked_sub(1),
                node.newest_window_end_s(),
            );
            node.publish(vec![hb]);
            progress(Progress {
                tick: robot.frames_seen,
                ticks_total: 0,
                frames: node.report.run.frames.len() as u64,
                lag_s: 0.0,
            });
        }
        if let Some(s) = status.as_mut() {
            let frames = &node.report.run.frames;
            if let Some(line) = s.due(
                node.wall_s(),
                || node.counters(0.0),
                |k| frames.get(k).map_or(0.0, |f| f.timing.cpu_ms),
                &node.report.latencies_ms,
            ) {
                tracing::info!(robot = cfg.robot_id, "status: {line}");
            }
        }
    }
    node.report.ticks = robot.frames_seen;
    drop(rx);
    match reader.join() {
        Ok(events) => events.close(Duration::from_secs(5)),
        Err(_) => tracing::warn!("the sensor reader panicked"),
    }
    let sensors_line = format!("{}; {}", counts.line(), latency.line());
    tracing::info!(robot = cfg.robot_id, "sensors: {sensors_line}");
    if let Some(p) = &poses {
        tracing::info!(
            robot = cfg.robot_id,
            "poses: {} published ({} refused)",
            p.sent,
            p.failed
        );
    }
    if let Some(p) = &odometry {
        tracing::info!(
            robot = cfg.robot_id,
            "odometry: {} published ({} refused)",
            p.sent,
            p.failed
        );
    }
    if robot.start.is_some() && !counts.nothing_received() {
        tracing::warn!(
            robot = cfg.robot_id,
            "the robot never stood still long enough to start: no estimate"
        );
    }
    let t_last = node.fleet_t.unwrap_or(0.0);
    let end = RunEnd {
        t_last,
        last_tick: robot.frames_seen.checked_sub(1),
        data_unfinished: false,
        fleet_s: t_first.map_or(0.0, |t0| t_last - t0),
    };
    let mut report = node.finish(cfg, &robot.est, run_files, stop, &end, cpu_start.as_ref());
    if counts.nothing_received() {
        return Err(LiveError::Setting(format!(
            "no sensor message decoded on {} or {} within {} s",
            keys.imu, keys.image, live.wait_s
        ))
        .into());
    }
    report.sensors = Some(sensors_line);
    Ok(report)
}
