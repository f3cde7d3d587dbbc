//! A sequence in the EuRoC ASL layout: `mav0/cam0/{data.csv, data/*.png,
//! sensor.yaml}`, `mav0/imu0/{data.csv, sensor.yaml}` and, when present, the
//! ground truth `mav0/state_groundtruth_estimate0/data.csv` (or `gt0`). TUM-VI
//! sequences in their EuRoC export have the same layout (16-bit images are
//! read by their high byte).
//!
//! Times are seconds of the sensors' common clock (EuRoC's nanoseconds). The
//! camera extrinsics are `T_CtoI = T_BI⁻¹ · T_BC` from the two sensor files'
//! `T_BS` (body to IMU is the identity in EuRoC, whose IMU file may be absent).

use super::sensor_yaml::{parse_camera, parse_imu_noise, parse_t_bs, split, ImuNoiseSpec};
use crate::estimator::static_init::{read_euroc_imu_csv, ImuCsvError};
use common::calibration::CameraCalibration;
use common::image::{GrayImage, ImageError};
use common::measurement::{FeatureFrame, ImuSample};
use common::trajectory::{interpolate_pose, read_euroc_csv, StampedPose, TrajectoryError};
use nalgebra::{Matrix4, Vector3};
use simulator::camera_sim::{CameraEvent, TruthState};
use simulator::imu::Biases;
use simulator::SimEvent;
use std::path::{Path, PathBuf};
use std::sync::Arc;
use thiserror::Error;

/// Largest accepted image file, bytes (a 16-bit 1024x1024 PNG is about 2 MB).
const MAX_IMAGE_FILE_BYTES: u64 = 64 << 20;
/// Largest accepted line of `cam0/data.csv`, bytes.
const MAX_CSV_LINE_BYTES: usize = 4096;

