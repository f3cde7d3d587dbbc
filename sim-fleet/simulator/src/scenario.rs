//! Scenario files (YAML): the robots, their sensors, the shared world and the
//! estimator settings. Units are in the key names. Unknown keys are errors.
//!
//! Trajectory paths are resolved relative to the scenario file. Each robot's
//! trajectory is re-timed onto the fleet clock: its first pose is at fleet time
//! `start_time_s` (default 0), so recordings made at different times fly together.

use crate::render::RenderSpec;
use common::calibration::CameraCalibration;
use common::camera::{CameraModel, Distortion};
use common::estimator_options::{
    CooperationOptions, EstimatorOptions, FeatureRepresentation, ImuNoise, MsckfJacobians,
    TriangulationLimits,
};
use nalgebra::{Matrix3, Vector3, Vector4};
use serde::{Deserialize, Serialize};
use std::path::{Path, PathBuf};
use thiserror::Error;

/// Why a scenario could not be loaded.
#[derive(Debug, Error)]
pub enum ScenarioError {
    /// The scenario file could not be read.
    #[error("cannot read scenario {path}: {source}")]
    Read {
        /// The file.
        path: PathBuf,
        /// The cause.
        source: std::io::Error,
    },
    /// The YAML is malformed or has unknown/missing keys.
    #[error("invalid scenario {path}: {source}")]
    Parse {
        /// The file.
        path: PathBuf,
        /// The cause, with line and column.
        source: serde_yaml::Error,
    },
    /// A referenced trajectory file does not exist.
    #[error(
        "scenario {path}: robot {robot}: trajectory file {trajectory} not found (a relative \
         path is taken from the scenario file's folder; the example scenarios read the \
         project's data folder `shared/` beside the repository)"
    )]
    MissingTrajectory {
        /// The scenario file.
        path: PathBuf,
        /// The robot index.
        robot: usize,
        /// The resolved trajectory path.
        trajectory: PathBuf,
    },
    /// A value is out of its valid range.
    #[error("scenario {path}: {what}")]
    Invalid {
        /// The scenario file.
        path: PathBuf,
        /// What is wrong.
        what: String,
    },
}

/// A whole fleet scenario.
#[derive(Clone, Debug, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Scenario {
    /// Human-readable name, used in reports.
    pub name: String,
    /// Default seed of every random draw (overridable on the command line).
    #[serde(default = "default_seed")]
    pub seed: u64,
    /// The robots, in index order.
    pub robots: Vec<RobotSpec>,
    /// Sensor models shared by all robots.
    #[serde(default)]
    pub sensors: SensorSpec,
    /// The shared landmark world.
    #[serde(default)]
    pub world: WorldSpec,
    /// Estimator settings (used by the agents).
    #[serde(default)]
    pub estimator: EstimatorSpec,
    /// Rendered camera images (off by default: feature-level simulation).
    #[serde(default)]
    pub render: RenderSpec,
    /// Folder the scenario file was in (paths are relative to it); not in the file.
    #[serde(skip)]
    pub base_dir: PathBuf,
}

fn default_seed() -> u64 {
    1
}

/// One robot of the scenario.
#[derive(Clone, Debug, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct RobotSpec {
    /// Trajectory file (TUM text or EuRoC CSV), relative to the scenario file.
    pub trajectory: PathBuf,
    /// Fleet time of the trajectory's first pose, in seconds.
    #[serde(default)]
    pub start_time_s: f64,
    /// Optional name; defaults to the trajectory file stem.
    #[serde(default)]
    pub name: Option<String>,
    /// Times the trajectory is flown, every other time backwards so the
    /// motion stays continuous (a long mission from a short recording); 1
    /// when unset.
    #[serde(default = "one_lap")]
    pub laps: u32,
    /// This robot's camera where it differs from the fleet's
    /// (`sensors.camera`): a fleet of different lenses. The keys given replace
    /// the fleet camera's; the frame rate must stay the fleet's.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub camera: Option<CameraOverride>,
}

