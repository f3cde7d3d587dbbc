//! One robot of a fleet as a sequence in the EuRoC ASL layout, with rendered
//! images: `mav0/cam0/{data.csv, data/<ns>.png, sensor.yaml}`,
//! `mav0/imu0/{data.csv, sensor.yaml}` and the ground truth in
//! `mav0/state_groundtruth_estimate0/data.csv` (pose, velocity and the true
//! biases at each image).
//!
//! It gives a moving sequence with a known truth to everything that reads
//! EuRoC: `agent dataset`, `agent publish-euroc` feeding `agent live`, and other
//! VIO systems. The calibration files hold the true calibration. The IMU file
//! holds the scenario's noise densities. The stamps are the fleet clock's, in
//! nanoseconds.

use crate::{Fleet, SimError, SimEvent};
use std::fmt::Write as _;
use std::io::Write as _;
use std::path::{Path, PathBuf};
use thiserror::Error;

/// Why a sequence could not be written.
#[derive(Debug, Error)]
pub enum ExportError {
    /// The fleet has no such robot, or its stream failed.
    #[error(transparent)]
    Sim(#[from] SimError),
    /// The fleet renders no images (its scenario's `render.enabled` is off).
    #[error("the fleet renders no images: switch `render.enabled` on")]
    NoImages,
    /// A file could not be written.
    #[error("{}: {source}", path.display())]
    Io {
        /// The file.
        path: PathBuf,
        /// The cause.
        source: std::io::Error,
    },
    /// An image could not be encoded.
    #[error("image at t={t}: {source}")]
    Image {
        /// Its time, s.
        t: f64,
        /// The cause.
        source: common::image::ImageError,
    },
}

/// What [`export_euroc`] wrote.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct Exported {
    /// Images (and ground-truth rows).
    pub images: u64,
    /// IMU samples.
    pub imu: u64,
}

/// Nanoseconds of a fleet time, as EuRoC stamps.
fn ns(t: f64) -> i64 {
    (t * 1e9).round() as i64
}

struct Files {
    root: PathBuf,
}

impl Files {
    fn path(&self, rel: &str) -> PathBuf {
        self.root.join(rel)
    }

    fn io(&self, path: &Path) -> impl FnOnce(std::io::Error) -> ExportError + '_ {
        let path = path.to_path_buf();
        move |source| ExportError::Io { path, source }
    }

    fn create(&self, rel: &str) -> Result<std::io::BufWriter<std::fs::File>, ExportError> {
        let path = self.path(rel);
        if let Some(dir) = path.parent() {
            std::fs::create_dir_all(dir).map_err(self.io(dir))?;
        }
        let file = std::fs::File::create(&path).map_err(self.io(&path))?;
        Ok(std::io::BufWriter::new(file))
    }

    fn write(&self, rel: &str, text: &str) -> Result<(), ExportError> {
        let path = self.path(rel);
        let mut w = self.create(rel)?;
        w.write_all(text.as_bytes())
            .and_then(|()| w.flush())
            .map_err(self.io(&path))
    }
}

/// A 4x4 matrix the way ASL's `sensor.yaml` writes it.
fn t_bs_yaml(rows: [[f64; 4]; 3]) -> String {
    let mut data: Vec<String> = rows.iter().flatten().map(|v| format!("{v:.12}")).collect();
    data.extend(["0.0", "0.0", "0.0", "1.0"].map(String::from));
    format!(
        "T_BS:\n  cols: 4\n  rows: 4\n  data: [{}]\n",
        data.join(", ")
    )
}

