//! [`Estimator`]: the per-robot filter as a state machine. IMU samples and feature
//! frames go in (validated; bad input is rejected with a reason and changes
//! nothing); after each processed frame the estimate and its covariance come out.

use super::camera_window::{camera_estimate, camera_window, CameraWindow};
use super::chi2::Chi2Table;
use super::cooperative::{self, frame_features, CoopFrameStats};
use super::feature_classes::{
    classify, clean_up, drop_non_keyframe, record_measurements, FeatureClasses,
};
use super::feature_db::FeatureDb;
use super::filter::Filter;
use super::frame_output::{cpu_ms, GyroAtFrame, ImuCovariance};
pub use super::frame_output::{FrameOutput, FrameRecord, FrameTiming};
pub use super::inputs::InputError;
use super::inputs::{check_frame, check_imu};
use super::options::EstimatorOptions;
use super::peer_frame_states;
use super::propagator::{gyro_at_frame, propagate, PropagateError};
use super::slam_pacing::SlamPacing;
use super::slow_start::SlowStart;
use super::state::{ClonePose, ImuState, State, Var};
use super::static_init::{static_initialize, StaticInitError, StaticInitOptions, StaticInitResult};
use super::triangulation::TriangulationOptions;
use super::updater_frame;
use super::{updater_msckf, updater_slam, updater_zupt};
use crate::cooperation::{Cooperation, Peers};
use common::calibration::CameraCalibration;
use common::measurement::{FeatureFrame, ImuSample};
use nalgebra::{DMatrix, Matrix3, Vector3};
use std::collections::VecDeque;
use std::sync::Arc;
use std::time::Instant;
use thiserror::Error;
use vocabulary::Vocabulary;

/// Why a queued frame could not be processed (it is dropped).
#[derive(Debug, Error, PartialEq)]
pub enum FrameError {
    /// Propagation failed.
    #[error(transparent)]
    Propagate(#[from] PropagateError),
    /// The filter is not initialized yet.
    #[error("frame at t={0} arrived before initialization")]
    NotInitialized(f64),
}

/// The initial state and its standard deviations.
#[derive(Clone, Debug)]
pub struct InitialState {
    /// IMU time, s.
    pub t: f64,
    /// `R_ItoG`.
    pub rot: Matrix3<f64>,
    /// `p_IinG`, m.
    pub pos: Vector3<f64>,
    /// `v_IinG`, m/s.
    pub vel: Vector3<f64>,
    /// Gyroscope bias, rad/s.
    pub bias_gyro: Vector3<f64>,
    /// Accelerometer bias, m/s².
    pub bias_accel: Vector3<f64>,
    /// Orientation σ, rad (each axis).
    pub sigma_ori_rad: f64,
    /// σ of the heading alone (about the vertical), rad, when it is known
    /// better or worse than the tilt: a robot whose start defines its frame
    /// knows its heading exactly, while gravity gives its tilt only so well.
    /// `None`: `sigma_ori_rad`.
    pub sigma_yaw_rad: Option<f64>,
    /// Position σ, m.
    pub sigma_pos_m: f64,
    /// Velocity σ, m/s.
    pub sigma_vel_mps: f64,
    /// Gyroscope bias σ, rad/s.
    pub sigma_bias_gyro: f64,
    /// Accelerometer bias σ, m/s².
    pub sigma_bias_accel: f64,
}

/// The single-robot filter.
#[derive(Debug)]
pub struct Estimator {
    opts: EstimatorOptions,
    calib: CameraCalibration,
    state: Option<State>,
    imu: VecDeque<ImuSample>,
    frames: VecDeque<FeatureFrame>,
    features: FeatureDb,
    seq: u64,
    last_frame_t: Option<f64>,
    /// IMU time the filter started at.
    start_t: f64,
    chi2: Chi2Table,
    tri: TriangulationOptions,
    /// What is taken from peers (when the options ask for anything).
    coop: Option<Cooperation>,
    vocabulary: Option<Arc<Vocabulary>>,
    /// Whether an MSCKF update has run (the first one is iterated).
    updated_once: bool,
    /// Whether the first update waited for parallax (a slow start).
    slow_start: SlowStart,
    /// Which SLAM features take a view on a keyframe window (`slam_pacing`).
    slam_pacing: SlamPacing,
}

fn ms(since: Instant) -> f64 {
    since.elapsed().as_secs_f64() * 1e3
}

impl Estimator {
    /// A filter with options and the initial calibration guess.
    pub fn new(opts: EstimatorOptions, calib: CameraCalibration) -> Self {
        let tri = TriangulationOptions::for_camera(&opts.triangulation, &calib.camera);
        Self {
            opts,
            calib,
            state: None,
            imu: VecDeque::new(),
            frames: VecDeque::new(),
            features: FeatureDb::default(),
            seq: 0,
            last_frame_t: None,
            start_t: 0.0,
            chi2: Chi2Table::new(0.95, 1000),
            tri,
            coop: None,
            vocabulary: None,
            updated_once: false,
            slow_start: SlowStart::default(),
            slam_pacing: SlamPacing::default(),
        }
    }

