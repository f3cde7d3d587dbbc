//! Sensor measurements as the estimator consumes them, whatever produced them
//! (the simulator, an image frontend, or a replayed log).

use crate::descriptor::Descriptor;
use nalgebra::{Vector2, Vector3};
use serde::{Deserialize, Serialize};

/// One IMU sample in the IMU frame `I`, at IMU time `t` (s).
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct ImuSample {
    /// Time in seconds (IMU clock).
    pub t: f64,
    /// Angular velocity measurement `ω_m` in rad/s.
    pub gyro: Vector3<f64>,
    /// Specific force measurement `a_m` in m/s².
    pub accel: Vector3<f64>,
}

/// One tracked feature seen in one image.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct FeatureObservation {
    /// Track id, unique within the robot: a feature that leaves the image and is
    /// detected again gets a new id (as a real tracker would).
    pub id: u64,
    /// Raw (distorted) pixel coordinates, in pixels.
    pub uv: Vector2<f64>,
    /// Binary descriptor of the feature in this image.
    pub descriptor: Descriptor,
}

/// All features of one camera image, at camera time `t` (s). The IMU time of the
/// image is `t + t_d` (see [`crate::conventions`]).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct FeatureFrame {
    /// Time in seconds (camera clock).
    pub t: f64,
    /// Camera index on the robot (0 for monocular).
    pub camera: u8,
    /// The observations, in increasing id order.
    pub features: Vec<FeatureObservation>,
}