/// The keys of a robot's camera that differ from the fleet's
/// (`robots[i].camera`); each is a [`CameraSpec`] key, with its units.
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct CameraOverride {
    /// Frame rate in Hz (must equal the fleet's).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub rate_hz: Option<f64>,
    /// Distortion model: `radtan` or `equidistant`.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub model: Option<Distortion>,
    /// Image width in pixels.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub width_px: Option<u32>,
    /// Image height in pixels.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub height_px: Option<u32>,
    /// `[fx, fy, cx, cy]` in pixels.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub intrinsics_px: Option<[f64; 4]>,
    /// radtan `[k1, k2, p1, p2]` or equidistant `[k1, k2, k3, k4]` (unitless).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub distortion: Option<[f64; 4]>,
    /// `T_imu_cam` = `[R_CtoI | p_CinI]`, 3 rows of 4 (rotation, metres).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub t_imu_cam: Option<[[f64; 4]; 3]>,
    /// True camera-IMU time offset `t_d` in seconds.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub time_offset_s: Option<f64>,
    /// Standard deviation of the pixel noise, in pixels.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub pixel_noise_px: Option<f64>,
    /// At most this many features per frame.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub max_features: Option<usize>,
    /// Landmarks nearer than this are not seen, metres.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub min_depth_m: Option<f64>,
    /// Landmarks farther than this are not seen, metres.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub max_depth_m: Option<f64>,
}

impl CameraOverride {
    /// `base` with the keys this override gives replaced.
    pub fn apply(&self, base: &CameraSpec) -> CameraSpec {
        let b = base;
        CameraSpec {
            rate_hz: self.rate_hz.unwrap_or(b.rate_hz),
            model: self.model.unwrap_or(b.model),
            width_px: self.width_px.unwrap_or(b.width_px),
            height_px: self.height_px.unwrap_or(b.height_px),
            intrinsics_px: self.intrinsics_px.unwrap_or(b.intrinsics_px),
            distortion: self.distortion.unwrap_or(b.distortion),
            t_imu_cam: self.t_imu_cam.unwrap_or(b.t_imu_cam),
            time_offset_s: self.time_offset_s.unwrap_or(b.time_offset_s),
            pixel_noise_px: self.pixel_noise_px.unwrap_or(b.pixel_noise_px),
            max_features: self.max_features.unwrap_or(b.max_features),
            min_depth_m: self.min_depth_m.unwrap_or(b.min_depth_m),
            max_depth_m: self.max_depth_m.unwrap_or(b.max_depth_m),
        }
    }
}

fn one_lap() -> u32 {
    1
}

/// Sensor settings.
#[derive(Clone, Debug, Default, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct SensorSpec {
    /// IMU model.
    pub imu: ImuSpec,
    /// Camera model.
    pub camera: CameraSpec,
    /// Perturbation of the estimator's initial calibration.
    pub calibration_perturbation: CalibrationPerturbation,
}

/// IMU noise model (thesis Table 5.1 defaults).
#[derive(Clone, Debug, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct ImuSpec {
    /// Sample rate in Hz.
    pub rate_hz: f64,
    /// Gyroscope white noise density, rad/s/√Hz.
    pub gyro_noise_density: f64,
    /// Gyroscope bias random walk, rad/s²/√Hz.
    pub gyro_random_walk: f64,
    /// Accelerometer white noise density, m/s²/√Hz.
    pub accel_noise_density: f64,
    /// Accelerometer bias random walk, m/s³/√Hz.
    pub accel_random_walk: f64,
    /// Gravity magnitude in m/s² (world z up).
    pub gravity_mps2: f64,
}

impl Default for ImuSpec {
    fn default() -> Self {
        Self {
            rate_hz: 400.0,
            gyro_noise_density: 1.6968e-04,
            gyro_random_walk: 1.9393e-05,
            accel_noise_density: 2.0e-3,
            accel_random_walk: 3.0e-3,
            gravity_mps2: common::conventions::GRAVITY_MPS2,
        }
    }
}

