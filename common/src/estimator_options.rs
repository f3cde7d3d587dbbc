//! The estimator's options, with OpenVINS's simulation defaults (thesis Table 5.1).
//!
//! They live here, not in the agent, so scenario files take their defaults from the
//! same place the estimator does.

use serde::{Deserialize, Serialize};

/// How SLAM features are parameterized in the state. OpenVINS's names
/// (`GLOBAL_3D`, `ANCHORED_3D`, `ANCHORED_MSCKF_INVERSE_DEPTH`) are accepted too,
/// so its `feat_rep_slam` values can be copied into an agent configuration.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum FeatureRepresentation {
    /// `p_FinG`.
    #[default]
    #[serde(alias = "GLOBAL_3D")]
    Global,
    /// `p_FinA` in the camera of the clone the feature was initialized at; the
    /// anchor moves to the newest clone when its clone leaves the window.
    #[serde(alias = "ANCHORED_3D")]
    Anchored,
    /// `(α, β, ρ) = (x/z, y/z, 1/z)` of `p_FinA`, anchored as `anchored` (thesis
    /// Appendix A.6.5; OpenVINS's `ANCHORED_MSCKF_INVERSE_DEPTH`). The pixels of a
    /// point seen over a short baseline are nearly linear in its inverse depth,
    /// not in its depth.
    #[serde(
        rename = "anchored_inverse_depth",
        alias = "ANCHORED_MSCKF_INVERSE_DEPTH"
    )]
    AnchoredInverseDepth,
}

/// Where the MSCKF's (or the SLAM features') measurement Jacobians are
/// evaluated (with `use_fej`).
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum MsckfJacobians {
    /// At the clones' first estimates (FEJ, OpenVINS).
    #[default]
    FirstEstimates,
    /// At the current estimate, then projected so that they give no
    /// information along the unobservable directions of the first estimates
    /// (observability-constrained, after Hesch et al.'s OC-EKF). Better on
    /// slow platforms without SLAM features (README).
    ObservabilityConstrained,
}

/// IMU noise model used by the filter (continuous-time densities).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct ImuNoise {
    /// Gyroscope white noise density, rad/s/√Hz.
    pub gyro_noise_density: f64,
    /// Gyroscope bias random walk, rad/s²/√Hz.
    pub gyro_random_walk: f64,
    /// Accelerometer white noise density, m/s²/√Hz.
    pub accel_noise_density: f64,
    /// Accelerometer bias random walk, m/s³/√Hz.
    pub accel_random_walk: f64,
    /// Gravity magnitude, m/s².
    pub gravity_mps2: f64,
}

impl Default for ImuNoise {
    fn default() -> Self {
        Self {
            gyro_noise_density: 1.6968e-04,
            gyro_random_walk: 1.9393e-05,
            accel_noise_density: 2.0e-3,
            accel_random_walk: 3.0e-3,
            gravity_mps2: crate::conventions::GRAVITY_MPS2,
        }
    }
}

/// Prior standard deviations of the calibration states.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct CalibrationPrior {
    /// Time offset, s.
    pub time_offset_s: f64,
    /// Extrinsic rotation, rad.
    pub extrinsic_rot_rad: f64,
    /// Extrinsic position, m.
    pub extrinsic_pos_m: f64,
    /// Focal lengths and principal point, px.
    pub intrinsics_px: f64,
    /// Distortion coefficients.
    pub distortion: f64,
}

impl Default for CalibrationPrior {
    fn default() -> Self {
        Self {
            time_offset_s: 0.01,
            extrinsic_rot_rad: 0.005,
            extrinsic_pos_m: 0.015,
            intrinsics_px: 1.0,
            distortion: 0.005,
        }
    }
}

/// How common VIO features are projected before the CI-EKF update (thesis
/// Section 5.3.3.2).
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum CommonProjection {
    /// Per-robot nullspace projection first, the rows that do not involve us
    /// dropped, then a second projection (Eqs. 5.18-5.19); our own rows go
    /// through a standard EKF update.
    #[default]
    TwoStage,
    /// One projection of every robot's stacked rows, all of them in the CI-EKF
    /// update (the naive baseline the thesis compares against).
    Combined,
}

/// How the covariance-intersection weights are chosen (thesis Eq. 5.14).
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum CiWeighting {
    /// Each participant (a peer's window) gets `ci_peer_weight`; ours is the rest.
    /// The thesis' simulation setting; the scenarios that reproduce its tables
    /// name it.
    FixedPeer,
    /// Ours is `ci_own_weight`; the participants split the rest evenly.
    FixedOwn,
    /// Minimize the trace of the updated covariance.
    MinTrace,
    /// Minimize the trace of our current pose's updated covariance (orientation
    /// and position, rad² and m²). The whole state's trace adds up units that do
    /// not compare (the intrinsics' px² against our position's m²), and the weights that
    /// minimize it need not serve the pose (README).
    ///
    /// The default: it needs no weight tuned on the fleet first, and over long
    /// missions it keeps the reported covariance near the error, where a fixed
    /// weight inflates it at every CI update however little the peers' rows
    /// tell (README, "an hour of flight").
    #[default]
    MinPoseTrace,
    /// Minimize the determinant of the updated covariance.
    MinDeterminant,
    /// Minimize the determinant of the updated covariance of our current pose
    /// and of the SLAM features the update measures. A determinant weighs no
    /// unit against another (a feature's cm² against the pose's mm²), so the
    /// features count as much as the pose. Over two minutes it beats
    /// `min_pose_trace` without history (dc-full-window 0.89x in position),
    /// not with it; over an hour it did worse with history and far worse
    /// without (yaw drift, overconfident: README).
    MinPoseFeaturesDeterminant,
}

/// Which triangulated features the estimator accepts (OpenVINS's `fi_*`
/// settings, with its defaults).
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct TriangulationLimits {
    /// Largest ratio of the largest to the smallest singular value of the 3x3
    /// linear triangulation system (`fi_max_cond_number`): rays closer than about
    /// 1 deg give a depth too uncertain to linearize at.
    pub max_condition_number: f64,
    /// Nearest accepted depth in the anchor camera, metres (`fi_min_dist`).
    pub min_depth_m: f64,
    /// Farthest accepted depth in the anchor camera, metres (`fi_max_dist`).
    pub max_depth_m: f64,
    /// Largest ratio of the anchor depth to the largest distance between two of
    /// the observing cameras (`fi_max_baseline`).
    pub max_baseline_ratio: f64,
}

