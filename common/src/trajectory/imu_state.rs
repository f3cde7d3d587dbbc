//! The IMU-state file of a simulated run: velocity and biases, their
//! covariances and the simulator's truth, one line per estimate. OpenVINS's
//! simulation evaluation plots these beside the pose; here they also feed the
//! band test of `sim-fleet anees`.

use std::path::Path;

use nalgebra::{Matrix3, Vector3};

use super::parse::{need, number, parse_file, symmetric, write_lines, UPPER};
use super::{LineError, TrajectoryError};

/// Header and format of the IMU-state file: the time (s), the estimated
/// velocity `v_IinG` (m/s, global frame), gyro bias (rad/s) and accelerometer
/// bias (m/s², both IMU frame); the upper triangles, row by row, of their 3x3
/// covariance blocks; then the true velocity and biases at the same time.
/// Separators, comments and extra columns are handled as in the trajectory
/// files; timestamps must increase.
pub const IMU_STATE_HEADER: &str = "# timestamp vx vy vz bgx bgy bgz bax bay baz \
vel_xx vel_xy vel_xz vel_yy vel_yz vel_zz \
bg_xx bg_xy bg_xz bg_yy bg_yz bg_zz \
ba_xx ba_xy ba_xz ba_yy ba_yz ba_zz \
true_vx true_vy true_vz true_bgx true_bgy true_bgz true_bax true_bay true_baz";

/// Values on one line of the file.
const COLUMNS: usize = 37;

/// The velocity and biases an estimator holds at one time, with their
/// covariance blocks.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct ImuEstimate {
    /// Time, s.
    pub t: f64,
    /// `v_IinG`, m/s.
    pub vel: Vector3<f64>,
    /// Gyro bias, rad/s.
    pub bias_gyro: Vector3<f64>,
    /// Accelerometer bias, m/s².
    pub bias_accel: Vector3<f64>,
    /// Velocity covariance, (m/s)².
    pub cov_vel: Matrix3<f64>,
    /// Gyro-bias covariance, (rad/s)².
    pub cov_bias_gyro: Matrix3<f64>,
    /// Accelerometer-bias covariance, (m/s²)².
    pub cov_bias_accel: Matrix3<f64>,
}

/// The true velocity and biases at one time.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct ImuTruth {
    /// `v_IinG`, m/s.
    pub vel: Vector3<f64>,
    /// Gyro bias, rad/s.
    pub bias_gyro: Vector3<f64>,
    /// Accelerometer bias, m/s².
    pub bias_accel: Vector3<f64>,
}

/// One line of the file: an estimate and the truth at its time.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct ImuStateRecord {
    /// The estimate.
    pub estimate: ImuEstimate,
    /// The truth at `estimate.t`.
    pub truth: ImuTruth,
}

/// Writes an IMU-state file (format: [`IMU_STATE_HEADER`]) that
/// [`read_imu_states`] reads back exactly (timestamps with 9 decimals).
pub fn write_imu_states(
    path: impl AsRef<Path>,
    records: &[ImuStateRecord],
) -> Result<(), TrajectoryError> {
    write_lines(path.as_ref(), IMU_STATE_HEADER, records.iter().map(row))
}

fn row(r: &ImuStateRecord) -> String {
    let e = &r.estimate;
    let mut row = format!("{:.9}", e.t);
    let mut push = |v: f64| {
        row.push(' ');
        row.push_str(&v.to_string());
    };
    for v in [&e.vel, &e.bias_gyro, &e.bias_accel] {
        v.iter().for_each(|x| push(*x));
    }
    for block in [&e.cov_vel, &e.cov_bias_gyro, &e.cov_bias_accel] {
        UPPER.iter().for_each(|&(i, k)| push(block[(i, k)]));
    }
    let t = &r.truth;
    for v in [&t.vel, &t.bias_gyro, &t.bias_accel] {
        v.iter().for_each(|x| push(*x));
    }
    row
}

/// Reads an IMU-state file (format: [`IMU_STATE_HEADER`]); the covariance
/// blocks are filled symmetrically from their upper triangles.
pub fn read_imu_states(path: impl AsRef<Path>) -> Result<Vec<ImuStateRecord>, TrajectoryError> {
    parse_file(
        path.as_ref(),
        |f| {
            need(f, COLUMNS)?;
            Ok(ImuStateRecord {
                estimate: ImuEstimate {
                    t: number(f, 0)?,
                    vel: vector(f, 1)?,
                    bias_gyro: vector(f, 4)?,
                    bias_accel: vector(f, 7)?,
                    cov_vel: symmetric(f, 10)?,
                    cov_bias_gyro: symmetric(f, 16)?,
                    cov_bias_accel: symmetric(f, 22)?,
                },
                truth: ImuTruth {
                    vel: vector(f, 28)?,
                    bias_gyro: vector(f, 31)?,
                    bias_accel: vector(f, 34)?,
                },
            })
        },
        |r| r.estimate.t,
    )
}

fn vector(fields: &[&str], first: usize) -> Result<Vector3<f64>, LineError> {
    Ok(Vector3::new(
        number(fields, first)?,
        number(fields, first + 1)?,
        number(fields, first + 2)?,
    ))
}

#[cfg(test)]
mod tests {
    use super::*;

    fn record(t: f64) -> ImuStateRecord {
        let m = |a: f64| Matrix3::new(a, 0.1, 0.2, 0.1, 2.0 * a, 0.3, 0.2, 0.3, 3.0 * a);
        ImuStateRecord {
            estimate: ImuEstimate {
                t,
                vel: Vector3::new(1.0, -2.0, 0.5),
                bias_gyro: Vector3::new(1e-3, -2e-3, 3e-4),
                bias_accel: Vector3::new(0.01, 0.02, -0.03),
                cov_vel: m(1e-4),
                cov_bias_gyro: m(1e-8),
                cov_bias_accel: m(1e-5),
            },
            truth: ImuTruth {
                vel: Vector3::new(1.01, -2.0, 0.49),
                bias_gyro: Vector3::new(0.0, -1e-3, 1e-4),
                bias_accel: Vector3::new(0.0, 0.03, -0.02),
            },
        }
    }

    #[test]
    fn the_file_reads_back_exactly_and_names_every_column() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("imu_state.txt");
        let records = vec![record(1.5), record(1.6)];
        write_imu_states(&path, &records).unwrap();
        assert_eq!(read_imu_states(&path).unwrap(), records);
        let named = IMU_STATE_HEADER.split_whitespace().count() - 1;
        assert_eq!(named, COLUMNS);
    }

    #[test]
    fn a_short_or_non_finite_line_is_an_error_naming_it() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("imu_state.txt");
        std::fs::write(&path, "1.0 2.0 3.0\n").unwrap();
        let err = read_imu_states(&path).unwrap_err().to_string();
        assert!(err.contains("line 1"), "{err}");
        let mut line = row(&record(1.0));
        line = line.replacen(" 1 ", " NaN ", 1);
        std::fs::write(&path, line + "\n").unwrap();
        assert!(read_imu_states(&path).is_err());
    }
}