    /// The vocabulary for historical loop closures (set before initializing).
    pub fn set_vocabulary(&mut self, vocabulary: Option<Arc<Vocabulary>>) {
        self.vocabulary = vocabulary;
    }

    /// The cooperation state, when the options take anything from peers.
    pub fn cooperation(&self) -> Option<&Cooperation> {
        self.coop.as_ref()
    }

    /// The options.
    pub fn options(&self) -> &EstimatorOptions {
        &self.opts
    }

    /// The state, once initialized.
    pub fn state(&self) -> Option<&State> {
        self.state.as_ref()
    }

    /// The sliding window as peers see it (camera poses, joint covariance, and the
    /// SLAM features when `with_landmarks`), once initialized.
    pub fn camera_window(&self, with_landmarks: bool) -> Option<CameraWindow> {
        self.state
            .as_ref()
            .map(|s| camera_window(s, with_landmarks))
    }

    /// The calibration in use: the state's estimate once initialized, the initial
    /// guess before.
    pub fn calibration(&self) -> &CameraCalibration {
        self.state.as_ref().map(|s| &s.calib).unwrap_or(&self.calib)
    }

    /// Starts the filter at a given state (e.g. ground truth in simulation, or the
    /// static initializer's result) with a diagonal prior covariance.
    pub fn initialize(&mut self, init: &InitialState) {
        let mut blocks = initial_blocks(&self.opts, init);
        let imu_cov = blocks.remove(0).1;
        let imu = ImuState {
            rot: init.rot,
            pos: init.pos,
            vel: init.vel,
            bias_gyro: init.bias_gyro,
            bias_accel: init.bias_accel,
        };
        self.start_t = init.t;
        self.coop = self.opts.cooperation.any().then(|| {
            let k = &self.calib.camera.intrinsics;
            let mut c = self.opts.cooperation.clone();
            c.peer_slam_newest_view = Some(self.opts.peer_slam_newest_view());
            Cooperation::new(c, self.vocabulary.clone(), (k[0] * k[1]).abs().sqrt())
        });
        self.state = Some(State::new(
            init.t,
            imu,
            imu_cov,
            self.calib.clone(),
            &blocks,
        ));
        // Frames before the start are not used.
        self.frames
            .retain(|f| f.t + self.calib.time_offset_s > init.t);
    }

    /// Starts the filter from the IMU buffer with the static initializer (thesis
    /// Eqs. 2.78-2.81): the robot must have stood still for the last
    /// `init.window_s` seconds. Position is the origin, velocity zero, gravity sets
    /// roll and pitch, the mean gyro reading the gyro bias; `sigmas` gives the prior
    /// standard deviations (its time and mean fields are ignored), but the gyro
    /// bias's is at most the window's standard error of it
    /// ([`StaticInitResult::bias_gyro_sigma`]), and at least the gyro's white
    /// noise over the window. Returns the
    /// initializer's result; on error nothing changes.
    pub fn initialize_static(
        &mut self,
        init: &StaticInitOptions,
        sigmas: &InitialState,
    ) -> Result<StaticInitResult, StaticInitError> {
        self.initialize_static_placed(init, sigmas, None)
    }

