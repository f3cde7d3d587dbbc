//! The centralized estimators `ce-cmsckf` and `ce-cmsckf-cslam` (thesis Section
//! 5.4): every robot's state in one joint EKF with the full cross-covariance, in
//! one process. They are the accuracy and cost reference of the distributed
//! CI-EKF: common features update every robot they involve through the tracked
//! correlations, and every update costs the joint state's size squared.
//!
//! Each robot's frame runs the single-robot steps through [`joint::RobotSlot`];
//! matching links its tracks to the other robots' current tracks (the same
//! descriptor and epipolar checks as the agents), and [`common`] adds the joint
//! common-feature updates.

pub mod common;
pub mod joint;
pub mod run;

use crate::cooperation::loop_closure::FrameFeatures;
use crate::cooperation::matcher::{epipolar_inliers, match_descriptors, MatchRules};
use crate::estimator::chi2::Chi2Table;
use crate::estimator::cooperative::{frame_features, CoopFrameStats};
use crate::estimator::feature_classes::{
    classify, clean_up, drop_non_keyframe, record_measurements,
};
use crate::estimator::feature_db::FeatureDb;
use crate::estimator::filter::FilterView;
use crate::estimator::frame_output::{cpu_ms, GyroAtFrame, ImuCovariance};
use crate::estimator::inputs::{check_frame, check_imu, InputError};
use crate::estimator::propagator::{gyro_at_frame, propagate, PropagateError};
use crate::estimator::slam_pacing::SlamPacing;
use crate::estimator::slow_start::SlowStart;
use crate::estimator::state::{ImuState, Means, Var};
use crate::estimator::triangulation::TriangulationOptions;
use crate::estimator::vio::{augment_clone, initial_blocks, FrameError};
use crate::estimator::{updater_msckf, updater_slam, updater_zupt};
use crate::estimator::{EstimatorOptions, FrameOutput, InitialState};
use ::common::calibration::CameraCalibration;
use ::common::measurement::{FeatureFrame, ImuSample};
use joint::{JointState, JointVar};
use std::collections::{BTreeMap, BTreeSet, VecDeque};
use std::time::Instant;

/// One robot's inputs and tracks.
#[derive(Debug)]
struct Robot {
    calib: CameraCalibration,
    imu: VecDeque<ImuSample>,
    frames: VecDeque<FeatureFrame>,
    features: FeatureDb,
    seq: u64,
    last_frame_t: Option<f64>,
    start_t: f64,
    /// The newest processed frame, for the other robots' matching.
    latest: Option<FrameFeatures>,
    /// Whether an MSCKF update has used a feature yet (the first is iterated).
    updated_once: bool,
    /// Whether the first update waited for parallax (`slow_start`).
    slow_start: SlowStart,
    /// Which SLAM features take a view on a keyframe window (`slam_pacing`).
    slam_pacing: SlamPacing,
    /// Its camera's pixel noise and its SLAM updates' noise, pixels.
    noise: PixelNoise,
}

/// A robot's measurement noise, pixels.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct PixelNoise {
    /// Its tracks' noise (`pixel_sigma_px`).
    pub pixel_sigma_px: f64,
    /// Its SLAM updates' noise (`EstimatorOptions::slam_sigma_px`).
    pub slam_sigma_px: f64,
}

impl PixelNoise {
    /// The noise `opts` weigh pixels with.
    pub fn of(opts: &EstimatorOptions) -> Self {
        Self {
            pixel_sigma_px: opts.pixel_sigma_px,
            slam_sigma_px: opts.slam_sigma_px(),
        }
    }
}

/// A track of a robot: `(robot, track id)`.
pub type TrackKey = (u16, u64);

/// The centralized estimator of a fleet.
#[derive(Debug)]
pub struct CentralEstimator {
    opts: EstimatorOptions,
    joint: JointState,
    robots: Vec<Robot>,
    /// Cross-robot links between tracks (symmetric).
    links: BTreeMap<TrackKey, BTreeSet<TrackKey>>,
    chi2: Chi2Table,
    tri: TriangulationOptions,
}

