//! Runs one robot of a simulated scenario through its estimator, standalone (no
//! peers): the agent reads its own robot's sensors from the simulator, as a real
//! robot reads its own, and the result is scored against the simulator's truth.

use crate::estimator::frame_output::{BodyTwist, StampedTwist};
use crate::estimator::{Estimator, EstimatorOptions, FrameOutput, FrameRecord, InitialState};
use common::estimator_options::TRACKED_SLAM_SIGMA_PX;
use common::measurement::FeatureFrame;
use common::metrics::{ate, nees, rpe, Alignment, PosePair, DEFAULT_RPE_SEGMENTS_M};
use common::so3::exp_so3;
use common::summary::MetricSet;
use common::trajectory::{ImuStateRecord, ImuTruth, StampedCovariance, StampedPose};
use simulator::camera_sim::{CameraEvent, TruthState};
use simulator::scenario::{EstimatorSpec, StartFrame};
use simulator::{Fleet, SimEvent};
use std::str::FromStr;
use thiserror::Error;

/// The estimator variants (thesis Section 5.4). Every variant but `indp` uses
/// SLAM features; the `dc-*` variants add what peers saw, with CI-EKF updates;
/// the `ce-*` variants are the centralized estimator (one joint state).
#[derive(Clone, Copy, Debug, PartialEq, Eq, PartialOrd, Ord, Hash)]
pub enum Variant {
    /// MSCKF only (no SLAM features, nothing from peers).
    Indp,
    /// MSCKF with SLAM features, nothing from peers.
    IndpSlam,
    /// Distributed: common VIO features over the window.
    DcCmsckf,
    /// Distributed: common VIO and SLAM features over the window, SLAM features
    /// always by the peers' measurements.
    DcCmsckfCslam,
    /// Distributed: as `dc-cmsckf-cslam` with the SLAM-to-SLAM constraint update.
    DcFullWindow,
    /// Distributed: as `dc-full-window` plus historical features (loop closures
    /// to peers' stored keyframe windows).
    DcFullHistory,
    /// Centralized: common VIO features over the window.
    CeCmsckf,
    /// Centralized: common VIO and SLAM features over the window.
    CeCmsckfCslam,
}

/// Every variant, in the thesis' table order.
pub const ALL_VARIANTS: [Variant; 8] = [
    Variant::Indp,
    Variant::IndpSlam,
    Variant::CeCmsckf,
    Variant::CeCmsckfCslam,
    Variant::DcCmsckf,
    Variant::DcCmsckfCslam,
    Variant::DcFullWindow,
    Variant::DcFullHistory,
];

impl Variant {
    /// The name used on command lines and in summaries.
    pub fn name(self) -> &'static str {
        match self {
            Variant::Indp => "indp",
            Variant::IndpSlam => "indp-slam",
            Variant::DcCmsckf => "dc-cmsckf",
            Variant::DcCmsckfCslam => "dc-cmsckf-cslam",
            Variant::DcFullWindow => "dc-full-window",
            Variant::DcFullHistory => "dc-full-history",
            Variant::CeCmsckf => "ce-cmsckf",
            Variant::CeCmsckfCslam => "ce-cmsckf-cslam",
        }
    }

    /// Whether the variant needs its peers (a fleet run).
    pub fn cooperative(self) -> bool {
        !matches!(self, Variant::Indp | Variant::IndpSlam)
    }

    /// Whether the variant is the centralized estimator (one process for all).
    pub fn centralized(self) -> bool {
        matches!(self, Variant::CeCmsckf | Variant::CeCmsckfCslam)
    }

    /// Sets what the variant takes from peers (distributed variants; the
    /// centralized ones use the same flags for their joint updates).
    pub fn apply(self, o: &mut EstimatorOptions) {
        let c = &mut o.cooperation;
        c.common_vio = self.cooperative();
        c.common_slam = matches!(
            self,
            Variant::DcCmsckfCslam
                | Variant::DcFullWindow
                | Variant::DcFullHistory
                | Variant::CeCmsckfCslam
        );
        c.slam_constraint = matches!(self, Variant::DcFullWindow | Variant::DcFullHistory);
        c.historical = self == Variant::DcFullHistory;
        if self == Variant::Indp {
            o.max_slam_features = 0;
        }
    }
}

