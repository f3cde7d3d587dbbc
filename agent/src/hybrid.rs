//! Hybrid runs: a real IMU recording with camera frames simulated from the
//! ground-truth trajectory of the same flight (EuRoC: IMU and ground truth in
//! the same clock). The estimator meets real IMU noise, biases and vibration
//! while its camera measurements stay exactly known.

use crate::estimator::static_init::{read_euroc_imu_csv, ImuCsvError};
use crate::estimator::EstimatorOptions;
use crate::runner::{require_features, run_stream, RobotRun, RunError};
use common::measurement::ImuSample;
use nalgebra::Vector3;
use simulator::imu::Biases;
use simulator::Fleet;
use std::path::{Path, PathBuf};
use thiserror::Error;

/// Why a hybrid run could not start.
#[derive(Debug, Error)]
pub enum HybridError {
    /// The IMU file is malformed.
    #[error(transparent)]
    Imu(#[from] ImuCsvError),
    /// The bias file is malformed.
    #[error("{}: line {line}: {what}", path.display())]
    Biases {
        /// The file.
        path: PathBuf,
        /// 1-based line.
        line: usize,
        /// What is wrong.
        what: String,
    },
    /// The run failed.
    #[error(transparent)]
    Run(#[from] RunError),
}

/// IMU biases over time from an EuRoC ground-truth CSV (columns 11-16: gyro
/// bias rad/s, accel bias m/s²), `(t [s], biases)`. Files with fewer columns
/// give no rows.
pub fn read_euroc_biases(path: &Path) -> Result<Vec<(f64, Biases)>, HybridError> {
    let text = std::fs::read_to_string(path).map_err(|e| HybridError::Biases {
        path: path.to_path_buf(),
        line: 0,
        what: e.to_string(),
    })?;
    let mut out = Vec::new();
    for (k, line) in text.lines().enumerate() {
        let line = line.trim();
        if line.is_empty() || line.starts_with('#') {
            continue;
        }
        let bad = |what: String| HybridError::Biases {
            path: path.to_path_buf(),
            line: k + 1,
            what,
        };
        let f: Vec<&str> = line.split(',').map(str::trim).collect();
        if f.len() < 17 {
            return Ok(Vec::new());
        }
        let ns: u64 = f[0].parse().map_err(|e| bad(format!("timestamp: {e}")))?;
        let mut v = [0.0f64; 6];
        for (i, x) in v.iter_mut().enumerate() {
            *x = f[11 + i]
                .parse()
                .map_err(|e| bad(format!("column {}: {e}", 12 + i)))?;
            if !x.is_finite() {
                return Err(bad(format!("column {} is not finite", 12 + i)));
            }
        }
        let t = (ns / 1_000_000_000) as f64 + (ns % 1_000_000_000) as f64 * 1e-9;
        out.push((
            t,
            Biases {
                gyro: Vector3::new(v[0], v[1], v[2]),
                accel: Vector3::new(v[3], v[4], v[5]),
            },
        ));
    }
    Ok(out)
}

/// Runs robot `robot` of `fleet` on the real IMU of `imu_csv` (EuRoC layout,
/// the trajectory file's clock) with simulated camera frames. The estimator
/// starts at the true state as in simulation, with the biases of `biases_csv`
/// (an EuRoC ground truth with bias columns) at that time, zero without one.
pub fn run_robot_hybrid(
    fleet: &Fleet,
    robot: usize,
    opts: EstimatorOptions,
    imu_csv: &Path,
    biases_csv: Option<&Path>,
) -> Result<RobotRun, HybridError> {
    let truth = fleet
        .truths
        .get(robot)
        .ok_or(RunError::Sim(simulator::SimError::NoSuchRobot(robot)))?;
    require_features(fleet)?;
    let shift = truth.time_shift_s;
    let samples: Vec<ImuSample> = read_euroc_imu_csv(imu_csv)?
        .into_iter()
        .map(|s| ImuSample {
            t: s.t + shift,
            ..s
        })
        .collect();
    let start = fleet.estimator_start_time(robot).unwrap_or(f64::NAN);
    let biases = match biases_csv {
        Some(p) => read_euroc_biases(p)?
            .into_iter()
            .min_by(|a, b| {
                (a.0 + shift - start)
                    .abs()
                    .total_cmp(&(b.0 + shift - start).abs())
            })
            .map(|(_, b)| b)
            .unwrap_or_default(),
        None => Biases::default(),
    };
    let events = fleet
        .stream_with_imu(robot, samples, biases)
        .map_err(RunError::Sim)?;
    Ok(run_stream(fleet, robot, opts, events, |c| {
        Ok(Some(c.frame))
    })?)
}