fn ms(t: Instant) -> f64 {
    t.elapsed().as_secs_f64() * 1e3
}

impl CentralEstimator {
    /// A fleet of robots with options `opts` and each robot's initial
    /// calibration; every robot's pixels weigh as `opts` say until
    /// [`CentralEstimator::set_pixel_noise`].
    pub fn new(opts: EstimatorOptions, calibs: Vec<CameraCalibration>) -> Self {
        let noise = PixelNoise::of(&opts);
        // One lens type for the fleet's rays (the first robot's): peers'
        // rays are triangulated together with ours.
        let tri = match calibs.first() {
            Some(c) => TriangulationOptions::for_camera(&opts.triangulation, &c.camera),
            None => TriangulationOptions::with_limits(&opts.triangulation),
        };
        Self {
            robots: calibs
                .into_iter()
                .map(|calib| Robot {
                    calib,
                    imu: VecDeque::new(),
                    frames: VecDeque::new(),
                    features: FeatureDb::default(),
                    seq: 0,
                    last_frame_t: None,
                    start_t: 0.0,
                    latest: None,
                    updated_once: false,
                    slow_start: SlowStart::default(),
                    slam_pacing: SlamPacing::default(),
                    noise,
                })
                .collect(),
            opts,
            joint: JointState::default(),
            links: BTreeMap::new(),
            chi2: Chi2Table::new(0.95, 1000),
            tri,
        }
    }

    /// The joint state.
    pub fn joint(&self) -> &JointState {
        &self.joint
    }

    /// Robot `r`'s pixels weigh at `noise` (its camera's), in its own
    /// updates and in the joint ones.
    pub fn set_pixel_noise(&mut self, r: usize, noise: PixelNoise) {
        if let Some(robot) = self.robots.get_mut(r) {
            robot.noise = noise;
        }
    }

    /// What robot `q`'s rows are multiplied by so that the joint updates,
    /// which weigh every row at the fleet's noise (`opts`), weigh them at
    /// its own: fleet noise over its noise, for its tracks and for its SLAM
    /// views (exactly 1 when they are the fleet's).
    fn whitening_ratios(&self, q: u16) -> (f64, f64) {
        match self.robots.get(usize::from(q)) {
            Some(rb) => (
                self.opts.pixel_sigma_px / rb.noise.pixel_sigma_px,
                self.opts.slam_sigma_px() / rb.noise.slam_sigma_px,
            ),
            None => (1.0, 1.0),
        }
    }

    /// Starts robot `r` at `init` (its variables join the joint state,
    /// uncorrelated with the others).
    pub fn initialize(&mut self, r: usize, init: &InitialState) {
        let Some(robot) = self.robots.get_mut(r) else {
            return;
        };
        let imu = ImuState {
            rot: init.rot,
            pos: init.pos,
            vel: init.vel,
            bias_gyro: init.bias_gyro,
            bias_accel: init.bias_accel,
        };
        robot.start_t = init.t;
        let td = robot.calib.time_offset_s;
        robot.frames.retain(|f| f.t + td > init.t);
        let blocks = initial_blocks(&self.opts, init);
        self.joint.add_robot(
            r as u16,
            Means::new(init.t, imu, robot.calib.clone()),
            &blocks,
        );
    }

    /// Adds an IMU sample of robot `r`.
    pub fn feed_imu(&mut self, r: usize, s: ImuSample) -> Result<(), InputError> {
        let Some(robot) = self.robots.get_mut(r) else {
            return Ok(());
        };
        check_imu(robot.imu.back(), &s, self.opts.max_imu_gap_s)?;
        robot.imu.push_back(s);
        Ok(())
    }