impl FromStr for Variant {
    type Err = RunError;
    fn from_str(s: &str) -> Result<Self, RunError> {
        ALL_VARIANTS
            .iter()
            .copied()
            .find(|v| v.name() == s)
            .ok_or_else(|| RunError::UnknownVariant(s.to_string()))
    }
}

/// Why a run failed.
#[derive(Debug, Error)]
pub enum RunError {
    /// Simulation error.
    #[error(transparent)]
    Sim(#[from] simulator::SimError),
    /// A variant name that does not exist.
    #[error("unknown variant `{0}` (known: indp, indp-slam, dc-cmsckf, dc-cmsckf-cslam, dc-full-window, dc-full-history, ce-cmsckf, ce-cmsckf-cslam)")]
    UnknownVariant(String),
    /// The options the scenario and the overrides give are refused.
    #[error("estimator options: {0}")]
    Options(String),
    /// A centralized variant asked to run robots in their own frames.
    #[error("{0} keeps every robot in one joint state: it needs `estimator.start_frame: fleet`")]
    NeedsFleetFrame(&'static str),
    /// The scenario renders images, and this run takes simulated features.
    #[error("the scenario renders images (render.enabled), and {0} takes simulated features: {1}")]
    RendersImages(&'static str, &'static str),
    /// The scenario renders images, and this build has no image frontend.
    #[error(
        "the scenario renders images (render.enabled), and this build has no image frontend: \
         build with `--features agent/vision` (OpenCV)"
    )]
    NoImageFrontend,
    /// The robot never moved enough to start.
    #[error("robot {0} has no camera frame after its start time")]
    NeverStarted(usize),
    /// The camera frames could not be made (e.g. by the image frontend).
    #[error("camera frame at t={t}: {reason}")]
    Frames {
        /// Camera time of the image.
        t: f64,
        /// What went wrong.
        reason: String,
    },
}

/// The estimator options a scenario asks for, for one variant.
///
/// With `start_frame: own` the distributed cooperative variants align their
/// peers' frames (`align_peer_frames`), which needs loop closures: of those,
/// only `dc-full-history` passes [`EstimatorOptions::validate`].
///
/// A fleet that renders images makes its features with the image frontend,
/// so unless the scenario sets `slam_pixel_sigma_px` its SLAM updates take the
/// camera-image default ([`TRACKED_SLAM_SIGMA_PX`]), and unless it sets
/// `slam_keyframe_updates` they are paced on a keyframe window, as `agent
/// dataset` and live sensors do ([`EstimatorOptions::for_tracked_images`]).
///
/// The pixel noise the filter expects is robot `robot`'s camera's (a fleet
/// may mix cameras, `robots[i].camera`).
pub fn options_for(
    spec: &EstimatorSpec,
    fleet: &Fleet,
    robot: usize,
    variant: Variant,
) -> EstimatorOptions {
    let mut o = spec.options(&fleet.scenario.sensors_of(robot));
    if fleet.renders() && o.slam_pixel_sigma_px.is_none() {
        o.slam_pixel_sigma_px = Some(TRACKED_SLAM_SIGMA_PX);
    }
    if fleet.renders() && spec.slam_keyframe_updates.is_none() {
        o.slam_keyframe_updates = true;
    }
    variant.apply(&mut o);
    if spec.start_frame == StartFrame::Own && variant.cooperative() && !variant.centralized() {
        o.cooperation.align_peer_frames = true;
    }
    o
}

