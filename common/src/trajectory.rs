//! Trajectory I/O: TUM / OpenVINS text, EuRoC ASL CSV ground truth, per-pose covariances.
//!
//! Orientations are `R_ItoG` and positions `p_IinG` (see [`crate::conventions`]).
//!
//! * [`read_tum`] / [`write_tum`]: `timestamp tx ty tz qx qy qz qw` (scalar last).
//! * [`read_euroc_csv`]: `ns, px, py, pz, qw, qx, qy, qz, ...` (scalar first).
//! * [`read_trajectory`]: one of the two, by file extension.
//! * [`read_covariances`] / [`write_covariances`]: the covariance file, see
//!   [`COVARIANCE_HEADER`].
//! * [`interpolate_pose`]: a pose between two samples (slerp, linear position).
//!
//! Every reader skips blank lines and lines starting with `#`, accepts spaces,
//! tabs or commas between values, ignores extra columns, and rejects NaN/inf,
//! zero quaternions and timestamps that do not increase, naming file and line.

use std::path::{Path, PathBuf};

use nalgebra::{Matrix3, Vector3};

use crate::so3::{exp_so3, log_so3};

mod covariance;
mod euroc;
mod imu_state;
mod parse;
#[cfg(test)]
mod tests;
mod tum;

pub use covariance::{covariance_row, read_covariances, write_covariances, COVARIANCE_HEADER};
pub use euroc::read_euroc_csv;
pub use imu_state::{
    read_imu_states, write_imu_states, ImuEstimate, ImuStateRecord, ImuTruth, IMU_STATE_HEADER,
};
pub use tum::{read_tum, tum_row, write_tum, TUM_HEADER};

/// One pose of a trajectory at time `t` (seconds).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct StampedPose {
    /// Time in seconds.
    pub t: f64,
    /// Orientation `R_ItoG`.
    pub rot: Matrix3<f64>,
    /// Position `p_IinG` in metres.
    pub pos: Vector3<f64>,
}

/// The filter's marginal covariance of one pose, in the error state of
/// [`crate::conventions`]: orientation in rad² (local frame), position in m² (global).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct StampedCovariance {
    /// Time in seconds.
    pub t: f64,
    /// 3x3 orientation block (rad²).
    pub ori: Matrix3<f64>,
    /// 3x3 position block (m²).
    pub pos: Matrix3<f64>,
}

/// Why a trajectory or covariance file could not be read or written.
#[derive(Debug, thiserror::Error)]
pub enum TrajectoryError {
    /// The file could not be opened or read (or is not UTF-8).
    #[error("cannot read {}", path.display())]
    Read {
        /// The file.
        path: PathBuf,
        /// The I/O error.
        #[source]
        source: std::io::Error,
    },
    /// The file could not be created or written.
    #[error("cannot write {}", path.display())]
    Write {
        /// The file.
        path: PathBuf,
        /// The I/O error.
        #[source]
        source: std::io::Error,
    },
    /// A data line is malformed.
    #[error("bad line {line} of {}", path.display())]
    Line {
        /// The file.
        path: PathBuf,
        /// 1-based line number.
        line: usize,
        /// What is wrong with the line.
        #[source]
        kind: LineError,
    },
}

