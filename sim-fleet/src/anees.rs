//! NEES averaged over Monte-Carlo runs at each epoch, against the two-sided
//! 95 % band a consistent filter stays in (the "average NEES" test of
//! Bar-Shalom, Li and Kirubarajan, *Estimation with Applications to Tracking
//! and Navigation*, 2001, Sec. 5.4.2): with `n` independent runs, `n` times
//! the average NEES of a `d`-DoF error is χ² with `d·n` degrees of freedom.
//!
//! A run's mean NEES over time says whether the filter is right on average; the
//! band, epoch by epoch, says when it is wrong and in which direction. The
//! orientation error is also split, in the world frame, into tilt (roll and
//! pitch, which gravity observes; 2 DoF) and yaw about gravity (1 DoF, which
//! nothing observes). From a start at the truth the unobservable directions
//! (yaw, global position) keep their prior while their error starts at zero, so
//! they sit below the band: that says the prior is loose, not that the filter
//! is wrong.
//!
//! `sim-fleet montecarlo` writes it for every robot of every variant
//! (`DIR/anees/<variant>/robot<i>.csv` and `anees` in `summary.json`);
//! `sim-fleet anees RUN_DIR...` computes it for any set of runs.

use std::collections::BTreeMap;
use std::fmt::Write as _;
use std::path::{Path, PathBuf};

use agent::estimator::chi2::chi2_quantile;
use common::metrics::{
    associate, find_covariance, nees_of, pose_error, COVARIANCE_MATCH_TOL_S, DEFAULT_MAX_DT_S,
};
use common::trajectory::{
    read_covariances, read_imu_states, read_trajectory, ImuStateRecord, StampedCovariance,
    StampedPose, TrajectoryError,
};
use nalgebra::Vector2;
use serde::{Deserialize, Serialize};

/// The error kinds with their DoF, in the order of [`PoseNees::values`] and of
/// the CSV. The last three come from `imu_state.txt`, which simulated runs
/// write.
pub const KINDS: [(&str, usize); 7] = [
    ("ori", 3),
    ("pos", 3),
    ("tilt", 2),
    ("yaw", 1),
    ("vel", 3),
    ("bias_gyro", 3),
    ("bias_accel", 3),
];

/// Number of [`KINDS`].
const N: usize = KINDS.len();

/// Probability outside the band on each side.
const TAIL: f64 = 0.025;

/// Why the runs could not be read.
#[derive(Debug, thiserror::Error)]
pub enum AneesError {
    /// A run's estimate, ground truth or covariance file.
    #[error("run {}: {source}", dir.display())]
    Run {
        /// The run's folder.
        dir: PathBuf,
        /// What went wrong.
        #[source]
        source: TrajectoryError,
    },
    /// The epoch length is not a positive finite number of seconds.
    #[error("the epoch length must be a positive number of seconds, not {0}")]
    BinLength(f64),
    /// Writing the CSV.
    #[error("cannot write {}", path.display())]
    Write {
        /// The file.
        path: PathBuf,
        /// The I/O error.
        #[source]
        source: std::io::Error,
    },
}

/// The NEES of one estimate, per kind of [`KINDS`] (`None` where the block is
/// not positive definite).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct PoseNees {
    /// Time of the estimate (s).
    pub t: f64,
    /// Orientation (3 DoF), position (3), tilt (2), yaw (1), velocity (3),
    /// gyro bias (3), accelerometer bias (3).
    pub values: [Option<f64>; N],
}

/// The NEES of each estimate of the run in `dir` (`estimate.txt`,
/// `groundtruth.txt`, `covariance.txt`, as `agent run` and `sim-fleet run`
/// write them, and `imu_state.txt` when there is one). Estimates without
/// ground truth or covariance are skipped.
pub fn run_nees(dir: &Path) -> Result<Vec<PoseNees>, AneesError> {
    let err = |source| AneesError::Run {
        dir: dir.to_path_buf(),
        source,
    };
    let est = read_trajectory(dir.join("estimate.txt")).map_err(err)?;
    let gt = read_trajectory(dir.join("groundtruth.txt")).map_err(err)?;
    let covs = read_covariances(dir.join("covariance.txt")).map_err(err)?;
    let imu_path = dir.join("imu_state.txt");
    let imu = match imu_path.is_file() {
        true => read_imu_states(&imu_path).map_err(err)?,
        false => Vec::new(),
    };
    let pairs = associate(&est, &gt, DEFAULT_MAX_DT_S);
    Ok(pairs
        .iter()
        .filter_map(|(e, g)| {
            let mut nees = pose_nees(e, g, find_covariance(&covs, e.t)?);
            // Both files are in time order, one line per estimate.
            let j = imu.partition_point(|r| r.estimate.t < e.t - COVARIANCE_MATCH_TOL_S);
            if let Some(r) = imu
                .get(j)
                .filter(|r| (r.estimate.t - e.t).abs() <= COVARIANCE_MATCH_TOL_S)
            {
                nees.values[4..].copy_from_slice(&imu_nees(r));
            }
            Some(nees)
        })
        .collect())
}