/// Why a dataset could not be read.
#[derive(Debug, Error)]
pub enum DatasetError {
    /// A file could not be read.
    #[error("{}: {source}", path.display())]
    Io {
        /// The file.
        path: PathBuf,
        /// The cause.
        source: std::io::Error,
    },
    /// A file is malformed.
    #[error("{}: {what}", path.display())]
    Malformed {
        /// The file.
        path: PathBuf,
        /// What is wrong.
        what: String,
    },
    /// The IMU file is malformed.
    #[error(transparent)]
    Imu(#[from] ImuCsvError),
    /// The ground-truth file is malformed.
    #[error(transparent)]
    GroundTruth(#[from] TrajectoryError),
    /// An image does not decode.
    #[error("{}: {source}", path.display())]
    Image {
        /// The file.
        path: PathBuf,
        /// The cause.
        source: ImageError,
    },
}

/// One image of the sequence: its time and file.
#[derive(Clone, Debug, PartialEq)]
pub struct ImageStamp {
    /// Camera time, s.
    pub t: f64,
    /// The PNG file.
    pub path: PathBuf,
}

/// A sequence: camera calibration, image list, IMU samples and ground truth.
#[derive(Clone, Debug)]
pub struct EurocDataset {
    /// The `mav0` folder.
    pub root: PathBuf,
    /// cam0's calibration (`time_offset_s` 0: the clocks are synchronized).
    pub calibration: CameraCalibration,
    /// cam0's frame rate, Hz (from `sensor.yaml`, else from the stamps).
    pub rate_hz: f64,
    /// The images in time order.
    pub images: Vec<ImageStamp>,
    /// The IMU samples in time order.
    pub imu: Vec<ImuSample>,
    /// The ground truth (`R_ItoG`, `p_IinG`), if the sequence has one.
    pub groundtruth: Option<Vec<StampedPose>>,
    /// The IMU's noise from `imu0/sensor.yaml`, if it gives it.
    pub imu_noise: Option<ImuNoiseSpec>,
}

fn io(path: &Path) -> impl FnOnce(std::io::Error) -> DatasetError + '_ {
    move |source| DatasetError::Io {
        path: path.to_path_buf(),
        source,
    }
}

fn malformed(path: &Path, what: impl Into<String>) -> DatasetError {
    DatasetError::Malformed {
        path: path.to_path_buf(),
        what: what.into(),
    }
}

/// The folder holding the sensor folders: `dir/mav0` when there is one, else `dir`.
pub fn mav0_root(dir: &Path) -> PathBuf {
    if dir.join("mav0").is_dir() {
        dir.join("mav0")
    } else {
        dir.to_path_buf()
    }
}

/// What the sensor files of the EuRoC (Kalibr) layout say: `cam0/sensor.yaml`
/// and, when present, `imu0/sensor.yaml`. A sequence has them beside its data;
/// a live robot keeps them in a folder of their own.
#[derive(Clone, Debug)]
pub struct SensorSetup {
    /// cam0's calibration (`time_offset_s` 0: the clocks are synchronized).
    pub calibration: CameraCalibration,
    /// cam0's frame rate, Hz, if `sensor.yaml` gives it.
    pub rate_hz: Option<f64>,
    /// The IMU's noise, if `imu0/sensor.yaml` gives it.
    pub imu_noise: Option<ImuNoiseSpec>,
}

impl SensorSetup {
    /// Reads `root/cam0/sensor.yaml` and `root/imu0/sensor.yaml` (body to IMU
    /// is the identity without it).
    pub fn load(root: &Path) -> Result<Self, DatasetError> {
        let cam_yaml = root.join("cam0/sensor.yaml");
        let text = std::fs::read_to_string(&cam_yaml).map_err(io(&cam_yaml))?;
        let cam = parse_camera(&text).map_err(|w| malformed(&cam_yaml, w))?;
        let imu_yaml = root.join("imu0/sensor.yaml");
        let (t_bi, imu_noise) = match std::fs::read_to_string(&imu_yaml) {
            Ok(text) => (
                parse_t_bs(&text).map_err(|w| malformed(&imu_yaml, w))?,
                parse_imu_noise(&text).map_err(|w| malformed(&imu_yaml, w))?,
            ),
            Err(e) if e.kind() == std::io::ErrorKind::NotFound => (Matrix4::identity(), None),
            Err(e) => return Err(io(&imu_yaml)(e)),
        };
        let t_bi_inv = t_bi
            .try_inverse()
            .ok_or_else(|| malformed(&imu_yaml, "T_BS is singular"))?;
        let (rot_c_to_i, p_c_in_i) = split(&(t_bi_inv * cam.t_bs));
        Ok(Self {
            calibration: CameraCalibration {
                camera: cam.camera,
                rot_c_to_i: common::so3::orthonormalize(&rot_c_to_i),
                p_c_in_i,
                time_offset_s: 0.0,
            },
            rate_hz: cam.rate_hz,
            imu_noise,
        })
    }
}

impl EurocDataset {
    /// Opens the sequence at `dir` (the folder holding `mav0`, or `mav0` itself).
    /// `groundtruth` overrides the sequence's own ground-truth file.
    pub fn open(dir: &Path, groundtruth: Option<&Path>) -> Result<Self, DatasetError> {
        let root = mav0_root(dir);
        let sensors = SensorSetup::load(&root)?;
        let images = read_image_list(&root.join("cam0"))?;
        let rate_hz = sensors.rate_hz.unwrap_or_else(|| rate_from(&images));
        let imu = read_euroc_imu_csv(root.join("imu0/data.csv"))?;
        let gt_path = match groundtruth {
            Some(p) => Some(p.to_path_buf()),
            None => ["state_groundtruth_estimate0/data.csv", "gt0/data.csv"]
                .iter()
                .map(|r| root.join(r))
                .find(|p| p.is_file()),
        };
        let groundtruth = gt_path.map(read_euroc_csv).transpose()?;
        Ok(Self {
            root,
            calibration: sensors.calibration,
            rate_hz,
            images,
            imu,
            groundtruth,
            imu_noise: sensors.imu_noise,
        })
    }

    /// Decodes image `index`.
    pub fn image(&self, index: usize) -> Result<GrayImage, DatasetError> {
        let stamp = self
            .images
            .get(index)
            .ok_or_else(|| malformed(&self.root, format!("no image {index}")))?;
        load_png(&stamp.path)
    }

    /// The true state at IMU time `t` from the ground truth (velocity from a
    /// central difference, biases unknown and zero), if it covers `t`.
    pub fn truth_at(&self, t: f64) -> Option<TruthState> {
        let gt = self.groundtruth.as_ref()?;
        let p = interpolate_pose(gt, t)?;
        let dt = 0.01;
        let vel = match (interpolate_pose(gt, t - dt), interpolate_pose(gt, t + dt)) {
            (Some(a), Some(b)) => (b.pos - a.pos) / (2.0 * dt),
            _ => Vector3::zeros(),
        };
        Some(TruthState {
            t,
            rot: p.rot,
            pos: p.pos,
            vel,
            biases: Biases::default(),
        })
    }

