//! The agent's configuration file (YAML). Units are in the key names; estimator
//! keys follow OpenVINS's names where one exists (`max_clones`, `max_slam`,
//! `use_fej`, `calib_cam_extrinsics`, ...).

use crate::frontend::FrontendOptions;
use crate::runner::Variant;
use crate::transport::{Iceoryx2Settings, TransportKind, TransportSettings, ZenohSettings};
use common::estimator_options::{
    CiWeighting, CommonProjection, CooperationOptions, EstimatorOptions, FeatureRepresentation,
    MsckfJacobians, TriangulationLimits,
};
use serde::{Deserialize, Serialize};
use std::path::{Path, PathBuf};
use thiserror::Error;

/// Why a configuration could not be used.
#[derive(Debug, Error)]
pub enum ConfigError {
    /// The file could not be read.
    #[error("reading {path}: {source}")]
    Read {
        /// The file.
        path: PathBuf,
        /// The cause.
        source: std::io::Error,
    },
    /// The YAML is invalid or has unknown keys.
    #[error("{path}: {source}")]
    Parse {
        /// The file.
        path: PathBuf,
        /// The cause (with line and column).
        source: serde_yaml::Error,
    },
    /// A value is out of range or inconsistent.
    #[error("{path}: {what}")]
    Invalid {
        /// The file.
        path: PathBuf,
        /// What is wrong.
        what: String,
    },
}

/// One agent: who it is, how it talks, what it reads, what it writes.
#[derive(Clone, Debug, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct AgentConfig {
    /// This robot's id in the fleet (also its robot index in a simulated scenario
    /// unless `input.robot_index` says otherwise).
    pub robot_id: u32,
    /// Fleet id: messages of other fleets are ignored and counted.
    #[serde(default = "default_fleet")]
    pub fleet_id: String,
    /// Where outputs go (created if missing).
    pub output_dir: PathBuf,
    /// Transport to the peers.
    #[serde(default)]
    pub transport: TransportSection,
    /// Where the sensor data come from.
    pub input: InputConfig,
    /// Estimator variant and option overrides.
    #[serde(default)]
    pub estimator: EstimatorSection,
    /// Lockstep or real-time clock.
    #[serde(default)]
    pub clock: ClockConfig,
    /// What is published and how often.
    #[serde(default)]
    pub publish: PublishConfig,
    /// Peer histories: what is kept, and the memory bound.
    #[serde(default)]
    pub history: HistoryConfig,
    /// Whether to write the MCAP log.
    #[serde(default = "yes")]
    pub mcap_log: bool,
    /// Wall seconds between status lines in the agent's log (fleet time,
    /// frames and their CPU ms, lag, peers, histories held, traffic); 0: none.
    #[serde(default = "default_status_period_s")]
    pub status_period_s: f64,
    /// Camera images (rendered or real): the frontend and their logging.
    #[serde(default)]
    pub images: ImagesConfig,
    /// Injected faults, for drills and tests (none by default).
    #[serde(default)]
    pub faults: FaultsConfig,
}

/// Faults injected on purpose, to see what the agent does about them.
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct FaultsConfig {
    /// A link outage `[from, to)` in fleet seconds: every message a peer sent
    /// in it is dropped on arrival. In lockstep runs the heartbeats still pass
    /// (the fleet clock needs them; without them the peers would be released
    /// as silent), so the outage takes all the data and none of the clock.
    pub outage_fleet_s: Option<[f64; 2]>,
    /// A lossy link: the fraction in `[0, 1]` of the peers' messages dropped on
    /// arrival, each receiver losing its own (as on a radio link). In lockstep
    /// runs the heartbeats pass, as in an outage.
    pub loss_fraction: f64,
    /// Seed of the loss draws, mixed with the run's seed. A draw depends only
    /// on the seeds, the receiver, the sender, the message kind and its
    /// sequence number, so the same run loses the same messages whatever order
    /// they arrive in.
    pub loss_seed: u64,
}

/// Why an injected fault took a message.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum FaultDrop {
    /// Sent inside `faults.outage_fleet_s`.
    Outage,
    /// Drawn by `faults.loss_fraction`.
    Loss,
}

impl FaultsConfig {
    /// These faults in the run of `run_seed`: the loss draws differ from run
    /// to run.
    pub fn for_run(&self, run_seed: u64) -> FaultsConfig {
        FaultsConfig {
            loss_seed: splitmix64(self.loss_seed) ^ run_seed,
            ..self.clone()
        }
    }

    /// Whether the injected faults take the message of `kind` that robot
    /// `sender` stamped `stamp_s` with sequence number `seq`, on its way to robot
    /// `receiver`.
    pub fn drops(
        &self,
        message: FaultedMessage,
        receiver: u32,
        lockstep: bool,
    ) -> Option<FaultDrop> {
        let clock = message.kind == common::messages::MessageKind::Heartbeat && lockstep;
        if clock {
            return None;
        }
        if let Some([from, to]) = self.outage_fleet_s {
            if message.stamp_s >= from && message.stamp_s < to {
                return Some(FaultDrop::Outage);
            }
        }
        if self.loss_fraction > 0.0 {
            let kind = common::messages::MessageKind::ALL
                .iter()
                .position(|k| *k == message.kind)
                .unwrap_or(0) as u64;
            let draw = [receiver as u64, message.sender as u64, kind, message.seq]
                .into_iter()
                .fold(splitmix64(self.loss_seed), |h, v| splitmix64(h ^ v));
            // The top 53 bits as a uniform number in [0, 1).
            let u = (draw >> 11) as f64 / (1u64 << 53) as f64;
            if u < self.loss_fraction {
                return Some(FaultDrop::Loss);
            }
        }
        None
    }
}

/// What [`FaultsConfig::drops`] needs to know of a message.
#[derive(Clone, Copy, Debug)]
pub struct FaultedMessage {
    /// Its kind.
    pub kind: common::messages::MessageKind,
    /// The sending robot.
    pub sender: u32,
    /// The sender's sequence number of this kind.
    pub seq: u64,
    /// The send time on the fleet clock, s.
    pub stamp_s: f64,
}

/// One step of the SplitMix64 generator: a well-mixed 64-bit hash of `x`.
fn splitmix64(x: u64) -> u64 {
    let mut z = x.wrapping_add(0x9E37_79B9_7F4A_7C15);
    z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
    z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
    z ^ (z >> 31)
}

/// What an agent does with camera images.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct ImagesConfig {
    /// The image frontend (KLT + ORB; needs the `vision` feature).
    pub frontend: FrontendOptions,
    /// Log every this many images, with their tracks, to the MCAP file.
    pub mcap_every: u64,
}

impl Default for ImagesConfig {
    fn default() -> Self {
        Self {
            frontend: FrontendOptions::default(),
            mcap_every: 5,
        }
    }
}

fn default_fleet() -> String {
    "fleet".into()
}

/// A status line a minute: enough to follow a mission, little in the log.
pub const DEFAULT_STATUS_PERIOD_S: f64 = 60.0;

fn default_status_period_s() -> f64 {
    DEFAULT_STATUS_PERIOD_S
}

fn yes() -> bool {
    true
}

/// The transport section: which transport and its settings (the fleet and robot
/// ids come from the top level).
#[derive(Clone, Debug, Default, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct TransportSection {
    /// `zenoh`, `iceoryx2` or `inproc`.
    #[serde(default)]
    pub kind: TransportKind,
    /// Zenoh settings (config by built-in name or path, endpoint overrides).
    #[serde(default)]
    pub zenoh: ZenohSettings,
    /// iceoryx2 settings.
    #[serde(default)]
    pub iceoryx2: Iceoryx2Settings,
}

