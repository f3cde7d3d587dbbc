//! A whole simulated fleet: every robot's true motion, the shared world, and each
//! robot's time-ordered measurement stream.

use crate::bspline::SplineError;
use crate::camera_sim::{CameraEvent, CameraGenerator};
use crate::imu::ImuGenerator;
use crate::perturb::perturb_calibration;
use crate::rng::{stream_rng, Stream};
use crate::scenario::Scenario;
use crate::truth::RobotTruth;
use crate::world::{ViewBounds, World};
use common::calibration::CameraCalibration;
use common::measurement::ImuSample;
use common::trajectory::{read_trajectory, TrajectoryError};
use std::path::PathBuf;
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
    /// The true camera calibration (the same for every robot).
    pub true_calibration: CameraCalibration,
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
            let poses = read_trajectory(&path)?;
            let truth =
                RobotTruth::new(&poses, spec.start_time_s).map_err(|source| SimError::Spline {
                    robot: i,
                    path: path.clone(),
                    source,
                })?;
            truths.push(truth);
        }
        let cam = &scenario.sensors.camera;
        let true_calibration = cam.calibration();
        let bounds = ViewBounds::new(&true_calibration, cam.min_depth_m, cam.max_depth_m);
        let mut world = World::default();
        let mut rng = stream_rng(seed, Stream::World);
        for truth in &truths {
            world.grow_along(truth, &true_calibration, &bounds, &scenario.world, &mut rng);
        }
        Ok(Self {
            scenario: scenario.clone(),
            seed,
            truths,
            world,
            true_calibration,
        })
    }

    /// Number of robots.
    pub fn robot_count(&self) -> usize {
        self.truths.len()
    }

    /// Robot `robot`'s measurement stream, from the start of its spline.
    pub fn stream(&self, robot: usize) -> Result<RobotStream<'_>, SimError> {
        let truth = self.truths.get(robot).ok_or(SimError::NoSuchRobot(robot))?;
        let sensors = &self.scenario.sensors;
        let t0 = truth.start_time();
        Ok(RobotStream {
            fleet: self,
            truth,
            imu: ImuGenerator::new(
                sensors.imu.clone(),
                stream_rng(self.seed, Stream::Imu(robot)),
                t0,
            ),
            camera: CameraGenerator::new(
                sensors.camera.clone(),
                self.scenario.world.clone(),
                stream_rng(self.seed, Stream::Camera(robot)),
                t0 - self.true_calibration.time_offset_s,
            ),
            camera_done: false,
        })
    }

    /// The calibration robot `robot`'s estimator starts from: the truth perturbed by
    /// the scenario's priors (its own random stream).
    pub fn initial_calibration(&self, robot: usize) -> CameraCalibration {
        let mut rng = stream_rng(self.seed, Stream::Calibration(robot));
        perturb_calibration(
            &self.true_calibration,
            &self.scenario.sensors.calibration_perturbation,
            &mut rng,
        )
    }

    /// When robot `robot`'s estimator starts: once it moved `start_after_motion_m`.
    pub fn estimator_start_time(&self, robot: usize) -> Option<f64> {
        let truth = self.truths.get(robot)?;
        Some(truth.motion_start_time(self.scenario.estimator.start_after_motion_m))
    }
}

/// A robot's measurements in time order: IMU samples, and each image right after
/// the IMU has passed the image's IMU time.
#[derive(Debug)]
pub struct RobotStream<'a> {
    fleet: &'a Fleet,
    truth: &'a RobotTruth,
    imu: ImuGenerator,
    camera: CameraGenerator,
    camera_done: bool,
}

impl Iterator for RobotStream<'_> {
    type Item = SimEvent;

    fn next(&mut self) -> Option<SimEvent> {
        if !self.camera_done && self.imu.next_time() > self.camera.next_imu_time() {
            match self
                .camera
                .next_frame(self.truth, &self.fleet.world, self.imu.biases())
            {
                Some(ev) => return Some(SimEvent::Camera(Box::new(ev))),
                None => self.camera_done = true,
            }
        }
        self.imu.next_sample(self.truth).map(SimEvent::Imu)
    }
}