/// The NEES of the velocity and of the two biases of one IMU-state line.
pub fn imu_nees(r: &ImuStateRecord) -> [Option<f64>; 3] {
    let (e, t) = (&r.estimate, &r.truth);
    [
        nees_of(&(t.vel - e.vel), &e.cov_vel),
        nees_of(&(t.bias_gyro - e.bias_gyro), &e.cov_bias_gyro),
        nees_of(&(t.bias_accel - e.bias_accel), &e.cov_bias_accel),
    ]
}

/// The NEES of estimate `e` against the truth `g` with its covariance.
pub fn pose_nees(e: &StampedPose, g: &StampedPose, cov: &StampedCovariance) -> PoseNees {
    let (d_theta, d_p) = pose_error(e, g);
    // R_gt = R_est Exp(δθ) = Exp(R_est δθ) R_est: the world-frame error and its
    // covariance, z along gravity.
    let e_w = e.rot * d_theta;
    let p_w = e.rot * cov.ori * e.rot.transpose();
    let tilt = nees_of(
        &Vector2::new(e_w.x, e_w.y),
        &p_w.fixed_view::<2, 2>(0, 0).into_owned(),
    );
    let yaw = (p_w[(2, 2)] > 0.0)
        .then(|| e_w.z * e_w.z / p_w[(2, 2)])
        .filter(|v| v.is_finite());
    PoseNees {
        t: e.t,
        values: [
            nees_of(&d_theta, &cov.ori),
            nees_of(&d_p, &cov.pos),
            tilt,
            yaw,
            None,
            None,
            None,
        ],
    }
}

/// The average over the runs of one kind at one epoch.
#[derive(Clone, Copy, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct Average {
    /// Mean NEES over the runs that have a value.
    pub value: f64,
    /// Runs that have a value.
    pub runs: usize,
}

/// One epoch: the NEES of each kind averaged over the runs.
#[derive(Clone, Debug, PartialEq)]
pub struct Epoch {
    /// Centre of the epoch (s, on the runs' clock).
    pub t: f64,
    /// Per kind of [`KINDS`]; `None` where fewer than the minimum of runs had it.
    pub averages: [Option<Average>; N],
}

/// The two-sided 95 % band of the average of `runs` NEES values of `dof` DoF.
pub fn band(dof: usize, runs: usize) -> (f64, f64) {
    let n = runs.max(1);
    let k = dof * n;
    (
        chi2_quantile(k, TAIL) / n as f64,
        chi2_quantile(k, 1.0 - TAIL) / n as f64,
    )
}

/// Cuts the runs into epochs of `bin_s` seconds around the earliest estimate and
/// its multiples of `bin_s`,
/// each run giving its first estimate in the epoch (so the values averaged are
/// one per run, as the band assumes), and averages them. An epoch keeps a kind
/// only when at least half of the runs, and two, have it.
pub fn epochs(runs: &[Vec<PoseNees>], bin_s: f64) -> Result<Vec<Epoch>, AneesError> {
    if !(bin_s.is_finite() && bin_s > 0.0) {
        return Err(AneesError::BinLength(bin_s));
    }
    let Some(t0) = runs
        .iter()
        .filter_map(|r| r.first().map(|p| p.t))
        .reduce(f64::min)
    else {
        return Ok(Vec::new());
    };
    let min_runs = runs.len().div_ceil(2).max(2);
    let mut sums: BTreeMap<i64, [(f64, usize); N]> = BTreeMap::new();
    for run in runs {
        let mut last = None;
        for p in run {
            // Epochs centred on the earliest estimate's multiples of `bin_s`,
            // so estimates one frame apart never share an epoch by rounding.
            let key = ((p.t - t0) / bin_s + 0.5).floor() as i64;
            if last == Some(key) {
                continue;
            }
            last = Some(key);
            let slot = sums.entry(key).or_default();
            for (s, v) in slot.iter_mut().zip(p.values) {
                if let Some(v) = v {
                    *s = (s.0 + v, s.1 + 1);
                }
            }
        }
    }
    Ok(sums
        .into_iter()
        .map(|(key, slot)| Epoch {
            t: t0 + key as f64 * bin_s,
            averages: slot.map(|(sum, n)| {
                (n >= min_runs).then(|| Average {
                    value: sum / n as f64,
                    runs: n,
                })
            }),
        })
        .filter(|e| e.averages.iter().any(Option::is_some))
        .collect())
}

