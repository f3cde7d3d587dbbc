//! The `sensor.yaml` of an ASL sensor folder: camera intrinsics, distortion,
//! resolution, rate, the extrinsics `T_BS` (sensor to body), and an IMU's
//! noise densities and random walks.
//!
//! The files start with OpenCV's `%YAML:1.0` directive, which is not YAML 1.2:
//! directive lines are skipped before parsing.

use common::camera::{CameraModel, Distortion};
use nalgebra::{Matrix3, Matrix4, Vector3, Vector4};
use serde::Deserialize;

/// A 4x4 matrix as ASL files write it.
#[derive(Debug, Deserialize)]
struct AslMatrix {
    rows: usize,
    cols: usize,
    data: Vec<f64>,
}

/// The keys of a camera or IMU `sensor.yaml` that matter here; others are ignored.
#[derive(Debug, Deserialize)]
struct RawSensor {
    #[serde(rename = "T_BS")]
    t_bs: Option<AslMatrix>,
    rate_hz: Option<f64>,
    resolution: Option<[u32; 2]>,
    camera_model: Option<String>,
    intrinsics: Option<[f64; 4]>,
    distortion_model: Option<String>,
    distortion_coefficients: Option<Vec<f64>>,
    gyroscope_noise_density: Option<f64>,
    gyroscope_random_walk: Option<f64>,
    accelerometer_noise_density: Option<f64>,
    accelerometer_random_walk: Option<f64>,
}

/// An IMU's continuous-time noise, as its `sensor.yaml` gives it.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct ImuNoiseSpec {
    /// Gyroscope white noise, rad/s/√Hz.
    pub gyroscope_noise_density: f64,
    /// Gyroscope bias random walk, rad/s²/√Hz.
    pub gyroscope_random_walk: f64,
    /// Accelerometer white noise, m/s²/√Hz.
    pub accelerometer_noise_density: f64,
    /// Accelerometer bias random walk, m/s³/√Hz.
    pub accelerometer_random_walk: f64,
}

impl ImuNoiseSpec {
    /// Sets the filter's IMU noise to this one.
    pub fn apply(&self, opts: &mut common::estimator_options::EstimatorOptions) {
        opts.imu.gyro_noise_density = self.gyroscope_noise_density;
        opts.imu.gyro_random_walk = self.gyroscope_random_walk;
        opts.imu.accel_noise_density = self.accelerometer_noise_density;
        opts.imu.accel_random_walk = self.accelerometer_random_walk;
    }
}

/// A parsed camera sensor.
#[derive(Clone, Debug, PartialEq)]
pub struct CameraSensor {
    /// Intrinsics, distortion and image size.
    pub camera: CameraModel,
    /// `T_BS`: the camera pose in the body frame.
    pub t_bs: Matrix4<f64>,
    /// Frame rate, Hz (if given).
    pub rate_hz: Option<f64>,
}

fn parse(text: &str) -> Result<RawSensor, String> {
    let yaml: String = text
        .lines()
        .filter(|l| !l.trim_start().starts_with('%'))
        .collect::<Vec<_>>()
        .join("\n");
    serde_yaml::from_str(&yaml).map_err(|e| e.to_string())
}

fn matrix4(m: &AslMatrix) -> Result<Matrix4<f64>, String> {
    if m.rows != 4 || m.cols != 4 || m.data.len() != 16 {
        return Err(format!(
            "T_BS must be 4x4 with 16 values, got {}x{} with {}",
            m.rows,
            m.cols,
            m.data.len()
        ));
    }
    if m.data.iter().any(|v| !v.is_finite()) {
        return Err("T_BS has a non-finite value".into());
    }
    let t = Matrix4::from_row_slice(&m.data);
    let r: Matrix3<f64> = t.fixed_view::<3, 3>(0, 0).into_owned();
    if (r.transpose() * r - Matrix3::identity()).norm() > 1e-3 {
        return Err("T_BS rotation is not orthonormal".into());
    }
    Ok(t)
}

/// `T_BS` of a sensor file (identity when absent, as for EuRoC's IMU).
pub fn parse_t_bs(text: &str) -> Result<Matrix4<f64>, String> {
    match parse(text)?.t_bs {
        Some(m) => matrix4(&m),
        None => Ok(Matrix4::identity()),
    }
}

/// An IMU `sensor.yaml`'s noise: all four values, or `None` if it gives
/// none; some but not all, or one not finite and positive, is an error.
pub fn parse_imu_noise(text: &str) -> Result<Option<ImuNoiseSpec>, String> {
    let raw = parse(text)?;
    let named = [
        ("gyroscope_noise_density", raw.gyroscope_noise_density),
        ("gyroscope_random_walk", raw.gyroscope_random_walk),
        (
            "accelerometer_noise_density",
            raw.accelerometer_noise_density,
        ),
        ("accelerometer_random_walk", raw.accelerometer_random_walk),
    ];
    if named.iter().all(|(_, v)| v.is_none()) {
        return Ok(None);
    }
    let mut values = [0.0; 4];
    for ((name, v), out) in named.into_iter().zip(&mut values) {
        let v =
            v.ok_or_else(|| format!("{name} is missing (the IMU noise needs all four values)"))?;
        if !(v.is_finite() && v > 0.0) {
            return Err(format!("{name} must be finite and positive, got {v}"));
        }
        *out = v;
    }
    Ok(Some(ImuNoiseSpec {
        gyroscope_noise_density: values[0],
        gyroscope_random_walk: values[1],
        accelerometer_noise_density: values[2],
        accelerometer_random_walk: values[3],
    }))
}