    /// Queues a feature frame of robot `r`.
    pub fn feed_frame(&mut self, r: usize, frame: FeatureFrame) -> Result<(), InputError> {
        let Some(robot) = self.robots.get_mut(r) else {
            return Ok(());
        };
        check_frame(
            robot.frames.back().map(|f| f.t).or(robot.last_frame_t),
            &frame,
        )?;
        robot.frames.push_back(frame);
        Ok(())
    }

    /// Processes robot `r`'s queued frames its IMU covers.
    pub fn poll(&mut self, r: usize) -> Vec<Result<FrameOutput, FrameError>> {
        let mut out = Vec::new();
        while let Some(robot) = self.robots.get_mut(r) {
            let Some(front) = robot.frames.front() else {
                break;
            };
            let td = self
                .joint
                .means(r as u16)
                .map_or(robot.calib.time_offset_s, |m| m.calib.time_offset_s);
            if !robot.imu.back().is_some_and(|s| s.t >= front.t + td) {
                break;
            }
            let Some(frame) = robot.frames.pop_front() else {
                break;
            };
            robot.last_frame_t = Some(frame.t);
            if self.joint.means(r as u16).is_none() {
                out.push(Err(FrameError::NotInitialized(frame.t)));
                continue;
            }
            out.push(self.process_frame(r, &frame));
        }
        out
    }

    /// Links robot `r`'s current features to the other robots' newest frames.
    fn match_frame(&mut self, r: usize, ours: &FrameFeatures, seq: u64) {
        let c = &self.opts.cooperation;
        let rules = MatchRules {
            max_distance: c.max_descriptor_distance_bits,
            ratio: c.match_ratio,
        };
        let k = &self.robots[r].calib.camera.intrinsics;
        let threshold = c.epipolar_threshold_px / (k[0] * k[1]).abs().sqrt().max(1.0);
        let mut new_links = Vec::new();
        for (q, other) in self.robots.iter().enumerate() {
            let Some(theirs) = other
                .latest
                .as_ref()
                .filter(|f| q != r && ours.t_s - f.t_s <= c.max_window_age_s)
            else {
                continue;
            };
            let pairs = match_descriptors(&ours.descriptors, &theirs.descriptors, &rules);
            let x1: Vec<_> = pairs.iter().map(|(a, _)| ours.xy[*a]).collect();
            let x2: Vec<_> = pairs.iter().map(|(_, b)| theirs.xy[*b]).collect();
            let seed = seq.wrapping_mul(1_000_003) ^ ((r as u64) << 32 | q as u64);
            let Some(inl) = epipolar_inliers(&x1, &x2, threshold, c.min_window_inliers, seed)
            else {
                continue;
            };
            for ((a, b), keep) in pairs.into_iter().zip(inl) {
                if keep {
                    new_links.push(((r as u16, ours.ids[a]), (q as u16, theirs.ids[b])));
                }
            }
        }
        for (a, b) in new_links {
            self.links.entry(a).or_default().insert(b);
            self.links.entry(b).or_default().insert(a);
        }
    }