/// Where one kind's averages fall against their bands, over the epochs.
#[derive(Clone, Copy, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct BandShare {
    /// Mean over the epochs of the average NEES.
    pub mean: Option<f64>,
    /// Epochs with a value.
    pub epochs: usize,
    /// Fraction of them inside the band.
    pub inside: f64,
    /// Fraction below it (the filter claims less than it knows).
    pub below: f64,
    /// Fraction above it (the filter claims more than it knows).
    pub above: f64,
}

/// The band test of one robot over its runs.
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct AneesSummary {
    /// Runs read.
    pub runs: usize,
    /// Epoch length (s).
    pub bin_s: f64,
    /// Orientation, 3 DoF.
    pub ori: BandShare,
    /// Position, 3 DoF.
    pub pos: BandShare,
    /// Roll and pitch in the world frame, 2 DoF.
    pub tilt: BandShare,
    /// Yaw about gravity, 1 DoF.
    pub yaw: BandShare,
    /// Velocity, 3 DoF (runs with `imu_state.txt`).
    #[serde(default)]
    pub vel: BandShare,
    /// Gyro bias, 3 DoF.
    #[serde(default)]
    pub bias_gyro: BandShare,
    /// Accelerometer bias, 3 DoF.
    #[serde(default)]
    pub bias_accel: BandShare,
}

impl AneesSummary {
    /// The shares of `epochs` made from `runs` runs.
    pub fn of(epochs: &[Epoch], runs: usize, bin_s: f64) -> AneesSummary {
        let share = |k: usize| {
            let dof = KINDS[k].1;
            let (mut sum, mut n, mut below, mut above) = (0.0, 0usize, 0usize, 0usize);
            for a in epochs.iter().filter_map(|e| e.averages[k]) {
                let (lo, hi) = band(dof, a.runs);
                sum += a.value;
                n += 1;
                below += usize::from(a.value < lo);
                above += usize::from(a.value > hi);
            }
            let frac = |c: usize| if n == 0 { 0.0 } else { c as f64 / n as f64 };
            BandShare {
                mean: (n > 0).then(|| sum / n as f64),
                epochs: n,
                inside: frac(n - below - above),
                below: frac(below),
                above: frac(above),
            }
        };
        AneesSummary {
            runs,
            bin_s,
            ori: share(0),
            pos: share(1),
            tilt: share(2),
            yaw: share(3),
            vel: share(4),
            bias_gyro: share(5),
            bias_accel: share(6),
        }
    }

    /// The kinds in the order of [`KINDS`].
    pub fn shares(&self) -> [&BandShare; N] {
        [
            &self.ori,
            &self.pos,
            &self.tilt,
            &self.yaw,
            &self.vel,
            &self.bias_gyro,
            &self.bias_accel,
        ]
    }
}

/// The epochs as CSV: time, then per kind the average, the runs it is over and
/// its band.
pub fn epochs_csv(epochs: &[Epoch]) -> String {
    let mut out = String::from("t_s");
    for (name, _) in KINDS {
        let _ = write!(out, ",{name},{name}_runs,{name}_low,{name}_high");
    }
    out.push('\n');
    for e in epochs {
        let _ = write!(out, "{:.6}", e.t);
        for (a, (_, dof)) in e.averages.iter().zip(KINDS) {
            match a {
                Some(a) => {
                    let (lo, hi) = band(dof, a.runs);
                    let _ = write!(out, ",{},{},{lo:.4},{hi:.4}", a.value, a.runs);
                }
                None => out.push_str(",,,,"),
            }
        }
        out.push('\n');
    }
    out
}