impl Default for TriangulationLimits {
    fn default() -> Self {
        Self {
            max_condition_number: 1e4,
            min_depth_m: 0.1,
            max_depth_m: 60.0,
            max_baseline_ratio: 40.0,
        }
    }
}

impl TriangulationLimits {
    /// Range checks: finite, positive, a condition number above 1 and
    /// `min_depth_m < max_depth_m`.
    pub fn validate(&self) -> Result<(), String> {
        let named = [
            ("max_condition_number", self.max_condition_number),
            ("min_depth_m", self.min_depth_m),
            ("max_depth_m", self.max_depth_m),
            ("max_baseline_ratio", self.max_baseline_ratio),
        ];
        for (name, v) in named {
            if !(v.is_finite() && v > 0.0) {
                return Err(format!(
                    "triangulation.{name} must be finite and positive, not {v}"
                ));
            }
        }
        if self.max_condition_number <= 1.0 {
            return Err(format!(
                "triangulation.max_condition_number must exceed 1 (it is a ratio of singular values), not {}",
                self.max_condition_number
            ));
        }
        if self.min_depth_m >= self.max_depth_m {
            return Err(format!(
                "triangulation.min_depth_m ({}) must be below max_depth_m ({})",
                self.min_depth_m, self.max_depth_m
            ));
        }
        Ok(())
    }
}

