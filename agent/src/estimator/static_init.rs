//! Static IMU initialization (thesis Section 2.3.6.1, Eqs. 2.78-2.81, as
//! OpenVINS `StaticInitializer`).
//!
//! While the platform stands still, the accelerometer measures only the
//! reaction to gravity, `a_m = R_ItoGᵀ [0, 0, g] + b_a` (see
//! [`common::conventions`]): it points **up**, expressed in `I`. Its mean over a
//! window gives roll and pitch; yaw is unobservable and chosen so that the IMU's
//! `x` axis, projected onto the horizontal plane, lies along the global `x`.
//! The mean gyroscope reading is the gyroscope bias.
//!
//! [`read_euroc_imu_csv`] reads IMU logs in the EuRoC ASL layout, for tests and
//! real-data replay.

use std::io::{BufRead, BufReader, Read};
use std::path::{Path, PathBuf};

use crate::estimator::InitialState;
use common::measurement::ImuSample;
use nalgebra::{Matrix3, Vector3};

/// Fewest samples a window must hold.
const MIN_SAMPLES: usize = 10;
/// The samples of a window must span at least this fraction of `window_s`.
const MIN_SPAN_FRACTION: f64 = 0.9;
/// Largest accepted difference between the mean specific force's norm and
/// gravity (m/s²): a bigger one means the platform accelerates steadily (or the
/// units are wrong), so the mean is not the gravity direction.
const MAX_GRAVITY_MISMATCH_MPS2: f64 = 1.0;
/// Below this norm, the IMU `x` axis is too close to vertical to fix the yaw and
/// the `y` axis is used instead.
const MIN_HORIZONTAL_AXIS_NORM: f64 = 0.1;

/// Options of [`static_initialize`].
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct StaticInitOptions {
    /// Length of the window (s) ending at the latest sample.
    pub window_s: f64,
    /// Excitation threshold: the accelerometer standard deviation over the window
    /// (m/s², see [`StaticInitResult::accel_std`]) must be below this to count as
    /// static.
    pub max_accel_std_mps2: f64,
    /// The gyroscope standard deviation over the window (rad/s, see
    /// [`StaticInitResult::gyro_std`]) must be below this to count as static.
    pub max_gyro_std_radps: f64,
    /// Gravity magnitude (m/s²).
    pub gravity_mps2: f64,
}

impl Default for StaticInitOptions {
    /// 2 s window, thresholds 1.0 m/s² and 0.1 rad/s, gravity 9.81 m/s².
    ///
    /// The thresholds are tuned on real EuRoC data, where the MAV stands with
    /// its rotors spinning: their vibration gives 2 s windows of 0.34-0.88 m/s²
    /// and 0.02-0.07 rad/s while standing (V1_01, V1_02), whereas no 2 s window
    /// of the V1_01 flight has both below 1.06 m/s² and 0.09 rad/s, and the
    /// V1_02 flight stays above 1.3 m/s² and 0.22 rad/s. A platform without
    /// vibration (sensor noise alone) shows about 0.05 m/s² and 0.005 rad/s.
    fn default() -> Self {
        Self {
            window_s: 2.0,
            max_accel_std_mps2: 1.0,
            max_gyro_std_radps: 0.1,
            gravity_mps2: common::conventions::GRAVITY_MPS2,
        }
    }
}

/// Prior standard deviations after a static start (position and yaw are
/// defined by the start itself; velocity is known to be zero).
pub fn static_start_sigmas() -> InitialState {
    InitialState {
        t: 0.0,
        rot: Matrix3::identity(),
        pos: Vector3::zeros(),
        vel: Vector3::zeros(),
        bias_gyro: Vector3::zeros(),
        bias_accel: Vector3::zeros(),
        sigma_ori_rad: 0.017,
        sigma_yaw_rad: None,
        sigma_pos_m: 0.001,
        sigma_vel_mps: 0.01,
        // The gyroscope's bias is the mean reading at rest; the accelerometer's
        // is unknown at rest (only its sum with gravity shows), and real ones
        // are far from zero: EuRoC V1_01's ground truth has 0.066 m/s² on y.
        // At 0.02 the tilt would be claimed to 0.12 deg; 0.1 allows 0.6 deg
        // (V1_01 micro with zero-velocity updates: orientation NEES 1.5, 25
        // at 0.02, against a truth 0.54-0.76 deg off in tilt).
        sigma_bias_gyro: 0.02,
        sigma_bias_accel: 0.1,
    }
}