/// Everything one standalone run produced.
#[derive(Clone, Debug, Default)]
pub struct RobotRun {
    /// The estimate after each frame.
    pub estimate: Vec<StampedPose>,
    /// Its 3x3 orientation and position covariances.
    pub covariance: Vec<StampedCovariance>,
    /// The truth at the estimate times (empty when
    /// [`RobotRun::without_truth`]).
    pub truth: Vec<StampedPose>,
    /// The run has no truth (live sensors): every estimate is recorded, and
    /// accuracy is for `sim-fleet eval` against a ground truth recorded
    /// apart. With a truth, an estimate outside its span is not recorded.
    pub without_truth: bool,
    /// Per-frame records (timing, feature counts).
    pub frames: Vec<FrameRecord>,
    /// The body twist of the last recorded estimate, with its whole
    /// covariance (published beside the pose on live sensors).
    pub last_twist: Option<BodyTwist>,
    /// The body twist after each frame, with its standard deviations.
    pub twists: Vec<StampedTwist>,
    /// Inputs and frames the estimator rejected, with the reason.
    pub rejected: Rejections,
    /// Cooperation counters at the end (cooperative variants only).
    pub cooperation: Option<crate::cooperation::CooperationStats>,
    /// CPU time of the run, s, simulating the sensors included (`None` where
    /// the platform has no thread clock). See [`MetricSet::cpu_s`].
    pub cpu_s: Option<f64>,
    /// Velocity and biases after each frame, with their covariances and the
    /// truth (simulated runs; `imu_state.txt`).
    pub imu_states: Vec<ImuStateRecord>,
    /// The simulator's true biases at the camera times not yet recorded.
    pub pending_biases: std::collections::VecDeque<(f64, simulator::imu::Biases)>,
}

/// Largest time difference (s) between an estimate and the camera time whose
/// true biases it is scored against: the estimate's time moves with the
/// estimated camera-IMU time offset, the biases change little within it.
const BIAS_MATCH_TOL_S: f64 = 0.02;

/// Camera times whose true biases wait for their estimate, at most.
const PENDING_BIASES_MAX: usize = 64;

/// Inputs the estimator rejected: all counted, the first
/// [`Rejections::KEPT`] reasons kept. A sensor that sends bad data for hours
/// must not grow the run's memory.
#[derive(Clone, Debug, Default, PartialEq, Eq)]
pub struct Rejections {
    count: usize,
    kept: Vec<String>,
}

impl Rejections {
    /// Reasons kept, at most.
    pub const KEPT: usize = 100;

    /// Counts one rejection and keeps its reason while there is room.
    pub fn push(&mut self, why: String) {
        self.count += 1;
        if self.kept.len() < Self::KEPT {
            self.kept.push(why);
        }
    }

    /// Rejections counted.
    pub fn len(&self) -> usize {
        self.count
    }

    /// Nothing was rejected.
    pub fn is_empty(&self) -> bool {
        self.count == 0
    }

    /// The reasons kept, first first.
    pub fn iter(&self) -> std::slice::Iter<'_, String> {
        self.kept.iter()
    }

    /// The first reason.
    pub fn first(&self) -> Option<&String> {
        self.kept.first()
    }
}

impl std::ops::Index<usize> for Rejections {
    type Output = String;

    /// The `i`-th reason kept (panics past [`Rejections::KEPT`] or the count).
    fn index(&self, i: usize) -> &String {
        &self.kept[i]
    }
}

/// The calling thread's CPU time since `start`, s (`None` without a clock).
pub fn thread_cpu_s(start: Option<&cpu_time::ThreadTime>) -> Option<f64> {
    start
        .and_then(|t| t.try_elapsed().ok())
        .map(|d| d.as_secs_f64())
}

/// Runs robot `robot` of `fleet` with `opts`, initialized at the true state once
/// it has moved `start_after_motion_m` (OpenVINS's simulation start).
pub fn run_robot(
    fleet: &Fleet,
    robot: usize,
    opts: EstimatorOptions,
) -> Result<RobotRun, RunError> {
    require_features(fleet)?;
    run_robot_with(fleet, robot, opts, |c| Ok(Some(c.frame)))
}