/// What a robot takes from its peers (thesis Section 5.3) and how.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct CooperationOptions {
    /// Common VIO features over the window: our lost or leaving tracks matched to
    /// peers' tracks (CI-EKF, Section 5.3.3).
    pub common_vio: bool,
    /// Common SLAM features: our SLAM features updated with peers' measurements
    /// (Section 5.3.4 case i; also case ii when `slam_constraint` is off).
    pub common_slam: bool,
    /// SLAM feature to peer SLAM feature: the position constraint update
    /// (Eqs. 5.22-5.24) instead of the measurement update.
    pub slam_constraint: bool,
    /// Historical features: loop closures to peers' stored keyframe windows
    /// (Section 5.3.5).
    pub historical: bool,
    /// Projection of common VIO features.
    pub projection: CommonProjection,
    /// How CI weights are chosen.
    pub ci_weighting: CiWeighting,
    /// Weight of each participant's covariance with `fixed_peer` (thesis
    /// simulation: 0.001; the covariance is divided by it). With weights chosen
    /// per update it and `constraint_peer_weight` only set how the peers' share
    /// `1 − ω` divides between windows and landmarks (measured to move the
    /// results by about 1 %, docs/evidence/cooperation.md, stop 64).
    pub ci_peer_weight: f64,
    /// Our weight with `fixed_own` (thesis real data: 0.99).
    pub ci_own_weight: f64,
    /// Weight of the peer's landmark in the constraint update (thesis: 0.005).
    pub constraint_peer_weight: f64,
    /// Synthetic noise of the constraint update, m (thesis: 0.02).
    pub constraint_sigma_m: f64,
    /// Largest Hamming distance of a descriptor match, bits (of 256).
    pub max_descriptor_distance_bits: u32,
    /// Ratio test: best distance below this fraction of the second best.
    pub match_ratio: f64,
    /// Fewest epipolar inliers to accept the matches to a peer's current frame.
    pub min_window_inliers: usize,
    /// Fewest epipolar inliers to accept a loop closure to a peer keyframe.
    pub min_loop_inliers: usize,
    /// Epipolar (Sampson) threshold of the fundamental-matrix RANSAC, px.
    pub epipolar_threshold_px: f64,
    /// Smallest bag-of-words score (L1, in [0, 1]) of a loop-closure candidate.
    pub loop_min_score: f64,
    /// Loop-closure candidates checked per peer and frame (best scores first).
    pub loop_candidates: usize,
    /// Historical keyframe windows of one peer a feature takes measurements
    /// from (the ones with the most; each is one more CI participant).
    pub max_keyframes_per_track: usize,
    /// Peers whose current windows a feature takes measurements from (the
    /// ones that saw it longest): bounds the update when many robots share a place.
    pub max_peers_per_track: usize,
    /// A peer's newest frame older than this (before ours, fleet clock) is no
    /// longer a current window to match, s: one that stopped publishing.
    pub max_window_age_s: f64,
    /// Peers matched per frame (current frames and keyframe databases), taken
    /// in turn when there are more: matching, like the update below, must not
    /// cost more as the fleet grows. A link, once made, lasts as long as our
    /// track, so a peer matched every few frames loses only its newest tracks'
    /// first frames. At least 1.
    pub max_peers_matched_per_frame: usize,
    /// CI participants (peer windows) of one frame's CI-EKF update, the ones
    /// behind the most of our tracks: each adds its window's poses to the
    /// update and inflates our covariance once more. At least 1.
    pub max_ci_participants: usize,
    /// Common VIO features per frame (our tracks in the order the MSCKF takes
    /// them, longest first); the rest are independent VIO features. With the
    /// two caps above, a frame's cooperative work has a bound that does not
    /// depend on the fleet's size. 0 turns common VIO features off.
    pub max_common_per_frame: usize,
    /// The peers' world frames are not ours (robots not given their start
    /// poses in one fleet frame): each peer's yaw and translation are measured
    /// from loop closures to its keyframe windows, and its windows are used
    /// only once that is confirmed. Needs `historical`.
    pub align_peer_frames: bool,
    /// With `align_peer_frames` (no effect without): how long each
    /// confirmed peer frame is held as 4 states of our filter (yaw and
    /// translation), s. It joins the state with its cross-covariance to our
    /// camera pose of the loop closure that confirmed it, and every update
    /// with the peer's windows corrects it; then it becomes a fixed alignment
    /// with the state's estimate, refined by later loop closures. 0: a fixed
    /// alignment from the start, its covariance folded into each of the
    /// peer's windows; `.inf`: the whole flight. `None` (the default): by
    /// the weighting ([`CooperationOptions::peer_frame_hold_s`]).
    pub peer_frame_state_s: Option<f64>,
    /// Later loop closures to a frame our state holds measure it again, at
    /// most once per this period per frame, s, and the estimator updates the
    /// frame and our camera pose with them (`updater_frame`). 0: never; a
    /// held frame then learns only from the updates that use its windows.
    pub held_frame_measurement_period_s: f64,
    /// Those measurements are taken only this long after the frame was
    /// confirmed, s (`.inf`: while it is held). Their noise holds the
    /// peer's anchor pose, whose drift they share and the filter takes as
    /// independent: over an hour without this bound the robots' position
    /// NEES reached 8-11 (README, "Robots in their own frames").
    pub held_frame_measurement_window_s: f64,
    /// At most this many of those measurements a second over all the frames
    /// we hold, 1/s (`.inf`: no cap): with `k` frames in their window, each
    /// is measured at most once per `max(period, k / rate)`. The noise the
    /// filter takes as independent of our state is not (above), so what each
    /// measurement over-tells adds up in our pose; with a period per frame
    /// alone, the NEES grew with the fleet (six robots 2.40 / 2.47, twelve
    /// 2.94 / 2.96, twenty-four 3.17 / 3.03; README, "Robots in their own
    /// frames"). The default 1 leaves fleets of up to six robots (five
    /// frames at 5 s) as they were.
    pub held_frame_measurements_per_s: f64,
    /// How much more of the peer's anchor pose each later measurement of a
    /// held frame counts: the k-th later measurement of a frame weighs that
    /// share of its noise `growth^k` times (`updater_frame`). The anchor's
    /// error is largely common to the seed and every later measurement (the
    /// peer's anchor poses drift together), so together they tell at most
    /// `1 + 1/(growth − 1)` times what the seed alone tells about it (3 at
    /// the default 1.5). 1: every measurement takes its whole noise as
    /// independent of our state (before stop 91), which left the last robot
    /// of a twelve-robot fleet and one of six above the NEES band; 1.5 keeps
    /// twelve robots' accuracy and costs six 6 % in orientation (README,
    /// "Robots in their own frames").
    pub held_frame_anchor_growth: f64,
    /// Most peer frames held in our state at once (with
    /// `peer_frame_state_s`); beyond it the longest held becomes a fixed
    /// alignment. Each adds 4 states to every update, and a peer that starts
    /// again brings a new frame. At least 1.
    pub max_held_peer_frames: usize,
    /// Split CI over the four directions no peer measurement observes (our
    /// world frame's yaw and translation, which move our pose, clones,
    /// features and the peer frames held in our state together): in a CI
    /// update whose participants all come through frames held in our state,
    /// our covariance along those directions (conditioned on the rest) is not
    /// inflated by `1/ω`. Our own measurements alone make that part, and the
    /// peers' windows, in their own frames, cannot carry it. Without it a
    /// frame and our pose drift together under the inflation.
    pub split_unobservable: bool,
    /// Split CI over our own calibration (camera-IMU time offset, extrinsics,
    /// intrinsics, when estimated): in every CI update our covariance of the
    /// calibration, conditioned on the rest of our state, is not inflated by
    /// `1/ω`. It describes our own sensor rig, which no peer estimates; without
    /// it the inflation of every frame's update wipes out what our own
    /// measurements taught the filter about it: the EuRoC fleet's robots ended
    /// their flights knowing their calibration 2-5 times worse than alone,
    /// one worse than its prior (README).
    pub split_calibration: bool,
    /// Fewest loop-closure points that must agree on an alignment.
    pub min_alignment_inliers: usize,
    /// Loop closures to different keyframe windows of a peer that must agree
    /// before its frame is taken (perceptual aliasing makes one wrong now and
    /// then). At least 1.
    pub alignment_confirmations: usize,
    /// Largest yaw standard deviation of an alignment measurement, deg.
    pub max_alignment_yaw_sigma_deg: f64,
    /// Largest root summed translation variance of an alignment
    /// measurement, m.
    pub max_alignment_translation_sigma_m: f64,
    /// A peer's track gives a common SLAM update only its newest view not
    /// yet used, not every view of its window (`None`: as
    /// `slam_keyframe_updates`, so on tracked images and off for simulated
    /// features; [`EstimatorOptions::peer_slam_newest_view`]). An image
    /// tracker's error persists along a track, and a link made to a window
    /// of eleven views counts that one error eleven times as independent
    /// evidence: rendered three-robot fleets with held tracks were pulled
    /// 1-2 deg off in one CI update when the robots set off (README,
    /// "Held tracks on live sensors").
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub peer_slam_newest_view: Option<bool>,
    /// Gate each peer window's rows stacked, not only block by block: a
    /// window whose stacked distance fails the chi-square test loses its
    /// blocks one at a time, the one whose removal lowers the distance
    /// most first, until it passes. A block's own innovation covariance
    /// holds the robots' whole relative pose uncertainty, which the other
    /// blocks of the window pin down, so a wrong link passes its own gate
    /// (mostly 0.0-1.4 over 3 rows on rendered flights) and pulls
    /// against every other row of the window.
    pub window_gate: bool,
}

impl Default for CooperationOptions {
    /// Nothing from peers (the independent variants); CI weights chosen per
    /// update on our pose (the thesis' fixed weights are kept for `fixed_peer`
    /// and `fixed_own`).
    fn default() -> Self {
        Self {
            common_vio: false,
            common_slam: false,
            slam_constraint: false,
            historical: false,
            projection: CommonProjection::TwoStage,
            ci_weighting: CiWeighting::MinPoseTrace,
            ci_peer_weight: 0.001,
            ci_own_weight: 0.99,
            constraint_peer_weight: 0.005,
            constraint_sigma_m: 0.02,
            max_descriptor_distance_bits: 64,
            match_ratio: 0.8,
            min_window_inliers: 10,
            min_loop_inliers: 15,
            epipolar_threshold_px: 2.0,
            loop_min_score: 0.05,
            loop_candidates: 2,
            max_keyframes_per_track: 1,
            max_peers_per_track: 2,
            max_window_age_s: 1.0,
            max_peers_matched_per_frame: 3,
            max_ci_participants: 2,
            max_common_per_frame: 6,
            align_peer_frames: false,
            peer_frame_state_s: None,
            max_held_peer_frames: 16,
            held_frame_measurement_period_s: 5.0,
            held_frame_measurement_window_s: 60.0,
            held_frame_measurements_per_s: 1.0,
            held_frame_anchor_growth: 1.5,
            split_unobservable: true,
            split_calibration: true,
            min_alignment_inliers: 12,
            alignment_confirmations: 2,
            max_alignment_yaw_sigma_deg: 2.0,
            max_alignment_translation_sigma_m: 0.5,
            peer_slam_newest_view: None,
            window_gate: true,
        }
    }
}