/// Sensor source.
#[derive(Clone, Debug, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct InputConfig {
    /// `simulator`: the agent simulates its own robot of `scenario` (as a real
    /// robot reads its own sensors); `mcap`: replays `mcap` (a file written by
    /// `sim-fleet simulate`), with sensor and estimator settings from `scenario`;
    /// `live`: the robot's own IMU and camera over Zenoh (`live`).
    pub source: InputSource,
    /// Scenario file (YAML); relative paths are relative to the config file.
    /// Needed by `simulator` and `mcap`, not read by `live`.
    #[serde(default)]
    pub scenario: PathBuf,
    /// Robot index in the scenario (default: `robot_id`).
    #[serde(default)]
    pub robot_index: Option<usize>,
    /// Seed of the simulation (default: the scenario's).
    #[serde(default)]
    pub seed: Option<u64>,
    /// MCAP file to replay (source `mcap`).
    #[serde(default)]
    pub mcap: Option<PathBuf>,
    /// Live sensors (source `live`).
    #[serde(default)]
    pub live: Option<LiveInputConfig>,
}

/// A robot's own IMU and camera, live: ROS 2 `sensor_msgs/msg/Imu` and
/// `sensor_msgs/msg/Image` in CDR over Zenoh (what `zenoh-bridge-ros2dds`
/// and `rmw_zenoh` carry), on a Zenoh session of their own (the robot's
/// router, say), apart from the fleet's transport.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct LiveInputConfig {
    /// The calibration: a folder with `cam0/sensor.yaml` and
    /// `imu0/sensor.yaml` (EuRoC / Kalibr layout; `mav0` inside it is
    /// found); relative to the config file. The IMU's noise densities come
    /// from `imu0/sensor.yaml` when it gives them.
    pub calibration: PathBuf,
    /// The sensors' Zenoh session (default: the built-in `loopback`,
    /// scouting for a local router or publisher).
    #[serde(default)]
    pub zenoh: ZenohSettings,
    /// The IMU's key: the topic without its leading `/` for
    /// `zenoh-bridge-ros2dds`, `<domain>/<topic>/**` for `rmw_zenoh`.
    #[serde(default = "default_imu_key")]
    pub imu_key: String,
    /// The camera's key (mono8, mono16, rgb8, bgr8, rgba8 or bgra8 images).
    #[serde(default = "default_image_key")]
    pub image_key: String,
    /// Where the estimated pose goes after every frame
    /// (`geometry_msgs/msg/PoseWithCovarianceStamped`, in the fleet's frame);
    /// none when unset.
    #[serde(default)]
    pub pose_key: Option<String>,
    /// The frame id of the published poses.
    #[serde(default = "default_world_frame")]
    pub world_frame: String,
    /// Where the estimate goes as `nav_msgs/msg/Odometry` after every frame
    /// (the pose in `world_frame`, the velocity and angular rate in
    /// `body_frame`, each with its covariance); none when unset.
    #[serde(default)]
    pub odom_key: Option<String>,
    /// The odometry's `child_frame_id`: the IMU, whose axes the twist is in.
    #[serde(default = "default_body_frame")]
    pub body_frame: String,
    /// Where the robot stands at its start, in the fleet's frame.
    pub start: StartPose,
    /// Wait this long for the first sensor message, s.
    #[serde(default = "default_live_wait_s")]
    pub wait_s: f64,
    /// End when no sensor message arrived for this long, s.
    #[serde(default = "default_live_idle_s")]
    pub idle_timeout_s: f64,
    /// End after this long in any case, s (unset: until the sensors stop or
    /// the agent is stopped).
    #[serde(default)]
    pub max_duration_s: Option<f64>,
}

/// The pose of a robot's IMU at its static start, in the fleet's frame
/// (gravity along -z): the static initializer measures roll and pitch; the
/// heading and the position are what the fleet's frame makes them, known
/// to `sigma_*` (a robot set down on a marked spot, or surveyed).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct StartPose {
    /// The IMU's position, m.
    pub position_m: [f64; 3],
    /// The heading of the IMU's axis `heading_axis`: its angle, projected on
    /// the horizontal plane, from the fleet's `x` towards its `y`, deg.
    pub yaw_deg: f64,
    /// The IMU axis `yaw_deg` is the heading of: `x`, `y` or `z`, each
    /// optionally with a leading `-` (default `x`). Take one far from the
    /// vertical: a tilt error turns an axis at elevation `e` by about
    /// `tilt / cos(e)` in heading (EuRoC's IMU has `x` up: use `y` there).
    #[serde(default = "default_heading_axis")]
    pub heading_axis: String,
    /// Standard deviation of the start's orientation, deg (each axis).
    #[serde(default = "default_start_sigma_ori_deg")]
    pub sigma_ori_deg: f64,
    /// Standard deviation of the start's heading alone, deg, when it is known
    /// better than the tilt (absent: `sigma_ori_deg`). A robot whose start
    /// defines its own frame (`estimator.align_peer_frames`) knows its
    /// heading exactly: a small value (0.05) keeps the peers' alignments
    /// from carrying a heading doubt it does not have.
    #[serde(default)]
    pub sigma_yaw_deg: Option<f64>,
    /// Standard deviation of the start's position, m (each axis).
    #[serde(default = "default_start_sigma_pos_m")]
    pub sigma_pos_m: f64,
}

fn default_heading_axis() -> String {
    "x".into()
}

impl StartPose {
    /// The unit vector of `heading_axis` in the IMU's frame.
    pub fn heading_axis_i(&self) -> Result<nalgebra::Vector3<f64>, String> {
        let (sign, axis) = match self.heading_axis.strip_prefix('-') {
            Some(a) => (-1.0, a),
            None => (1.0, self.heading_axis.as_str()),
        };
        let unit = match axis {
            "x" => nalgebra::Vector3::x(),
            "y" => nalgebra::Vector3::y(),
            "z" => nalgebra::Vector3::z(),
            _ => {
                return Err(format!(
                    "input.live.start.heading_axis must be x, y or z, optionally with a \
                     leading - (got `{}`)",
                    self.heading_axis
                ))
            }
        };
        Ok(unit * sign)
    }
}

fn default_imu_key() -> String {
    "imu0".into()
}

fn default_image_key() -> String {
    "cam0/image_raw".into()
}

fn default_body_frame() -> String {
    "imu".to_owned()
}

fn default_world_frame() -> String {
    "fleet_world".into()
}

fn default_live_wait_s() -> f64 {
    60.0
}

fn default_live_idle_s() -> f64 {
    5.0
}

fn default_start_sigma_ori_deg() -> f64 {
    1.0
}

fn default_start_sigma_pos_m() -> f64 {
    0.05
}

/// Where sensor data come from.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum InputSource {
    /// The fleet simulator, for this robot only.
    Simulator,
    /// A recorded MCAP file.
    Mcap,
    /// The robot's own sensors, live over Zenoh.
    Live,
}