/// The initial state found by [`static_initialize`].
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct StaticInitResult {
    /// Time of the state: the latest sample of the window (s, IMU clock).
    pub t: f64,
    /// Orientation `R_ItoG`: roll and pitch from gravity, yaw by convention
    /// (IMU `x` axis projected onto the horizontal plane along global `x`).
    pub rot_i_to_g: Matrix3<f64>,
    /// Gyroscope bias: the mean angular rate over the window (rad/s).
    pub bias_gyro: Vector3<f64>,
    /// Accelerometer bias: zero. From a static window only the component along
    /// gravity, `|ā| - g`, could be estimated, and it is indistinguishable from a
    /// gravity magnitude or scale error; the horizontal components are absorbed
    /// into the tilt. As OpenVINS, the bias is left to the filter (m/s²).
    pub bias_accel: Vector3<f64>,
    /// Velocity in `G`: zero, the platform is static (m/s).
    pub velocity: Vector3<f64>,
    /// Accelerometer standard deviation over the window (m/s²): the root of the
    /// summed per-axis sample variances, `sqrt(Σ|a_i - ā|² / (N - 1))`.
    pub accel_std: f64,
    /// Gyroscope standard deviation over the window (rad/s), defined as
    /// [`StaticInitResult::accel_std`].
    pub gyro_std: f64,
    /// Standard error of [`StaticInitResult::bias_gyro`], rad/s, largest
    /// over the axes: how well the window measured the bias. A platform
    /// "at rest" may still wobble slowly (a drone on its skids, the
    /// motion-capture jitter a simulator's B-spline follows), and its
    /// readings are then correlated over tenths of a second, so the error
    /// is estimated from the scatter of the means of [`BIAS_BLOCK_S`]
    /// blocks (batch means), not from the samples as if independent.
    pub bias_gyro_sigma: f64,
}

/// Length of the blocks whose mean readings give
/// [`StaticInitResult::bias_gyro_sigma`], s: as long as the zero-velocity
/// updates' reading windows (one camera period), so that a wobble slow
/// enough to fool one of them shows in the blocks' scatter.
pub const BIAS_BLOCK_S: f64 = 0.1;

/// Fewest whole blocks for [`StaticInitResult::bias_gyro_sigma`]; with fewer
/// it is infinite (unknown).
const MIN_BIAS_BLOCKS: usize = 5;

/// Batch-means standard error of the mean gyro reading of `window`, the
/// largest over the axes (see [`StaticInitResult::bias_gyro_sigma`]).
fn gyro_mean_standard_error(window: &[ImuSample]) -> f64 {
    let Some(first) = window.first() else {
        return f64::INFINITY;
    };
    let mut means: Vec<Vector3<f64>> = Vec::new();
    let (mut sum, mut n, mut block) = (Vector3::zeros(), 0usize, 0usize);
    for s in window {
        let b = ((s.t - first.t) / BIAS_BLOCK_S).floor() as usize;
        if b != block {
            if n > 0 {
                means.push(sum / n as f64);
            }
            (sum, n, block) = (Vector3::zeros(), 0, b);
        }
        sum += s.gyro;
        n += 1;
    }
    // The last block is partial unless the window ends on a boundary: left out.
    let k = means.len();
    if k < MIN_BIAS_BLOCKS {
        return f64::INFINITY;
    }
    let mean: Vector3<f64> = means.iter().sum::<Vector3<f64>>() / k as f64;
    let mut var = Vector3::<f64>::zeros();
    for m in &means {
        var += (m - mean).component_mul(&(m - mean)) / (k - 1) as f64;
    }
    (var.max() / k as f64).sqrt()
}

/// Why [`static_initialize`] did not initialize.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum StaticInitError {
    /// The options are invalid (non-positive or non-finite window, thresholds or gravity).
    #[error("invalid static initialization options: {0}")]
    BadOptions(&'static str),
    /// Too few samples in the window.
    #[error("only {found} IMU samples in the window, need at least {needed}")]
    TooFewSamples {
        /// Samples in the window.
        found: usize,
        /// Samples needed.
        needed: usize,
    },
    /// The samples do not cover enough of the window.
    #[error("IMU samples span {span_s:.3} s, need at least {needed_s:.3} s")]
    TooShort {
        /// Time between the first and last samples of the window (s).
        span_s: f64,
        /// Span needed (s).
        needed_s: f64,
    },
    /// A sample has a NaN or infinite value.
    #[error("IMU sample {index} has a non-finite time or value")]
    NotFinite {
        /// Index of the sample in the input.
        index: usize,
    },
    /// Sample times decrease.
    #[error("IMU sample {index} is earlier than the sample before it")]
    NotSorted {
        /// Index of the sample in the input.
        index: usize,
    },
    /// The platform moves: the accelerometer or gyroscope varies too much.
    #[error(
        "too much motion to initialize statically: accel std {accel_std:.4} m/s² \
         (max {max_accel_std:.4}), gyro std {gyro_std:.5} rad/s (max {max_gyro_std:.5})"
    )]
    TooMuchMotion {
        /// Accelerometer standard deviation (m/s²).
        accel_std: f64,
        /// Its threshold (m/s²).
        max_accel_std: f64,
        /// Gyroscope standard deviation (rad/s).
        gyro_std: f64,
        /// Its threshold (rad/s).
        max_gyro_std: f64,
    },
    /// The mean specific force is not gravity.
    #[error("mean specific force {norm:.3} m/s² is not gravity {gravity:.3} m/s²")]
    NotGravity {
        /// Norm of the mean accelerometer reading (m/s²).
        norm: f64,
        /// The configured gravity (m/s²).
        gravity: f64,
    },
}