/// How long a peer frame is held in our state with fixed CI weights
/// (`cooperation.peer_frame_state_s` unset), s.
pub const FIXED_WEIGHT_FRAME_HOLD_S: f64 = 60.0;

impl CooperationOptions {
    /// How long each confirmed peer frame is held in our state, s:
    /// `peer_frame_state_s`, or when unset, by the weighting. A held frame
    /// learns from the CI updates through it, and in its first
    /// `held_frame_measurement_window_s` from later loop closures to it.
    /// With weights chosen per update the CI updates teach it for as long
    /// as it is held, and holding it for the whole flight gains (README,
    /// "Robots in their own frames"). A fixed
    /// small peer weight (`fixed_peer` 0.005 divides each window's covariance
    /// by 200) starves it, while the fixed alignment that replaces it is
    /// refined by every later loop closure: it is held for
    /// [`FIXED_WEIGHT_FRAME_HOLD_S`].
    pub fn peer_frame_hold_s(&self) -> f64 {
        self.peer_frame_state_s.unwrap_or(match self.ci_weighting {
            CiWeighting::FixedPeer | CiWeighting::FixedOwn => FIXED_WEIGHT_FRAME_HOLD_S,
            CiWeighting::MinTrace
            | CiWeighting::MinPoseTrace
            | CiWeighting::MinDeterminant
            | CiWeighting::MinPoseFeaturesDeterminant => f64::INFINITY,
        })
    }

    /// Whether anything is taken from peers.
    pub fn any(&self) -> bool {
        self.common_vio || self.common_slam || self.historical
    }

    /// Range checks, each error naming its key. A CI weight of 0 divides a
    /// covariance by zero and one of 1 or more leaves the other side none
    /// (Eq. 5.14 needs weights in (0, 1)); a zero constraint sigma divides by
    /// zero in every constraint update; no CI participant or no peer matched
    /// per frame would silently turn the cooperation off.
    pub fn validate(&self) -> Result<(), String> {
        for (name, v) in [
            ("ci_peer_weight", self.ci_peer_weight),
            ("ci_own_weight", self.ci_own_weight),
            ("constraint_peer_weight", self.constraint_peer_weight),
        ] {
            if !(v > 0.0 && v < 1.0) {
                return Err(format!(
                    "cooperation.{name} must be in (0, 1) (a CI weight), not {v}"
                ));
            }
        }
        for (name, v) in [
            ("constraint_sigma_m", self.constraint_sigma_m),
            ("epipolar_threshold_px", self.epipolar_threshold_px),
            ("max_window_age_s", self.max_window_age_s),
            (
                "max_alignment_yaw_sigma_deg",
                self.max_alignment_yaw_sigma_deg,
            ),
            (
                "max_alignment_translation_sigma_m",
                self.max_alignment_translation_sigma_m,
            ),
        ] {
            if !(v.is_finite() && v > 0.0) {
                return Err(format!(
                    "cooperation.{name} must be finite and positive, not {v}"
                ));
            }
        }
        if !(self.match_ratio > 0.0 && self.match_ratio <= 1.0) {
            return Err(format!(
                "cooperation.match_ratio must be in (0, 1] (best over second-best distance), not {}",
                self.match_ratio
            ));
        }
        if !(0.0..=1.0).contains(&self.loop_min_score) {
            return Err(format!(
                "cooperation.loop_min_score must be in [0, 1] (an L1 score), not {}",
                self.loop_min_score
            ));
        }
        let bits = crate::descriptor::Descriptor::BITS;
        if self.max_descriptor_distance_bits as usize > bits {
            return Err(format!(
                "cooperation.max_descriptor_distance_bits must be at most {bits} \
                 (a descriptor's length), not {}",
                self.max_descriptor_distance_bits
            ));
        }
        // The eight-point solver fits any eight pairs exactly: a floor at or
        // below it would accept matches that agree on nothing.
        for (name, v) in [
            ("min_window_inliers", self.min_window_inliers),
            ("min_loop_inliers", self.min_loop_inliers),
        ] {
            if v <= crate::epipolar::MIN_POINTS {
                return Err(format!(
                    "cooperation.{name} must be above {} (the eight-point solver fits any {0} \
                     pairs), not {v}",
                    crate::epipolar::MIN_POINTS
                ));
            }
        }
        for (name, v) in [
            ("loop_candidates", self.loop_candidates),
            ("max_ci_participants", self.max_ci_participants),
            (
                "max_peers_matched_per_frame",
                self.max_peers_matched_per_frame,
            ),
        ] {
            if v == 0 {
                return Err(format!("cooperation.{name} must be at least 1"));
            }
        }
        if self.align_peer_frames && self.any() && !self.historical {
            return Err(
                "cooperation.align_peer_frames needs historical (variant dc-full-history): \
                 the peers' frames are measured from loop closures to their keyframe windows"
                    .into(),
            );
        }
        if let Some(s) = self.peer_frame_state_s {
            // `.inf` is allowed: held for the whole flight.
            if s.is_nan() || s < 0.0 {
                return Err(format!(
                    "cooperation.peer_frame_state_s must be at least 0 (or .inf), not {s}"
                ));
            }
        }
        let p = self.held_frame_measurement_period_s;
        if !(p.is_finite() && p >= 0.0) {
            return Err(format!(
                "cooperation.held_frame_measurement_period_s must be finite and at least 0, not {p}"
            ));
        }
        let w = self.held_frame_measurement_window_s;
        if w.is_nan() || w < 0.0 {
            return Err(format!(
                "cooperation.held_frame_measurement_window_s must be at least 0 (or .inf), not {w}"
            ));
        }
        let r = self.held_frame_measurements_per_s;
        if r.is_nan() || r <= 0.0 {
            return Err(format!(
                "cooperation.held_frame_measurements_per_s must be above 0 (or .inf), not {r}"
            ));
        }
        let g = self.held_frame_anchor_growth;
        if !(g.is_finite() && g >= 1.0) {
            return Err(format!(
                "cooperation.held_frame_anchor_growth must be finite and at least 1, not {g}"
            ));
        }
        if self.max_held_peer_frames == 0 {
            return Err("cooperation.max_held_peer_frames must be at least 1".into());
        }
        if self.min_alignment_inliers < 3 || self.alignment_confirmations == 0 {
            return Err(format!(
                "cooperation.min_alignment_inliers must be at least 3 and \
                 alignment_confirmations at least 1 (got {} and {})",
                self.min_alignment_inliers, self.alignment_confirmations
            ));
        }
        Ok(())
    }
}