    /// The flow of one frame of robot `r`: propagate and clone, link to the
    /// other robots' tracks, update (common features jointly), marginalize.
    fn process_frame(&mut self, r: usize, frame: &FeatureFrame) -> Result<FrameOutput, FrameError> {
        let t_start = Instant::now();
        let cpu_start = cpu_time::ThreadTime::try_now().ok();
        let mut opts = self.opts.clone();
        let rid = r as u16;
        if let Some(robot) = self.robots.get(r) {
            // Its own updates weigh its pixels at its camera's noise.
            opts.pixel_sigma_px = robot.noise.pixel_sigma_px;
            if opts.slam_pixel_sigma_px.is_some() {
                opts.slam_pixel_sigma_px = Some(robot.noise.slam_sigma_px);
            }
            // After a slow start the robot's window keeps keyframes, and the
            // settings for slow platforms hold (`slow_start`).
            robot.slow_start.apply(&mut opts);
        }
        let mut timing = crate::estimator::vio::FrameTiming::default();
        let mut coop = CoopFrameStats::default();

        // 1. Propagate to the image's IMU time and clone the pose there.
        let (t_imu, t_prev) = {
            let m = self
                .joint
                .means(rid)
                .ok_or(FrameError::NotInitialized(frame.t))?;
            (frame.t + m.calib.time_offset_s, m.t)
        };
        if t_imu <= t_prev {
            return Err(FrameError::Propagate(PropagateError::Backwards {
                from: t_prev,
                to: t_imu,
            }));
        }
        let robot = &mut self.robots[r];
        let buf = robot.imu.make_contiguous();
        let Some(mut slot) = self.joint.slot(rid) else {
            return Err(FrameError::NotInitialized(frame.t));
        };
        let omega = propagate(&mut slot, buf, t_imu, &opts.imu, opts.use_fej)?;
        let gyro = gyro_at_frame(buf, t_prev, t_imu, &opts.imu);
        if opts.zero_velocity_update {
            let readings: Vec<ImuSample> = buf
                .iter()
                .filter(|s| s.t > t_prev && s.t <= t_imu)
                .copied()
                .collect();
            let images = updater_zupt::image_motion(slot.means(), frame, &robot.features);
            if updater_zupt::try_update(&mut slot, &readings, &opts, &self.chi2, images) {
                timing.propagate_ms = ms(t_start);
                timing.total_ms = timing.propagate_ms;
                timing.cpu_ms = cpu_ms(cpu_start);
                return Ok(self.output_without_updates(rid, &gyro, timing, coop, true));
            }
        }
        robot.seq += 1;
        let key = robot.seq;
        augment_clone(&mut slot, key, frame.t, &omega);
        timing.propagate_ms = ms(t_start);

        // 2. Record the measurements; 3. link them to the other robots' tracks.
        record_measurements(&mut robot.features, slot.means(), frame, key);
        let ours = frame_features(frame, &robot.features, key);
        let t = Instant::now();
        if opts.cooperation.common_vio || opts.cooperation.common_slam {
            self.match_frame(r, &ours, key);
        }
        coop.matching_ms = ms(t);

        // 4. Classes; the linked tracks leaving the window are common.
        let robot = &self.robots[r];
        let Some(means) = self.joint.means(rid) else {
            return Err(FrameError::NotInitialized(frame.t));
        };
        if !opts.window_ready(means.clones.len()) {
            // Too few views to triangulate: as in the single-robot estimator.
            let robot = &mut self.robots[r];
            if let Some(mut slot) = self.joint.slot(rid) {
                drop_non_keyframe(&mut robot.features, &mut slot, opts.keyframe_parallax_px);
            }
            timing.total_ms = ms(t_start);
            timing.cpu_ms = cpu_ms(cpu_start);
            return Ok(self.output_without_updates(rid, &gyro, timing, coop, false));
        }
        let slam_allowed = means.t - robot.start_t >= opts.slam_delay_s;
        let mut classes = classify(&robot.features, means, key, &opts, slam_allowed);
        // A slow start: the robot's first update waits for its window to gain
        // parallax, as in the agents' filter, its candidates kept for it.
        let robot = &mut self.robots[r];
        // A flight that turns slow takes the constrained MSCKF and the keyframe
        // window from the next frame on (`slow_start`).
        if robot.updated_once {
            robot
                .slow_start
                .observe_window(means, &robot.features, &opts);
        }
        if !robot.updated_once {
            let Some(mut slot) = self.joint.slot(rid) else {
                return Err(FrameError::NotInitialized(frame.t));
            };
            if robot.slow_start.first_update_waits(
                &slot,
                &robot.features,
                &classes.candidates(),
                &opts,
                &self.chi2,
                &self.tri,
            ) {
                classes.keep_all_candidates();
                clean_up(&mut robot.features, &mut slot, &classes, opts.max_clones);
                timing.total_ms = ms(t_start);
                timing.cpu_ms = cpu_ms(cpu_start);
                return Ok(self.output_without_updates(rid, &gyro, timing, coop, false));
            }
        }

        // 5. Common VIO features: one joint update with every robot's measurements.
        let t = Instant::now();
        let common_ids: Vec<u64> = if opts.cooperation.common_vio {
            classes
                .msckf_ids
                .iter()
                .copied()
                .filter(|id| self.links.contains_key(&(rid, *id)))
                .collect()
        } else {
            Vec::new()
        };
        let common_used = common::common_vio(self, r, &common_ids, &mut coop);
        coop.common_vio_ms = ms(t);

        // 6. MSCKF with the rest; 7. SLAM update; 8. common SLAM; 9. SLAM init.
        let t = Instant::now();
        // The common tracks the joint update did not use go first, whatever the
        // cap; then our own, longest first, until the cap is full.
        let common_left: Vec<u64> = common_ids
            .iter()
            .copied()
            .filter(|id| !common_used.contains(id))
            .collect();
        let independent: Vec<u64> = common_left
            .iter()
            .copied()
            .chain(
                classes
                    .msckf_ids
                    .iter()
                    .copied()
                    .filter(|id| !common_ids.contains(id)),
            )
            .collect();
        let cap = opts.max_msckf_in_update.saturating_add(common_left.len());
        let robot = &mut self.robots[r];
        let Some(mut slot) = self.joint.slot(rid) else {
            return Err(FrameError::NotInitialized(frame.t));
        };
        let mut untriangulated = Vec::new();
        // The robot's first update is iterated (`first_update_iterations`), as
        // in the agents; its prior and every redo are the whole joint state.
        // One that waited for parallax is one plain step (`slow_start`).
        let iterations = if robot.updated_once || robot.slow_start.plain_first_update() {
            0
        } else {
            opts.first_update_iterations
        };
        let (msckf, tried) = updater_msckf::iterated_update_up_to(
            &mut slot,
            &robot.features,
            &independent,
            cap,
            &opts,
            &self.chi2,
            &self.tri,
            &mut untriangulated,
            iterations,
        );
        robot.updated_once |= msckf.used > 0;

        // Common tracks are used once, jointly or here, whatever the outcome.
        untriangulated.retain(|id| !common_ids.contains(id));
        timing.msckf_ms = ms(t);
        let t = Instant::now();
        let mut slam = updater_slam::SlamStats::default();
        let slam_due = robot.slam_pacing.due_in_frame(
            &robot.features,
            slot.means(),
            &classes.slam_seen,
            key,
            &opts,
        );
        updater_slam::update(
            &mut slot,
            &robot.features,
            slam_due.as_deref().unwrap_or(&classes.slam_seen),
            key,
            &opts,
            &self.chi2,
            &mut slam,
        );
        timing.slam_update_ms = ms(t);
        if opts.cooperation.common_slam {
            let t = Instant::now();
            common::common_slam(self, r, &mut coop);
            coop.common_slam_ms = ms(t);
        }
        let t = Instant::now();
        let robot = &mut self.robots[r];
        let Some(mut slot) = self.joint.slot(rid) else {
            return Err(FrameError::NotInitialized(frame.t));
        };
        updater_slam::initialize_candidates(
            &mut slot,
            &robot.features,
            &classes.slam_candidates,
            |id| independent.contains(&id),
            &opts,
            &self.chi2,
            &self.tri,
            &mut slam,
            &mut untriangulated,
        );
        timing.slam_init_ms = ms(t);

        // 10. Clean up, and forget the links of ended tracks.
        let t = Instant::now();
        // Every common track was used (jointly or in the MSCKF), even beyond the cap.
        classes.mark_used(&common_ids);
        classes.defer(independent.get(tried..).unwrap_or_default());
        classes.retry_untriangulated(&robot.features, key, &untriangulated);
        clean_up(&mut robot.features, &mut slot, &classes, opts.max_clones);
        let state_t = slot.means().t;
        while robot.imu.len() > 2 && robot.imu[1].t < state_t {
            robot.imu.pop_front();
        }
        robot.latest = Some(ours);
        self.forget_ended_links();
        timing.marginalize_ms = ms(t);
        timing.total_ms = ms(t_start);
        timing.cpu_ms = cpu_ms(cpu_start);
        timing.cooperation_ms = coop.matching_ms + coop.common_vio_ms + coop.common_slam_ms;
        Ok(self.output(rid, &gyro, timing, (msckf, slam, coop), false))
    }