/// Estimator variant and OpenVINS-named overrides of the scenario's settings.
#[derive(Clone, Debug, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct EstimatorSection {
    /// `indp` (MSCKF only), `indp-slam`, or a cooperative variant:
    /// `dc-cmsckf`, `dc-cmsckf-cslam`, `dc-full-window`, `dc-full-history`.
    #[serde(default = "default_variant")]
    pub variant: String,
    /// Sliding-window size (clones).
    #[serde(default)]
    pub max_clones: Option<usize>,
    /// Maximum SLAM features in the state.
    #[serde(default)]
    pub max_slam: Option<usize>,
    /// Maximum SLAM features per update.
    #[serde(default)]
    pub max_slam_in_update: Option<usize>,
    /// Maximum MSCKF features per update.
    #[serde(default)]
    pub max_msckf_in_update: Option<usize>,
    /// Times the first MSCKF update is iterated (0: one plain update).
    #[serde(default)]
    pub first_update_iterations: Option<usize>,
    /// Redo a first update whose step left its rays apart at the current
    /// estimate.
    #[serde(default)]
    pub rescue_first_update: Option<bool>,
    /// Pixels of parallax the window's second-newest clone needs to stay, while
    /// the window fills too (0: every clone stays, the oldest leaves).
    #[serde(default)]
    pub keyframe_parallax_px: Option<f64>,
    /// A slow start's keyframe window, px of parallax (0: off): a starved
    /// first update on a window without parallax waits for baseline.
    #[serde(default)]
    pub slow_start_keyframe_px: Option<f64>,
    /// Whether a platform found slow takes the settings for slow platforms by
    /// itself: a slow start the observability-constrained Jacobians and
    /// anchored inverse-depth SLAM features, a flight that turns slow later the
    /// constrained MSCKF Jacobians and the keyframe window.
    #[serde(default)]
    pub slow_platform_settings: Option<bool>,
    /// Where the MSCKF's Jacobians are evaluated (`first_estimates` or
    /// `observability_constrained`).
    #[serde(default)]
    pub msckf_jacobians: Option<MsckfJacobians>,
    /// Where the SLAM features' Jacobians are evaluated (`first_estimates` or
    /// `observability_constrained`).
    #[serde(default)]
    pub slam_jacobians: Option<MsckfJacobians>,
    /// First-Estimates Jacobians.
    #[serde(default)]
    pub use_fej: Option<bool>,
    /// Online extrinsic calibration.
    #[serde(default)]
    pub calib_cam_extrinsics: Option<bool>,
    /// Online intrinsic calibration.
    #[serde(default)]
    pub calib_cam_intrinsics: Option<bool>,
    /// Online camera-IMU time-offset calibration.
    #[serde(default)]
    pub calib_cam_timeoffset: Option<bool>,
    /// Zero-velocity updates at standstills.
    #[serde(default)]
    pub try_zupt: Option<bool>,
    /// A standstill also when the image's tracks moved less than this on
    /// average over at least 0.3 s, px (0: by the IMU alone, which tracks
    /// moved beyond the pixel noise still refuse; OpenVINS's
    /// `zupt_max_disparity`).
    #[serde(default)]
    pub zupt_max_disparity_px: Option<f64>,
    /// Pixel noise of the MSCKF updates and of SLAM initialization, px
    /// (OpenVINS's `up_msckf_sigma_px`; default 1 on camera images, the
    /// scenario's in simulation). The default frontend's tracks, held to their
    /// first patch (`images.frontend.first_patch: drop`), were measured on
    /// rendered images at 0.5 with `up_slam_sigma_px` 1 too (README, "Pixel
    /// noise for held tracks"); 1 keeps a margin for real images.
    #[serde(default)]
    pub up_msckf_sigma_px: Option<f64>,
    /// Pixel noise of the SLAM features' updates, px (OpenVINS's
    /// `up_slam_sigma_px`; default 2 on camera images, where it keeps 50
    /// SLAM features consistent, and the pixel noise in simulation).
    #[serde(default)]
    pub up_slam_sigma_px: Option<f64>,
    /// A peer's track gives a common SLAM update only its newest unused view
    /// (`cooperation.peer_slam_newest_view`; default: on camera images, as
    /// `slam_keyframe_updates`).
    #[serde(default)]
    pub peer_slam_newest_view: Option<bool>,
    /// Gate each peer window's stacked rows (`cooperation.window_gate`,
    /// default on).
    #[serde(default)]
    pub window_gate: Option<bool>,
    /// On a keyframe window, a SLAM feature takes a view only once its image
    /// point moved the keyframe parallax (default on camera images, where a
    /// track's error persists from image to image; off in simulation).
    #[serde(default)]
    pub slam_keyframe_updates: Option<bool>,
    /// SLAM feature representation: `global`, `anchored` or
    /// `anchored_inverse_depth`.
    #[serde(default)]
    pub feat_rep_slam: Option<FeatureRepresentation>,
    /// Largest condition number of a triangulation (`fi_max_cond_number`).
    #[serde(default)]
    pub fi_max_cond_number: Option<f64>,
    /// Nearest accepted feature depth, metres (`fi_min_dist`).
    #[serde(default)]
    pub fi_min_dist: Option<f64>,
    /// Farthest accepted feature depth, metres (`fi_max_dist`).
    #[serde(default)]
    pub fi_max_dist: Option<f64>,
    /// Largest feature depth / baseline ratio (`fi_max_baseline`).
    #[serde(default)]
    pub fi_max_baseline: Option<f64>,
    /// Override of the variant: common VIO features.
    #[serde(default)]
    pub common_vio: Option<bool>,
    /// Override of the variant: common SLAM features.
    #[serde(default)]
    pub common_slam: Option<bool>,
    /// Override of the variant: SLAM-to-SLAM constraint update.
    #[serde(default)]
    pub slam_constraint: Option<bool>,
    /// Override of the variant: historical features (loop closures to peers).
    #[serde(default)]
    pub historical: Option<bool>,
    /// Projection of common VIO features: `two_stage` or `combined`.
    #[serde(default)]
    pub projection: Option<CommonProjection>,
    /// How the CI weights are chosen (`min_pose_trace`, `fixed_peer`, ...).
    #[serde(default)]
    pub ci_weighting: Option<CiWeighting>,
    /// Each peer window's weight with `fixed_peer`, in (0, 1): its covariance
    /// is divided by it. With chosen weights it only sets the windows' part of
    /// the peers' share (`CooperationOptions::ci_peer_weight`).
    #[serde(default)]
    pub ci_peer_weight: Option<f64>,
    /// The robots were not given their start poses in one fleet frame: find
    /// each peer's frame from loop closures before using its windows (needs
    /// the loop closures of `dc-full-history`).
    #[serde(default)]
    pub align_peer_frames: Option<bool>,
    /// How long each confirmed peer frame is held as 4 states of the filter
    /// before it becomes a fixed alignment, s; 0: fixed from the start,
    /// `.inf`: the whole flight; unset: by the weighting
    /// (`cooperation.peer_frame_state_s`).
    #[serde(default)]
    pub peer_frame_state_s: Option<f64>,
    /// Most peer frames held in the filter at once; beyond it the longest
    /// held becomes a fixed alignment (`cooperation.max_held_peer_frames`).
    #[serde(default)]
    pub max_held_peer_frames: Option<usize>,
    /// Later loop closures to a frame the filter holds measure it again, at
    /// most once per this period, s; 0: never
    /// (`cooperation.held_frame_measurement_period_s`).
    #[serde(default)]
    pub held_frame_measurement_period_s: Option<f64>,
    /// Those measurements only this long after the frame was confirmed, s
    /// (`cooperation.held_frame_measurement_window_s`).
    #[serde(default)]
    pub held_frame_measurement_window_s: Option<f64>,
    /// At most this many of those measurements a second over all held
    /// frames, 1/s (`cooperation.held_frame_measurements_per_s`).
    #[serde(default)]
    pub held_frame_measurements_per_s: Option<f64>,
    /// The k-th later measurement of a held frame counts the peer's anchor
    /// pose `growth^k` times (`cooperation.held_frame_anchor_growth`).
    #[serde(default)]
    pub held_frame_anchor_growth: Option<f64>,
    /// While peer frames are held in the state, leave our covariance along
    /// our world's yaw and translation (which no peer measurement through
    /// them observes) out of CI's inflation
    /// (`cooperation.split_unobservable`).
    #[serde(default)]
    pub split_unobservable: Option<bool>,
    /// Split CI over our own calibration (`cooperation.split_calibration`).
    #[serde(default)]
    pub split_calibration: Option<bool>,
    /// Largest Hamming distance of a descriptor match, bits of 256
    /// (`cooperation.max_descriptor_distance_bits`).
    #[serde(default)]
    pub max_descriptor_distance_bits: Option<u32>,
    /// Ratio test of a descriptor match: best distance below this fraction
    /// of the second best (`cooperation.match_ratio`).
    #[serde(default)]
    pub match_ratio: Option<f64>,
    /// Fewest epipolar inliers of the matches to a peer's current frame
    /// (`cooperation.min_window_inliers`).
    #[serde(default)]
    pub min_window_inliers: Option<usize>,
    /// Fewest epipolar inliers of a loop closure to a peer keyframe
    /// (`cooperation.min_loop_inliers`).
    #[serde(default)]
    pub min_loop_inliers: Option<usize>,
    /// Sampson threshold of the fundamental-matrix RANSAC, px
    /// (`cooperation.epipolar_threshold_px`).
    #[serde(default)]
    pub epipolar_threshold_px: Option<f64>,
    /// Smallest bag-of-words score of a loop-closure candidate, in [0, 1]
    /// (`cooperation.loop_min_score`).
    #[serde(default)]
    pub loop_min_score: Option<f64>,
    /// Loop-closure candidates checked per peer and frame
    /// (`cooperation.loop_candidates`).
    #[serde(default)]
    pub loop_candidates: Option<usize>,
    /// Vocabulary file for historical loop closures (`vocab train` output);
    /// without it, a vocabulary for random binary descriptors (the simulator's)
    /// is built in memory.
    #[serde(default)]
    pub vocabulary: Option<PathBuf>,
}