    /// All measurements in time order, as the simulator's events: each image
    /// comes right after the last IMU sample at or before its time, decoded
    /// lazily, with the ground truth when known (else a NaN time).
    pub fn events(&self) -> impl Iterator<Item = Result<SimEvent, DatasetError>> + '_ {
        let mut imu = self.imu.iter().peekable();
        let mut images = self.images.iter().enumerate().peekable();
        std::iter::from_fn(move || {
            let next_image_t = images.peek().map(|(_, s)| s.t);
            match (imu.peek(), next_image_t) {
                (Some(s), Some(ti)) if s.t <= ti => imu.next().map(|s| Ok(SimEvent::Imu(*s))),
                (Some(_), None) => imu.next().map(|s| Ok(SimEvent::Imu(*s))),
                (_, Some(_)) => images.next().map(|(i, stamp)| self.camera_event(i, stamp)),
                (None, None) => None,
            }
        })
    }

    fn camera_event(&self, index: usize, stamp: &ImageStamp) -> Result<SimEvent, DatasetError> {
        let image = self.image(index)?;
        let truth = self.truth_at(stamp.t).unwrap_or(TruthState {
            t: f64::NAN,
            rot: nalgebra::Matrix3::identity(),
            pos: Vector3::zeros(),
            vel: Vector3::zeros(),
            biases: Biases::default(),
        });
        Ok(SimEvent::Camera(Box::new(CameraEvent {
            frame: FeatureFrame {
                t: stamp.t,
                camera: 0,
                features: Vec::new(),
            },
            truth,
            landmark_ids: Vec::new(),
            outlier: Vec::new(),
            image: Some(Arc::new(image)),
        })))
    }
}

/// Reads a PNG file (bounded size) into a gray image.
pub fn load_png(path: &Path) -> Result<GrayImage, DatasetError> {
    let len = std::fs::metadata(path).map_err(io(path))?.len();
    if len > MAX_IMAGE_FILE_BYTES {
        return Err(malformed(
            path,
            format!("{len} bytes is too large for an image"),
        ));
    }
    let bytes = std::fs::read(path).map_err(io(path))?;
    GrayImage::from_png(&bytes).map_err(|source| DatasetError::Image {
        path: path.to_path_buf(),
        source,
    })
}

/// `cam0/data.csv`: `timestamp [ns], filename` lines, increasing times. An
/// unfinished last line (no newline: the recording was cut off) that does not
/// read is dropped with a warning.
fn read_image_list(cam: &Path) -> Result<Vec<ImageStamp>, DatasetError> {
    let csv = cam.join("data.csv");
    let text = std::fs::read_to_string(&csv).map_err(io(&csv))?;
    let lines = text.lines().count();
    let mut out: Vec<ImageStamp> = Vec::new();
    for (k, line) in text.lines().enumerate() {
        match image_line(cam, line, out.last()) {
            Ok(Some(stamp)) => out.push(stamp),
            Ok(None) => {}
            Err(what) if k + 1 == lines && !text.ends_with('\n') => {
                tracing::warn!(
                    "{}: the last line ({}) is cut short and dropped: {what}",
                    csv.display(),
                    k + 1
                );
            }
            Err(what) => return Err(malformed(&csv, format!("line {}: {what}", k + 1))),
        }
    }
    if out.is_empty() {
        return Err(malformed(&csv, "no images"));
    }
    Ok(out)
}

/// One line of `cam0/data.csv` after `previous`: `None` for a blank line or
/// a comment, else the image or what is wrong.
fn image_line(
    cam: &Path,
    line: &str,
    previous: Option<&ImageStamp>,
) -> Result<Option<ImageStamp>, String> {
    let line = line.trim();
    if line.is_empty() || line.starts_with('#') {
        return Ok(None);
    }
    if line.len() > MAX_CSV_LINE_BYTES {
        return Err("line too long".into());
    }
    let mut fields = line.split(',').map(str::trim);
    let ns: u64 = fields
        .next()
        .unwrap_or("")
        .parse()
        .map_err(|e| format!("timestamp: {e}"))?;
    let name = fields
        .next()
        .filter(|n| !n.is_empty())
        .ok_or("no file name")?;
    if name.contains("..") || Path::new(name).is_absolute() {
        return Err(format!("file name `{name}` leaves the data folder"));
    }
    let t = (ns / 1_000_000_000) as f64 + (ns % 1_000_000_000) as f64 * 1e-9;
    if previous.is_some_and(|p| t <= p.t) {
        return Err("timestamps must increase".into());
    }
    Ok(Some(ImageStamp {
        t,
        path: cam.join("data").join(name),
    }))
}