/// Reads the runs in `dirs` and cuts them into epochs of `bin_s` seconds;
/// returns the summary and the epochs.
pub fn study(dirs: &[PathBuf], bin_s: f64) -> Result<(AneesSummary, Vec<Epoch>), AneesError> {
    let runs = dirs
        .iter()
        .map(|d| run_nees(d))
        .collect::<Result<Vec<_>, _>>()?;
    let epochs = epochs(&runs, bin_s)?;
    Ok((AneesSummary::of(&epochs, runs.len(), bin_s), epochs))
}

/// Writes the epochs as CSV ([`epochs_csv`]) to `path`, creating its folder.
pub fn write_csv(path: &Path, epochs: &[Epoch]) -> Result<(), AneesError> {
    let write = || -> std::io::Result<()> {
        if let Some(parent) = path.parent() {
            std::fs::create_dir_all(parent)?;
        }
        std::fs::write(path, epochs_csv(epochs))
    };
    write().map_err(|source| AneesError::Write {
        path: path.to_path_buf(),
        source,
    })
}

/// One cell of a table: `mean: inside / below / above %`.
pub fn cell(s: &BandShare) -> String {
    match s.mean {
        Some(m) => format!(
            "{m:.2}: {:.0} / {:.0} / {:.0}",
            100.0 * s.inside,
            100.0 * s.below,
            100.0 * s.above
        ),
        None => "-".to_string(),
    }
}

/// Arguments of `sim-fleet anees`.
#[derive(clap::Args, Debug, Clone)]
pub struct AneesArgs {
    /// Run folders, each with `estimate.txt`, `groundtruth.txt` and
    /// `covariance.txt` (e.g. `DIR/runs/indp-slam/seed*/robot0` of a study).
    #[arg(required = true, num_args = 1..)]
    pub runs: Vec<PathBuf>,
    /// Epoch length, s: each run gives its first estimate in each epoch.
    #[arg(long, default_value_t = 0.1)]
    pub bin_s: f64,
    /// Write the epochs to this CSV file.
    #[arg(long)]
    pub csv: Option<PathBuf>,
    /// Draw the averages and their bands over time into this SVG file.
    #[arg(long)]
    pub plot: Option<PathBuf>,
    /// Print the summary as JSON.
    #[arg(long)]
    pub json: bool,
}