/// Monocular camera settings (EuRoC cam0 defaults).
#[derive(Clone, Debug, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct CameraSpec {
    /// Frame rate in Hz.
    pub rate_hz: f64,
    /// Distortion model: `radtan` or `equidistant`.
    pub model: Distortion,
    /// Image width in pixels.
    pub width_px: u32,
    /// Image height in pixels.
    pub height_px: u32,
    /// `[fx, fy, cx, cy]` in pixels.
    pub intrinsics_px: [f64; 4],
    /// radtan `[k1, k2, p1, p2]` or equidistant `[k1, k2, k3, k4]` (unitless).
    pub distortion: [f64; 4],
    /// `T_imu_cam` = `[R_CtoI | p_CinI]`, 3 rows of 4 (rotation, metres).
    pub t_imu_cam: [[f64; 4]; 3],
    /// True camera-IMU time offset `t_d` in seconds (`t_imu = t_cam + t_d`).
    pub time_offset_s: f64,
    /// Standard deviation of the pixel noise, in pixels.
    pub pixel_noise_px: f64,
    /// At most this many features per frame.
    pub max_features: usize,
    /// Landmarks nearer than this are not seen, metres.
    pub min_depth_m: f64,
    /// Landmarks farther than this are not seen, metres.
    pub max_depth_m: f64,
}

impl Default for CameraSpec {
    fn default() -> Self {
        let c = CameraCalibration::euroc_cam0();
        let r = c.rot_c_to_i;
        let p = c.p_c_in_i;
        Self {
            rate_hz: 10.0,
            model: Distortion::RadTan,
            width_px: c.camera.width,
            height_px: c.camera.height,
            intrinsics_px: c.camera.intrinsics.into(),
            distortion: c.camera.distortion.into(),
            t_imu_cam: [
                [r[(0, 0)], r[(0, 1)], r[(0, 2)], p.x],
                [r[(1, 0)], r[(1, 1)], r[(1, 2)], p.y],
                [r[(2, 0)], r[(2, 1)], r[(2, 2)], p.z],
            ],
            time_offset_s: 0.0,
            pixel_noise_px: 1.0,
            max_features: 100,
            min_depth_m: 0.1,
            max_depth_m: 7.0,
        }
    }
}

impl CameraSpec {
    /// The true calibration this spec describes (rotation re-orthonormalized).
    pub fn calibration(&self) -> CameraCalibration {
        let m = &self.t_imu_cam;
        let rot = Matrix3::new(
            m[0][0], m[0][1], m[0][2], m[1][0], m[1][1], m[1][2], m[2][0], m[2][1], m[2][2],
        );
        CameraCalibration {
            camera: CameraModel {
                model: self.model,
                width: self.width_px,
                height: self.height_px,
                intrinsics: Vector4::from(self.intrinsics_px),
                distortion: Vector4::from(self.distortion),
            },
            rot_c_to_i: common::so3::orthonormalize(&rot),
            p_c_in_i: Vector3::new(m[0][3], m[1][3], m[2][3]),
            time_offset_s: self.time_offset_s,
        }
    }
}

/// Standard deviations of the perturbation applied to the estimator's initial
/// calibration (OpenVINS simulator defaults). All zero means "true calibration".
#[derive(Clone, Debug, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct CalibrationPerturbation {
    /// Apply the perturbation at all.
    pub enabled: bool,
    /// Time offset, seconds.
    pub time_offset_s: f64,
    /// Focal lengths and principal point, pixels.
    pub intrinsics_px: f64,
    /// Distortion coefficients (unitless).
    pub distortion: f64,
    /// Extrinsic rotation, radians per axis.
    pub extrinsic_rot_rad: f64,
    /// Extrinsic position, metres per axis.
    pub extrinsic_pos_m: f64,
}

impl Default for CalibrationPerturbation {
    fn default() -> Self {
        Self {
            enabled: true,
            time_offset_s: 0.01,
            intrinsics_px: 1.0,
            distortion: 0.005,
            extrinsic_rot_rad: 0.001,
            extrinsic_pos_m: 0.01,
        }
    }
}