impl EstimatorSection {
    /// Applies the overrides that are set to `o`.
    pub fn apply(&self, o: &mut EstimatorOptions) {
        if let Some(v) = self.max_clones {
            o.max_clones = v;
            // The first update waits for the oldest clone of the full window
            // to leave, whatever the window's size.
            o.min_clones_to_update = v.saturating_add(1);
        }
        if let Some(v) = self.max_slam {
            o.max_slam_features = v;
        }
        if let Some(v) = self.max_slam_in_update {
            o.max_slam_in_update = v;
        }
        if let Some(v) = self.max_msckf_in_update {
            o.max_msckf_in_update = v;
        }
        if let Some(v) = self.first_update_iterations {
            o.first_update_iterations = v;
        }
        if let Some(v) = self.rescue_first_update {
            o.rescue_first_update = v;
        }
        if let Some(v) = self.keyframe_parallax_px {
            o.keyframe_parallax_px = v;
        }
        if let Some(v) = self.slow_start_keyframe_px {
            o.slow_start_keyframe_px = v;
        }
        if let Some(v) = self.slow_platform_settings {
            o.slow_platform_settings = v;
        }
        if let Some(v) = self.msckf_jacobians {
            o.msckf_jacobians = v;
        }
        if let Some(v) = self.slam_jacobians {
            o.slam_jacobians = v;
        }
        if let Some(v) = self.use_fej {
            o.use_fej = v;
        }
        if let Some(v) = self.calib_cam_extrinsics {
            o.calib_extrinsics = v;
        }
        if let Some(v) = self.calib_cam_intrinsics {
            o.calib_intrinsics = v;
        }
        if let Some(v) = self.calib_cam_timeoffset {
            o.calib_time_offset = v;
        }
        if let Some(v) = self.try_zupt {
            o.zero_velocity_update = v;
        }
        if let Some(v) = self.zupt_max_disparity_px {
            o.zupt_max_disparity_px = v;
        }
        if let Some(v) = self.up_msckf_sigma_px {
            o.pixel_sigma_px = v;
        }
        if let Some(v) = self.up_slam_sigma_px {
            o.slam_pixel_sigma_px = Some(v);
        }
        if let Some(v) = self.slam_keyframe_updates {
            o.slam_keyframe_updates = v;
        }
        if let Some(v) = self.feat_rep_slam {
            o.feature_representation = v;
        }
        self.apply_triangulation(&mut o.triangulation);
        let c = &mut o.cooperation;
        for (flag, value) in [
            (&mut c.common_vio, self.common_vio),
            (&mut c.common_slam, self.common_slam),
            (&mut c.slam_constraint, self.slam_constraint),
            (&mut c.historical, self.historical),
            (&mut c.align_peer_frames, self.align_peer_frames),
        ] {
            if let Some(v) = value {
                *flag = v;
            }
        }
        if let Some(p) = self.projection {
            c.projection = p;
        }
        if let Some(w) = self.ci_weighting {
            c.ci_weighting = w;
        }
        if let Some(w) = self.ci_peer_weight {
            c.ci_peer_weight = w;
        }
        if let Some(s) = self.peer_frame_state_s {
            c.peer_frame_state_s = Some(s);
        }
        if let Some(n) = self.max_held_peer_frames {
            c.max_held_peer_frames = n;
        }
        if let Some(p) = self.held_frame_measurement_period_s {
            c.held_frame_measurement_period_s = p;
        }
        if let Some(w) = self.held_frame_measurement_window_s {
            c.held_frame_measurement_window_s = w;
        }
        if let Some(r) = self.held_frame_measurements_per_s {
            c.held_frame_measurements_per_s = r;
        }
        if let Some(g) = self.held_frame_anchor_growth {
            c.held_frame_anchor_growth = g;
        }
        if let Some(s) = self.split_unobservable {
            c.split_unobservable = s;
        }
        if let Some(s) = self.split_calibration {
            c.split_calibration = s;
        }
        if let Some(v) = self.peer_slam_newest_view {
            c.peer_slam_newest_view = Some(v);
        }
        if let Some(g) = self.window_gate {
            c.window_gate = g;
        }
        self.apply_matching(c);
    }

    /// Applies the descriptor-matching and loop-closure overrides that are set.
    fn apply_matching(&self, c: &mut CooperationOptions) {
        if let Some(v) = self.max_descriptor_distance_bits {
            c.max_descriptor_distance_bits = v;
        }
        for (field, value) in [
            (&mut c.match_ratio, self.match_ratio),
            (&mut c.epipolar_threshold_px, self.epipolar_threshold_px),
            (&mut c.loop_min_score, self.loop_min_score),
        ] {
            if let Some(v) = value {
                *field = v;
            }
        }
        for (field, value) in [
            (&mut c.min_window_inliers, self.min_window_inliers),
            (&mut c.min_loop_inliers, self.min_loop_inliers),
            (&mut c.loop_candidates, self.loop_candidates),
        ] {
            if let Some(v) = value {
                *field = v;
            }
        }
    }
}

impl EstimatorSection {
    /// Applies the `fi_*` overrides that are set to `l`.
    pub fn apply_triangulation(&self, l: &mut TriangulationLimits) {
        for (field, value) in [
            (&mut l.max_condition_number, self.fi_max_cond_number),
            (&mut l.min_depth_m, self.fi_min_dist),
            (&mut l.max_depth_m, self.fi_max_dist),
            (&mut l.max_baseline_ratio, self.fi_max_baseline),
        ] {
            if let Some(v) = value {
                *field = v;
            }
        }
    }
}

fn default_variant() -> String {
    "indp-slam".into()
}

impl Default for EstimatorSection {
    fn default() -> Self {
        Self {
            variant: default_variant(),
            max_clones: None,
            max_slam: None,
            max_slam_in_update: None,
            max_msckf_in_update: None,
            first_update_iterations: None,
            rescue_first_update: None,
            keyframe_parallax_px: None,
            slow_start_keyframe_px: None,
            slow_platform_settings: None,
            msckf_jacobians: None,
            slam_jacobians: None,
            use_fej: None,
            calib_cam_extrinsics: None,
            calib_cam_intrinsics: None,
            calib_cam_timeoffset: None,
            try_zupt: None,
            zupt_max_disparity_px: None,
            up_msckf_sigma_px: None,
            up_slam_sigma_px: None,
            peer_slam_newest_view: None,
            window_gate: None,
            slam_keyframe_updates: None,
            feat_rep_slam: None,
            fi_max_cond_number: None,
            fi_min_dist: None,
            fi_max_dist: None,
            fi_max_baseline: None,
            common_vio: None,
            common_slam: None,
            slam_constraint: None,
            historical: None,
            projection: None,
            ci_weighting: None,
            ci_peer_weight: None,
            align_peer_frames: None,
            peer_frame_state_s: None,
            max_held_peer_frames: None,
            held_frame_measurement_period_s: None,
            held_frame_measurement_window_s: None,
            held_frame_measurements_per_s: None,
            held_frame_anchor_growth: None,
            split_unobservable: None,
            split_calibration: None,
            max_descriptor_distance_bits: None,
            match_ratio: None,
            min_window_inliers: None,
            min_loop_inliers: None,
            epipolar_threshold_px: None,
            loop_min_score: None,
            loop_candidates: None,
            vocabulary: None,
        }
    }
}