    /// [`Self::initialize_static`] with the start placed in a frame that is
    /// not the start's own (a fleet's): there, the IMU's axis `axis_i` (a
    /// unit vector in the IMU's frame) has the heading `yaw_rad` (projected
    /// on the horizontal plane, from the frame's `x` towards its `y`), and
    /// the IMU is at `pos`. Take an axis far from the vertical: a tilt error
    /// turns an axis at elevation `e` by about `tilt / cos(e)` in heading.
    /// The result's `rot_i_to_g` stays in the initializer's convention.
    pub fn initialize_static_at(
        &mut self,
        init: &StaticInitOptions,
        sigmas: &InitialState,
        axis_i: &Vector3<f64>,
        yaw_rad: f64,
        pos: Vector3<f64>,
    ) -> Result<StaticInitResult, StaticInitError> {
        self.initialize_static_placed(init, sigmas, Some((axis_i, yaw_rad, pos)))
    }

    fn initialize_static_placed(
        &mut self,
        init: &StaticInitOptions,
        sigmas: &InitialState,
        place: Option<(&Vector3<f64>, f64, Vector3<f64>)>,
    ) -> Result<StaticInitResult, StaticInitError> {
        let samples = self.imu.make_contiguous();
        let res = static_initialize(samples, init)?;
        let (rot, pos) = match place {
            // Turning the orientation about the vertical by the difference
            // of headings gives the axis the heading asked for.
            Some((axis_i, yaw, pos)) => {
                let r = &res.rot_i_to_g;
                let a = r * axis_i;
                let turn = yaw - a.y.atan2(a.x);
                (
                    nalgebra::Rotation3::from_axis_angle(&Vector3::z_axis(), turn).into_inner() * r,
                    pos,
                )
            }
            None => (res.rot_i_to_g, Vector3::zeros()),
        };
        self.initialize(&InitialState {
            t: res.t,
            rot,
            pos,
            vel: res.velocity,
            bias_gyro: res.bias_gyro,
            bias_accel: res.bias_accel,
            // The window measured the gyro bias this well; a looser prior
            // lets the first zero-velocity update, 0.1 s of readings, take a
            // slow wobble for bias (a rendered V1_03 start: 0.008 rad/s off,
            // and the orientation drifted 0.3 deg/s while standing). Never
            // below what the gyro's white noise allows over the window (a
            // noise-free IMU would otherwise claim the bias exactly).
            sigma_bias_gyro: sigmas
                .sigma_bias_gyro
                .min(res.bias_gyro_sigma)
                .max(self.opts.imu.gyro_noise_density / init.window_s.sqrt()),
            ..sigmas.clone()
        });
        Ok(res)
    }

    /// Adds an IMU sample (rejects NaN, time going backwards and gaps).
    pub fn feed_imu(&mut self, s: ImuSample) -> Result<(), InputError> {
        check_imu(self.imu.back(), &s, self.opts.max_imu_gap_s)?;
        self.imu.push_back(s);
        Ok(())
    }

    /// Queues a feature frame (validated); it is processed by [`Estimator::poll`]
    /// once the IMU covers its time.
    pub fn feed_frame(&mut self, frame: FeatureFrame) -> Result<(), InputError> {
        check_frame(
            self.frames.back().map(|f| f.t).or(self.last_frame_t),
            &frame,
        )?;
        self.frames.push_back(frame);
        Ok(())
    }

    /// Processes every queued frame whose IMU time the IMU buffer covers, alone.
    pub fn poll(&mut self) -> Vec<Result<FrameOutput, FrameError>> {
        self.poll_with(&Peers::new())
    }