/// Initializes orientation and gyroscope bias from the latest `opts.window_s`
/// seconds of `samples` (sorted by time), if the platform stood still during it.
///
/// The window holds every sample with `t >= t_last - window_s`. It is rejected
/// when it has fewer than 10 samples or spans less than 90% of the window, has
/// non-finite or unsorted samples, when either standard deviation exceeds its
/// threshold, or when the mean specific force differs from gravity by more than
/// 1 m/s².
pub fn static_initialize(
    samples: &[ImuSample],
    opts: &StaticInitOptions,
) -> Result<StaticInitResult, StaticInitError> {
    check_options(opts)?;
    let window = latest_window(samples, opts.window_s)?;
    let (first, last) = match (window.first(), window.last()) {
        (Some(f), Some(l)) if window.len() >= MIN_SAMPLES => (f, l),
        _ => {
            return Err(StaticInitError::TooFewSamples {
                found: window.len(),
                needed: MIN_SAMPLES,
            })
        }
    };
    let span_s = last.t - first.t;
    let needed_s = MIN_SPAN_FRACTION * opts.window_s;
    if span_s < needed_s {
        return Err(StaticInitError::TooShort { span_s, needed_s });
    }

    let n = window.len() as f64;
    let (sum_a, sum_w) = window
        .iter()
        .fold((Vector3::zeros(), Vector3::zeros()), |(a, w), s| {
            (a + s.accel, w + s.gyro)
        });
    let mean_a: Vector3<f64> = sum_a / n;
    let mean_w: Vector3<f64> = sum_w / n;
    let (var_a, var_w) = window.iter().fold((0.0, 0.0), |(va, vw), s| {
        (
            va + (s.accel - mean_a).norm_squared(),
            vw + (s.gyro - mean_w).norm_squared(),
        )
    });
    let accel_std = (var_a / (n - 1.0)).sqrt();
    let gyro_std = (var_w / (n - 1.0)).sqrt();
    if accel_std > opts.max_accel_std_mps2 || gyro_std > opts.max_gyro_std_radps {
        return Err(StaticInitError::TooMuchMotion {
            accel_std,
            max_accel_std: opts.max_accel_std_mps2,
            gyro_std,
            max_gyro_std: opts.max_gyro_std_radps,
        });
    }
    let norm = mean_a.norm();
    if (norm - opts.gravity_mps2).abs() > MAX_GRAVITY_MISMATCH_MPS2 {
        return Err(StaticInitError::NotGravity {
            norm,
            gravity: opts.gravity_mps2,
        });
    }

    Ok(StaticInitResult {
        t: last.t,
        rot_i_to_g: rot_i_to_g_from_up(&(mean_a / norm)),
        bias_gyro: mean_w,
        bias_accel: Vector3::zeros(),
        velocity: Vector3::zeros(),
        accel_std,
        gyro_std,
        bias_gyro_sigma: gyro_mean_standard_error(window),
    })
}

/// Rejects options that cannot work.
fn check_options(opts: &StaticInitOptions) -> Result<(), StaticInitError> {
    let positive = |v: f64| v.is_finite() && v > 0.0;
    if !positive(opts.window_s) {
        return Err(StaticInitError::BadOptions("window_s must be positive"));
    }
    if !positive(opts.max_accel_std_mps2) || !positive(opts.max_gyro_std_radps) {
        return Err(StaticInitError::BadOptions(
            "standard deviation thresholds must be positive",
        ));
    }
    if !positive(opts.gravity_mps2) {
        return Err(StaticInitError::BadOptions("gravity must be positive"));
    }
    Ok(())
}

/// The samples with `t >= t_last - window_s`, checked finite and sorted.
fn latest_window(samples: &[ImuSample], window_s: f64) -> Result<&[ImuSample], StaticInitError> {
    let finite = |s: &ImuSample| {
        s.t.is_finite() && s.accel.iter().chain(s.gyro.iter()).all(|v| v.is_finite())
    };
    let Some(last) = samples.last() else {
        return Ok(samples);
    };
    if !finite(last) {
        return Err(StaticInitError::NotFinite {
            index: samples.len() - 1,
        });
    }
    let start_t = last.t - window_s;
    let mut start = samples.len() - 1;
    let mut later_t = last.t;
    while start > 0 {
        let index = start - 1;
        let s = &samples[index];
        if !s.t.is_finite() {
            return Err(StaticInitError::NotFinite { index });
        }
        if s.t > later_t {
            return Err(StaticInitError::NotSorted { index: start });
        }
        if s.t < start_t {
            break;
        }
        if !finite(s) {
            return Err(StaticInitError::NotFinite { index });
        }
        later_t = s.t;
        start = index;
    }
    Ok(&samples[start..])
}