/// Pixel noise of the SLAM updates for features tracked in images, px
/// ([`EstimatorOptions::for_tracked_images`]).
pub const TRACKED_SLAM_SIGMA_PX: f64 = 2.0;

/// Everything that configures one estimator.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct EstimatorOptions {
    /// Sliding window size (clones).
    pub max_clones: usize,
    /// Maximum SLAM features in the state (0: MSCKF only).
    pub max_slam_features: usize,
    /// Maximum SLAM features initialized per frame.
    pub max_slam_in_update: usize,
    /// No SLAM feature is initialized before the filter has run this long, s: the
    /// calibration converges first, so features are not frozen (FEJ) at positions
    /// biased by a wrong initial calibration (OpenVINS's `dt_slam_delay`).
    pub slam_delay_s: f64,
    /// No feature update before the window holds this many clones, counting the
    /// clone of the frame being processed; at most `max_clones + 1`, the count at
    /// which the oldest clone of a full window leaves (the default, 12 with 11
    /// clones). Measurements of the frames before are kept for the first update.
    ///
    /// Why wait for the oldest clone to leave and not OpenVINS's `min(max_clones,
    /// 5)`: an early update moves the state by what it learns (the gyro bias by
    /// 0.7 deg/s in one V1_02 run), and every clone taken after it keeps that
    /// estimate as its first estimate (FEJ) for a whole window; gyro bias and
    /// velocity NEES sat at 5-7 (ideal 3) from 1 to 3 s (V1_02, 60 seeds, measured
    /// at stop 17: 0.365 -> 0.292 deg with a full window). Why one frame more than
    /// a full window: at `max_clones` only the tracks lost meanwhile are
    /// candidates, short ones that barely triangulate on a slow start; on V1_01 it
    /// was often one to three features, and in seed 54 one feature turned pitch by
    /// 1.1 deg and left velocity 10 cm/s off. When the oldest clone leaves, the
    /// tracks spanning the window join them (30-40 features in most seeds; V1_01,
    /// seeds 21-60: 0.324 -> 0.299 deg with SLAM features, largest MSCKF-only run
    /// 1.93 -> 1.22 deg; README).
    pub min_clones_to_update: usize,
    /// Times the first MSCKF update is iterated (an iterated EKF: its features
    /// triangulated again at the updated clones, the system rebuilt there, the
    /// update redone from the prior; 0: one plain update). The first update
    /// comes after a whole window of flight on the start's errors alone; from a
    /// start tilted by a degree one step left a third of the tilt while the
    /// covariance claimed it gone (V1_02, 20 seeds: roll/pitch NEES 22.6 right
    /// after it, 0.897 deg / 0.134 m, NEES 6.31 / 12.30), and two iterations
    /// fix it (2.40 after it; 0.633 / 0.095, NEES 2.90 / 3.16) with the
    /// reference tables unchanged within seed noise (README).
    pub first_update_iterations: usize,
    /// Redo a first update whose step left its features' rays apart (fewer
    /// than half of them triangulate at the updated clones) from the prior,
    /// with Jacobians at the current estimate and looser ray limits, and reset
    /// the first estimates to its result. A start a few degrees off with a
    /// 0.02 rad/s gyro-bias error on a slow start bends the window so far that
    /// the step taken at the first estimates goes the wrong way (V1_01 from
    /// OpenVINS's prior, 20 seeds: 2 runs diverged, none with it; README).
    /// It only acts when that happens: every truth-start table is unchanged.
    pub rescue_first_update: bool,
    /// Pixels of rotation-compensated parallax (median over the shared tracks)
    /// the second-newest clone must have moved from the clone before it to stay
    /// in the window (while it fills too, so the first update has the keyframes'
    /// baseline); one that moved less leaves instead of the oldest, with its
    /// views unused (VINS-Mono's keyframe rule). 0: every clone stays and the
    /// oldest leaves (OpenVINS's window). On a slow flight a window of 11
    /// consecutive frames spans too little baseline to triangulate from: V1_01 at
    /// 0.3 of its speed diverged in 3 of 10 runs without SLAM features and 2 of
    /// 10 with them, and none with the camera at a third of its rate (README,
    /// Slow flights).
    pub keyframe_parallax_px: f64,
    /// A slow start's keyframe window, in pixels of parallax (0: off). When the
    /// first full window spans less than three times this much parallax and
    /// the first update would starve (fewer than one candidate in four passes
    /// the ray limits), the first update waits, up to 2.5 s, for the window to
    /// gain baseline, and from then on the window keeps keyframes of this
    /// parallax as with [`Self::keyframe_parallax_px`]; the late first update
    /// is one plain step (the iterated one if the wait ended still starved).
    /// A flight whose first window has parallax never waits: the reference
    /// trajectories from the truth are unchanged bit for bit. On V1_01 played at 0.3 of its speed the default window, whose
    /// first update took the few tracks that triangulated, diverged in 3 of 10
    /// runs without SLAM features and 2 of 10 with them (README, Slow flights).
    pub slow_start_keyframe_px: f64,
    /// Whether a platform found slow takes the settings for slow platforms by
    /// itself. A slow start (one whose first update waited, see
    /// [`Self::slow_start_keyframe_px`]) takes, besides its keyframe window,
    /// the MSCKF's and the SLAM features' Jacobians observability-constrained
    /// and new SLAM features as anchored inverse depths; a flight that turns
    /// slow later (its window spans under three keyframes' parallax for 4 s in
    /// a row) takes the constrained MSCKF Jacobians and the keyframe window
    /// (V1_02 at 0.3 of its speed without SLAM features, 10 seeds: 0.421 m,
    /// position NEES 12.8 without, 0.143 m, 2.11 with).
    /// With first estimates the clones of a slow flight are corrected long
    /// after they were cloned and the filter claims what it does not know:
    /// V1_01 played at 0.5 of its speed with SLAM features, 10 seeds, 0.475 deg /
    /// 0.061 m, position NEES 2.35 with the keyframe window alone, 0.225 deg /
    /// 0.033 m, NEES 0.39 with these too (README, A platform found slow
    /// takes the settings for slow platforms). A flight that is never found slow is
    /// unchanged bit for bit.
    pub slow_platform_settings: bool,
    /// Where the MSCKF's Jacobians are evaluated when `use_fej`: at the first
    /// estimates (default), or at the current estimate with the unobservable
    /// directions projected out. On a slowly starting circle without SLAM
    /// features (20 seeds from the truth) the first gives 0.414 m, position
    /// NEES 14.3, the second 0.231 m, NEES 1.46; on the reference trajectories
    /// both are within seed noise of each other (README).
    pub msckf_jacobians: MsckfJacobians,
    /// Where the SLAM features' Jacobians are evaluated when `use_fej`, in
    /// their updates and their delayed initialization: at the first estimates
    /// (default, OpenVINS), or at the current estimate with the unobservable
    /// directions projected out. On a slow flight the first estimates of the
    /// clones and features are far from the current ones and the filter claims
    /// a position it does not have: V1_01 at 0.3x with a keyframe window,
    /// inverse-depth features and constrained MSCKF Jacobians, 10 seeds,
    /// position NEES 14.6 with the first, 2.5 with the second (README, Slow
    /// flights). With 3-D points, constrained MSCKF Jacobians and no keyframe
    /// window it costs orientation at full speed (V1_01 0.230 -> 0.384 deg).
    pub slam_jacobians: MsckfJacobians,
    /// Global or anchored 3-D SLAM features.
    pub feature_representation: FeatureRepresentation,
    /// Maximum MSCKF features used per frame (the longest tracks first). A
    /// candidate that cannot be triangulated takes no place: with the window-spanning
    /// tracks that lack parallax retried every frame, counting them let the same
    /// hopeless tracks fill a cap of 10 frame after frame on V1_01 until the filter,
    /// starved, diverged (seed 15, MSCKF only: 27 deg / 1327 m; 0.22 deg / 0.08 m
    /// once they take no place).
    pub max_msckf_in_update: usize,
    /// First-Estimates Jacobians.
    pub use_fej: bool,
    /// Estimate the camera-IMU extrinsics.
    pub calib_extrinsics: bool,
    /// Estimate intrinsics and distortion.
    pub calib_intrinsics: bool,
    /// Estimate the camera-IMU time offset.
    pub calib_time_offset: bool,
    /// Zero-velocity updates when standing still.
    pub zero_velocity_update: bool,
    /// A standstill is also recognized from the images: the image's tracks
    /// moved less than this on average over at least 0.3 s, px (0: from the
    /// IMU alone; tracks that moved beyond `pixel_sigma_px` still refuse
    /// it). A real IMU at rest on a vehicle with running rotors or engines
    /// vibrates far beyond its datasheet noise and fails the IMU test
    /// (OpenVINS's `zupt_max_disparity`).
    pub zupt_max_disparity_px: f64,
    /// Pixel measurement noise, px.
    pub pixel_sigma_px: f64,
    /// Pixel noise of the updates of the SLAM features in the state, px
    /// (`None`: `pixel_sigma_px`; OpenVINS's `up_slam_sigma_px`). Their
    /// delayed initialization keeps `pixel_sigma_px`. A SLAM feature is
    /// tracked for as long as it stays in view, and an image tracker's error
    /// along a long track is not white noise that each update may trust
    /// afresh: on rendered EuRoC flights 2 px keeps 50 SLAM features
    /// consistent where 1 px does not, and is more accurate
    /// ([`EstimatorOptions::for_tracked_images`]).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub slam_pixel_sigma_px: Option<f64>,
    /// On a keyframe window (a slow start, a flight found slow, or
    /// `keyframe_parallax_px` set), a SLAM feature in the state takes a view
    /// only once its image point has moved the window's keyframe parallax
    /// since the last view it took (`agent::estimator::slam_pacing`). An image
    /// tracker's error persists from frame to frame, and a slow platform's
    /// frames would count it again at every frame: rendered V1_01 at 0.3 of
    /// its speed with SLAM features (seeds 1-8), orientation NEES 3.94 ->
    /// 3.04, lower in every seed. Off for simulated features, whose pixel
    /// noise is white and every frame new (the same flight simulated, 10
    /// seeds: 0.152 deg / 0.083 m -> 0.192 / 0.114 with it); on for tracked
    /// images ([`EstimatorOptions::for_tracked_images`]).
    #[serde(default)]
    pub slam_keyframe_updates: bool,
    /// Multiplier of the chi-square gate (1 = 95 % quantile).
    pub chi2_multiplier: f64,
    /// IMU noise model.
    pub imu: ImuNoise,
    /// Calibration priors.
    pub calib_prior: CalibrationPrior,
    /// Largest IMU gap accepted, s.
    pub max_imu_gap_s: f64,
    /// Which triangulated features are accepted.
    pub triangulation: TriangulationLimits,
    /// What is taken from peers.
    pub cooperation: CooperationOptions,
}

