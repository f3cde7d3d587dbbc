//! A whole simulated fleet: every robot's true motion, the shared world, and each
//! robot's time-ordered measurement stream.

use crate::bspline::SplineError;
use crate::camera_sim::{CameraEvent, CameraGenerator, TruthState};
use crate::imu::{Biases, ImuGenerator};
use crate::perturb::{perturb_calibration, start_error, StartError};
use crate::render::{RenderError, Renderer};
use crate::rng::{stream_rng, Stream};
use crate::scenario::{Scenario, StartFrame};
use crate::truth::RobotTruth;
use crate::world::{camera_pose, ViewBounds, World};
use common::calibration::CameraCalibration;
use common::measurement::ImuSample;
use common::so3::Se3;
use common::trajectory::{laps, read_trajectory, TrajectoryError};
use nalgebra::Vector3;
use rand_chacha::ChaCha8Rng;
use std::path::PathBuf;
use std::sync::Arc;
use thiserror::Error;

/// Why a fleet could not be simulated.
#[derive(Debug, Error)]
pub enum SimError {
    /// A trajectory file could not be read.
    #[error(transparent)]
    Trajectory(#[from] TrajectoryError),
    /// A trajectory could not be fitted.
    #[error("robot {robot} ({path}): {source}")]
    Spline {
        /// Robot index.
        robot: usize,
        /// Its trajectory file.
        path: PathBuf,
        /// The cause.
        source: SplineError,
    },
    /// The requested robot does not exist.
    #[error("robot {0} is not in the scenario")]
    NoSuchRobot(usize),
    /// The rendered world could not be built.
    #[error(transparent)]
    Render(#[from] RenderError),
    /// An image could not be rendered.
    #[error("rendering an image: {0}")]
    Image(#[from] common::image::ImageError),
}

/// One item of a robot's measurement stream.
#[derive(Clone, Debug)]
pub enum SimEvent {
    /// An IMU sample.
    Imu(ImuSample),
    /// An image's features, with its ground truth.
    Camera(Box<CameraEvent>),
}

/// The simulated fleet: a pure function of (scenario, seed).
#[derive(Clone, Debug)]
pub struct Fleet {
    /// The scenario it was built from.
    pub scenario: Scenario,
    /// The seed of every random draw.
    pub seed: u64,
    /// Each robot's true motion.
    pub truths: Vec<RobotTruth>,
    /// The shared landmarks.
    pub world: World,
    /// Each robot's true camera calibration, in robot order (the fleet's
    /// camera unless a robot has its own).
    pub true_calibrations: Vec<CameraCalibration>,
    /// The rendered world through each robot's camera (robots with the same
    /// camera share one), when the scenario renders images; empty otherwise.
    pub renderers: Vec<Arc<Renderer>>,
}

impl Fleet {
    /// Fits every robot's spline and grows the shared world along all of them, in
    /// robot order, from the `World` random stream of `seed`.
    pub fn build(scenario: &Scenario, seed: u64) -> Result<Self, SimError> {
        let mut truths = Vec::with_capacity(scenario.robots.len());
        for (i, spec) in scenario.robots.iter().enumerate() {
            let path = scenario
                .trajectory_path(i)
                .ok_or(SimError::NoSuchRobot(i))?;
            let poses = laps(&read_trajectory(&path)?, spec.laps);
            let truth =
                RobotTruth::new(&poses, spec.start_time_s).map_err(|source| SimError::Spline {
                    robot: i,
                    path: path.clone(),
                    source,
                })?;
            truths.push(truth);
        }
        let cameras: Vec<_> = (0..truths.len()).map(|i| scenario.camera(i)).collect();
        let true_calibrations: Vec<_> = cameras.iter().map(|c| c.calibration()).collect();
        let mut world = World::default();
        let mut rng = stream_rng(seed, Stream::World);
        // Each robot's camera sees enough points along its own path.
        for ((truth, cam), calib) in truths.iter().zip(&cameras).zip(&true_calibrations) {
            let bounds = ViewBounds::new(calib, cam.min_depth_m, cam.max_depth_m);
            world.grow_along(truth, calib, &bounds, &scenario.world, &mut rng);
        }
        world.alias_places(
            scenario.world.aliased_places,
            scenario.world.aliased_place_radius_m,
            &mut rng,
        );
        world.set_selection_order(scenario.world.selection_order);
        let mut renderers: Vec<Arc<Renderer>> = Vec::new();
        if scenario.render.enabled {
            // One room and its textures; another camera only casts other rays.
            let mut rng = stream_rng(seed, Stream::Texture);
            for (i, calib) in true_calibrations.iter().enumerate() {
                let same = (0..i).find(|&j| true_calibrations[j] == *calib);
                let r = match (same, renderers.first()) {
                    (Some(j), _) => renderers[j].clone(),
                    (None, Some(first)) => Arc::new(first.with_camera(calib)?),
                    (None, None) => Arc::new(Renderer::new(
                        &scenario.render,
                        calib,
                        truths.iter().flat_map(trajectory_points),
                        &mut rng,
                    )?),
                };
                renderers.push(r);
            }
        }
        Ok(Self {
            scenario: scenario.clone(),
            seed,
            truths,
            world,
            true_calibrations,
            renderers,
        })
    }

    /// Robot `robot`'s true camera calibration.
    pub fn true_calibration(&self, robot: usize) -> Option<&CameraCalibration> {
        self.true_calibrations.get(robot)
    }

    /// Whether the scenario renders images.
    pub fn renders(&self) -> bool {
        !self.renderers.is_empty()
    }

    /// The rendered world through robot `robot`'s camera, when the scenario
    /// renders images.
    pub fn renderer(&self, robot: usize) -> Option<&Arc<Renderer>> {
        self.renderers.get(robot)
    }

    /// Number of robots.
    pub fn robot_count(&self) -> usize {
        self.truths.len()
    }

    /// Robot `robot`'s measurement stream, from the start of its spline.
    pub fn stream(&self, robot: usize) -> Result<RobotStream<'_>, SimError> {
        let truth = self.truths.get(robot).ok_or(SimError::NoSuchRobot(robot))?;
        let imu = ImuGenerator::new(
            self.scenario.sensors.imu.clone(),
            stream_rng(self.seed, Stream::Imu(robot)),
            truth.start_time(),
        );
        self.stream_from(robot, ImuSource::Simulated(Box::new(imu)))
    }

    /// A hybrid stream: recorded IMU `samples` (fleet clock, time order) with
    /// camera frames simulated from robot `robot`'s trajectory. `biases` are
    /// the recorded IMU's biases as far as they are known (the truth that
    /// camera events carry). Samples outside the trajectory's span are dropped.
    pub fn stream_with_imu(
        &self,
        robot: usize,
        samples: Vec<ImuSample>,
        biases: Biases,
    ) -> Result<RobotStream<'_>, SimError> {
        let truth = self.truths.get(robot).ok_or(SimError::NoSuchRobot(robot))?;
        let (t0, t1) = (truth.start_time(), truth.end_time());
        let mut samples: Vec<ImuSample> = samples
            .into_iter()
            .filter(|s| s.t >= t0 && s.t <= t1)
            .collect();
        samples.reverse();
        self.stream_from(robot, ImuSource::Recorded { samples, biases })
    }

    fn stream_from(&self, robot: usize, imu: ImuSource) -> Result<RobotStream<'_>, SimError> {
        let truth = self.truths.get(robot).ok_or(SimError::NoSuchRobot(robot))?;
        let calib = self
            .true_calibrations
            .get(robot)
            .ok_or(SimError::NoSuchRobot(robot))?;
        let t0 = truth.start_time();
        Ok(RobotStream {
            fleet: self,
            truth,
            calib,
            renderer: self.renderers.get(robot).map(Arc::as_ref),
            imu,
            camera: CameraGenerator::new(
                self.scenario.camera(robot),
                self.scenario.world.clone(),
                stream_rng(self.seed, Stream::Camera(robot)),
                t0 - calib.time_offset_s,
            ),
            camera_done: false,
            render_rng: stream_rng(self.seed, Stream::Render(robot)),
            lighting_rng: stream_rng(self.seed, Stream::Lighting(robot)),
            gain: 1.0,
        })
    }