/// How the agent's clock advances.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum ClockMode {
    /// Frame by frame on the fleet clock: no agent starts camera tick `k + 1`
    /// before every live peer finished tick `k`; bit-identical across transports.
    Lockstep,
    /// Paced to the wall clock times `realtime_rate`, as on real robots.
    Realtime,
}

/// Clock settings.
#[derive(Clone, Debug, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct ClockConfig {
    /// `lockstep` or `realtime`.
    #[serde(default = "default_mode")]
    pub mode: ClockMode,
    /// Real time: simulated seconds per wall second.
    #[serde(default = "one")]
    pub realtime_rate: f64,
    /// The peers this agent expects (lockstep waits for them; both modes wait up
    /// to `start_timeout_s` for them to appear before starting).
    #[serde(default)]
    pub peers: Vec<u32>,
    /// How long to wait for the expected peers at start, s.
    #[serde(default = "default_start_timeout")]
    pub start_timeout_s: f64,
    /// Lockstep: a peer that sends nothing for this long is no longer waited for, s.
    #[serde(default = "default_barrier_timeout")]
    pub barrier_timeout_s: f64,
    /// After its own data end, how long the agent keeps receiving while peers are
    /// still running, s.
    #[serde(default = "default_linger")]
    pub linger_timeout_s: f64,
    /// Once every peer's data have ended, how long the agent may go on
    /// asking its peers for the keyframe windows it lacks or holds short, and
    /// answering theirs, before it leaves anyway, s (wall clock). It leaves
    /// as soon as it and every peer are done.
    #[serde(default = "default_settle_timeout")]
    pub settle_timeout_s: f64,
}

fn default_mode() -> ClockMode {
    ClockMode::Lockstep
}
fn one() -> f64 {
    1.0
}
fn default_start_timeout() -> f64 {
    30.0
}
fn default_barrier_timeout() -> f64 {
    10.0
}
fn default_linger() -> f64 {
    60.0
}
fn default_settle_timeout() -> f64 {
    5.0
}

impl Default for ClockConfig {
    fn default() -> Self {
        Self {
            mode: default_mode(),
            realtime_rate: 1.0,
            peers: Vec::new(),
            start_timeout_s: default_start_timeout(),
            barrier_timeout_s: default_barrier_timeout(),
            linger_timeout_s: default_linger(),
            settle_timeout_s: default_settle_timeout(),
        }
    }
}

/// Publication rates.
#[derive(Clone, Debug, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct PublishConfig {
    /// A window snapshot once this many camera frames have passed since the last
    /// one (keyframe snapshots count; 1 = every frame). The default 6 puts one
    /// snapshot between two keyframes of an 11-clone window at 10 Hz.
    #[serde(default = "default_snapshot_every")]
    pub snapshot_every_frames: u32,
    /// Keyframe windows for peers' histories, at most this often, s (a keyframe
    /// window never overlaps the previous one).
    #[serde(default = "one")]
    pub keyframe_period_s: f64,
    /// Include SLAM features (positions and 3x3 marginals) in every snapshot
    /// (they are always in keyframe snapshots). Off by default: bandwidth.
    #[serde(default)]
    pub landmarks_in_snapshots: bool,
    /// Heartbeat period in real-time mode, s (lockstep sends one per tick).
    #[serde(default = "one")]
    pub heartbeat_period_s: f64,
}

fn default_snapshot_every() -> u32 {
    6
}

impl Default for PublishConfig {
    fn default() -> Self {
        Self {
            snapshot_every_frames: default_snapshot_every(),
            keyframe_period_s: 1.0,
            landmarks_in_snapshots: false,
            heartbeat_period_s: 1.0,
        }
    }
}

/// Peer-history bounds.
#[derive(Clone, Debug, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct HistoryConfig {
    /// Memory bound per peer, MiB: beyond it keyframe windows are dropped, as
    /// `retention` says.
    #[serde(default = "default_history_mib")]
    pub max_mib_per_peer: f64,
    /// Which keyframe windows go first: `informed` (default: the least
    /// certain window of a place seen more than once, then the least certain
    /// overall; see `history_retention`) or `oldest`.
    #[serde(default)]
    pub retention: crate::history_retention::Retention,
    /// Recent (non-keyframe) track frames kept per peer, s; frames the peer's
    /// latest window still spans stay longer (a standstill stretches it).
    #[serde(default = "default_recent_s")]
    pub recent_tracks_s: f64,
    /// Distinct peers kept (first come, first served); messages from further
    /// robot ids are dropped and counted, so forged ids cannot grow memory.
    #[serde(default = "default_max_peers")]
    pub max_peers: usize,
    /// Received bytes per peer and second (MiB/s, with a one-second burst);
    /// beyond it a peer's messages are dropped undecoded. A peer sends about
    /// 0.03 MiB/s of fleet time; lockstep runs some 30x faster than real time.
    #[serde(default = "default_max_peer_mib_per_s")]
    pub max_peer_mib_per_s: f64,
    /// History catch-up: ask peers again for the keyframe windows a late
    /// start, a link outage or lost messages kept from us, and answer their
    /// requests from an archive of our own windows (held within
    /// `max_mib_per_peer`). On by default.
    #[serde(default = "yes")]
    pub catch_up: bool,
    /// Windows sent again to peers, KiB per second of fleet time (with a
    /// one-second burst): a catch-up must not crowd out the live messages,
    /// about 33 KiB/s. An hour of a peer's windows (some 3 600 of about 20 KB
    /// each on the wire) takes about 2.5 min at the default.
    #[serde(default = "default_replay_kib_per_s")]
    pub replay_kib_per_s: f64,
    /// Fleet seconds without a reply before a catch-up request is sent again
    /// (a request costs some 50-120 bytes; it is only given up when its peer
    /// vanishes). Any replay from the peer counts as a reply, so a long
    /// catch-up is not asked again while it flows; on a lossy link a short
    /// period gets a lost request or replay back before the peer lands (5 s
    /// left a window of a robot's last seconds missing at 30 % loss).
    #[serde(default = "default_catch_up_retry_s")]
    pub catch_up_retry_s: f64,
    /// Folder where the agent keeps its peers' keyframe windows, and its
    /// archive of its own (with `catch_up`), across restarts: read back at
    /// start, written as they grow (none: memory only). Relative to the
    /// configuration file's folder. One folder per agent.
    #[serde(default)]
    pub store_dir: Option<PathBuf>,
    /// Fleet seconds between writes of the histories that changed; they are
    /// written once more at the end.
    #[serde(default = "default_store_period_s")]
    pub store_period_s: f64,
}

fn default_store_period_s() -> f64 {
    10.0
}

fn default_replay_kib_per_s() -> f64 {
    512.0
}
fn default_catch_up_retry_s() -> f64 {
    2.0
}

fn default_history_mib() -> f64 {
    64.0
}
fn default_recent_s() -> f64 {
    2.0
}
fn default_max_peers() -> usize {
    64
}
fn default_max_peer_mib_per_s() -> f64 {
    16.0
}

impl Default for HistoryConfig {
    fn default() -> Self {
        Self {
            max_mib_per_peer: default_history_mib(),
            retention: Default::default(),
            recent_tracks_s: default_recent_s(),
            max_peers: default_max_peers(),
            max_peer_mib_per_s: default_max_peer_mib_per_s(),
            catch_up: true,
            replay_kib_per_s: default_replay_kib_per_s(),
            catch_up_retry_s: default_catch_up_retry_s(),
            store_dir: None,
            store_period_s: default_store_period_s(),
        }
    }
}

