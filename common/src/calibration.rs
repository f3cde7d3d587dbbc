//! Camera calibration: intrinsics, camera-IMU extrinsics and time offset.

use crate::camera::CameraModel;
use crate::so3::Se3;
use nalgebra::{Matrix3, Vector3};
use serde::{Deserialize, Serialize};

/// Everything that maps a landmark in the IMU frame to a pixel.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct CameraCalibration {
    /// Intrinsics and distortion.
    pub camera: CameraModel,
    /// Extrinsic rotation `R_CtoI`.
    pub rot_c_to_i: Matrix3<f64>,
    /// Extrinsic translation `p_CinI` in metres.
    pub p_c_in_i: Vector3<f64>,
    /// Time offset `t_d` in seconds: `t_imu = t_cam + t_d`.
    pub time_offset_s: f64,
}

impl CameraCalibration {
    /// The EuRoC cam0 calibration (intrinsics, radtan distortion, `T_imu_cam`), `t_d = 0`.
    pub fn euroc_cam0() -> Self {
        Self {
            camera: CameraModel::euroc_cam0(),
            rot_c_to_i: Matrix3::new(
                0.0148655429818,
                -0.999880929698,
                0.00414029679422,
                0.999557249008,
                0.0149672133247,
                0.025715529948,
                -0.0257744366974,
                0.00375618835797,
                0.999660727178,
            ),
            p_c_in_i: Vector3::new(-0.0216401454975, -0.064676986768, 0.00981073058949),
            time_offset_s: 0.0,
        }
    }

    /// The extrinsic transform `T_CtoI`.
    pub fn t_c_to_i(&self) -> Se3 {
        Se3::new(self.rot_c_to_i, self.p_c_in_i)
    }
}