/// Refuses a fleet that renders images where simulated features are expected:
/// rendered frames carry images, and without the image frontend every frame
/// would be empty.
pub fn require_features(fleet: &Fleet) -> Result<(), RunError> {
    if fleet.renders() {
        return Err(RunError::RendersImages(
            "this run",
            "run it through the image frontend (`agent run --render`, cargo feature `vision`)",
        ));
    }
    Ok(())
}

/// [`run_robot`] with the feature frames made by `frames` from each camera
/// event (an image frontend, for rendered images). `frames` sees every event,
/// also those before the estimator starts (tracks must begin somewhere), and
/// returns `None` for an image without a frame; its errors stop the run.
pub fn run_robot_with(
    fleet: &Fleet,
    robot: usize,
    opts: EstimatorOptions,
    frames: impl FnMut(CameraEvent) -> Result<Option<FeatureFrame>, RunError>,
) -> Result<RobotRun, RunError> {
    run_stream(fleet, robot, opts, fleet.stream(robot)?, frames)
}

/// [`run_robot_with`] on a given measurement stream of robot `robot` (e.g.
/// [`Fleet::stream_with_imu`]: recorded IMU, simulated camera).
pub fn run_stream(
    fleet: &Fleet,
    robot: usize,
    opts: EstimatorOptions,
    events: impl Iterator<Item = SimEvent>,
    mut frames: impl FnMut(CameraEvent) -> Result<Option<FeatureFrame>, RunError>,
) -> Result<RobotRun, RunError> {
    let truth = &fleet
        .agent_truth(robot)
        .ok_or(simulator::SimError::NoSuchRobot(robot))?;
    let start = fleet
        .estimator_start_time(robot)
        .ok_or(simulator::SimError::NoSuchRobot(robot))?;
    let cpu_start = cpu_time::ThreadTime::try_now().ok();
    let mut est = Estimator::new(opts, fleet.initial_calibration(robot));
    let mut run = RobotRun::default();
    let mut initialized = false;
    for ev in events {
        match ev {
            SimEvent::Imu(s) => {
                if let Err(e) = est.feed_imu(s) {
                    run.rejected.push(e.to_string());
                }
            }
            SimEvent::Camera(c) => {
                let state = c.truth;
                run.note_true_biases(state.t, state.biases);
                let frame = frames(*c)?;
                if !initialized {
                    if state.t < start {
                        continue;
                    }
                    est.initialize(&initial_state(fleet, robot, &state));
                    initialized = true;
                    continue;
                }
                let Some(frame) = frame else { continue };
                if let Err(e) = est.feed_frame(frame) {
                    run.rejected.push(e.to_string());
                }
            }
        }
        for out in est.poll() {
            match out {
                Ok(o) => record(&mut run, truth, o),
                Err(e) => run.rejected.push(e.to_string()),
            }
        }
    }
    if !initialized {
        return Err(RunError::NeverStarted(robot));
    }
    run.cpu_s = thread_cpu_s(cpu_start.as_ref());
    Ok(run)
}

/// Robot `robot`'s start: the true state plus the fleet's start error for it
/// (zero unless the scenario samples it from the prior), with the scenario's
/// prior standard deviations (OpenVINS's simulation start when it is zero).
///
/// With `start_frame: own` the state is in the robot's own frame.
pub fn initial_state(fleet: &Fleet, robot: usize, truth: &TruthState) -> InitialState {
    let spec = &fleet.scenario.estimator;
    let truth = &fleet.state_in_robot_frame(robot, truth).unwrap_or(*truth);
    let err = fleet.start_error(robot);
    InitialState {
        t: truth.t,
        rot: truth.rot * exp_so3(&err.rot),
        pos: truth.pos + err.pos,
        vel: truth.vel + err.vel,
        bias_gyro: truth.biases.gyro + err.bias_gyro,
        bias_accel: truth.biases.accel + err.bias_accel,
        sigma_ori_rad: spec.init_sigma_ori_rad,
        sigma_yaw_rad: None,
        sigma_pos_m: spec.init_sigma_pos_m,
        sigma_vel_mps: spec.init_sigma_vel_mps,
        sigma_bias_gyro: spec.init_sigma_bias,
        sigma_bias_accel: spec.init_sigma_bias,
    }
}