    /// Processes every queued frame whose IMU time the IMU buffer covers, with
    /// what the peers have sent so far.
    pub fn poll_with(&mut self, peers: &Peers) -> Vec<Result<FrameOutput, FrameError>> {
        let mut out = Vec::new();
        while let Some(front) = self.frames.front() {
            let td = self
                .state
                .as_ref()
                .map(|s| s.calib.time_offset_s)
                .unwrap_or(self.calib.time_offset_s);
            let t_imu = front.t + td;
            let covered = self.imu.back().is_some_and(|s| s.t >= t_imu);
            if !covered {
                break;
            }
            let Some(frame) = self.frames.pop_front() else {
                break;
            };
            self.last_frame_t = Some(frame.t);
            if self.state.is_none() {
                out.push(Err(FrameError::NotInitialized(frame.t)));
                continue;
            }
            out.push(self.process_frame(&frame, peers));
        }
        out
    }

    /// The flow of one camera frame: propagate and clone, match with the peers,
    /// sort the features into classes, update each class, marginalize.
    fn process_frame(
        &mut self,
        frame: &FeatureFrame,
        peers: &Peers,
    ) -> Result<FrameOutput, FrameError> {
        let t_start = Instant::now();
        let cpu_start = cpu_time::ThreadTime::try_now().ok();
        let mut timing = FrameTiming::default();
        let mut opts = self.opts.clone();
        // After a slow start the window keeps keyframes, and the settings for
        // slow platforms hold (`slow_start`).
        self.slow_start.apply(&mut opts);
        let Some(state) = self.state.as_mut() else {
            return Err(FrameError::NotInitialized(frame.t));
        };

        // 1. Propagate to the image's IMU time and clone the pose there.
        let t_imu = frame.t + state.calib.time_offset_s;
        if t_imu <= state.t {
            return Err(FrameError::Propagate(PropagateError::Backwards {
                from: state.t,
                to: t_imu,
            }));
        }
        let t_prev = state.t;
        let buf = self.imu.make_contiguous();
        let omega = propagate(state, buf, t_imu, &opts.imu, opts.use_fej)?;
        let gyro = gyro_at_frame(buf, t_prev, t_imu, &opts.imu);
        // A standstill: the zero-velocity update replaces this frame's visual update
        // (no parallax to gain, and no clone to spend).
        if opts.zero_velocity_update {
            let readings: Vec<ImuSample> = buf
                .iter()
                .filter(|s| s.t > t_prev && s.t <= t_imu)
                .copied()
                .collect();
            // Asked only when the robot is slow: a moving robot's frames never
            // pay for the track lookups.
            let images = updater_zupt::image_motion(&state.means, frame, &self.features);
            if updater_zupt::try_update(state, &readings, &opts, &self.chi2, images) {
                timing.propagate_ms = ms(t_start);
                timing.total_ms = timing.propagate_ms;
                timing.cpu_ms = cpu_ms(cpu_start);
                return Ok(output_without_updates(
                    state,
                    &gyro,
                    timing,
                    Default::default(),
                    true,
                ));
            }
        }
        self.seq += 1;
        let key = self.seq;
        augment_clone(state, key, frame.t, &omega);
        timing.propagate_ms = ms(t_start);

        // 2. Record the measurements; 3. link them to the peers' tracks.
        record_measurements(&mut self.features, state, frame, key);
        let mut coop = CoopFrameStats::default();
        let t = Instant::now();
        if let Some(c) = self.coop.as_mut() {
            let mut ours = frame_features(frame, &self.features, key);
            if c.aligns_peer_frames() {
                ours.camera = camera_estimate(state, key);
                ours.sigma_normalized = updater_msckf::ray_noise_rad(state, &opts);
                ours.pixel_sigma_px = opts.pixel_sigma_px;
            }
            c.match_frame(&ours, peers, key);
            peer_frame_states::take_from(state, c, &opts.cooperation);
            for m in c.take_held_frame_measurements() {
                if let Err(e) = updater_frame::update(state, &m, &opts.cooperation) {
                    tracing::warn!(peer = m.peer, "peer frame measurement not used: {e}");
                }
            }
        }
        coop.matching_ms = ms(t);
        if !opts.window_ready(state.clones.len()) {
            // Too few views to triangulate: keep every track for the first update.
            drop_non_keyframe(&mut self.features, state, opts.keyframe_parallax_px);
            timing.total_ms = ms(t_start);
            timing.cpu_ms = cpu_ms(cpu_start);
            return Ok(output_without_updates(state, &gyro, timing, coop, false));
        }

        // A flight that turns slow takes the constrained MSCKF and the keyframe
        // window from the next frame on (`slow_start`).
        if self.updated_once {
            self.slow_start
                .observe_window(&state.means, &self.features, &opts);
        }
        // 4. Sort the features into classes, with the peers' evidence for ours.
        let slam_allowed = state.t - self.start_t >= opts.slam_delay_s;
        let mut classes = classify(&self.features, state, key, &opts, slam_allowed);
        // A slow start: the first update waits for the window to gain parallax,
        // its candidates kept for it.
        if !self.updated_once
            && self.slow_start.first_update_waits(
                state,
                &self.features,
                &classes.candidates(),
                &opts,
                &self.chi2,
                &self.tri,
            )
        {
            classes.keep_all_candidates();
            clean_up(&mut self.features, state, &classes, opts.max_clones);
            timing.total_ms = ms(t_start);
            timing.cpu_ms = cpu_ms(cpu_start);
            return Ok(output_without_updates(state, &gyro, timing, coop, false));
        }
        let FeatureClasses {
            slam_seen,
            slam_candidates,
            msckf_ids,
            ..
        } = &classes;
        let slam_ids: Vec<u64> = state.features.keys().copied().collect();
        let t = Instant::now();
        let ev = self
            .coop
            .as_mut()
            .map(|c| {
                c.set_state_frames(peer_frame_states::held(state));
                c.evidence(msckf_ids, &slam_ids, peers)
            })
            .unwrap_or_default();
        coop.evidence_ms = ms(t);

        // 5. MSCKF update with the independent VIO features.
        let t = Instant::now();
        let common: Vec<u64> = ev.vio.iter().map(|c| c.id).collect();
        let independent: Vec<u64> = msckf_ids
            .iter()
            .copied()
            .filter(|id| !common.contains(id))
            .collect();
        let mut untriangulated = Vec::new();
        // The filter's first update is iterated (`first_update_iterations`).
        // One that waited for parallax is one plain step (`slow_start`).
        let iterations = if self.updated_once || self.slow_start.plain_first_update() {
            0
        } else {
            opts.first_update_iterations
        };
        let (mut msckf, tried) = updater_msckf::iterated_update_up_to(
            state,
            &self.features,
            &independent,
            opts.max_msckf_in_update,
            &opts,
            &self.chi2,
            &self.tri,
            &mut untriangulated,
            iterations,
        );
        self.updated_once |= msckf.used > 0;

        timing.msckf_ms = ms(t);

        // 6. SLAM update with the features seen now (on a keyframe window of
        //    tracked images, those whose view moved: `slam_pacing`).
        let t = Instant::now();
        let mut slam = updater_slam::SlamStats::default();
        let slam_due =
            self.slam_pacing
                .due_in_frame(&self.features, &state.means, slam_seen, key, &opts);
        updater_slam::update(
            state,
            &self.features,
            slam_due.as_deref().unwrap_or(slam_seen),
            key,
            &opts,
            &self.chi2,
            &mut slam,
        );
        timing.slam_update_ms = ms(t);

        // 7. What the peers saw: common VIO and SLAM features, SLAM constraints,
        //    in one CI-EKF update; common tracks it could not use go to the MSCKF.
        let used = cooperative::update(
            state,
            &self.features,
            &ev,
            &opts,
            &self.chi2,
            &self.tri,
            &mut coop,
        );
        if !used.vio_fallback.is_empty() {
            let fallback = updater_msckf::update(
                state,
                &self.features,
                &used.vio_fallback,
                &opts,
                &self.chi2,
                &self.tri,
            );
            msckf.used += fallback.used;
            msckf.rejected_chi2 += fallback.rejected_chi2;
            msckf.failed += fallback.failed;
        }

        // 8. Delayed initialization of new SLAM features.
        let t = Instant::now();
        updater_slam::initialize_candidates(
            state,
            &self.features,
            slam_candidates,
            |id| independent.contains(&id) || common.contains(&id),
            &opts,
            &self.chi2,
            &self.tri,
            &mut slam,
            &mut untriangulated,
        );
        timing.slam_init_ms = ms(t);

        // 9. Clean up: used and lost features, lost SLAM features, oldest clone,
        //    the links of ended tracks; the peers' measurements used are marked.
        let t = Instant::now();
        // The common tracks went to the cooperative update (or its MSCKF fallback)
        // even when beyond the cap: none is kept for later.
        classes.mark_used(&common);
        classes.defer(independent.get(tried..).unwrap_or_default());
        classes.retry_untriangulated(&self.features, key, &untriangulated);
        clean_up(&mut self.features, state, &classes, opts.max_clones);
        if let Some(c) = self.coop.as_mut() {
            cooperative::finish(c, &ev, &used, &mut coop);
            let (db, st) = (&self.features, &*state);
            c.retain_tracks(|id| db.contains(id) || st.features.contains_key(&id), peers);
        }
        // IMU readings older than the state are no longer needed.
        while self.imu.len() > 2 && self.imu[1].t < state.t {
            self.imu.pop_front();
        }
        timing.marginalize_ms = ms(t);
        timing.total_ms = ms(t_start);
        timing.cpu_ms = cpu_ms(cpu_start);

        timing.cooperation_ms = coop.matching_ms
            + coop.evidence_ms
            + coop.common_vio_ms
            + coop.common_slam_ms
            + coop.constraint_ms
            + coop.ci_update_ms;
        Ok(output(state, &gyro, timing, msckf, slam, coop, false))
    }
}

/// The prior blocks of a filter started at `init`: the IMU (15, first), then the
/// calibration variables the options estimate, with their prior covariances.
pub(crate) fn initial_blocks(
    opts: &EstimatorOptions,
    init: &InitialState,
) -> Vec<(Var, DMatrix<f64>)> {
    let mut cov = DMatrix::zeros(15, 15);
    let sig = [
        init.sigma_ori_rad,
        init.sigma_pos_m,
        init.sigma_vel_mps,
        init.sigma_bias_gyro,
        init.sigma_bias_accel,
    ];
    for (b, s) in sig.iter().enumerate() {
        for i in 0..3 {
            cov[(3 * b + i, 3 * b + i)] = s * s;
        }
    }
    if let Some(yaw) = init.sigma_yaw_rad {
        // The σ are of the global axes, the error is local (R = R̂ Exp(δθ):
        // δθ_G = R̂ δθ), so the block is R̂ᵀ diag(σ², σ², σ_ψ²) R̂.
        let s2 = init.sigma_ori_rad.powi(2);
        let global = Matrix3::from_diagonal(&Vector3::new(s2, s2, yaw * yaw));
        let local = init.rot.transpose() * global * init.rot;
        cov.view_mut((0, 0), (3, 3)).copy_from(&local);
    }
    let mut blocks = vec![(Var::Imu, cov)];
    let p = &opts.calib_prior;
    if opts.calib_time_offset {
        blocks.push((
            Var::TimeOffset,
            DMatrix::from_element(1, 1, p.time_offset_s.powi(2)),
        ));
    }
    if opts.calib_extrinsics {
        let mut c = DMatrix::zeros(6, 6);
        for i in 0..3 {
            c[(i, i)] = p.extrinsic_rot_rad.powi(2);
            c[(3 + i, 3 + i)] = p.extrinsic_pos_m.powi(2);
        }
        blocks.push((Var::Extrinsic, c));
    }
    if opts.calib_intrinsics {
        let mut c = DMatrix::zeros(8, 8);
        for i in 0..4 {
            c[(i, i)] = p.intrinsics_px.powi(2);
            c[(4 + i, 4 + i)] = p.distortion.powi(2);
        }
        blocks.push((Var::Intrinsics, c));
    }
    blocks
}

/// [`output`] of a frame that updated nothing (a standstill, or a window still
/// filling).
fn output_without_updates(
    state: &State,
    gyro: &GyroAtFrame,
    timing: FrameTiming,
    coop: CoopFrameStats,
    zero_velocity: bool,
) -> FrameOutput {
    output(
        state,
        gyro,
        timing,
        Default::default(),
        Default::default(),
        coop,
        zero_velocity,
    )
}

/// The estimate and its marginal covariances after a frame.
fn output(
    state: &State,
    gyro: &GyroAtFrame,
    timing: FrameTiming,
    msckf: updater_msckf::MsckfStats,
    slam: updater_slam::SlamStats,
    coop: CoopFrameStats,
    zero_velocity: bool,
) -> FrameOutput {
    let p = state.cov();
    let o = state.offset(Var::Imu).unwrap_or(0);
    let cov_imu: ImuCovariance = p.fixed_view::<15, 15>(o, o).into_owned();
    FrameOutput::of(
        state,
        &cov_imu,
        gyro,
        timing,
        (msckf, slam, coop),
        zero_velocity,
    )
}

/// Stochastic cloning of the IMU pose at the image time; with online time-offset
/// calibration the clone also depends on `t_d` through `[ω; v]` (the pose moves
/// with the estimated offset).
pub(crate) fn augment_clone<F: Filter + ?Sized>(
    filter: &mut F,
    key: u64,
    t_cam: f64,
    omega: &Vector3<f64>,
) {
    let mut j_imu = DMatrix::zeros(6, 15);
    j_imu.view_mut((0, 0), (6, 6)).fill_with_identity();
    let mut jac = vec![(Var::Imu, j_imu)];
    if filter.has(Var::TimeOffset) {
        let mut j_td = DMatrix::zeros(6, 1);
        j_td.view_mut((0, 0), (3, 1)).copy_from(omega);
        j_td.view_mut((3, 0), (3, 1))
            .copy_from(&filter.means().imu.vel);
        jac.push((Var::TimeOffset, j_td));
    }
    if filter
        .augment(Var::Clone(key), &jac, &DMatrix::zeros(6, 6))
        .is_ok()
    {
        let state = filter.means_mut();
        state.clones.insert(
            key,
            ClonePose {
                t: state.t,
                t_cam,
                rot: state.imu.rot,
                pos: state.imu.pos,
                rot_fej: state.imu.rot,
                pos_fej: state.imu.pos,
            },
        );
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_heading_sigma_of_its_own_holds_in_the_global_axes() {
        // A tilted, turned IMU: its local axes are none of the global ones.
        let rot = *nalgebra::Rotation3::from_euler_angles(0.3, -0.2, 1.1).matrix();
        let init = InitialState {
            rot,
            sigma_ori_rad: 0.01,
            sigma_yaw_rad: Some(0.001),
            ..crate::estimator::static_init::static_start_sigmas()
        };
        let blocks = initial_blocks(&EstimatorOptions::default(), &init);
        let imu = &blocks[0].1;
        let local: Matrix3<f64> = imu.fixed_view::<3, 3>(0, 0).into_owned();
        // δθ_G = R δθ: the global covariance is R P Rᵀ.
        let global = rot * local * rot.transpose();
        let want = Matrix3::from_diagonal(&Vector3::new(1e-4, 1e-4, 1e-6));
        assert!((global - want).norm() < 1e-15, "{global}");
        // Without it, every axis has sigma_ori_rad.
        let plain = initial_blocks(
            &EstimatorOptions::default(),
            &InitialState {
                sigma_yaw_rad: None,
                ..init
            },
        );
        let local: Matrix3<f64> = plain[0].1.fixed_view::<3, 3>(0, 0).into_owned();
        assert!((local - Matrix3::identity() * 1e-4).norm() < 1e-15);
    }
}