/// `R_ItoG` with `R_ItoG · up_i = e_z` for the unit "up" direction `up_i` in
/// `I`, and zero yaw: the IMU `x` axis (or `y`, if `x` is nearly vertical),
/// projected onto the horizontal plane, maps onto the global `x` axis.
///
/// The rows of `R_ItoG` are the global axes expressed in `I` (Gram-Schmidt):
/// `z = up_i`, `x = e_x - z (z·e_x)` normalized, `y = z × x`.
fn rot_i_to_g_from_up(up_i: &Vector3<f64>) -> Matrix3<f64> {
    let z = *up_i;
    let horizontal = |axis: Vector3<f64>| axis - z * z.dot(&axis);
    let mut x = horizontal(Vector3::x());
    if x.norm() < MIN_HORIZONTAL_AXIS_NORM {
        // IMU x is vertical: put the projected IMU y along global y instead,
        // so global x is y × z.
        let y = horizontal(Vector3::y()).normalize();
        x = y.cross(&z);
    }
    let x = x.normalize();
    let y = z.cross(&x);
    Matrix3::from_rows(&[x.transpose(), y.transpose(), z.transpose()])
}

/// Nanoseconds per second.
const NS_PER_S: u64 = 1_000_000_000;
/// Longest accepted line of an IMU CSV file (bytes).
const MAX_LINE_BYTES: usize = 4096;
/// Most samples read from one IMU CSV file (a day at 200 Hz), to bound memory.
pub const MAX_IMU_SAMPLES: usize = 200 * 86_400;

/// Why an IMU CSV file could not be read.
#[derive(Debug, thiserror::Error)]
pub enum ImuCsvError {
    /// The file could not be opened or read.
    #[error("cannot read {}", path.display())]
    Read {
        /// The file.
        path: PathBuf,
        /// The I/O error.
        #[source]
        source: std::io::Error,
    },
    /// A line is malformed.
    #[error("bad line {line} of {}: {reason}", path.display())]
    Line {
        /// The file.
        path: PathBuf,
        /// 1-based line number.
        line: usize,
        /// What is wrong with it.
        reason: String,
    },
    /// The file holds more than [`MAX_IMU_SAMPLES`] samples.
    #[error("{} has more than {max} IMU samples", path.display())]
    TooManySamples {
        /// The file.
        path: PathBuf,
        /// The limit.
        max: usize,
    },
}

/// Reads an IMU log in the EuRoC ASL layout,
/// `timestamp [ns], ω_x, ω_y, ω_z [rad/s], a_x, a_y, a_z [m/s²]`, into samples
/// with times in seconds.
///
/// Blank lines and lines starting with `#` are skipped; values may be separated
/// by commas or whitespace; extra columns are ignored. Lines longer than 4096
/// bytes, unparsable or non-finite values, and timestamps that do not strictly
/// increase are errors naming the line, except on an unfinished last line (no
/// newline: the recording was cut off), which is dropped with a warning. At
/// most [`MAX_IMU_SAMPLES`] are read.
pub fn read_euroc_imu_csv(path: impl AsRef<Path>) -> Result<Vec<ImuSample>, ImuCsvError> {
    let path = path.as_ref();
    let file = std::fs::File::open(path).map_err(|source| ImuCsvError::Read {
        path: path.to_path_buf(),
        source,
    })?;
    parse_euroc_imu(BufReader::new(file), path)
}