/// The shared landmark world (OpenVINS-style generation along every trajectory).
#[derive(Clone, Debug, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct WorldSpec {
    /// New landmarks are made when fewer than this many are visible.
    pub min_visible: usize,
    /// Depth range of new landmarks, metres `[min, max]`.
    pub new_point_depth_m: [f64; 2],
    /// How often visibility is checked while building the world, seconds.
    pub check_interval_s: f64,
    /// Probability that each descriptor bit is flipped in one observation.
    pub descriptor_bit_flip_prob: f64,
    /// Probability that an observation's pixel belongs to another place (a wrong
    /// track association): the pixel is drawn uniformly over the image.
    pub outlier_pixel_prob: f64,
    /// Probability that an observation carries another landmark's descriptor (a
    /// wrong descriptor association, which misleads matching and loop closure).
    pub outlier_descriptor_prob: f64,
    /// Perceptual aliasing: this many places are made to look like other places
    /// (their landmarks replaced by a rigid copy of another place's, descriptors
    /// included), so that descriptor matching and the epipolar check accept a
    /// loop closure to the wrong place. The estimator must reject it.
    pub aliased_places: usize,
    /// Radius of an aliased place, metres.
    pub aliased_place_radius_m: f64,
    /// Which of the visible landmarks an image keeps when more than
    /// `camera.max_features` project into it.
    pub selection_order: SelectionOrder,
}

/// The order in which an image keeps its visible landmarks, up to
/// `camera.max_features`.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum SelectionOrder {
    /// The oldest landmarks (lowest ids) first: the same landmarks stay selected
    /// for as long as they are in view.
    #[default]
    LowestId,
    /// The iteration order of OpenVINS's map (a GCC `std::unordered_map` keyed
    /// by id, filled in id order): see [`crate::world::World::set_selection_order`].
    OpenvinsMap,
}

impl Default for WorldSpec {
    fn default() -> Self {
        Self {
            min_visible: 100,
            new_point_depth_m: [5.0, 7.0],
            check_interval_s: 0.25,
            descriptor_bit_flip_prob: 0.03,
            outlier_pixel_prob: 0.0,
            outlier_descriptor_prob: 0.0,
            aliased_places: 0,
            aliased_place_radius_m: 1.5,
            selection_order: SelectionOrder::LowestId,
        }
    }
}

/// Where each estimator starts relative to the truth.
///
/// OpenVINS's simulation starts every filter at the true state and states a
/// prior of 1 deg / 5 cm: the error starts at zero while the covariance claims
/// the prior, so NEES in the unobservable directions (global position, yaw)
/// stays below its dimension, and cooperating robots that tie their frames
/// together move each other's exact start by what their relative measurements
/// say. `sampled` draws the start from the prior instead, so the prior is true.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum InitialError {
    /// The true state (the prior's standard deviations around a zero error).
    #[default]
    Truth,
    /// The true state plus a zero-mean Gaussian error with the prior's
    /// standard deviations (orientation, position, velocity, biases).
    Sampled,
}

/// The world frame each robot's estimator starts in.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum StartFrame {
    /// One fleet frame: every robot starts at its true pose in the scenario's
    /// world, as if each had been given it.
    #[default]
    Fleet,
    /// Each robot its own frame: the origin at its start position, `x` along
    /// the heading of its most horizontal IMU axis (gravity fixes the rest).
    /// The robots do not know where the others started: the cooperative
    /// variants align the peers' frames from loop closures
    /// (`cooperation.align_peer_frames`), and each robot's truth and scores are
    /// in its own frame.
    Own,
}