impl AgentConfig {
    /// Reads and checks a configuration file; relative paths in it become relative
    /// to the file's folder.
    pub fn load(path: &Path) -> Result<Self, ConfigError> {
        let text = std::fs::read_to_string(path).map_err(|source| ConfigError::Read {
            path: path.to_path_buf(),
            source,
        })?;
        let mut cfg: AgentConfig =
            serde_yaml::from_str(&text).map_err(|source| ConfigError::Parse {
                path: path.to_path_buf(),
                source,
            })?;
        let base = path.parent().unwrap_or(Path::new("."));
        if !cfg.input.scenario.as_os_str().is_empty() {
            cfg.input.scenario = base.join(&cfg.input.scenario);
        }
        if let Some(live) = cfg.input.live.as_mut() {
            live.calibration = base.join(&live.calibration);
        }
        cfg.input.mcap = cfg.input.mcap.map(|m| base.join(m));
        cfg.output_dir = base.join(&cfg.output_dir);
        cfg.history.store_dir = cfg.history.store_dir.map(|d| base.join(d));
        cfg.validate().map_err(|what| ConfigError::Invalid {
            path: path.to_path_buf(),
            what,
        })?;
        Ok(cfg)
    }

    /// Range and consistency checks.
    pub fn validate(&self) -> Result<(), String> {
        if self.fleet_id.is_empty() || self.fleet_id.len() > 64 {
            return Err("fleet_id must have 1 to 64 bytes".into());
        }
        if !self
            .fleet_id
            .chars()
            .all(|c| c.is_ascii_alphanumeric() || c == '-' || c == '_')
        {
            return Err(format!(
                "fleet_id `{}` may only hold letters, digits, `-` and `_` (it is a key segment)",
                self.fleet_id
            ));
        }
        self.estimator
            .variant
            .parse::<Variant>()
            .map_err(|e| e.to_string())?;
        let mut limits = TriangulationLimits::default();
        self.estimator.apply_triangulation(&mut limits);
        limits
            .validate()
            .map_err(|e| format!("estimator: {e} (the fi_* keys)"))?;
        let mut options = EstimatorOptions::default();
        self.estimator.apply(&mut options);
        options.validate().map_err(|e| format!("estimator: {e}"))?;
        if self.input.source == InputSource::Mcap && self.input.mcap.is_none() {
            return Err("input.source is mcap but input.mcap is not set".into());
        }
        self.validate_input()?;
        if !(self.status_period_s.is_finite() && self.status_period_s >= 0.0) {
            return Err(format!(
                "status_period_s must be a number of seconds >= 0, 0 for none (got {})",
                self.status_period_s
            ));
        }
        let c = &self.clock;
        if !(c.realtime_rate.is_finite() && c.realtime_rate > 0.0) {
            return Err(format!(
                "clock.realtime_rate must be > 0 (got {})",
                c.realtime_rate
            ));
        }
        for (name, v) in [
            ("clock.start_timeout_s", c.start_timeout_s),
            ("clock.barrier_timeout_s", c.barrier_timeout_s),
            ("clock.linger_timeout_s", c.linger_timeout_s),
            ("clock.settle_timeout_s", c.settle_timeout_s),
            ("publish.keyframe_period_s", self.publish.keyframe_period_s),
            (
                "publish.heartbeat_period_s",
                self.publish.heartbeat_period_s,
            ),
            ("history.max_mib_per_peer", self.history.max_mib_per_peer),
            ("history.recent_tracks_s", self.history.recent_tracks_s),
            (
                "history.max_peer_mib_per_s",
                self.history.max_peer_mib_per_s,
            ),
            ("history.replay_kib_per_s", self.history.replay_kib_per_s),
            ("history.catch_up_retry_s", self.history.catch_up_retry_s),
            ("history.store_period_s", self.history.store_period_s),
        ] {
            if !(v.is_finite() && v >= 0.0) {
                return Err(format!("{name} must be a finite number >= 0 (got {v})"));
            }
        }
        let loss = self.faults.loss_fraction;
        if !(0.0..=1.0).contains(&loss) {
            return Err(format!(
                "faults.loss_fraction must be a fraction in [0, 1] (got {loss})"
            ));
        }
        if let Some([from, to]) = self.faults.outage_fleet_s {
            if !(from.is_finite() && to.is_finite() && from < to) {
                return Err(format!(
                    "faults.outage_fleet_s must be [from, to] with from < to (got [{from}, {to}])"
                ));
            }
        }
        if self.publish.snapshot_every_frames == 0 {
            return Err("publish.snapshot_every_frames must be >= 1".into());
        }
        if c.peers.contains(&self.robot_id) {
            return Err(format!(
                "clock.peers lists this agent's own robot_id {}",
                self.robot_id
            ));
        }
        if c.peers.len() > self.history.max_peers {
            return Err(format!(
                "history.max_peers ({}) is below the {} clock.peers: their messages would be dropped",
                self.history.max_peers,
                c.peers.len()
            ));
        }
        Ok(())
    }

    /// The transport settings of this agent.
    pub fn transport_settings(&self) -> TransportSettings {
        TransportSettings {
            fleet_id: self.fleet_id.clone(),
            robot_id: self.robot_id,
            kind: self.transport.kind,
            zenoh: self.transport.zenoh.clone(),
            iceoryx2: self.transport.iceoryx2.clone(),
        }
    }

    /// The scenario robot this agent simulates.
    pub fn robot_index(&self) -> usize {
        self.input.robot_index.unwrap_or(self.robot_id as usize)
    }

    /// The input's keys agree with its source.
    fn validate_input(&self) -> Result<(), String> {
        let input = &self.input;
        match (input.source, &input.live) {
            (InputSource::Live, None) => {
                return Err("input.source is live but input.live is not set".into())
            }
            (InputSource::Live, Some(live)) => {
                if self.clock.mode == ClockMode::Lockstep {
                    return Err(
                        "input.source live runs on the sensors' clock: set clock.mode to \
                                realtime (lockstep is for simulated and replayed fleets)"
                            .into(),
                    );
                }
                live.validate()?;
            }
            (_, Some(_)) => {
                return Err("input.live is only read with input.source live".into());
            }
            (_, None) if input.scenario.as_os_str().is_empty() => {
                return Err("input.scenario is not set".into());
            }
            (_, None) => {}
        }
        Ok(())
    }
}