/// Writes robot `robot` of `fleet` (whose scenario renders images) up to
/// fleet time `t_end` into `dir/mav0`; `origin` names where it came from in the
/// camera file's comment.
pub fn export_euroc(
    fleet: &Fleet,
    robot: usize,
    t_end: f64,
    dir: &Path,
    origin: &str,
) -> Result<Exported, ExportError> {
    if !fleet.renders() {
        return Err(ExportError::NoImages);
    }
    let files = Files {
        root: dir.join("mav0"),
    };
    let scenario = &fleet.scenario;
    let cam = &scenario.camera(robot);
    let imu = &scenario.sensors.imu;
    let model = match cam.model {
        common::camera::Distortion::RadTan => "radial-tangential",
        common::camera::Distortion::Equidistant => "equidistant",
    };
    let mut cam_yaml = format!(
        "%YAML:1.0\n# {origin} (robot {robot}, seed {}): rendered, with the true calibration.\n\
         sensor_type: camera\ncomment: simulated cam0\n",
        fleet.seed
    );
    cam_yaml += &t_bs_yaml(cam.t_imu_cam);
    let [fx, fy, cx, cy] = cam.intrinsics_px;
    let [d0, d1, d2, d3] = cam.distortion;
    let _ = write!(
        cam_yaml,
        "rate_hz: {}\nresolution: [{}, {}]\ncamera_model: pinhole\nintrinsics: [{fx}, {fy}, {cx}, {cy}]\n\
         distortion_model: {model}\ndistortion_coefficients: [{d0}, {d1}, {d2}, {d3}]\n",
        cam.rate_hz, cam.width_px, cam.height_px
    );
    files.write("cam0/sensor.yaml", &cam_yaml)?;
    let mut imu_yaml = String::from("%YAML:1.0\nsensor_type: imu\ncomment: simulated imu0\n");
    imu_yaml += &t_bs_yaml([
        [1.0, 0.0, 0.0, 0.0],
        [0.0, 1.0, 0.0, 0.0],
        [0.0, 0.0, 1.0, 0.0],
    ]);
    let _ = write!(
        imu_yaml,
        "rate_hz: {}\ngyroscope_noise_density: {}\ngyroscope_random_walk: {}\n\
         accelerometer_noise_density: {}\naccelerometer_random_walk: {}\n",
        imu.rate_hz,
        imu.gyro_noise_density,
        imu.gyro_random_walk,
        imu.accel_noise_density,
        imu.accel_random_walk
    );
    files.write("imu0/sensor.yaml", &imu_yaml)?;

    let (imu_path, cam_path, gt_path) = (
        files.path("imu0/data.csv"),
        files.path("cam0/data.csv"),
        files.path("state_groundtruth_estimate0/data.csv"),
    );
    let mut imu_csv = files.create("imu0/data.csv")?;
    let mut cam_csv = files.create("cam0/data.csv")?;
    let mut gt_csv = files.create("state_groundtruth_estimate0/data.csv")?;
    let images = files.path("cam0/data");
    std::fs::create_dir_all(&images).map_err(files.io(&images))?;
    (|| {
        writeln!(
            imu_csv,
            "#timestamp [ns],w_RS_S_x [rad s^-1],w_RS_S_y [rad s^-1],w_RS_S_z [rad s^-1],\
             a_RS_S_x [m s^-2],a_RS_S_y [m s^-2],a_RS_S_z [m s^-2]"
        )?;
        writeln!(cam_csv, "#timestamp [ns],filename")?;
        writeln!(
            gt_csv,
            "#timestamp, p_RS_R_x [m], p_RS_R_y [m], p_RS_R_z [m], q_RS_w [], q_RS_x [], q_RS_y [], q_RS_z [], \
             v_RS_R_x [m s^-1], v_RS_R_y [m s^-1], v_RS_R_z [m s^-1], b_w_RS_S_x [rad s^-1], b_w_RS_S_y [rad s^-1], \
             b_w_RS_S_z [rad s^-1], b_a_RS_S_x [m s^-2], b_a_RS_S_y [m s^-2], b_a_RS_S_z [m s^-2]"
        )
    })()
    .map_err(files.io(&gt_path))?;
    let mut out = Exported::default();
    for ev in fleet.stream(robot)? {
        match ev {
            SimEvent::Imu(s) if s.t <= t_end => {
                let (w, a) = (s.gyro, s.accel);
                writeln!(
                    imu_csv,
                    "{},{:.17e},{:.17e},{:.17e},{:.17e},{:.17e},{:.17e}",
                    ns(s.t),
                    w.x,
                    w.y,
                    w.z,
                    a.x,
                    a.y,
                    a.z
                )
                .map_err(files.io(&imu_path))?;
                out.imu += 1;
            }
            SimEvent::Camera(c) if c.frame.t <= t_end => {
                let t = c.frame.t;
                let image = c.image.as_deref().ok_or(ExportError::NoImages)?;
                let png = image
                    .to_png()
                    .map_err(|source| ExportError::Image { t, source })?;
                let name = format!("{}.png", ns(t));
                let path = images.join(&name);
                std::fs::write(&path, png).map_err(files.io(&path))?;
                writeln!(cam_csv, "{},{name}", ns(t)).map_err(files.io(&cam_path))?;
                let g = &c.truth;
                let q = nalgebra::UnitQuaternion::from_matrix(&g.rot);
                let (bw, ba) = (g.biases.gyro, g.biases.accel);
                writeln!(
                    gt_csv,
                    "{},{:.9},{:.9},{:.9},{:.12},{:.12},{:.12},{:.12},{:.9},{:.9},{:.9},{:.12e},{:.12e},{:.12e},{:.12e},{:.12e},{:.12e}",
                    ns(g.t),
                    g.pos.x,
                    g.pos.y,
                    g.pos.z,
                    q.w,
                    q.i,
                    q.j,
                    q.k,
                    g.vel.x,
                    g.vel.y,
                    g.vel.z,
                    bw.x,
                    bw.y,
                    bw.z,
                    ba.x,
                    ba.y,
                    ba.z
                )
                .map_err(files.io(&gt_path))?;
                out.images += 1;
            }
            // The stream is in time order: the rest is past the end.
            _ => break,
        }
    }
    for (mut w, path) in [(imu_csv, imu_path), (cam_csv, cam_path), (gt_csv, gt_path)] {
        w.flush().map_err(files.io(&path))?;
    }
    Ok(out)
}