/// The parser of [`read_euroc_imu_csv`] on any reader; `path` names the source
/// in errors.
fn parse_euroc_imu(mut reader: impl BufRead, path: &Path) -> Result<Vec<ImuSample>, ImuCsvError> {
    let mut out: Vec<ImuSample> = Vec::new();
    let mut buf = String::new();
    let mut line_no = 0usize;
    let bad = |line: usize, reason: String| ImuCsvError::Line {
        path: path.to_path_buf(),
        line,
        reason,
    };
    loop {
        buf.clear();
        line_no += 1;
        let limit = (MAX_LINE_BYTES + 1) as u64;
        let read =
            reader
                .by_ref()
                .take(limit)
                .read_line(&mut buf)
                .map_err(|source| match source.kind() {
                    std::io::ErrorKind::InvalidData => bad(line_no, "not UTF-8".to_string()),
                    _ => ImuCsvError::Read {
                        path: path.to_path_buf(),
                        source,
                    },
                })?;
        if read == 0 {
            break;
        }
        if read > MAX_LINE_BYTES {
            return Err(bad(line_no, format!("longer than {MAX_LINE_BYTES} bytes")));
        }
        let line = buf.trim();
        if line.is_empty() || line.starts_with('#') {
            continue;
        }
        let sample = match parse_imu_line(line) {
            Ok(sample) => sample,
            // The last line, unfinished (no newline): a recording cut off
            // mid-write loses that sample, not the file.
            Err(reason) if !buf.ends_with('\n') => {
                tracing::warn!(
                    "{}: the last line ({line_no}) is cut short and dropped: {reason}",
                    path.display()
                );
                break;
            }
            Err(reason) => return Err(bad(line_no, reason)),
        };
        if let Some(prev) = out.last() {
            if sample.t <= prev.t {
                return Err(bad(
                    line_no,
                    format!(
                        "timestamp {} s is not after the previous {} s",
                        sample.t, prev.t
                    ),
                ));
            }
        }
        if out.len() >= MAX_IMU_SAMPLES {
            return Err(ImuCsvError::TooManySamples {
                path: path.to_path_buf(),
                max: MAX_IMU_SAMPLES,
            });
        }
        out.push(sample);
    }
    Ok(out)
}