    /// The calibration robot `robot`'s estimator starts from: the truth perturbed by
    /// the scenario's priors (its own random stream).
    pub fn initial_calibration(&self, robot: usize) -> CameraCalibration {
        let mut rng = stream_rng(self.seed, Stream::Calibration(robot));
        perturb_calibration(
            &self.scenario.camera(robot).calibration(),
            &self.scenario.sensors.calibration_perturbation,
            &mut rng,
        )
    }

    /// The error robot `robot`'s estimator starts with (zero unless the scenario
    /// asks for `initial_error: sampled`; its own random stream).
    pub fn start_error(&self, robot: usize) -> StartError {
        let mut rng = stream_rng(self.seed, Stream::InitialState(robot));
        start_error(&self.scenario.estimator, &mut rng)
    }

    /// `T_world→frame` of robot `robot`'s estimator frame: the identity with
    /// `start_frame: fleet`; with `own`, the frame at its pose when its
    /// estimator starts, yawed along its most horizontal IMU axis.
    pub fn robot_frame(&self, robot: usize) -> Option<Se3> {
        if self.scenario.estimator.start_frame == StartFrame::Fleet {
            return Some(Se3::identity());
        }
        let start = self.estimator_start_time(robot)?;
        let pose = self.truths.get(robot)?.spline.pose(start)?;
        let axis = pose
            .rot
            .column_iter()
            .min_by(|a, b| a.z.abs().total_cmp(&b.z.abs()))?
            .into_owned();
        let yaw = axis.y.atan2(axis.x);
        let own_to_world = Se3::new(
            common::so3::exp_so3(&Vector3::new(0.0, 0.0, yaw)),
            pose.trans,
        );
        Some(own_to_world.inverse())
    }

