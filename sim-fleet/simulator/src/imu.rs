//! IMU measurement generation: true signals from the spline (Eqs. 2.111-2.112)
//! corrupted by white noise and random-walk biases.

use crate::scenario::ImuSpec;
use crate::truth::RobotTruth;
use common::measurement::ImuSample;
use nalgebra::Vector3;
use rand_chacha::ChaCha8Rng;
use rand_distr::{Distribution, StandardNormal};

/// Draws a vector of three independent standard normals.
pub(crate) fn normal3(rng: &mut ChaCha8Rng) -> Vector3<f64> {
    Vector3::new(
        StandardNormal.sample(rng),
        StandardNormal.sample(rng),
        StandardNormal.sample(rng),
    )
}

/// True IMU biases at one time.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct Biases {
    /// Gyroscope bias, rad/s.
    pub gyro: Vector3<f64>,
    /// Accelerometer bias, m/s².
    pub accel: Vector3<f64>,
}

/// Generates one robot's IMU samples in time order.
#[derive(Clone, Debug)]
pub struct ImuGenerator {
    spec: ImuSpec,
    rng: ChaCha8Rng,
    t0: f64,
    k: u64,
    biases: Biases,
}

impl ImuGenerator {
    /// A generator whose first sample is at fleet time `t0`, with zero initial biases.
    pub fn new(spec: ImuSpec, rng: ChaCha8Rng, t0: f64) -> Self {
        Self {
            spec,
            rng,
            t0,
            k: 0,
            biases: Biases::default(),
        }
    }

    /// Time of the next sample.
    pub fn next_time(&self) -> f64 {
        self.t0 + self.k as f64 / self.spec.rate_hz
    }

    /// The biases the next sample will carry.
    pub fn biases(&self) -> Biases {
        self.biases
    }

    /// The next sample, or `None` once the spline ends.
    pub fn next_sample(&mut self, truth: &RobotTruth) -> Option<ImuSample> {
        let t = self.next_time();
        let s = truth.state(t)?;
        let dt = 1.0 / self.spec.rate_hz;
        let g = Vector3::new(0.0, 0.0, self.spec.gravity_mps2);
        let sqrt_dt = dt.sqrt();
        // Discrete white noise std = density / √dt.
        let gyro = s.omega
            + self.biases.gyro
            + normal3(&mut self.rng) * (self.spec.gyro_noise_density / sqrt_dt);
        // Eq. 2.112 with gravity: a_m = R_ItoGᵀ (a_G + g e_z) + b_a + n_a.
        let accel = s.rot.transpose() * (s.acc + g)
            + self.biases.accel
            + normal3(&mut self.rng) * (self.spec.accel_noise_density / sqrt_dt);
        // Random walk: discrete std = rw · √dt.
        self.biases.gyro += normal3(&mut self.rng) * (self.spec.gyro_random_walk * sqrt_dt);
        self.biases.accel += normal3(&mut self.rng) * (self.spec.accel_random_walk * sqrt_dt);
        self.k += 1;
        Some(ImuSample { t, gyro, accel })
    }
}