impl EstimatorOptions {
    /// The pixel noise of the SLAM features' updates, px.
    pub fn slam_sigma_px(&self) -> f64 {
        self.slam_pixel_sigma_px.unwrap_or(self.pixel_sigma_px)
    }

    /// Whether a peer's track gives a common SLAM update only its newest
    /// unused view (`cooperation.peer_slam_newest_view`, by default as
    /// `slam_keyframe_updates`: an image tracker's error persists).
    pub fn peer_slam_newest_view(&self) -> bool {
        self.cooperation
            .peer_slam_newest_view
            .unwrap_or(self.slam_keyframe_updates)
    }

    /// The defaults for features tracked in camera images (`agent dataset`,
    /// live sensors) rather than simulated with white pixel noise: SLAM
    /// updates at [`TRACKED_SLAM_SIGMA_PX`], paced on a keyframe window
    /// (`slam_keyframe_updates`). Nine rendered EuRoC flights
    /// replayed from a static start (V1_01-03, seeds 1-3, 50 SLAM features;
    /// docs/evidence/single_robot.md, stop 58): ATE 0.214 deg / 0.027 m,
    /// NEES 2.37 / 4.33 at 1 px; 0.203 / 0.024, NEES 1.81 / 2.36 at 2 px.
    pub fn for_tracked_images() -> Self {
        Self {
            slam_pixel_sigma_px: Some(TRACKED_SLAM_SIGMA_PX),
            slam_keyframe_updates: true,
            ..Self::default()
        }
    }