/// The true body twist at `t` from the spline's state: the velocity in the
/// body's axes and the angular rate (standard deviations zero).
pub fn truth_twist(t: f64, s: &simulator::bspline::SplineState) -> StampedTwist {
    StampedTwist {
        t,
        linear: s.rot.transpose() * s.vel,
        angular: s.omega,
        sigma: [0.0; 6],
    }
}

/// Appends a frame's output to `run`, with the truth at the estimate's time
/// (and its velocity and biases when [`RobotRun::note_true_biases`] gave them).
pub fn record(run: &mut RobotRun, truth: &simulator::truth::RobotTruth, o: FrameOutput) {
    let Some(gt) = truth.spline.pose(o.t()) else {
        return;
    };
    if let (Some(biases), Some(state)) = (run.true_biases_at(o.t()), truth.spline.state(o.t())) {
        run.imu_states.push(ImuStateRecord {
            estimate: o.imu,
            truth: ImuTruth {
                vel: state.vel,
                bias_gyro: biases.gyro,
                bias_accel: biases.accel,
            },
        });
    }
    run.estimate.push(o.pose());
    run.truth.push(StampedPose {
        t: o.t(),
        rot: gt.rot,
        pos: gt.trans,
    });
    run.covariance.push(o.covariance());
    run.twists.push(o.twist.stamped(o.t()));
    run.last_twist = Some(o.twist);
    run.frames.push(o.record);
}

impl RobotRun {
    /// Keeps the simulator's true biases at a camera time for the estimate of
    /// that frame, which [`record`] takes when the estimator returns it.
    pub fn note_true_biases(&mut self, t: f64, biases: simulator::imu::Biases) {
        // Estimates trail their frames by a few frames at most; frames the
        // estimator refused never come back, so the queue stays short.
        if self.pending_biases.len() >= PENDING_BIASES_MAX {
            self.pending_biases.pop_front();
        }
        self.pending_biases.push_back((t, biases));
    }

    /// The true biases noted nearest to `t` (within [`BIAS_MATCH_TOL_S`]);
    /// those noted before it are dropped, as estimates come in time order.
    fn true_biases_at(&mut self, t: f64) -> Option<simulator::imu::Biases> {
        while self
            .pending_biases
            .get(1)
            .is_some_and(|(next, _)| (next - t).abs() <= (self.pending_biases[0].0 - t).abs())
        {
            self.pending_biases.pop_front();
        }
        let &(at, biases) = self.pending_biases.front()?;
        ((at - t).abs() <= BIAS_MATCH_TOL_S).then_some(biases)
    }

    /// Records an estimate of a run [`RobotRun::without_truth`].
    pub fn record_without_truth(&mut self, o: FrameOutput) {
        debug_assert!(self.without_truth && self.truth.is_empty());
        self.estimate.push(o.pose());
        self.covariance.push(o.covariance());
        self.twists.push(o.twist.stamped(o.t()));
        self.last_twist = Some(o.twist);
        self.frames.push(o.record);
    }

    /// Accuracy, consistency and cost of the run (ATE without alignment).
    pub fn metrics(&self) -> MetricSet {
        let pairs: Vec<PosePair> = self
            .estimate
            .iter()
            .copied()
            .zip(self.truth.iter().copied())
            .collect();
        MetricSet {
            loop_closures: self.cooperation.map(|c| c.loop_closures),
            common_feature_updates: self
                .cooperation
                .map(|_| self.frames.iter().map(|f| f.coop.updates() as u64).sum()),
            cpu_s: self.cpu_s,
            ..record_metrics(&pairs, &self.covariance, &self.frames)
        }
    }
}