/// One data line: integer nanoseconds, then three gyro and three accel values.
fn parse_imu_line(line: &str) -> Result<ImuSample, String> {
    let mut fields = line
        .split(|c: char| c == ',' || c.is_whitespace())
        .filter(|f| !f.is_empty());
    let ns_text = fields.next().unwrap_or("");
    let ns: u64 = ns_text
        .parse()
        .map_err(|e| format!("column 1: cannot parse {ns_text:?} as integer nanoseconds: {e}"))?;
    let mut v = [0.0f64; 6];
    for (i, slot) in v.iter_mut().enumerate() {
        let column = i + 2;
        let text = fields
            .next()
            .ok_or_else(|| format!("expected 7 values, found {}", column - 1))?;
        let value: f64 = text
            .parse()
            .map_err(|e| format!("column {column}: cannot parse {text:?}: {e}"))?;
        if !value.is_finite() {
            return Err(format!("column {column}: value {value} is not finite"));
        }
        *slot = value;
    }
    Ok(ImuSample {
        t: (ns / NS_PER_S) as f64 + (ns % NS_PER_S) as f64 * 1e-9,
        gyro: Vector3::new(v[0], v[1], v[2]),
        accel: Vector3::new(v[3], v[4], v[5]),
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use common::so3::exp_so3;
    use common::trajectory::{interpolate_pose, read_euroc_csv};
    use rand::{Rng, SeedableRng};
    use rand_chacha::ChaCha8Rng;

    fn data_path(rel: &str) -> PathBuf {
        PathBuf::from(env!("CARGO_MANIFEST_DIR"))
            .join("../../shared/data")
            .join(rel)
    }

    /// Angle (deg) between the "up" directions in `I` of two orientations
    /// `R_ItoG`: the tilt (roll/pitch) error, independent of yaw.
    fn tilt_error_deg(r_est: &Matrix3<f64>, r_ref: &Matrix3<f64>) -> f64 {
        let up_est = r_est.transpose() * Vector3::z();
        let up_ref = r_ref.transpose() * Vector3::z();
        up_est
            .cross(&up_ref)
            .norm()
            .atan2(up_est.dot(&up_ref))
            .to_degrees()
    }

    fn synthetic_static(
        rng: &mut ChaCha8Rng,
        rot_i_to_g: &Matrix3<f64>,
        bias_gyro: &Vector3<f64>,
        n: usize,
        noise_a: f64,
        noise_g: f64,
    ) -> Vec<ImuSample> {
        let up_i = rot_i_to_g.transpose() * Vector3::new(0.0, 0.0, 9.81);
        let mut noise = |s: f64| {
            Vector3::new(
                rng.random_range(-s..s),
                rng.random_range(-s..s),
                rng.random_range(-s..s),
            )
        };
        (0..n)
            .map(|i| ImuSample {
                t: 100.0 + i as f64 * 0.005,
                gyro: bias_gyro + noise(noise_g),
                accel: up_i + noise(noise_a),
            })
            .collect()
    }

    #[test]
    fn real_euroc_static_start_gives_roll_and_pitch_within_one_degree_of_ground_truth() {
        let imu = read_euroc_imu_csv(data_path("euroc_v1_01_micro/mav0/imu0/data.csv"))
            .unwrap_or_else(|e| panic!("{e}"));
        let gt = read_euroc_csv(data_path("trajectories/V1_01_easy.csv"))
            .unwrap_or_else(|e| panic!("{e}"));
        let t_end = 1_403_715_277.5;
        let n = imu.partition_point(|s| s.t <= t_end);
        let opts = StaticInitOptions::default();
        let init = static_initialize(&imu[..n], &opts).unwrap_or_else(|e| panic!("{e}"));
        let gt_pose = interpolate_pose(&gt, init.t).unwrap_or_else(|| panic!("no gt at init"));
        let tilt = tilt_error_deg(&init.rot_i_to_g, &gt_pose.rot);
        println!(
            "EuRoC V1_01 static init at {:.3}: tilt error {tilt:.4} deg, accel std {:.4} m/s², \
             gyro std {:.5} rad/s, gyro bias {:?}",
            init.t,
            init.accel_std,
            init.gyro_std,
            init.bias_gyro.as_slice()
        );
        assert!(tilt < 1.0, "tilt error {tilt} deg");
        assert!(init.accel_std < opts.max_accel_std_mps2);
        assert!(init.gyro_std < opts.max_gyro_std_radps);
        // Ground truth's gyro bias there is about (-0.0022, 0.0215, 0.0770) rad/s.
        let gt_bg = Vector3::new(-0.002_247, 0.021_535, 0.077_030);
        assert!((init.bias_gyro - gt_bg).norm() < 5e-3, "{}", init.bias_gyro);
        // The standard error the window claims covers that (the rotors shake
        // the readings far beyond the datasheet's noise).
        println!("gyro bias standard error {:.5} rad/s", init.bias_gyro_sigma);
        let worst_axis = (init.bias_gyro - gt_bg).amax();
        assert!(worst_axis < 3.0 * init.bias_gyro_sigma, "{worst_axis}");
        assert_eq!(init.velocity, Vector3::zeros());
        assert_eq!(init.bias_accel, Vector3::zeros());
    }

    #[test]
    fn real_euroc_flight_window_is_rejected_as_moving() {
        let imu = read_euroc_imu_csv(data_path("euroc_v1_02_imu_segment/mav0/imu0/data.csv"))
            .unwrap_or_else(|e| panic!("{e}"));
        let (Some(first), Some(last)) = (imu.first(), imu.last()) else {
            panic!("empty IMU segment");
        };
        let mid = 0.5 * (first.t + last.t);
        let n = imu.partition_point(|s| s.t <= mid);
        match static_initialize(&imu[..n], &StaticInitOptions::default()) {
            Err(e @ StaticInitError::TooMuchMotion { .. }) => println!("V1_02 mid-flight: {e}"),
            other => panic!("expected TooMuchMotion, got {other:?}"),
        }
    }

    #[test]
    fn every_window_of_the_real_euroc_v1_01_flight_is_rejected() {
        let imu = read_euroc_imu_csv(data_path("euroc_v1_01_micro/mav0/imu0/data.csv"))
            .unwrap_or_else(|e| panic!("{e}"));
        // Take-off at about 1403715278.0 s, landing at about 1403715418.0 s.
        let opts = StaticInitOptions::default();
        let mut t_end = 1_403_715_279.0;
        let mut windows = 0;
        while t_end < 1_403_715_417.0 {
            let n = imu.partition_point(|s| s.t <= t_end);
            let result = static_initialize(&imu[..n], &opts);
            assert!(
                matches!(result, Err(StaticInitError::TooMuchMotion { .. })),
                "window ending at {t_end} accepted: {result:?}"
            );
            t_end += 0.5;
            windows += 1;
        }
        assert!(windows > 250);
    }

    #[test]
    fn real_euroc_v1_02_static_start_gives_roll_and_pitch_within_one_degree() {
        let imu = read_euroc_imu_csv(data_path("euroc_v1_02_imu_segment/mav0/imu0/data.csv"))
            .unwrap_or_else(|e| panic!("{e}"));
        let gt = read_euroc_csv(data_path("euroc_v1_02_imu_segment/mav0/gt0/data.csv"))
            .unwrap_or_else(|e| panic!("{e}"));
        let n = imu.partition_point(|s| s.t <= 1_403_715_527.5);
        let init = static_initialize(&imu[..n], &StaticInitOptions::default())
            .unwrap_or_else(|e| panic!("{e}"));
        let gt_pose = interpolate_pose(&gt, init.t).unwrap_or_else(|| panic!("no gt at init"));
        let tilt = tilt_error_deg(&init.rot_i_to_g, &gt_pose.rot);
        println!(
            "EuRoC V1_02 static init at {:.3}: tilt error {tilt:.4} deg, accel std {:.4} m/s², \
             gyro std {:.5} rad/s",
            init.t, init.accel_std, init.gyro_std
        );
        assert!(tilt < 1.0, "tilt error {tilt} deg");
    }

    #[test]
    fn synthetic_static_window_with_known_tilt_is_recovered() {
        let mut rng = ChaCha8Rng::seed_from_u64(7);
        for w in [
            Vector3::new(0.2, -0.3, 1.1),
            Vector3::new(-2.5, 0.4, -0.7),
            Vector3::new(0.0, 1.5, 0.0),
            Vector3::new(0.0, std::f64::consts::FRAC_PI_2, 0.0),
        ] {
            let rot = exp_so3(&w);
            let bg = Vector3::new(0.01, -0.02, 0.005);
            let samples = synthetic_static(&mut rng, &rot, &bg, 600, 0.05, 0.002);
            let init = static_initialize(&samples, &StaticInitOptions::default())
                .unwrap_or_else(|e| panic!("{e}"));
            assert!(tilt_error_deg(&init.rot_i_to_g, &rot) < 0.05);
            assert!((init.bias_gyro - bg).norm() < 5e-4);
            let r = init.rot_i_to_g;
            assert!((r.transpose() * r - Matrix3::identity()).norm() < 1e-12);
            assert!((r.determinant() - 1.0).abs() < 1e-12);
            // The window is the last 2 s of the 3 s of samples.
            assert_eq!(init.t, samples[599].t);
        }
    }

    /// White noise: the batch-means standard error is the samples' σ/√n.
    /// A slow wobble (0.01 rad/s at 1.3 Hz, as a simulator's B-spline
    /// through motion-capture jitter, or a drone on its skids) correlates
    /// the readings, and the error is larger than that formula says.
    #[test]
    fn the_gyro_bias_standard_error_counts_a_slow_wobble() {
        let mut rng = ChaCha8Rng::seed_from_u64(3);
        let rot = Matrix3::identity();
        let bg = Vector3::new(0.001, -0.002, 0.0);
        // Uniform in ±0.006: σ = 0.006/√3 per axis; the window holds 400 samples.
        let still = synthetic_static(&mut rng, &rot, &bg, 600, 0.05, 0.006);
        let init = static_initialize(&still, &StaticInitOptions::default())
            .unwrap_or_else(|e| panic!("{e}"));
        let white = 0.006 / 3f64.sqrt() / 400f64.sqrt();
        assert!(
            (init.bias_gyro_sigma / white - 1.0).abs() < 0.5,
            "{} against {white}",
            init.bias_gyro_sigma
        );
        let mut wobbling = still.clone();
        for s in &mut wobbling {
            s.gyro.y += 0.01 * (2.0 * std::f64::consts::PI * 1.3 * s.t).sin();
        }
        let init_w = static_initialize(&wobbling, &StaticInitOptions::default())
            .unwrap_or_else(|e| panic!("{e}"));
        assert!(
            init_w.bias_gyro_sigma > 3.0 * white,
            "{} against {white}",
            init_w.bias_gyro_sigma
        );
        // And the bias it found is off by no more than a few of those.
        assert!((init_w.bias_gyro - bg).amax() < 3.0 * init_w.bias_gyro_sigma);
        // Too short a window to tell: unknown.
        assert_eq!(gyro_mean_standard_error(&still[..30]), f64::INFINITY);
    }

    #[test]
    fn yaw_puts_the_projected_imu_x_axis_along_global_x() {
        let rot = exp_so3(&Vector3::new(0.3, -0.2, 2.0));
        let up_i = rot.transpose() * Vector3::z();
        let r = rot_i_to_g_from_up(&up_i);
        assert!((r * up_i - Vector3::z()).norm() < 1e-12);
        let x_in_g = r * Vector3::x();
        assert!(x_in_g.y.abs() < 1e-12 && x_in_g.x > 0.0, "{x_in_g}");
        // Only yaw differs from the truth: r = Rz(ψ) rot.
        let rel = r * rot.transpose();
        assert!((rel * Vector3::z() - Vector3::z()).norm() < 1e-12);
    }

    #[test]
    fn vertical_imu_x_axis_falls_back_to_the_y_axis_for_yaw() {
        let r = rot_i_to_g_from_up(&Vector3::x());
        assert!((r * Vector3::x() - Vector3::z()).norm() < 1e-12);
        let y_in_g = r * Vector3::y();
        assert!(y_in_g.x.abs() < 1e-12 && y_in_g.y > 0.0, "{y_in_g}");
        assert!((r.determinant() - 1.0).abs() < 1e-12);
    }

    #[test]
    fn short_sparse_non_finite_or_moving_windows_are_rejected() {
        let mut rng = ChaCha8Rng::seed_from_u64(8);
        let rot = exp_so3(&Vector3::new(0.1, 0.1, 0.0));
        let bg = Vector3::zeros();
        let opts = StaticInitOptions::default();
        let good = synthetic_static(&mut rng, &rot, &bg, 600, 0.05, 0.002);

        let too_short = &good[..300];
        assert!(matches!(
            static_initialize(too_short, &opts),
            Err(StaticInitError::TooShort { .. })
        ));
        assert!(matches!(
            static_initialize(&good[..5], &opts),
            Err(StaticInitError::TooFewSamples { found: 5, .. })
        ));
        assert!(matches!(
            static_initialize(&[], &opts),
            Err(StaticInitError::TooFewSamples { found: 0, .. })
        ));

        let mut nan = good.clone();
        nan[500].accel.y = f64::NAN;
        assert_eq!(
            static_initialize(&nan, &opts),
            Err(StaticInitError::NotFinite { index: 500 })
        );
        // A bad sample before the window does not matter.
        let mut old_nan = good.clone();
        old_nan[10].gyro.x = f64::INFINITY;
        assert!(static_initialize(&old_nan, &opts).is_ok());

        let mut unsorted = good.clone();
        unsorted.swap(450, 451);
        assert!(matches!(
            static_initialize(&unsorted, &opts),
            Err(StaticInitError::NotSorted { .. })
        ));

        let shaking = synthetic_static(&mut rng, &rot, &bg, 600, 1.0, 0.002);
        assert!(matches!(
            static_initialize(&shaking, &opts),
            Err(StaticInitError::TooMuchMotion { .. })
        ));
        let rotating = synthetic_static(&mut rng, &rot, &bg, 600, 0.05, 0.2);
        assert!(matches!(
            static_initialize(&rotating, &opts),
            Err(StaticInitError::TooMuchMotion { .. })
        ));

        let mut falling = good.clone();
        for s in &mut falling {
            s.accel *= 0.5;
        }
        assert!(matches!(
            static_initialize(&falling, &opts),
            Err(StaticInitError::NotGravity { .. })
        ));

        let bad_opts = StaticInitOptions {
            window_s: -1.0,
            ..opts
        };
        assert!(matches!(
            static_initialize(&good, &bad_opts),
            Err(StaticInitError::BadOptions(_))
        ));
    }

    #[test]
    fn imu_csv_parser_reads_euroc_lines_and_names_bad_lines() {
        let text = "#timestamp [ns],w_x,w_y,w_z,a_x,a_y,a_z\n\
                    1403715273262142976,-0.002,0.017,0.077,9.08,0.13,-3.69\n\
                    \n\
                    1403715273267142912 -0.001 0.019 0.078 9.07 0.12 -3.69 extra\n";
        let path = Path::new("mem.csv");
        let samples =
            parse_euroc_imu(std::io::Cursor::new(text), path).unwrap_or_else(|e| panic!("{e}"));
        assert_eq!(samples.len(), 2);
        assert!((samples[0].t - 1_403_715_273.262_143).abs() < 1e-6);
        // f64 seconds resolve 2.4e-7 s at this epoch.
        assert!((samples[1].t - samples[0].t - 0.004_999_936).abs() < 5e-7);
        assert_eq!(samples[1].gyro, Vector3::new(-0.001, 0.019, 0.078));
        assert_eq!(samples[0].accel, Vector3::new(9.08, 0.13, -3.69));

        let line_of = |text: &str| match parse_euroc_imu(std::io::Cursor::new(text), path) {
            Err(ImuCsvError::Line { line, .. }) => line,
            other => panic!("expected a line error, got {other:?}"),
        };
        assert_eq!(line_of("#h\n1,0,0,0,0,0\n"), 2);
        assert_eq!(line_of("1,0,0,0,0,0,0\n2,0,0,nan,0,0,0\n"), 2);
        assert_eq!(line_of("1,0,0,0,0,0,0\n\n1,0,0,0,0,0,0\n"), 3);
        assert_eq!(line_of("1.5,0,0,0,0,0,0\n"), 1);
        assert_eq!(line_of("1,0,0,x,0,0,0\n"), 1);
        let long = format!("1,0,0,0,0,0,0{}\n", " ".repeat(MAX_LINE_BYTES));
        assert_eq!(line_of(&long), 1);
    }

    /// A recording cut off mid-write: its unfinished last line is dropped; a
    /// whole last line without a newline is read.
    #[test]
    fn imu_csv_parser_drops_a_last_line_cut_short() {
        let path = Path::new("mem.csv");
        let read = |text: &str| {
            parse_euroc_imu(std::io::Cursor::new(text), path)
                .unwrap_or_else(|e| panic!("{e}"))
                .len()
        };
        assert_eq!(read("1,0,0,0,0,0,0\n2,0,0,0,0.1"), 1);
        assert_eq!(read("1,0,0,0,0,0,0\n2,0,0,0,0,0,0"), 2);
        assert_eq!(read("1,0,0,0,0,0,0\n2,0,0,0,0,0,0\n"), 2);
    }

    #[test]
    fn missing_imu_file_is_a_read_error() {
        assert!(matches!(
            read_euroc_imu_csv(data_path("does/not/exist.csv")),
            Err(ImuCsvError::Read { .. })
        ));
    }
}
