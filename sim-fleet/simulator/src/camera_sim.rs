//! Camera feature frames: landmarks projected through the true calibration, with
//! pixel noise, noisy descriptors, track ids and optional outliers.

use crate::imu::Biases;
use crate::scenario::{CameraSpec, WorldSpec};
use crate::truth::RobotTruth;
use crate::world::{camera_pose, ViewBounds, World};
use common::calibration::CameraCalibration;
use common::descriptor::Descriptor;
use common::image::GrayImage;
use common::measurement::{FeatureFrame, FeatureObservation};
use nalgebra::{Matrix3, Vector2, Vector3};
use rand::Rng;
use rand_chacha::ChaCha8Rng;
use rand_distr::{Binomial, Distribution, StandardNormal};
use std::collections::HashMap;
use std::sync::Arc;

/// The true state of a robot at the IMU time of one image.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct TruthState {
    /// IMU time (fleet clock), seconds.
    pub t: f64,
    /// `R_ItoG`.
    pub rot: Matrix3<f64>,
    /// `p_IinG`, metres.
    pub pos: Vector3<f64>,
    /// `v_IinG`, m/s.
    pub vel: Vector3<f64>,
    /// True IMU biases.
    pub biases: Biases,
}

/// One simulated image: what the estimator sees and what really happened.
#[derive(Clone, Debug)]
pub struct CameraEvent {
    /// The measurement.
    pub frame: FeatureFrame,
    /// Ground truth at the image's IMU time.
    pub truth: TruthState,
    /// The landmark behind each feature of `frame` (same order); ground truth only.
    pub landmark_ids: Vec<u64>,
    /// Which features are injected outliers (same order); ground truth only.
    pub outlier: Vec<bool>,
    /// The camera image, when the scenario renders images or a dataset has
    /// them; `frame` then has no features until an image frontend makes them.
    pub image: Option<Arc<GrayImage>>,
}

/// Generates one robot's camera frames in time order.
#[derive(Clone, Debug)]
pub struct CameraGenerator {
    spec: CameraSpec,
    world_spec: WorldSpec,
    calib: CameraCalibration,
    bounds: ViewBounds,
    rng: ChaCha8Rng,
    t0: f64,
    k: u64,
    /// Track id of each landmark seen in the previous frame.
    tracks: HashMap<u64, u64>,
    next_track: u64,
}

impl CameraGenerator {
    /// A generator whose first image is at camera time `t0`.
    pub fn new(spec: CameraSpec, world_spec: WorldSpec, rng: ChaCha8Rng, t0: f64) -> Self {
        let calib = spec.calibration();
        let bounds = ViewBounds::new(&calib, spec.min_depth_m, spec.max_depth_m);
        Self {
            spec,
            world_spec,
            calib,
            bounds,
            rng,
            t0,
            k: 0,
            tracks: HashMap::new(),
            next_track: 0,
        }
    }

    /// Camera time of the next image.
    pub fn next_time(&self) -> f64 {
        self.t0 + self.k as f64 / self.spec.rate_hz
    }

    /// IMU time of the next image (`t_cam + t_d`).
    pub fn next_imu_time(&self) -> f64 {
        self.next_time() + self.calib.time_offset_s
    }