/// What is wrong with one line of a trajectory or covariance file.
#[derive(Debug, thiserror::Error)]
pub enum LineError {
    /// Fewer values than the format needs.
    #[error("expected at least {expected} values, found {found}")]
    TooFewColumns {
        /// Values the format needs.
        expected: usize,
        /// Values found on the line.
        found: usize,
    },
    /// A value is not a decimal number.
    #[error("column {column}: cannot parse {text:?} as a number")]
    Number {
        /// 1-based column.
        column: usize,
        /// The text of the value.
        text: String,
        /// The parser's error.
        #[source]
        source: std::num::ParseFloatError,
    },
    /// A nanosecond timestamp is not a non-negative integer.
    #[error("column {column}: cannot parse {text:?} as integer nanoseconds")]
    Nanoseconds {
        /// 1-based column.
        column: usize,
        /// The text of the value.
        text: String,
        /// The parser's error.
        #[source]
        source: std::num::ParseIntError,
    },
    /// A value is NaN or infinite.
    #[error("column {column}: value {value} is not finite")]
    NotFinite {
        /// 1-based column.
        column: usize,
        /// The value.
        value: f64,
    },
    /// The quaternion cannot be normalized.
    #[error("quaternion has norm {norm}, cannot be normalized")]
    BadQuaternion {
        /// Its norm.
        norm: f64,
    },
    /// The timestamp does not increase.
    #[error("timestamp {t} is not after the previous timestamp {previous}")]
    TimeNotIncreasing {
        /// This line's time (s).
        t: f64,
        /// The previous data line's time (s).
        previous: f64,
    },
}

/// Reads a trajectory, choosing the format by extension: `.csv` (any case) is
/// EuRoC ground truth ([`read_euroc_csv`]), anything else TUM ([`read_tum`]).
pub fn read_trajectory(path: impl AsRef<Path>) -> Result<Vec<StampedPose>, TrajectoryError> {
    let path = path.as_ref();
    let is_csv = path
        .extension()
        .and_then(|e| e.to_str())
        .is_some_and(|e| e.eq_ignore_ascii_case("csv"));
    if is_csv {
        read_euroc_csv(path)
    } else {
        read_tum(path)
    }
}

/// `traj` flown `laps` times, every other lap backwards: the poses of each
/// lap after the first, with their times continuing from the previous lap's
/// end (a backward lap retraces the previous one, at the same speeds), so
/// the motion stays continuous and a fitted spline slows to a stop at each
/// turn. Long missions from short recordings, for soak tests. `laps` of 0 or
/// 1, or fewer than two poses, give `traj` unchanged.
pub fn laps(traj: &[StampedPose], laps: u32) -> Vec<StampedPose> {
    let mut out = traj.to_vec();
    let (Some(first), Some(last)) = (traj.first(), traj.last()) else {
        return out;
    };
    if traj.len() < 2 || laps < 2 {
        return out;
    }
    out.reserve(traj.len() * (laps as usize - 1));
    let mut end = last.t;
    for lap in 1..laps {
        let backwards = lap % 2 == 1;
        let leg: Vec<StampedPose> = if backwards {
            // From the second to last pose back to the first.
            traj.iter()
                .rev()
                .skip(1)
                .map(|p| StampedPose {
                    t: end + (last.t - p.t),
                    ..*p
                })
                .collect()
        } else {
            traj.iter()
                .skip(1)
                .map(|p| StampedPose {
                    t: end + (p.t - first.t),
                    ..*p
                })
                .collect()
        };
        end += last.t - first.t;
        out.extend(leg);
    }
    out
}

/// The pose at time `t`, interpolated between the two samples around it
/// (orientation `R_a Exp(s Log(R_aᵀ R_b))`, position linear), or `None` if `t`
/// is outside `[first, last]` of `traj`. `traj` must be sorted by time, as the
/// readers return it. A sample exactly at `t` is returned unchanged.
pub fn interpolate_pose(traj: &[StampedPose], t: f64) -> Option<StampedPose> {
    let first = traj.first()?;
    let last = traj.last()?;
    if !(t >= first.t && t <= last.t) {
        return None;
    }
    // Index of the first sample with time >= t; exists since t <= last.t.
    let j = traj.partition_point(|p| p.t < t);
    let b = traj.get(j)?;
    if b.t == t || j == 0 {
        return Some(StampedPose { t, ..*b });
    }
    let a = traj.get(j - 1)?;
    let s = (t - a.t) / (b.t - a.t);
    let delta = log_so3(&(a.rot.transpose() * b.rot));
    Some(StampedPose {
        t,
        rot: a.rot * exp_so3(&(delta * s)),
        pos: a.pos + (b.pos - a.pos) * s,
    })
}