    /// Robot `robot`'s truth as its estimator knows it: in its frame
    /// ([`Fleet::robot_frame`]).
    pub fn agent_truth(&self, robot: usize) -> Option<RobotTruth> {
        let f = self.robot_frame(robot)?;
        Some(self.truths.get(robot)?.transformed(&f))
    }

    /// A true state of robot `robot` in its estimator's frame.
    pub fn state_in_robot_frame(&self, robot: usize, s: &TruthState) -> Option<TruthState> {
        let f = self.robot_frame(robot)?;
        Some(TruthState {
            t: s.t,
            rot: f.rot * s.rot,
            pos: f.transform_point(&s.pos),
            vel: f.rot * s.vel,
            biases: s.biases,
        })
    }

    /// `T_b→a`: where robot `b`'s estimator frame is in robot `a`'s (the
    /// alignment robot `a` has to find with `start_frame: own`).
    pub fn frame_between(&self, a: usize, b: usize) -> Option<Se3> {
        Some(
            self.robot_frame(a)?
                .compose(&self.robot_frame(b)?.inverse()),
        )
    }

    /// When robot `robot`'s estimator starts: once it moved `start_after_motion_m`.
    pub fn estimator_start_time(&self, robot: usize) -> Option<f64> {
        let truth = self.truths.get(robot)?;
        Some(truth.motion_start_time(self.scenario.estimator.start_after_motion_m))
    }
}

/// Where a stream's IMU samples come from.
#[derive(Debug)]
enum ImuSource {
    /// The IMU model of the scenario.
    Simulated(Box<ImuGenerator>),
    /// A recording, latest sample first (popped from the back).
    Recorded {
        samples: Vec<ImuSample>,
        biases: Biases,
    },
}