impl LiveInputConfig {
    /// Range checks.
    pub fn validate(&self) -> Result<(), String> {
        let s = &self.start;
        s.heading_axis_i()?;
        if !s.position_m.iter().all(|v| v.is_finite()) || !s.yaw_deg.is_finite() {
            return Err(format!(
                "input.live.start: position_m and yaw_deg must be finite (got {:?}, {})",
                s.position_m, s.yaw_deg
            ));
        }
        for (name, v) in [
            ("input.live.start.sigma_ori_deg", s.sigma_ori_deg),
            ("input.live.start.sigma_pos_m", s.sigma_pos_m),
            (
                "input.live.start.sigma_yaw_deg",
                s.sigma_yaw_deg.unwrap_or(1.0),
            ),
            ("input.live.wait_s", self.wait_s),
            ("input.live.idle_timeout_s", self.idle_timeout_s),
            (
                "input.live.max_duration_s",
                self.max_duration_s.unwrap_or(1.0),
            ),
        ] {
            if !(v.is_finite() && v > 0.0 && v < 1e9) {
                return Err(format!("{name} must be a number > 0 (got {v})"));
            }
        }
        for (name, key) in [
            ("input.live.imu_key", &self.imu_key),
            ("input.live.image_key", &self.image_key),
        ] {
            if key.is_empty() {
                return Err(format!("{name} is empty"));
            }
        }
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::history_retention::Retention;

    const MINIMAL: &str =
        "robot_id: 1\noutput_dir: out\ninput:\n  source: simulator\n  scenario: s.yaml\n";

    #[test]
    fn injected_loss_takes_its_fraction_the_same_messages_every_time_and_spares_the_clock() {
        use common::messages::MessageKind;
        let faults = FaultsConfig {
            loss_fraction: 0.2,
            ..FaultsConfig::default()
        }
        .for_run(7);
        let msg = |sender, seq| FaultedMessage {
            kind: MessageKind::Snapshot,
            sender,
            seq,
            stamp_s: seq as f64,
        };
        let lost = |f: &FaultsConfig, receiver| {
            (0..20_000)
                .filter(|&seq| f.drops(msg(2, seq), receiver, true).is_some())
                .collect::<Vec<u64>>()
        };
        let at_1 = lost(&faults, 1);
        // 20 % of 20 000, within 4 binomial sigmas (57).
        assert!((at_1.len() as f64 - 4000.0).abs() < 230.0, "{}", at_1.len());
        assert_eq!(at_1, lost(&faults, 1), "the same draws");
        // Each receiver and each run loses its own.
        assert_ne!(at_1, lost(&faults, 3));
        let other_run = FaultsConfig {
            loss_fraction: 0.2,
            ..FaultsConfig::default()
        }
        .for_run(8);
        assert_ne!(at_1, lost(&other_run, 1));
        // Heartbeats are the lockstep clock: they pass there, not in real time.
        let hb = FaultedMessage {
            kind: MessageKind::Heartbeat,
            ..msg(2, 0)
        };
        let all = FaultsConfig {
            loss_fraction: 1.0,
            outage_fleet_s: Some([0.0, 10.0]),
            ..FaultsConfig::default()
        };
        assert_eq!(all.drops(hb, 1, true), None);
        assert_eq!(all.drops(hb, 1, false), Some(FaultDrop::Outage));
        assert_eq!(all.drops(msg(2, 20), 1, true), Some(FaultDrop::Loss));
        assert_eq!(FaultsConfig::default().drops(msg(2, 1), 1, false), None);
    }

    #[test]
    fn minimal_config_takes_defaults_and_resolves_paths() {
        let dir = tempfile::tempdir().unwrap();
        let p = dir.path().join("a.yaml");
        std::fs::write(&p, MINIMAL).unwrap();
        let c = AgentConfig::load(&p).unwrap();
        assert_eq!(c.robot_id, 1);
        assert_eq!(c.fleet_id, "fleet");
        assert_eq!(c.clock.mode, ClockMode::Lockstep);
        assert_eq!(c.publish.snapshot_every_frames, 6);
        assert_eq!(c.input.scenario, dir.path().join("s.yaml"));
        assert_eq!(c.robot_index(), 1);
    }

    /// A live robot: no scenario, the calibration relative to the file, the
    /// start pose with its default σ; a live input needs real time, and a
    /// `live` block anywhere else is refused rather than ignored.
    #[test]
    fn a_live_input_reads_its_block_and_refuses_what_cannot_work() {
        let dir = tempfile::tempdir().unwrap();
        let p = dir.path().join("a.yaml");
        let live = "robot_id: 2\noutput_dir: out\nclock:\n  mode: realtime\n\
                    input:\n  source: live\n  live:\n    calibration: cal\n    \
                    start: {position_m: [1.0, 2.0, 0.5], yaw_deg: 30.0}\n";
        std::fs::write(&p, live).unwrap();
        let c = AgentConfig::load(&p).unwrap();
        let l = c.input.live.as_ref().unwrap();
        assert_eq!(l.calibration, dir.path().join("cal"));
        assert_eq!(l.imu_key, "imu0");
        assert_eq!(l.image_key, "cam0/image_raw");
        assert_eq!(l.pose_key, None);
        assert_eq!(
            (l.odom_key.as_deref(), l.body_frame.as_str()),
            (None, "imu")
        );
        assert_eq!(l.start.position_m, [1.0, 2.0, 0.5]);
        assert_eq!((l.start.sigma_ori_deg, l.start.sigma_pos_m), (1.0, 0.05));
        assert!(c.input.scenario.as_os_str().is_empty());
        let refused = |text: &str| {
            std::fs::write(&p, text).unwrap();
            AgentConfig::load(&p).unwrap_err().to_string()
        };
        let e = refused(&live.replace("realtime", "lockstep"));
        assert!(e.contains("clock.mode to realtime"), "{e}");
        assert_eq!(l.start.heading_axis_i(), Ok(nalgebra::Vector3::x()));
        let e = refused(&live.replace("yaw_deg: 30.0", "yaw_deg: 30.0, heading_axis: w"));
        assert!(e.contains("heading_axis must be x, y or z"), "{e}");
        let e = refused(&live.replace("yaw_deg: 30.0", "yaw_deg: .nan"));
        assert!(e.contains("must be finite"), "{e}");
        let e = refused(&live.replace("yaw_deg: 30.0", "yaw_deg: 30.0, sigma_pos_m: 0"));
        assert!(
            e.contains("input.live.start.sigma_pos_m must be a number > 0"),
            "{e}"
        );
        let e = refused(&live.replace("yaw_deg: 30.0", "yaw_deg: 30.0, sigma_yaw_deg: -1"));
        assert!(
            e.contains("input.live.start.sigma_yaw_deg must be a number > 0"),
            "{e}"
        );
        let e = refused(
            "robot_id: 2\noutput_dir: out\nclock: {mode: realtime}\ninput: {source: live}\n",
        );
        assert!(e.contains("input.live is not set"), "{e}");
        let e = refused(&live.replace("source: live", "source: simulator\n  scenario: s.yaml"));
        assert!(e.contains("only read with input.source live"), "{e}");
        let e = refused("robot_id: 1\noutput_dir: out\ninput:\n  source: simulator\n");
        assert!(e.contains("input.scenario is not set"), "{e}");
    }

    #[test]
    fn triangulation_overrides_apply_and_bad_ones_are_reported() {
        let dir = tempfile::tempdir().unwrap();
        let p = dir.path().join("a.yaml");
        let with = |extra: &str| format!("{MINIMAL}estimator:\n  variant: indp\n{extra}");
        std::fs::write(
            &p,
            with("  fi_max_cond_number: 5.0e4\n  fi_max_dist: 30.0\n"),
        )
        .unwrap();
        let c = AgentConfig::load(&p).unwrap();
        let mut o = EstimatorOptions::default();
        c.estimator.apply(&mut o);
        assert_eq!(o.triangulation.max_condition_number, 5.0e4);
        assert_eq!(o.triangulation.max_depth_m, 30.0);
        assert_eq!(o.triangulation.min_depth_m, 0.1);
        std::fs::write(&p, with("  max_clones: 15\n")).unwrap();
        let mut o = EstimatorOptions::default();
        AgentConfig::load(&p).unwrap().estimator.apply(&mut o);
        assert!(!o.window_ready(15) && o.window_ready(16), "{o:?}");
        std::fs::write(&p, with("  fi_min_dist: -1.0\n")).unwrap();
        let e = AgentConfig::load(&p).unwrap_err().to_string();
        assert!(e.contains("min_depth_m") && e.contains("fi_"), "{e}");
    }

    #[test]
    fn slam_representations_take_our_names_and_openvins_ones() {
        let dir = tempfile::tempdir().unwrap();
        let p = dir.path().join("a.yaml");
        for (name, want) in [
            ("global", FeatureRepresentation::Global),
            ("GLOBAL_3D", FeatureRepresentation::Global),
            ("anchored", FeatureRepresentation::Anchored),
            ("ANCHORED_3D", FeatureRepresentation::Anchored),
            (
                "anchored_inverse_depth",
                FeatureRepresentation::AnchoredInverseDepth,
            ),
            (
                "ANCHORED_MSCKF_INVERSE_DEPTH",
                FeatureRepresentation::AnchoredInverseDepth,
            ),
        ] {
            std::fs::write(
                &p,
                format!("{MINIMAL}estimator:\n  feat_rep_slam: {name}\n"),
            )
            .unwrap();
            let mut o = EstimatorOptions::default();
            AgentConfig::load(&p).unwrap().estimator.apply(&mut o);
            assert_eq!(o.feature_representation, want, "{name}");
        }
        // OpenVINS's other representations are not implemented: said, not guessed.
        std::fs::write(
            &p,
            format!("{MINIMAL}estimator:\n  feat_rep_slam: GLOBAL_FULL_INVERSE_DEPTH\n"),
        )
        .unwrap();
        let e = AgentConfig::load(&p).unwrap_err().to_string();
        assert!(e.contains("GLOBAL_FULL_INVERSE_DEPTH"), "{e}");
    }

    /// A configuration of a `dc-full-history` agent with `extra` estimator keys.
    fn dc_full_history_with(extra: &str) -> String {
        format!("{MINIMAL}estimator:\n  variant: dc-full-history\n{extra}")
    }

    #[test]
    fn ci_weighting_overrides_apply_and_bad_weights_are_reported() {
        let dir = tempfile::tempdir().unwrap();
        let p = dir.path().join("a.yaml");
        let with = dc_full_history_with;
        std::fs::write(
            &p,
            with("  ci_weighting: fixed_peer\n  ci_peer_weight: 0.005\n"),
        )
        .unwrap();
        let mut o = EstimatorOptions::default();
        AgentConfig::load(&p).unwrap().estimator.apply(&mut o);
        assert_eq!(o.cooperation.ci_weighting, CiWeighting::FixedPeer);
        assert_eq!(o.cooperation.ci_peer_weight, 0.005);
        std::fs::write(&p, with("  ci_weighting: min_pose_features_determinant\n")).unwrap();
        let mut o = EstimatorOptions::default();
        AgentConfig::load(&p).unwrap().estimator.apply(&mut o);
        assert_eq!(
            o.cooperation.ci_weighting,
            CiWeighting::MinPoseFeaturesDeterminant
        );
        for w in ["0.0", "1.0", "-0.1", ".nan"] {
            std::fs::write(&p, with(&format!("  ci_peer_weight: {w}\n"))).unwrap();
            let e = AgentConfig::load(&p).unwrap_err().to_string();
            assert!(e.contains("ci_peer_weight"), "{w}: {e}");
        }
        std::fs::write(&p, with("  ci_weighting: best\n")).unwrap();
        let e = AgentConfig::load(&p).unwrap_err().to_string();
        assert!(e.contains("best") && e.contains("min_pose_trace"), "{e}");
    }

    #[test]
    fn matching_and_loop_closure_keys_apply_and_bad_ones_are_reported() {
        let dir = tempfile::tempdir().unwrap();
        let p = dir.path().join("a.yaml");
        let with = dc_full_history_with;
        std::fs::write(
            &p,
            with(
                "  max_descriptor_distance_bits: 50\n  match_ratio: 0.7\n  \
                 min_window_inliers: 12\n  min_loop_inliers: 10\n  \
                 epipolar_threshold_px: 1.5\n  loop_min_score: 0.05\n  loop_candidates: 4\n",
            ),
        )
        .unwrap();
        let mut o = EstimatorOptions::default();
        AgentConfig::load(&p).unwrap().estimator.apply(&mut o);
        let c = &o.cooperation;
        assert_eq!(c.max_descriptor_distance_bits, 50);
        assert_eq!(c.match_ratio, 0.7);
        assert_eq!((c.min_window_inliers, c.min_loop_inliers), (12, 10));
        assert_eq!(c.epipolar_threshold_px, 1.5);
        assert_eq!((c.loop_min_score, c.loop_candidates), (0.05, 4));
        // Unset keys keep the defaults.
        std::fs::write(&p, with("  min_loop_inliers: 20\n")).unwrap();
        let mut o = EstimatorOptions::default();
        AgentConfig::load(&p).unwrap().estimator.apply(&mut o);
        let d = EstimatorOptions::default().cooperation;
        assert_eq!(o.cooperation.min_loop_inliers, 20);
        assert_eq!(o.cooperation.min_window_inliers, d.min_window_inliers);
        assert_eq!(o.cooperation.loop_candidates, d.loop_candidates);
        for (key, value) in [
            ("min_loop_inliers", "8"),
            ("min_window_inliers", "3"),
            ("loop_candidates", "0"),
            ("match_ratio", "1.5"),
            ("max_descriptor_distance_bits", "300"),
        ] {
            std::fs::write(&p, with(&format!("  {key}: {value}\n"))).unwrap();
            let e = AgentConfig::load(&p).unwrap_err().to_string();
            assert!(e.contains(key), "{key}: {e}");
        }
    }

    #[test]
    fn peer_slam_newest_view_follows_the_keyframe_updates_unless_set() {
        let dir = tempfile::tempdir().unwrap();
        let p = dir.path().join("a.yaml");
        let with = dc_full_history_with;
        let load = |o: &mut EstimatorOptions| AgentConfig::load(&p).unwrap().estimator.apply(o);
        std::fs::write(&p, with("")).unwrap();
        let mut tracked = EstimatorOptions::for_tracked_images();
        load(&mut tracked);
        assert!(tracked.peer_slam_newest_view());
        let mut simulated = EstimatorOptions::default();
        load(&mut simulated);
        assert!(!simulated.peer_slam_newest_view());
        std::fs::write(&p, with("  peer_slam_newest_view: false\n")).unwrap();
        let mut tracked = EstimatorOptions::for_tracked_images();
        load(&mut tracked);
        assert!(!tracked.peer_slam_newest_view());
    }

    #[test]
    fn unknown_keys_and_bad_values_are_reported() {
        let dir = tempfile::tempdir().unwrap();
        let p = dir.path().join("a.yaml");
        std::fs::write(&p, format!("{MINIMAL}colour: red\n")).unwrap();
        let e = AgentConfig::load(&p).unwrap_err().to_string();
        assert!(e.contains("colour"), "{e}");
        std::fs::write(&p, format!("{MINIMAL}fleet_id: a/b\n")).unwrap();
        let e = AgentConfig::load(&p).unwrap_err().to_string();
        assert!(e.contains("fleet_id"), "{e}");
        std::fs::write(&p, format!("{MINIMAL}estimator:\n  variant: magic\n")).unwrap();
        let e = AgentConfig::load(&p).unwrap_err().to_string();
        assert!(e.contains("magic"), "{e}");
        std::fs::write(&p, format!("{MINIMAL}clock:\n  peers: [1]\n")).unwrap();
        let e = AgentConfig::load(&p).unwrap_err().to_string();
        assert!(e.contains("own robot_id"), "{e}");
        std::fs::write(&p, format!("{MINIMAL}history:\n  retention: newest\n")).unwrap();
        let e = AgentConfig::load(&p).unwrap_err().to_string();
        assert!(e.contains("newest") && e.contains("informed"), "{e}");
        for loss in ["1.5", "-0.1", ".nan"] {
            std::fs::write(&p, format!("{MINIMAL}faults:\n  loss_fraction: {loss}\n")).unwrap();
            let e = AgentConfig::load(&p).unwrap_err().to_string();
            assert!(e.contains("loss_fraction"), "{loss}: {e}");
        }
    }

    #[test]
    fn history_retention_is_informed_unless_asked() {
        let dir = tempfile::tempdir().unwrap();
        let p = dir.path().join("a.yaml");
        std::fs::write(&p, MINIMAL).unwrap();
        let c = AgentConfig::load(&p).unwrap();
        assert_eq!(c.history.retention, Retention::Informed);
        std::fs::write(&p, format!("{MINIMAL}history:\n  retention: oldest\n")).unwrap();
        let c = AgentConfig::load(&p).unwrap();
        assert_eq!(c.history.retention, Retention::Oldest);
        assert_eq!(c.history.max_mib_per_peer, 64.0);
        assert_eq!(c.history.store_dir, None);
        std::fs::write(&p, format!("{MINIMAL}history:\n  store_dir: kept\n")).unwrap();
        let c = AgentConfig::load(&p).unwrap();
        assert_eq!(c.history.store_dir, Some(dir.path().join("kept")));
        assert_eq!(c.history.store_period_s, 10.0);
    }
}
