//! `sim-fleet eval --imu-state FILE`: the velocity and the two biases of a
//! simulated run against the simulator's truth (`imu_state.txt`, which
//! `agent run`, the Monte-Carlo runs and the fleet's agents write): their RMS
//! errors and mean NEES, and plots of each axis's error with ±3σ. A bias that
//! converges, or one that the filter claims to know better than it does, shows
//! here long before it shows in the pose.

use std::fmt::Write as _;

use common::trajectory::ImuStateRecord;
use nalgebra::Vector3;
use serde::Serialize;

use super::opt;
use crate::anees::imu_nees;

/// The errors of a run's velocity and biases.
#[derive(Clone, Debug, Default, PartialEq, Serialize)]
pub struct ImuStateReport {
    /// Lines read.
    pub records: usize,
    /// Velocity RMS error, m/s.
    pub vel_rmse_mps: Option<f64>,
    /// Gyro-bias RMS error, rad/s.
    pub bias_gyro_rmse_radps: Option<f64>,
    /// Accelerometer-bias RMS error, m/s².
    pub bias_accel_rmse_mps2: Option<f64>,
    /// Mean NEES of the velocity (3 DoF, ideal 3).
    pub nees_vel: Option<f64>,
    /// Mean NEES of the gyro bias.
    pub nees_bias_gyro: Option<f64>,
    /// Mean NEES of the accelerometer bias.
    pub nees_bias_accel: Option<f64>,
}

/// The report of `records`.
pub fn evaluate(records: &[ImuStateRecord]) -> ImuStateReport {
    let rmse = |err: &dyn Fn(&ImuStateRecord) -> Vector3<f64>| {
        (!records.is_empty()).then(|| {
            let sum: f64 = records.iter().map(|r| err(r).norm_squared()).sum();
            (sum / records.len() as f64).sqrt()
        })
    };
    let nees = records.iter().map(imu_nees).collect::<Vec<_>>();
    let mean = |k: usize| {
        let values: Vec<f64> = nees.iter().filter_map(|n| n[k]).collect();
        (!values.is_empty()).then(|| values.iter().sum::<f64>() / values.len() as f64)
    };
    ImuStateReport {
        records: records.len(),
        vel_rmse_mps: rmse(&|r| r.truth.vel - r.estimate.vel),
        bias_gyro_rmse_radps: rmse(&|r| r.truth.bias_gyro - r.estimate.bias_gyro),
        bias_accel_rmse_mps2: rmse(&|r| r.truth.bias_accel - r.estimate.bias_accel),
        nees_vel: mean(0),
        nees_bias_gyro: mean(1),
        nees_bias_accel: mean(2),
    }
}

impl ImuStateReport {
    /// The lines `sim-fleet eval` prints.
    pub fn table(&self) -> String {
        let mut s = String::new();
        let _ = writeln!(
            s,
            "IMU state ({} estimates)   RMS error / mean NEES (3 DoF): velocity {} m/s / {}   gyro bias {} rad/s / {}   accel bias {} m/s² / {}",
            self.records,
            opt(self.vel_rmse_mps, 4),
            opt(self.nees_vel, 3),
            sci(self.bias_gyro_rmse_radps),
            opt(self.nees_bias_gyro, 3),
            sci(self.bias_accel_rmse_mps2),
            opt(self.nees_bias_accel, 3),
        );
        s
    }
}

/// A small number in scientific notation, or `-`.
fn sci(v: Option<f64>) -> String {
    v.map_or_else(|| "-".to_string(), |x| format!("{x:.3e}"))
}

#[cfg(test)]
mod tests {
    use super::*;
    use common::trajectory::{ImuEstimate, ImuTruth};
    use nalgebra::Matrix3;

    #[test]
    fn errors_and_nees_of_a_known_offset() {
        let record = |t: f64| ImuStateRecord {
            estimate: ImuEstimate {
                t,
                vel: Vector3::new(1.0, 0.0, 0.0),
                bias_gyro: Vector3::new(0.0, 0.0, 1e-3),
                cov_vel: Matrix3::identity() * 0.04,
                cov_bias_gyro: Matrix3::identity() * 1e-6,
                cov_bias_accel: Matrix3::identity() * 1e-4,
                ..Default::default()
            },
            truth: ImuTruth {
                vel: Vector3::new(1.0, 0.3, -0.4),
                bias_accel: Vector3::new(0.01, 0.0, 0.0),
                ..Default::default()
            },
        };
        let r = evaluate(&[record(0.0), record(0.1)]);
        assert_eq!(r.records, 2);
        assert!((r.vel_rmse_mps.unwrap() - 0.5).abs() < 1e-12);
        assert!((r.nees_vel.unwrap() - 0.25 / 0.04).abs() < 1e-9);
        assert!((r.bias_gyro_rmse_radps.unwrap() - 1e-3).abs() < 1e-15);
        assert!((r.nees_bias_gyro.unwrap() - 1.0).abs() < 1e-9);
        assert!((r.nees_bias_accel.unwrap() - 1.0).abs() < 1e-9);
        assert!(
            r.table().contains("velocity 0.5000 m/s / 6.250"),
            "{}",
            r.table()
        );
        let empty = evaluate(&[]);
        assert_eq!(empty.vel_rmse_mps, None);
        assert_eq!(empty.nees_vel, None);
    }
}