/// Estimator settings (consumed by the agents; defaults follow thesis Table 5.1 and
/// OpenVINS's simulation setup).
#[derive(Clone, Debug, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct EstimatorSpec {
    /// Sliding window size (number of clones).
    pub max_clones: usize,
    /// Maximum SLAM features in the state (0 = MSCKF only).
    pub max_slam_features: usize,
    /// Maximum SLAM features initialized or updated per frame.
    pub max_slam_in_update: usize,
    /// Seconds after the start before SLAM features are initialized.
    pub slam_delay_s: f64,
    /// Clones, the frame's own included, before the first feature update (at most
    /// `max_clones + 1`, when the oldest clone of a full window leaves; unset: that
    /// count, whatever `max_clones` is).
    pub min_clones_to_update: Option<usize>,
    /// Times the first MSCKF update is iterated (0: one plain update).
    pub first_update_iterations: usize,
    /// Redo a first update whose step left its rays apart at the current
    /// estimate (`EstimatorOptions::rescue_first_update`).
    pub rescue_first_update: bool,
    /// Pixels of parallax the window's second-newest clone needs to stay, while
    /// the window fills too (`EstimatorOptions::keyframe_parallax_px`; 0: every
    /// clone stays).
    pub keyframe_parallax_px: f64,
    /// A slow start's keyframe window, px of parallax (0: off): a starved first
    /// update on a window without parallax waits for baseline
    /// (`EstimatorOptions::slow_start_keyframe_px`).
    pub slow_start_keyframe_px: f64,
    /// Whether a platform found slow takes the settings for slow platforms by
    /// itself: a slow start (its first update waited) observability-constrained
    /// MSCKF and SLAM Jacobians and inverse-depth SLAM features, a flight that
    /// turns slow later the constrained MSCKF Jacobians and the keyframe window
    /// (`EstimatorOptions::slow_platform_settings`).
    pub slow_platform_settings: bool,
    /// Where the MSCKF's Jacobians are evaluated: `first_estimates` or
    /// `observability_constrained` (`EstimatorOptions::msckf_jacobians`).
    pub msckf_jacobians: MsckfJacobians,
    /// Where the SLAM features' Jacobians are evaluated: `first_estimates` or
    /// `observability_constrained` (`EstimatorOptions::slam_jacobians`).
    pub slam_jacobians: MsckfJacobians,
    /// SLAM feature parameterization: `global` (p_FinG), `anchored` (in the
    /// camera of the clone that initialized it) or `anchored_inverse_depth` (its
    /// inverse depth there).
    pub feature_representation: FeatureRepresentation,
    /// Maximum MSCKF features per update.
    pub max_msckf_in_update: usize,
    /// The pixel noise the filter assumes, px; unset: the simulated
    /// `sensors.camera.pixel_noise_px`. Set it to run noise-free measurements
    /// (pixel noise 0) through a filter that still weighs them.
    pub pixel_sigma_px: Option<f64>,
    /// The pixel noise of the updates of the SLAM features in the state, px
    /// (`EstimatorOptions::slam_pixel_sigma_px`); unset: the filter's pixel
    /// noise on simulated features, and `TRACKED_SLAM_SIGMA_PX` (2) on rendered
    /// images, whose KLT tracks err along a track rather than afresh per image.
    pub slam_pixel_sigma_px: Option<f64>,
    /// Whether, on a keyframe window, a SLAM feature takes a view only once its
    /// image point moved the keyframe parallax
    /// (`EstimatorOptions::slam_keyframe_updates`); unset: off on simulated
    /// features, on for rendered images, whose tracks' errors persist from
    /// image to image.
    pub slam_keyframe_updates: Option<bool>,
    /// First-Estimates Jacobians on.
    pub use_fej: bool,
    /// Online calibration of the camera-IMU extrinsics.
    pub calib_extrinsics: bool,
    /// Online calibration of intrinsics and distortion.
    pub calib_intrinsics: bool,
    /// Online calibration of the camera-IMU time offset.
    pub calib_time_offset: bool,
    /// Zero-velocity updates on standstill.
    pub zero_velocity_update: bool,
    /// Initial standard deviation of orientation, radians.
    pub init_sigma_ori_rad: f64,
    /// Initial standard deviation of position, metres.
    pub init_sigma_pos_m: f64,
    /// Initial standard deviation of velocity, m/s.
    pub init_sigma_vel_mps: f64,
    /// Initial standard deviation of each bias axis (rad/s and m/s²).
    pub init_sigma_bias: f64,
    /// Where the estimator starts: `truth` (OpenVINS's simulation start, the
    /// prior's standard deviations around a zero error) or `sampled` (the truth
    /// plus an error drawn from that prior, per robot and seed).
    pub initial_error: InitialError,
    /// Path the robot must have travelled (summed over 0.1 s steps) before the
    /// filter starts, metres.
    pub start_after_motion_m: f64,
    /// The frame each robot's estimator works in: `fleet` (one for all) or
    /// `own` (its start; the peers' frames unknown to it).
    pub start_frame: StartFrame,
    /// Which triangulated features are accepted (condition number, depth range in
    /// metres, depth/baseline ratio).
    pub triangulation: TriangulationLimits,
    /// What the cooperative variants take from peers and how (weights,
    /// matching); the variant decides which classes are on.
    pub cooperation: CooperationOptions,
}