impl ImuSource {
    fn next_time(&self) -> f64 {
        match self {
            ImuSource::Simulated(g) => g.next_time(),
            ImuSource::Recorded { samples, .. } => samples.last().map_or(f64::INFINITY, |s| s.t),
        }
    }

    fn biases(&self) -> Biases {
        match self {
            ImuSource::Simulated(g) => g.biases(),
            ImuSource::Recorded { biases, .. } => *biases,
        }
    }

    fn next_sample(&mut self, truth: &RobotTruth) -> Option<ImuSample> {
        match self {
            ImuSource::Simulated(g) => g.next_sample(truth),
            ImuSource::Recorded { samples, .. } => samples.pop(),
        }
    }
}

/// A robot's measurements in time order: IMU samples, and each image right after
/// the IMU has passed the image's IMU time.
#[derive(Debug)]
pub struct RobotStream<'a> {
    fleet: &'a Fleet,
    truth: &'a RobotTruth,
    /// The robot's true camera calibration.
    calib: &'a CameraCalibration,
    /// The rendered world through its camera, when the scenario renders.
    renderer: Option<&'a Renderer>,
    imu: ImuSource,
    camera: CameraGenerator,
    camera_done: bool,
    render_rng: ChaCha8Rng,
    /// The auto-exposure's steps (their own stream, so the image noise does not
    /// change with them).
    lighting_rng: ChaCha8Rng,
    /// Brightness of the last rendered image relative to the scene's.
    gain: f64,
}

impl RobotStream<'_> {
    /// The next camera event: simulated features, or a rendered image.
    fn next_camera(&mut self) -> Option<CameraEvent> {
        let biases = self.imu.biases();
        let Some(renderer) = self.renderer else {
            return self
                .camera
                .next_frame(self.truth, &self.fleet.world, biases);
        };
        let mut ev = self.camera.next_blank_frame(self.truth, biases)?;
        let calib = self.calib;
        camera_pose(self.truth, calib, ev.truth.t)?;
        // The poses of the exposure, those on the spline (a frame at its very
        // end blurs over the part it has).
        let poses: Vec<_> = self
            .fleet
            .scenario
            .render
            .exposure_times(ev.truth.t)
            .into_iter()
            .filter_map(|t| camera_pose(self.truth, calib, t))
            .collect();
        let spec = &self.fleet.scenario.render;
        self.gain = spec.next_gain(self.gain, &mut self.lighting_rng);
        match renderer.render_exposed(&poses, self.gain, &mut self.render_rng) {
            Ok(img) => ev.image = Some(Arc::new(img)),
            // Only an image size GrayImage cannot hold fails, which
            // Renderer::new already refused.
            Err(e) => tracing::warn!("frame at t={} not rendered: {e}", ev.frame.t),
        }
        Some(ev)
    }
}

/// Positions along a trajectory every 0.1 s (to put the rendered room around).
fn trajectory_points(truth: &RobotTruth) -> Vec<Vector3<f64>> {
    let (t0, t1) = (truth.start_time(), truth.end_time());
    let steps = ((t1 - t0) / 0.1).ceil().max(0.0) as usize;
    (0..=steps)
        .filter_map(|k| truth.spline.pose((t0 + k as f64 * 0.1).min(t1)))
        .map(|p| p.trans)
        .collect()
}

impl Iterator for RobotStream<'_> {
    type Item = SimEvent;

    fn next(&mut self) -> Option<SimEvent> {
        if !self.camera_done && self.imu.next_time() > self.camera.next_imu_time() {
            match self.next_camera() {
                Some(ev) => return Some(SimEvent::Camera(Box::new(ev))),
                None => self.camera_done = true,
            }
        }
        self.imu.next_sample(self.truth).map(SimEvent::Imu)
    }
}