/// Runs `sim-fleet anees`.
pub fn run_anees(args: &AneesArgs) -> anyhow::Result<()> {
    let (summary, epochs) = study(&args.runs, args.bin_s)?;
    if let Some(path) = &args.csv {
        write_csv(path, &epochs)?;
    }
    if let Some(path) = &args.plot {
        crate::plots::write_anees_plot(path, &epochs, summary.runs)?;
    }
    if args.json {
        println!("{}", serde_json::to_string_pretty(&summary)?);
        return Ok(());
    }
    println!(
        "{} runs, epochs of {} s; average NEES over the runs: mean over the epochs, then the share of epochs inside / below / above the two-sided 95 % band, %",
        summary.runs, summary.bin_s
    );
    println!("| kind | DoF | epochs | mean: inside / below / above |");
    println!("| --- | ---: | ---: | --- |");
    for ((name, dof), s) in KINDS.iter().zip(summary.shares()) {
        println!("| {name} | {dof} | {} | {} |", s.epochs, cell(s));
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;
    use rand::{Rng, SeedableRng};
    use rand_chacha::ChaCha8Rng;

    #[test]
    fn the_band_holds_the_chi_square_quantiles_of_the_average() {
        // One run, 3 DoF: the χ²₃ 2.5 % and 97.5 % quantiles.
        let (lo, hi) = band(3, 1);
        assert!((lo - 0.2158).abs() < 1e-3 && (hi - 9.3484).abs() < 1e-3);
        // 20 runs, 3 DoF: χ²₆₀ quantiles 40.48 and 83.30, over 20.
        let (lo, hi) = band(3, 20);
        assert!((lo - 40.482 / 20.0).abs() < 1e-3, "{lo}");
        assert!((hi - 83.298 / 20.0).abs() < 1e-3, "{hi}");
    }

    fn pose(t: f64, v: f64) -> PoseNees {
        PoseNees {
            t,
            values: [Some(v), Some(2.0 * v), None, Some(v), None, None, None],
        }
    }

    #[test]
    fn each_run_gives_one_value_per_epoch_and_thin_epochs_are_dropped() {
        // Run a: two estimates in epoch 0 (only the first counts), one in 1.
        // Run b: epochs 0 and 3. Run c: epoch 0.
        let runs = vec![
            vec![pose(10.0, 1.0), pose(10.03, 100.0), pose(10.1, 3.0)],
            vec![pose(10.02, 2.0), pose(10.25, 5.0)],
            vec![pose(10.0, 3.0)],
        ];
        let e = epochs(&runs, 0.1).unwrap();
        // Epoch 0 has three runs; epochs 1 and 3 one each, under the minimum of 2.
        assert_eq!(e.len(), 1);
        assert_eq!(e[0].t, 10.0);
        assert_eq!(
            e[0].averages[0],
            Some(Average {
                value: 2.0,
                runs: 3
            })
        );
        assert_eq!(
            e[0].averages[1],
            Some(Average {
                value: 4.0,
                runs: 3
            })
        );
        assert_eq!(e[0].averages[2], None);
        assert!(epochs(&runs, 0.0).is_err() && epochs(&runs, f64::NAN).is_err());
        assert!(epochs(&[], 0.1).unwrap().is_empty());
    }

    /// A standard normal sample (Box–Muller).
    fn normal(rng: &mut ChaCha8Rng) -> f64 {
        let u1: f64 = 1.0 - rng.random::<f64>();
        let u2: f64 = rng.random::<f64>();
        (-2.0 * u1.ln()).sqrt() * (std::f64::consts::TAU * u2).cos()
    }

    #[test]
    fn consistent_runs_stay_in_the_band_and_scaled_ones_leave_it() {
        let mut rng = ChaCha8Rng::seed_from_u64(3);
        // 20 runs of 500 epochs whose NEES are sums of d squared normals:
        // consistent, then errors twice (NEES x4) and half (x1/4) as large.
        let draw = |rng: &mut ChaCha8Rng, dof: usize| -> f64 {
            (0..dof).map(|_| normal(rng).powi(2)).sum()
        };
        for (scale, expect) in [(1.0, "inside"), (4.0, "above"), (0.25, "below")] {
            let runs: Vec<Vec<PoseNees>> = (0..20)
                .map(|_| {
                    (0..500)
                        .map(|i| PoseNees {
                            t: i as f64 * 0.1,
                            values: KINDS.map(|(_, dof)| Some(scale * draw(&mut rng, dof))),
                        })
                        .collect()
                })
                .collect();
            let e = epochs(&runs, 0.1).unwrap();
            assert_eq!(e.len(), 500);
            let s = AneesSummary::of(&e, 20, 0.1);
            for share in s.shares() {
                let got = match expect {
                    "inside" => share.inside,
                    "above" => share.above,
                    _ => share.below,
                };
                // 95 % inside when consistent; all outside when 4x off.
                let want = if expect == "inside" { 0.9 } else { 0.99 };
                assert!(got >= want, "{expect}: {share:?}");
            }
        }
    }

    #[test]
    fn a_yaw_error_counts_in_yaw_only_whatever_the_body_attitude() {
        use common::so3::exp_so3;
        use nalgebra::{Matrix3, Vector3};
        // The body rolled 90 deg about x: its y axis points along world z.
        let r_est = exp_so3(&Vector3::new(std::f64::consts::FRAC_PI_2, 0.0, 0.0));
        let est = StampedPose {
            t: 1.0,
            rot: r_est,
            pos: Vector3::zeros(),
        };
        // The truth: 0.01 rad of yaw about world z, 3 cm along x.
        let gt = StampedPose {
            t: 1.0,
            rot: exp_so3(&Vector3::new(0.0, 0.0, 0.01)) * r_est,
            pos: Vector3::new(0.03, 0.0, 0.0),
        };
        let cov = StampedCovariance {
            t: 1.0,
            ori: Matrix3::from_diagonal(&Vector3::new(1e-6, 4e-4, 9e-6)),
            pos: Matrix3::from_diagonal(&Vector3::new(1e-4, 1e-4, 1e-4)),
        };
        let v = pose_nees(&est, &gt, &cov).values;
        assert_eq!(v[4..], [None; 3], "no IMU state from a pose");
        let n: Vec<f64> = v[..4].iter().map(|x| x.unwrap()).collect();
        // World yaw has the body-y variance, 4e-4: 1e-4 / 4e-4.
        assert!((n[0] - 0.25).abs() < 1e-9, "{n:?}");
        assert!((n[1] - 9.0).abs() < 1e-9, "{n:?}");
        assert!(n[2].abs() < 1e-12, "{n:?}");
        assert!((n[3] - 0.25).abs() < 1e-9, "{n:?}");
    }

    #[test]
    fn a_run_folder_gives_the_imu_states_nees_where_it_has_the_file() {
        use common::trajectory::{
            write_covariances, write_imu_states, write_tum, ImuEstimate, ImuTruth,
        };
        use nalgebra::{Matrix3, Vector3};
        let dir = tempfile::tempdir().unwrap();
        let pose = |t: f64| StampedPose {
            t,
            rot: Matrix3::identity(),
            pos: Vector3::new(t, 0.0, 0.0),
        };
        let poses: Vec<StampedPose> = (0..3).map(|k| pose(k as f64 * 0.1)).collect();
        write_tum(dir.path().join("estimate.txt"), &poses).unwrap();
        write_tum(dir.path().join("groundtruth.txt"), &poses).unwrap();
        let covs: Vec<StampedCovariance> = poses
            .iter()
            .map(|p| StampedCovariance {
                t: p.t,
                ori: Matrix3::identity() * 1e-4,
                pos: Matrix3::identity() * 1e-2,
            })
            .collect();
        write_covariances(dir.path().join("covariance.txt"), &covs).unwrap();
        let first = run_nees(dir.path()).unwrap();
        assert_eq!(first.len(), 3);
        assert!(first.iter().all(|p| p.values[4..] == [None; 3]));
        // The velocity 0.2 m/s off at a 0.1 m/s sigma: NEES 4; the biases exact.
        let states: Vec<ImuStateRecord> = poses[1..]
            .iter()
            .map(|p| ImuStateRecord {
                estimate: ImuEstimate {
                    t: p.t,
                    vel: Vector3::new(1.0, 0.0, 0.0),
                    cov_vel: Matrix3::identity() * 0.01,
                    cov_bias_gyro: Matrix3::identity() * 1e-6,
                    cov_bias_accel: Matrix3::identity() * 1e-4,
                    ..Default::default()
                },
                truth: ImuTruth {
                    vel: Vector3::new(1.0, 0.2, 0.0),
                    ..Default::default()
                },
            })
            .collect();
        write_imu_states(dir.path().join("imu_state.txt"), &states).unwrap();
        let n = run_nees(dir.path()).unwrap();
        assert_eq!(
            n[0].values[4..],
            [None; 3],
            "no line for the first estimate"
        );
        for p in &n[1..] {
            assert!((p.values[4].unwrap() - 4.0).abs() < 1e-9, "{p:?}");
            assert_eq!(p.values[5..], [Some(0.0), Some(0.0)]);
        }
    }

    #[test]
    fn the_csv_has_a_column_set_per_kind_and_blanks_for_missing_ones() {
        let runs = vec![vec![pose(0.0, 1.0)], vec![pose(0.0, 3.0)]];
        let csv = epochs_csv(&epochs(&runs, 0.1).unwrap());
        let mut lines = csv.lines();
        assert_eq!(
            lines.next().unwrap(),
            "t_s,ori,ori_runs,ori_low,ori_high,pos,pos_runs,pos_low,pos_high,\
             tilt,tilt_runs,tilt_low,tilt_high,yaw,yaw_runs,yaw_low,yaw_high,\
             vel,vel_runs,vel_low,vel_high,bias_gyro,bias_gyro_runs,bias_gyro_low,bias_gyro_high,\
             bias_accel,bias_accel_runs,bias_accel_low,bias_accel_high"
        );
        let row: Vec<&str> = lines.next().unwrap().split(',').collect();
        assert_eq!(row.len(), 29);
        assert_eq!((row[1], row[2], row[5]), ("2", "2", "4"));
        assert_eq!(&row[9..13], &["", "", "", ""]);
    }
}