impl EstimatorSpec {
    /// The pixel noise the filter assumes, px: `pixel_sigma_px`, or the
    /// simulated `pixel_noise_px` when unset.
    pub fn filter_pixel_sigma_px(&self, pixel_noise_px: f64) -> f64 {
        self.pixel_sigma_px.unwrap_or(pixel_noise_px)
    }

    /// The estimator options these settings and the `sensors` ask for (noise
    /// models from the simulated sensors), before a variant picks what is taken
    /// from peers. A zero filter pixel sigma (pixel noise 0 with
    /// `pixel_sigma_px` unset) fails [`EstimatorOptions::validate`].
    pub fn options(&self, sensors: &SensorSpec) -> EstimatorOptions {
        let imu = &sensors.imu;
        EstimatorOptions {
            max_clones: self.max_clones,
            max_slam_features: self.max_slam_features,
            max_slam_in_update: self.max_slam_in_update,
            slam_delay_s: self.slam_delay_s,
            min_clones_to_update: self.first_update_clones(),
            first_update_iterations: self.first_update_iterations,
            rescue_first_update: self.rescue_first_update,
            keyframe_parallax_px: self.keyframe_parallax_px,
            slow_start_keyframe_px: self.slow_start_keyframe_px,
            slow_platform_settings: self.slow_platform_settings,
            msckf_jacobians: self.msckf_jacobians,
            slam_jacobians: self.slam_jacobians,
            feature_representation: self.feature_representation,
            max_msckf_in_update: self.max_msckf_in_update,
            use_fej: self.use_fej,
            calib_extrinsics: self.calib_extrinsics,
            calib_intrinsics: self.calib_intrinsics,
            calib_time_offset: self.calib_time_offset,
            zero_velocity_update: self.zero_velocity_update,
            pixel_sigma_px: self.filter_pixel_sigma_px(sensors.camera.pixel_noise_px),
            slam_pixel_sigma_px: self.slam_pixel_sigma_px,
            slam_keyframe_updates: self.slam_keyframe_updates.unwrap_or(false),
            imu: ImuNoise {
                gyro_noise_density: imu.gyro_noise_density,
                gyro_random_walk: imu.gyro_random_walk,
                accel_noise_density: imu.accel_noise_density,
                accel_random_walk: imu.accel_random_walk,
                gravity_mps2: imu.gravity_mps2,
            },
            triangulation: self.triangulation,
            cooperation: self.cooperation.clone(),
            ..EstimatorOptions::default()
        }
    }

    /// Clones before the first feature update: `min_clones_to_update`, or
    /// `max_clones + 1` (the oldest clone of a full window leaves) when unset.
    pub fn first_update_clones(&self) -> usize {
        self.min_clones_to_update
            .unwrap_or(self.max_clones.saturating_add(1))
    }
}