    /// The next image, or `None` once its IMU time is past the spline.
    pub fn next_frame(
        &mut self,
        truth: &RobotTruth,
        world: &World,
        biases: Biases,
    ) -> Option<CameraEvent> {
        let t_cam = self.next_time();
        let t_imu = self.next_imu_time();
        let state = truth.state(t_imu)?;
        let t_c_to_g = camera_pose(truth, &self.calib, t_imu)?;
        self.k += 1;
        let mut visible = world.visible(&t_c_to_g, &self.calib, &self.bounds);
        world.select(&mut visible, self.spec.max_features);

        let mut tracks = HashMap::with_capacity(visible.len());
        let mut features = Vec::with_capacity(visible.len());
        let mut landmark_ids = Vec::with_capacity(visible.len());
        let mut outlier = Vec::with_capacity(visible.len());
        for v in &visible {
            let id = match self.tracks.get(&v.id) {
                Some(&id) => id,
                None => {
                    self.next_track += 1;
                    self.next_track
                }
            };
            tracks.insert(v.id, id);
            let (uv, descriptor, is_outlier) = self.observe(world, v.id, v.uv);
            features.push(FeatureObservation { id, uv, descriptor });
            landmark_ids.push(v.id);
            outlier.push(is_outlier);
        }
        self.tracks = tracks;
        Some(CameraEvent {
            frame: FeatureFrame {
                t: t_cam,
                camera: 0,
                features,
            },
            truth: TruthState {
                t: t_imu,
                rot: state.rot,
                pos: state.pos,
                vel: state.vel,
                biases,
            },
            landmark_ids,
            outlier,
            image: None,
        })
    }

    /// The next image's time and truth without simulated features (for
    /// rendered images), or `None` once its IMU time is past the spline.
    pub fn next_blank_frame(&mut self, truth: &RobotTruth, biases: Biases) -> Option<CameraEvent> {
        let t_cam = self.next_time();
        let t_imu = self.next_imu_time();
        let state = truth.state(t_imu)?;
        self.k += 1;
        Some(CameraEvent {
            frame: FeatureFrame {
                t: t_cam,
                camera: 0,
                features: Vec::new(),
            },
            truth: TruthState {
                t: t_imu,
                rot: state.rot,
                pos: state.pos,
                vel: state.vel,
                biases,
            },
            landmark_ids: Vec::new(),
            outlier: Vec::new(),
            image: None,
        })
    }

    /// Noisy pixel and descriptor of one observation of landmark `id`.
    fn observe(
        &mut self,
        world: &World,
        id: u64,
        uv: Vector2<f64>,
    ) -> (Vector2<f64>, Descriptor, bool) {
        let sigma = self.spec.pixel_noise_px;
        let noise = Vector2::new(
            StandardNormal.sample(&mut self.rng),
            StandardNormal.sample(&mut self.rng),
        );
        let mut uv = uv + noise * sigma;
        let mut is_outlier = false;
        let w = &self.world_spec;
        if w.outlier_pixel_prob > 0.0 && self.rng.random::<f64>() < w.outlier_pixel_prob {
            uv = Vector2::new(
                self.rng.random_range(0.0..self.calib.camera.width as f64),
                self.rng.random_range(0.0..self.calib.camera.height as f64),
            );
            is_outlier = true;
        }
        let mut source = id;
        if w.outlier_descriptor_prob > 0.0
            && world.landmarks.len() > 1
            && self.rng.random::<f64>() < w.outlier_descriptor_prob
        {
            let other = self.rng.random_range(0..world.landmarks.len() as u64 - 1);
            source = if other >= id { other + 1 } else { other };
            is_outlier = true;
        }
        let mut descriptor = world
            .landmarks
            .get(source as usize)
            .map(|l| l.descriptor)
            .unwrap_or_default();
        flip_bits(&mut descriptor, w.descriptor_bit_flip_prob, &mut self.rng);
        (uv, descriptor, is_outlier)
    }
}

/// Flips each of the 256 bits independently with probability `p`.
fn flip_bits(d: &mut Descriptor, p: f64, rng: &mut ChaCha8Rng) {
    if p <= 0.0 {
        return;
    }
    let count = Binomial::new(Descriptor::BITS as u64, p.min(1.0))
        .map(|b| b.sample(rng))
        .unwrap_or(0);
    // Choose `count` distinct bits (partial Fisher-Yates over bit indices).
    let mut idx: [u16; Descriptor::BITS] = std::array::from_fn(|i| i as u16);
    for i in 0..count as usize {
        let j = rng.random_range(i..Descriptor::BITS);
        idx.swap(i, j);
        d.flip(idx[i] as usize);
    }
}