    /// Drops links whose tracks no longer exist.
    fn forget_ended_links(&mut self) {
        let alive = |robots: &[Robot], joint: &JointState, (q, id): TrackKey| {
            robots
                .get(usize::from(q))
                .is_some_and(|rb| rb.features.contains(id))
                || joint.means(q).is_some_and(|m| m.features.contains_key(&id))
        };
        let (robots, joint) = (&self.robots, &self.joint);
        self.links.retain(|k, set| {
            set.retain(|o| alive(robots, joint, *o));
            alive(robots, joint, *k) && !set.is_empty()
        });
    }

    /// [`Self::output`] of a frame that updated nothing.
    fn output_without_updates(
        &self,
        r: u16,
        gyro: &GyroAtFrame,
        timing: crate::estimator::vio::FrameTiming,
        coop: CoopFrameStats,
        zero_velocity: bool,
    ) -> FrameOutput {
        self.output(
            r,
            gyro,
            timing,
            (Default::default(), Default::default(), coop),
            zero_velocity,
        )
    }

    fn output(
        &self,
        r: u16,
        gyro: &GyroAtFrame,
        timing: crate::estimator::vio::FrameTiming,
        stats: (
            updater_msckf::MsckfStats,
            updater_slam::SlamStats,
            CoopFrameStats,
        ),
        zero_velocity: bool,
    ) -> FrameOutput {
        let cov = self.joint.cov.matrix();
        let o = self
            .joint
            .cov
            .offset(JointVar {
                robot: r,
                var: Var::Imu,
            })
            .unwrap_or(0);
        let cov_imu: ImuCovariance = if cov.nrows() >= o + 15 {
            cov.fixed_view::<15, 15>(o, o).into_owned()
        } else {
            ImuCovariance::zeros()
        };
        match self.joint.means(r) {
            Some(m) => FrameOutput::of(m, &cov_imu, gyro, timing, stats, zero_velocity),
            None => FrameOutput::of(
                &Means::new(0.0, ImuState::default(), CameraCalibration::euroc_cam0()),
                &cov_imu,
                gyro,
                timing,
                stats,
                zero_velocity,
            ),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_robot_rows_are_scaled_from_the_fleet_noise_to_its_own() {
        let opts = EstimatorOptions {
            pixel_sigma_px: 1.0,
            slam_pixel_sigma_px: Some(2.0),
            ..EstimatorOptions::default()
        };
        let calib = CameraCalibration::euroc_cam0();
        let mut ce = CentralEstimator::new(opts, vec![calib.clone(), calib]);
        // Every robot at the fleet's noise: exactly 1, so such fleets do not
        // change.
        assert_eq!(ce.whitening_ratios(0), (1.0, 1.0));
        assert_eq!(ce.whitening_ratios(1), (1.0, 1.0));
        ce.set_pixel_noise(
            1,
            PixelNoise {
                pixel_sigma_px: 4.0,
                slam_sigma_px: 8.0,
            },
        );
        assert_eq!(ce.whitening_ratios(0), (1.0, 1.0));
        assert_eq!(ce.whitening_ratios(1), (0.25, 0.25));
        // A robot the fleet does not have: left as it is.
        assert_eq!(ce.whitening_ratios(7), (1.0, 1.0));
    }
}