/// Accuracy (ATE unaligned and position-and-yaw aligned, RPE), consistency
/// (NEES against the covariance of each estimate's time) and cost per frame
/// of a run's record: `pairs` are its estimates with the truth at their times.
pub fn record_metrics(
    pairs: &[PosePair],
    covariance: &[StampedCovariance],
    frames: &[FrameRecord],
) -> MetricSet {
    let a = ate(pairs, Alignment::None);
    let aligned = ate(pairs, Alignment::PosYaw);
    let n = nees(pairs, covariance);
    let mut times: Vec<f64> = frames.iter().map(|f| f.timing.total_ms).collect();
    times.sort_by(f64::total_cmp);
    let mean = (!times.is_empty()).then(|| times.iter().sum::<f64>() / times.len() as f64);
    let p95 = common::metrics::percentile_sorted(&times, 0.95);
    MetricSet {
        ate_ori_deg: (a.n > 0).then_some(a.ori_deg),
        ate_pos_m: (a.n > 0).then_some(a.pos_m),
        ate_posyaw_ori_deg: (aligned.n > 0).then_some(aligned.ori_deg),
        ate_posyaw_pos_m: (aligned.n > 0).then_some(aligned.pos_m),
        nees_ori: n.ori_mean,
        nees_pos: n.pos_mean,
        rpe: Some(rpe(pairs, &DEFAULT_RPE_SEGMENTS_M)),
        frames: Some(frames.len() as u64),
        ms_per_frame_mean: mean,
        ms_per_frame_p95: p95,
        ..MetricSet::default()
    }
}

/// The header line of `timing.csv` (one row per frame, [`timing_row`]).
pub const TIMING_HEADER: &str = "t,propagate_ms,msckf_ms,slam_update_ms,slam_init_ms,marginalize_ms,total_ms,msckf_features,msckf_rejected,msckf_failed,slam_features,slam_updated,slam_rejected,slam_initialized,slam_init_failed,matching_ms,common_vio_ms,common_slam_ms,constraint_ms,common_vio_used,common_vio_rejected,common_slam_used,constraints_used,participants,historical_participants,ci_participants,omega_own,ci_update_ms,cpu_ms,evidence_ms,zero_velocity,first_update_rescued";

/// One row of `timing.csv` (no newline): a frame's costs and counts.
pub fn timing_row(f: &FrameRecord) -> String {
    let t = &f.timing;
    format!(
        "{:.6},{:.4},{:.4},{:.4},{:.4},{:.4},{:.4},{},{},{},{},{},{},{},{},{:.4},{:.4},{:.4},{:.4},{},{},{},{},{},{},{},{:.6},{:.4},{:.4},{:.4},{},{}",
        f.t,
        t.propagate_ms,
        t.msckf_ms,
        t.slam_update_ms,
        t.slam_init_ms,
        t.marginalize_ms,
        t.total_ms,
        f.msckf_features,
        f.msckf.rejected_chi2,
        f.msckf.failed,
        f.slam_features,
        f.slam.updated,
        f.slam.rejected_chi2,
        f.slam.initialized,
        f.slam.init_failed,
        f.coop.matching_ms,
        f.coop.common_vio_ms,
        f.coop.common_slam_ms,
        f.coop.constraint_ms,
        f.coop.common_vio.used,
        f.coop.common_vio.rejected_chi2,
        f.coop.common_slam.used,
        f.coop.constraints.used,
        f.coop.participants,
        f.coop.historical_participants,
        f.coop.ci_participants,
        f.coop.omega_own,
        f.coop.ci_update_ms,
        t.cpu_ms,
        f.coop.evidence_ms,
        u8::from(f.zero_velocity),
        u8::from(f.msckf.rescued)
    )
}

/// Writes a run's estimate and ground truth (TUM), per-pose covariances and
/// per-frame timing (`timing.csv`) into `dir`.
pub fn write_run_outputs(run: &RobotRun, dir: &std::path::Path) -> std::io::Result<()> {
    crate::run_files::write_all(run, dir)?;
    write_imu_states(run, dir)
}