/// A camera `sensor.yaml`: pinhole with `radial-tangential` (or `radtan`) or
/// `equidistant` distortion.
pub fn parse_camera(text: &str) -> Result<CameraSensor, String> {
    let raw = parse(text)?;
    if let Some(model) = &raw.camera_model {
        if model != "pinhole" {
            return Err(format!(
                "camera_model `{model}` is not supported (pinhole only)"
            ));
        }
    }
    let model = match raw.distortion_model.as_deref() {
        Some("radial-tangential") | Some("radtan") | Some("plumb_bob") => Distortion::RadTan,
        Some("equidistant") | Some("fisheye") => Distortion::Equidistant,
        Some(other) => return Err(format!("distortion_model `{other}` is not supported")),
        None => return Err("distortion_model is missing".into()),
    };
    let [width, height] = raw.resolution.ok_or("resolution is missing")?;
    let k = raw.intrinsics.ok_or("intrinsics are missing")?;
    let d = raw
        .distortion_coefficients
        .ok_or("distortion_coefficients are missing")?;
    if d.len() != 4 {
        return Err(format!("need 4 distortion_coefficients, got {}", d.len()));
    }
    let camera = CameraModel {
        model,
        width,
        height,
        intrinsics: Vector4::from(k),
        distortion: Vector4::new(d[0], d[1], d[2], d[3]),
    };
    camera.validate().map_err(|e| e.to_string())?;
    if let Some(r) = raw.rate_hz {
        if !(r.is_finite() && r > 0.0) {
            return Err(format!("rate_hz must be positive, got {r}"));
        }
    }
    Ok(CameraSensor {
        camera,
        t_bs: match &raw.t_bs {
            Some(m) => matrix4(m)?,
            None => return Err("T_BS is missing".into()),
        },
        rate_hz: raw.rate_hz,
    })
}

/// Rotation and translation of a homogeneous transform.
pub fn split(t: &Matrix4<f64>) -> (Matrix3<f64>, Vector3<f64>) {
    (
        t.fixed_view::<3, 3>(0, 0).into_owned(),
        t.fixed_view::<3, 1>(0, 3).into_owned(),
    )
}

#[cfg(test)]
mod tests {
    use super::*;

    const CAM0: &str = "%YAML:1.0\nsensor_type: camera\nT_BS:\n  cols: 4\n  rows: 4\n  data: [1.0, 0.0, 0.0, 0.1, 0.0, 1.0, 0.0, 0.2, 0.0, 0.0, 1.0, 0.3, 0.0, 0.0, 0.0, 1.0]\nrate_hz: 20\nresolution: [752, 480]\ncamera_model: pinhole\nintrinsics: [458.654, 457.296, 367.215, 248.375]\ndistortion_model: radial-tangential\ndistortion_coefficients: [-0.28, 0.07, 0.0002, 0.00002]\n";

    #[test]
    fn reads_an_asl_camera_file_with_its_opencv_directive() {
        let s = parse_camera(CAM0).expect("valid");
        assert_eq!(s.camera.width, 752);
        assert_eq!(s.camera.model, Distortion::RadTan);
        assert_eq!(s.rate_hz, Some(20.0));
        assert_eq!(split(&s.t_bs).1, Vector3::new(0.1, 0.2, 0.3));
    }

    #[test]
    fn bad_camera_files_name_the_problem() {
        let fisheye_free = CAM0.replace("radial-tangential", "kannala");
        assert!(parse_camera(&fisheye_free).unwrap_err().contains("kannala"));
        let no_res = CAM0.replace("resolution: [752, 480]\n", "");
        assert!(parse_camera(&no_res).unwrap_err().contains("resolution"));
        let bad_t = CAM0.replace("cols: 4", "cols: 3");
        assert!(parse_camera(&bad_t).unwrap_err().contains("4x4"));
        assert!(parse_camera("::: not yaml").is_err());
        assert_eq!(
            parse_t_bs("sensor_type: imu\n").unwrap(),
            Matrix4::identity()
        );
    }

    #[test]
    fn reads_an_imu_file_s_noise_and_refuses_half_of_one() {
        let imu = "%YAML:1.0\nsensor_type: imu\nT_BS:\n  cols: 4\n  rows: 4\n  data: [1.0, 0.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 0.0, 1.0]\nrate_hz: 200\ngyroscope_noise_density: 1.6968e-04     # [ rad / s / sqrt(Hz) ]\ngyroscope_random_walk: 1.9393e-05\naccelerometer_noise_density: 2.0000e-3\naccelerometer_random_walk: 3.0000e-3\n";
        let n = parse_imu_noise(imu).unwrap().unwrap();
        assert_eq!(n.gyroscope_noise_density, 1.6968e-4);
        assert_eq!(n.accelerometer_random_walk, 3.0e-3);
        assert_eq!(parse_imu_noise("rate_hz: 200\n").unwrap(), None);
        let half = "gyroscope_noise_density: 1e-4\naccelerometer_noise_density: 2e-3\n";
        assert!(parse_imu_noise(half)
            .unwrap_err()
            .contains("gyroscope_random_walk"));
        let negative = imu.replace("2.0000e-3", "-2.0e-3");
        assert!(parse_imu_noise(&negative)
            .unwrap_err()
            .contains("accelerometer_noise_density"));
    }
}