    /// Range checks, each error naming its key: a window of at least 2 clones (a
    /// feature needs two views), a positive pixel sigma and chi-square multiplier,
    /// non-negative noise densities and delays, positive calibration priors, and
    /// the triangulation limits. A zero pixel sigma divides by zero in every
    /// update; a window of 0 clones never triangulates and drifts unbounded.
    pub fn validate(&self) -> Result<(), String> {
        if self.max_clones < 2 {
            return Err(format!(
                "max_clones must be at least 2 (a feature needs two views), not {}",
                self.max_clones
            ));
        }
        if self.min_clones_to_update == 0 {
            return Err("min_clones_to_update must be at least 1".into());
        }
        let positive = [
            ("pixel_sigma_px", self.pixel_sigma_px),
            ("slam_pixel_sigma_px", self.slam_sigma_px()),
            ("chi2_multiplier", self.chi2_multiplier),
            ("max_imu_gap_s", self.max_imu_gap_s),
            ("imu.gravity_mps2", self.imu.gravity_mps2),
            ("calib_prior.time_offset_s", self.calib_prior.time_offset_s),
            (
                "calib_prior.extrinsic_rot_rad",
                self.calib_prior.extrinsic_rot_rad,
            ),
            (
                "calib_prior.extrinsic_pos_m",
                self.calib_prior.extrinsic_pos_m,
            ),
            ("calib_prior.intrinsics_px", self.calib_prior.intrinsics_px),
            ("calib_prior.distortion", self.calib_prior.distortion),
        ];
        for (name, v) in positive {
            if !(v.is_finite() && v > 0.0) {
                return Err(format!("{name} must be finite and positive, not {v}"));
            }
        }
        // Every snapshot declares it, and peers refuse a snapshot above this.
        let most = crate::messages::MAX_PIXEL_SIGMA_PX;
        if self.pixel_sigma_px > most {
            return Err(format!(
                "pixel_sigma_px must be at most {most} px (what a snapshot may declare), not {}",
                self.pixel_sigma_px
            ));
        }
        let non_negative = [
            ("slam_delay_s", self.slam_delay_s),
            ("keyframe_parallax_px", self.keyframe_parallax_px),
            ("slow_start_keyframe_px", self.slow_start_keyframe_px),
            ("zupt_max_disparity_px", self.zupt_max_disparity_px),
            ("imu.gyro_noise_density", self.imu.gyro_noise_density),
            ("imu.gyro_random_walk", self.imu.gyro_random_walk),
            ("imu.accel_noise_density", self.imu.accel_noise_density),
            ("imu.accel_random_walk", self.imu.accel_random_walk),
        ];
        for (name, v) in non_negative {
            if !(v.is_finite() && v >= 0.0) {
                return Err(format!("{name} must be finite and at least 0, not {v}"));
            }
        }
        self.cooperation.validate()?;
        self.triangulation.validate()
    }

    /// Whether a window of `clones` clones (the newest included) may be updated:
    /// [`Self::min_clones_to_update`], or `max_clones + 1` when that is smaller.
    pub fn window_ready(&self, clones: usize) -> bool {
        clones >= self.min_clones_to_update.min(self.max_clones + 1)
    }
}