impl Default for EstimatorSpec {
    /// The estimator's own defaults (`common::estimator_options`), plus OpenVINS's
    /// simulation start: 1 deg / 5 cm / 1 cm/s / 0.02 prior sigmas, after 1.1 m.
    fn default() -> Self {
        let o = EstimatorOptions::default();
        Self {
            max_clones: o.max_clones,
            max_slam_features: o.max_slam_features,
            max_slam_in_update: o.max_slam_in_update,
            slam_delay_s: o.slam_delay_s,
            min_clones_to_update: None,
            first_update_iterations: o.first_update_iterations,
            rescue_first_update: o.rescue_first_update,
            keyframe_parallax_px: o.keyframe_parallax_px,
            slow_start_keyframe_px: o.slow_start_keyframe_px,
            slow_platform_settings: o.slow_platform_settings,
            msckf_jacobians: o.msckf_jacobians,
            slam_jacobians: o.slam_jacobians,
            feature_representation: o.feature_representation,
            max_msckf_in_update: o.max_msckf_in_update,
            pixel_sigma_px: None,
            slam_pixel_sigma_px: None,
            slam_keyframe_updates: None,
            use_fej: o.use_fej,
            calib_extrinsics: o.calib_extrinsics,
            calib_intrinsics: o.calib_intrinsics,
            calib_time_offset: o.calib_time_offset,
            zero_velocity_update: o.zero_velocity_update,
            init_sigma_ori_rad: 0.017,
            init_sigma_pos_m: 0.05,
            init_sigma_vel_mps: 0.01,
            init_sigma_bias: 0.02,
            initial_error: InitialError::Truth,
            start_after_motion_m: 1.1,
            start_frame: StartFrame::Fleet,
            triangulation: o.triangulation,
            cooperation: o.cooperation,
        }
    }
}

/// Checks the ranges of camera `cam`, named `at` in the messages.
fn check_camera(at: &str, cam: &CameraSpec, imu_rate_hz: f64) -> Result<(), String> {
    for (k, v) in [("rate_hz", cam.rate_hz), ("max_depth_m", cam.max_depth_m)] {
        if !(v.is_finite() && v > 0.0) {
            return Err(format!("{at}.{k} must be positive, got {v}"));
        }
    }
    let noise = cam.pixel_noise_px;
    if !(noise.is_finite() && noise >= 0.0) {
        return Err(format!(
            "{at}.pixel_noise_px must be at least 0, got {noise}"
        ));
    }
    if cam.rate_hz > imu_rate_hz {
        return Err(format!("{at}: camera rate above IMU rate"));
    }
    cam.calibration()
        .camera
        .validate()
        .map_err(|e| format!("{at}: {e}"))
}

impl Scenario {
    /// Reads and validates a scenario file; trajectory paths become absolute.
    pub fn load(path: &Path) -> Result<Self, ScenarioError> {
        let text = std::fs::read_to_string(path).map_err(|source| ScenarioError::Read {
            path: path.to_path_buf(),
            source,
        })?;
        let mut sc: Scenario =
            serde_yaml::from_str(&text).map_err(|source| ScenarioError::Parse {
                path: path.to_path_buf(),
                source,
            })?;
        sc.base_dir = path
            .parent()
            .map(Path::to_path_buf)
            .unwrap_or_else(|| PathBuf::from("."));
        sc.validate(path)?;
        Ok(sc)
    }

    /// The absolute (or scenario-relative resolved) path of robot `i`'s trajectory.
    pub fn trajectory_path(&self, robot: usize) -> Option<PathBuf> {
        self.robots.get(robot).map(|r| {
            if r.trajectory.is_absolute() {
                r.trajectory.clone()
            } else {
                self.base_dir.join(&r.trajectory)
            }
        })
    }

    /// Robot `robot`'s camera: the fleet's (`sensors.camera`) with the keys of
    /// its own `camera:` replaced.
    pub fn camera(&self, robot: usize) -> CameraSpec {
        match self.robots.get(robot).and_then(|r| r.camera.as_ref()) {
            Some(own) => own.apply(&self.sensors.camera),
            None => self.sensors.camera.clone(),
        }
    }

    /// The sensors of robot `robot`: the fleet's, with its own camera.
    pub fn sensors_of(&self, robot: usize) -> SensorSpec {
        SensorSpec {
            camera: self.camera(robot),
            ..self.sensors.clone()
        }
    }