/// Frame rate from the median spacing of the stamps (20 Hz if there is one image).
fn rate_from(images: &[ImageStamp]) -> f64 {
    let mut dts: Vec<f64> = images.windows(2).map(|w| w[1].t - w[0].t).collect();
    dts.sort_by(f64::total_cmp);
    dts.get(dts.len() / 2).map_or(20.0, |dt| 1.0 / dt)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn micro() -> PathBuf {
        PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("../../shared/data/euroc_v1_01_micro")
    }

    #[test]
    fn opens_the_micro_sequence_with_its_calibration_and_interleaves_events() {
        let ds = EurocDataset::open(&micro(), None).expect("dataset");
        assert_eq!(ds.images.len(), 95);
        let cam0 = CameraCalibration::euroc_cam0();
        assert_eq!(ds.calibration.camera, cam0.camera);
        assert_eq!(ds.calibration.p_c_in_i, cam0.p_c_in_i);
        // Re-orthonormalized: equal to the file's digits.
        assert!((ds.calibration.rot_c_to_i - cam0.rot_c_to_i).norm() < 1e-9);
        assert!((ds.rate_hz - 20.0).abs() < 1e-9);
        let img = ds.image(0).expect("png");
        assert_eq!((img.width(), img.height()), (752, 480));
        let mut last = f64::NEG_INFINITY;
        let mut cameras = 0;
        for ev in ds.events().take(2000) {
            let t = match ev.expect("event") {
                SimEvent::Imu(s) => s.t,
                SimEvent::Camera(c) => {
                    cameras += 1;
                    c.frame.t
                }
            };
            assert!(t >= last);
            last = t;
        }
        assert!(cameras >= 95, "{cameras}");
    }

    #[test]
    fn broken_layouts_are_clear_errors() {
        let dir = tempfile::tempdir().expect("tmp");
        let err = EurocDataset::open(dir.path(), None)
            .unwrap_err()
            .to_string();
        assert!(err.contains("sensor.yaml"), "{err}");
        let cam = dir.path().join("mav0/cam0");
        std::fs::create_dir_all(cam.join("data")).expect("mkdir");
        std::fs::copy(
            micro().join("mav0/cam0/sensor.yaml"),
            cam.join("sensor.yaml"),
        )
        .expect("cp");
        std::fs::write(cam.join("data.csv"), "#t,f\n5,a.png\n4,b.png\n").expect("write");
        let err = EurocDataset::open(dir.path(), None)
            .unwrap_err()
            .to_string();
        assert!(err.contains("increase"), "{err}");
        std::fs::write(cam.join("data.csv"), "5,../../etc/passwd\n").expect("write");
        let err = EurocDataset::open(dir.path(), None)
            .unwrap_err()
            .to_string();
        assert!(err.contains("leaves"), "{err}");
        std::fs::write(cam.join("data/x.png"), b"garbage").expect("write");
        assert!(load_png(&cam.join("data/x.png")).is_err());
    }

    /// A recording cut off mid-write: the image list's unfinished last line
    /// is dropped; the same line finished is an error naming it.
    #[test]
    fn an_image_list_cut_short_loses_its_last_line() {
        let dir = tempfile::tempdir().expect("tmp");
        let cam = dir.path();
        std::fs::write(cam.join("data.csv"), "#t,f\n5,a.png\n6,b.png\n4").expect("write");
        let images = read_image_list(cam).expect("the cut line is dropped");
        assert_eq!(images.len(), 2);
        std::fs::write(cam.join("data.csv"), "#t,f\n5,a.png\n6,b.png\n4\n").expect("write");
        let err = read_image_list(cam).unwrap_err().to_string();
        assert!(err.contains("line 4"), "{err}");
        std::fs::write(cam.join("data.csv"), "5,a.png\n6,b.png").expect("write");
        assert_eq!(read_image_list(cam).expect("whole").len(), 2);
    }
}