/// Writes `DIR/imu_state.txt` when the run recorded velocities and biases
/// against a truth (simulated runs).
pub fn write_imu_states(run: &RobotRun, dir: &std::path::Path) -> std::io::Result<()> {
    if run.imu_states.is_empty() {
        return Ok(());
    }
    common::trajectory::write_imu_states(dir.join("imu_state.txt"), &run.imu_states)
        .map_err(std::io::Error::other)
}

#[cfg(test)]
mod tests {
    use super::*;
    use nalgebra::{Rotation3, Vector3};

    /// Each estimate takes the true biases noted at the camera time nearest
    /// to it, within 20 ms; older notes go, and a frame with none is skipped.
    #[test]
    fn an_estimate_is_scored_against_the_biases_of_its_nearest_camera_time() {
        let biases = |x: f64| simulator::imu::Biases {
            gyro: Vector3::new(x, 0.0, 0.0),
            accel: Vector3::zeros(),
        };
        let mut run = RobotRun::default();
        for k in 0..4 {
            run.note_true_biases(0.1 * k as f64, biases(k as f64));
        }
        // An estimate 3 ms after the camera time (an estimated time offset).
        assert_eq!(run.true_biases_at(0.103), Some(biases(1.0)));
        assert_eq!(run.pending_biases.len(), 3, "the note at 0.0 is gone");
        // No note within 20 ms of 0.25: nothing, and the queue keeps 0.3.
        assert_eq!(run.true_biases_at(0.25), None);
        assert_eq!(run.true_biases_at(0.3), Some(biases(3.0)));
        // The queue stays bounded when no estimate comes.
        for k in 0..200 {
            run.note_true_biases(1.0 + 0.1 * k as f64, biases(0.0));
        }
        assert_eq!(run.pending_biases.len(), PENDING_BIASES_MAX);
    }

    /// An estimate that is the truth turned by 2 deg of yaw and moved by 10 cm:
    /// the unaligned ATE sees both, the position-and-yaw aligned one neither.
    #[test]
    fn the_aligned_ate_removes_a_yaw_and_offset_the_plain_one_keeps() {
        let yaw = Rotation3::from_axis_angle(&Vector3::z_axis(), 2f64.to_radians());
        let offset = Vector3::new(0.06, -0.08, 0.0);
        let mut run = RobotRun::default();
        for k in 0..50 {
            let t = 0.1 * k as f64;
            let rot = Rotation3::from_euler_angles(0.1 * t.sin(), 0.05, 0.3 * t).into_inner();
            let pos = Vector3::new(2.0 * t.cos(), 1.5 * t.sin(), 0.2 * t);
            run.truth.push(StampedPose { t, rot, pos });
            run.estimate.push(StampedPose {
                t,
                rot: yaw.matrix() * rot,
                pos: yaw * pos + offset,
            });
        }
        let m = run.metrics();
        assert!(m.ate_pos_m.unwrap() > 0.09, "{:?}", m.ate_pos_m);
        assert!((m.ate_ori_deg.unwrap() - 2.0).abs() < 1e-9);
        assert!(m.ate_posyaw_pos_m.unwrap() < 1e-9, "{m:?}");
        assert!(m.ate_posyaw_ori_deg.unwrap() < 1e-6, "{m:?}");
    }

    #[test]
    fn rejections_are_all_counted_and_the_first_hundred_kept() {
        let mut r = Rejections::default();
        assert!(r.is_empty() && r.first().is_none());
        for k in 0..250 {
            r.push(format!("sample {k}"));
        }
        assert_eq!(r.len(), 250);
        assert_eq!(r.iter().count(), Rejections::KEPT);
        assert_eq!(r[0], "sample 0");
        assert_eq!(r.iter().last().map(String::as_str), Some("sample 99"));
    }
}