impl Default for EstimatorOptions {
    fn default() -> Self {
        Self {
            max_clones: 11,
            max_slam_features: 50,
            max_slam_in_update: 25,
            slam_delay_s: 2.0,
            min_clones_to_update: 12,
            first_update_iterations: 2,
            rescue_first_update: true,
            keyframe_parallax_px: 0.0,
            slow_start_keyframe_px: 4.0,
            slow_platform_settings: true,
            msckf_jacobians: MsckfJacobians::default(),
            slam_jacobians: MsckfJacobians::default(),
            feature_representation: Default::default(),
            max_msckf_in_update: 40,
            use_fej: true,
            calib_extrinsics: true,
            calib_intrinsics: true,
            calib_time_offset: true,
            // On by default: it never fired on the moving V1_01 flight (10 seeds,
            // identical results) and keeps a robot that stops from diverging.
            zero_velocity_update: true,
            // Below the simulator's pixel noise (1 px gives a standing robot's
            // tracks an expected mean disparity of √π ≈ 1.8 px), so feature-level runs find
            // standstills by the IMU; KLT tracks at rest pass it (EuRoC V1_01
            // micro: 45 of 58 frames; rendered: 94 of 95 standing frames).
            zupt_max_disparity_px: 1.0,
            pixel_sigma_px: 1.0,
            slam_pixel_sigma_px: None,
            slam_keyframe_updates: false,
            chi2_multiplier: 1.0,
            imu: ImuNoise::default(),
            calib_prior: CalibrationPrior::default(),
            max_imu_gap_s: 0.1,
            triangulation: TriangulationLimits::default(),
            cooperation: CooperationOptions::default(),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn triangulation_limits_reject_nonsense_with_the_key() {
        assert!(TriangulationLimits::default().validate().is_ok());
        let bad = |f: fn(&mut TriangulationLimits)| {
            let mut l = TriangulationLimits::default();
            f(&mut l);
            l.validate().expect_err("accepted")
        };
        assert!(bad(|l| l.max_condition_number = f64::NAN).contains("max_condition_number"));
        assert!(bad(|l| l.max_condition_number = 0.5).contains("exceed 1"));
        assert!(bad(|l| l.min_depth_m = -1.0).contains("min_depth_m"));
        assert!(bad(|l| l.max_depth_m = 0.05).contains("below max_depth_m"));
        assert!(bad(|l| l.max_baseline_ratio = f64::INFINITY).contains("max_baseline_ratio"));
    }

    #[test]
    fn options_that_cannot_run_are_named() {
        assert!(EstimatorOptions::default().validate().is_ok());
        let bad = |f: fn(&mut EstimatorOptions)| {
            let mut o = EstimatorOptions::default();
            f(&mut o);
            o.validate().unwrap_err()
        };
        assert!(bad(|o| o.max_clones = 0).contains("max_clones"));
        assert!(bad(|o| o.max_clones = 1).contains("two views"));
        assert!(bad(|o| o.pixel_sigma_px = 0.0).contains("pixel_sigma_px"));
        assert!(bad(|o| o.pixel_sigma_px = 101.0).contains("at most 100 px"));
        assert!(bad(|o| o.slam_pixel_sigma_px = Some(-1.0)).contains("slam_pixel_sigma_px"));
        assert!(bad(|o| o.chi2_multiplier = f64::NAN).contains("chi2_multiplier"));
        assert!(bad(|o| o.slam_delay_s = -1.0).contains("slam_delay_s"));
        assert!(bad(|o| o.imu.gyro_noise_density = -1e-4).contains("gyro_noise_density"));
        assert!(bad(|o| o.calib_prior.intrinsics_px = 0.0).contains("intrinsics_px"));
        assert!(bad(|o| o.triangulation.min_depth_m = -1.0).contains("min_depth_m"));
        assert!(bad(|o| o.cooperation.ci_peer_weight = 0.0).contains("ci_peer_weight"));
        assert!(bad(|o| o.cooperation.ci_own_weight = 1.0).contains("ci_own_weight"));
        assert!(bad(|o| o.cooperation.constraint_peer_weight = f64::NAN)
            .contains("constraint_peer_weight"));
        assert!(bad(|o| o.cooperation.constraint_sigma_m = 0.0).contains("constraint_sigma_m"));
        assert!(bad(|o| o.cooperation.epipolar_threshold_px = -2.0).contains("epipolar"));
        assert!(bad(|o| o.cooperation.max_window_age_s = f64::INFINITY).contains("window_age"));
        assert!(bad(|o| o.cooperation.match_ratio = 0.0).contains("match_ratio"));
        assert!(bad(|o| o.cooperation.loop_min_score = 1.5).contains("loop_min_score"));
        assert!(bad(|o| o.cooperation.max_descriptor_distance_bits = 257)
            .contains("max_descriptor_distance_bits"));
        assert!(bad(|o| o.cooperation.min_loop_inliers = 8).contains("min_loop_inliers"));
        assert!(bad(|o| o.cooperation.min_window_inliers = 0).contains("min_window_inliers"));
        assert!(bad(|o| o.cooperation.loop_candidates = 0).contains("loop_candidates"));
        assert!(bad(|o| {
            o.cooperation.align_peer_frames = true;
            o.cooperation.common_vio = true;
        })
        .contains("needs historical"));
        assert!(bad(|o| o.cooperation.alignment_confirmations = 0).contains("confirmations"));
        assert!(
            bad(|o| o.cooperation.peer_frame_state_s = Some(-1.0)).contains("peer_frame_state_s")
        );
        assert!(bad(|o| o.cooperation.peer_frame_state_s = Some(f64::NAN))
            .contains("peer_frame_state_s"));
        assert!(bad(|o| o.cooperation.max_held_peer_frames = 0).contains("max_held_peer_frames"));
        assert!(
            bad(|o| o.cooperation.held_frame_measurement_period_s = f64::NAN)
                .contains("held_frame_measurement_period_s")
        );
        assert!(
            bad(|o| o.cooperation.held_frame_measurement_window_s = -1.0)
                .contains("held_frame_measurement_window_s")
        );
        assert!(bad(|o| o.cooperation.held_frame_measurements_per_s = 0.0)
            .contains("held_frame_measurements_per_s"));
        assert!(bad(|o| o.cooperation.held_frame_anchor_growth = 0.5)
            .contains("held_frame_anchor_growth"));
        assert!(
            bad(|o| o.cooperation.held_frame_anchor_growth = f64::INFINITY)
                .contains("held_frame_anchor_growth")
        );
        assert!(bad(|o| o.cooperation.max_alignment_yaw_sigma_deg = 0.0).contains("yaw_sigma"));
        assert!(bad(|o| o.cooperation.max_ci_participants = 0).contains("max_ci_participants"));
        assert!(bad(|o| o.cooperation.max_peers_matched_per_frame = 0)
            .contains("max_peers_matched_per_frame"));
        let noise_free_imu = EstimatorOptions {
            imu: ImuNoise {
                gyro_noise_density: 0.0,
                ..ImuNoise::default()
            },
            ..EstimatorOptions::default()
        };
        assert!(noise_free_imu.validate().is_ok());
    }

    #[test]
    fn the_window_is_ready_when_its_oldest_clone_leaves_or_at_the_chosen_count() {
        let o = EstimatorOptions::default();
        assert!(!o.window_ready(o.max_clones));
        assert!(o.window_ready(o.max_clones + 1));
        let five = EstimatorOptions {
            min_clones_to_update: 5,
            ..o.clone()
        };
        assert!(!five.window_ready(4));
        assert!(five.window_ready(5));
        // A count beyond the window waits only for the oldest clone to leave.
        let small = EstimatorOptions { max_clones: 3, ..o };
        assert!(!small.window_ready(3));
        assert!(small.window_ready(4));
    }

    #[test]
    fn a_peer_frame_is_held_by_the_weighting_unless_named() {
        let mut c = CooperationOptions::default();
        assert_eq!(c.ci_weighting, CiWeighting::MinPoseTrace);
        assert_eq!(c.peer_frame_hold_s(), f64::INFINITY);
        c.ci_weighting = CiWeighting::FixedPeer;
        assert_eq!(c.peer_frame_hold_s(), FIXED_WEIGHT_FRAME_HOLD_S);
        c.peer_frame_state_s = Some(0.0);
        assert_eq!(c.peer_frame_hold_s(), 0.0);
        // `.inf` in YAML: the whole flight, and valid.
        let o: CooperationOptions =
            serde_yaml::from_str("peer_frame_state_s: .inf").expect("parses");
        assert_eq!(o.peer_frame_state_s, Some(f64::INFINITY));
        let e = EstimatorOptions {
            cooperation: o,
            ..EstimatorOptions::default()
        };
        assert!(e.validate().is_ok());
    }
}