    /// Whether every robot has the fleet's camera.
    pub fn one_camera(&self) -> bool {
        self.robots.iter().all(|r| r.camera.is_none())
    }

    /// Display name of robot `i`.
    pub fn robot_name(&self, robot: usize) -> String {
        match self.robots.get(robot) {
            Some(RobotSpec { name: Some(n), .. }) => n.clone(),
            Some(r) => r
                .trajectory
                .file_stem()
                .map(|s| s.to_string_lossy().into_owned())
                .unwrap_or_else(|| format!("robot{robot}")),
            None => format!("robot{robot}"),
        }
    }

    fn validate(&self, path: &Path) -> Result<(), ScenarioError> {
        let invalid = |what: String| ScenarioError::Invalid {
            path: path.to_path_buf(),
            what,
        };
        if self.robots.is_empty() {
            return Err(invalid("no robots".into()));
        }
        for i in 0..self.robots.len() {
            let Some(t) = self.trajectory_path(i) else {
                continue;
            };
            if !t.is_file() {
                return Err(ScenarioError::MissingTrajectory {
                    path: path.to_path_buf(),
                    robot: i,
                    trajectory: t,
                });
            }
            if !self.robots[i].start_time_s.is_finite() {
                return Err(invalid(format!("robot {i}: start_time_s is not finite")));
            }
        }
        let s = &self.sensors;
        let positive = [
            ("sensors.imu.rate_hz", s.imu.rate_hz),
            ("world.check_interval_s", self.world.check_interval_s),
        ];
        for (k, v) in positive {
            if !(v.is_finite() && v > 0.0) {
                return Err(invalid(format!("{k} must be positive, got {v}")));
            }
        }
        check_camera("sensors.camera", &s.camera, s.imu.rate_hz).map_err(invalid)?;
        for (i, robot) in self.robots.iter().enumerate() {
            let Some(own) = &robot.camera else { continue };
            let cam = own.apply(&s.camera);
            check_camera(&format!("robots[{i}].camera"), &cam, s.imu.rate_hz).map_err(invalid)?;
            // Fleet runs step every robot on one camera clock.
            if cam.rate_hz != s.camera.rate_hz {
                return Err(invalid(format!(
                    "robots[{i}].camera.rate_hz must be the fleet's ({} Hz), got {}",
                    s.camera.rate_hz, cam.rate_hz
                )));
            }
        }
        let [dmin, dmax] = self.world.new_point_depth_m;
        if !(dmin > 0.0 && dmax >= dmin) {
            return Err(invalid(format!(
                "world.new_point_depth_m must be 0 < min <= max, got [{dmin}, {dmax}]"
            )));
        }
        for (k, p) in [
            (
                "descriptor_bit_flip_prob",
                self.world.descriptor_bit_flip_prob,
            ),
            ("outlier_pixel_prob", self.world.outlier_pixel_prob),
            (
                "outlier_descriptor_prob",
                self.world.outlier_descriptor_prob,
            ),
        ] {
            if !(0.0..=1.0).contains(&p) {
                return Err(invalid(format!("world.{k} must be in [0, 1], got {p}")));
            }
        }
        self.render.validate().map_err(|e| invalid(e.to_string()))?;
        let e = &self.estimator;
        for robot in 0..self.robots.len() {
            e.options(&self.sensors_of(robot))
                .validate()
                .map_err(|what| invalid(format!("estimator.{what}")))?;
        }
        for (k, v) in [
            ("init_sigma_ori_rad", e.init_sigma_ori_rad),
            ("init_sigma_pos_m", e.init_sigma_pos_m),
            ("init_sigma_vel_mps", e.init_sigma_vel_mps),
            ("init_sigma_bias", e.init_sigma_bias),
            ("start_after_motion_m", e.start_after_motion_m),
        ] {
            if !(v.is_finite() && v >= 0.0) {
                return Err(invalid(format!(
                    "estimator.{k} must be finite and at least 0, got {v}"
                )));
            }
        }
        Ok(())
    }
}
