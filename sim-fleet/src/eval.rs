//! `sim-fleet eval`: ATE, RPE and NEES of an estimate against ground truth,
//! printed as a table or JSON, with SVG plots ([`crate::plots`]).

use std::fmt::Write as _;
use std::path::{Path, PathBuf};

use anyhow::{bail, Context};
use common::metrics::{
    align, apply_alignment, associate, ate_with, find_covariance, nees, nees_of, pose_error, rpe,
    Alignment, PosePair, RpeResult, CHI2_3DOF_95_HIGH, CHI2_3DOF_95_LOW, DEFAULT_MAX_DT_S,
    DEFAULT_RPE_SEGMENTS_M,
};
use common::so3::xyzw_from_rot;
use common::summary::MetricSet;
use common::trajectory::{
    read_covariances, read_imu_states, read_trajectory, StampedCovariance, StampedPose,
};
use nalgebra::Vector3;
use serde::{Deserialize, Serialize};

/// Arguments of `sim-fleet eval`.
#[derive(clap::Args, Debug, Clone)]
pub struct EvalArgs {
    /// Ground truth: TUM text, or EuRoC CSV when the name ends in `.csv`.
    #[arg(long)]
    pub gt: PathBuf,
    /// Estimated trajectory (TUM text, or EuRoC CSV when the name ends in `.csv`).
    #[arg(long)]
    pub est: PathBuf,
    /// Per-pose covariances of the estimate (enables NEES and ±3σ bounds).
    #[arg(long)]
    pub cov: Option<PathBuf>,
    /// Alignment of the estimate before the ATE: none, posyaw or se3.
    #[arg(long, default_value_t = Alignment::None)]
    pub align: Alignment,
    /// RPE segment lengths in metres, comma separated.
    #[arg(long, value_delimiter = ',', default_values_t = DEFAULT_RPE_SEGMENTS_M)]
    pub segments: Vec<f64>,
    /// Skip estimates whose nearest ground-truth sample is further than this (s).
    #[arg(long, default_value_t = DEFAULT_MAX_DT_S)]
    pub max_dt: f64,
    /// Print one JSON object instead of the table.
    #[arg(long)]
    pub json: bool,
    /// Folder of the plots (default: `<est stem>_plots` next to the estimate).
    #[arg(long)]
    pub plots_dir: Option<PathBuf>,
    /// Do not write plots.
    #[arg(long)]
    pub no_plots: bool,
    /// Also cut the run into bins of this many seconds from its first pose:
    /// RMS and largest error and mean NEES per bin (how a long run evolves).
    #[arg(long)]
    pub bins_s: Option<f64>,
    /// The agent's `timing.csv` of the run: its per-frame cost in the same
    /// bins (CPU ms mean, p95 and largest; matching and evidence ms).
    #[arg(long, requires = "bins_s")]
    pub timing: Option<PathBuf>,
    /// The run's `imu_state.txt` (simulated runs): the velocity and both
    /// biases against the truth, RMS error and mean NEES, with plots of their
    /// errors and ±3σ.
    #[arg(long)]
    pub imu_state: Option<PathBuf>,
}

/// Errors of one associated pose, for plots (see [`EvalReport::per_pose`]).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct PoseError {
    /// Time (s).
    pub t: f64,
    /// Aligned estimated position (m).
    pub est_pos: [f64; 3],
    /// Ground-truth position (m).
    pub gt_pos: [f64; 3],
    /// `δp = p_gt − p_est'` in the global frame (m), of the aligned estimate.
    pub pos_err: [f64; 3],
    /// `δθ = Log(R_est'ᵀ R_gt)` (local frame, degrees), of the aligned estimate.
    pub ori_err_deg: [f64; 3],
    /// Filter standard deviations of the position (m), if a covariance matched.
    pub pos_sigma: Option<[f64; 3]>,
    /// Filter standard deviations of the orientation (degrees), if a covariance matched.
    pub ori_sigma_deg: Option<[f64; 3]>,
    /// Orientation NEES of the unaligned estimate.
    pub nees_ori: Option<f64>,
    /// Position NEES of the unaligned estimate.
    pub nees_pos: Option<f64>,
}

/// Everything `sim-fleet eval` computes for one trajectory.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct EvalReport {
    /// Alignment mode used for the ATE and the per-pose errors.
    pub align: Alignment,
    /// Rotation of the alignment applied to the estimate, `[qx, qy, qz, qw]`.
    pub align_rot_xyzw: [f64; 4],
    /// Translation of the alignment applied to the estimate (m).
    pub align_trans: [f64; 3],
    /// Number of associated pose pairs.
    pub pairs: usize,
    /// ATE orientation RMSE (degrees), `None` without pairs.
    pub ate_ori_deg: Option<f64>,
    /// ATE position RMSE (m), `None` without pairs.
    pub ate_pos_m: Option<f64>,
    /// RPE per segment length.
    pub rpe: Vec<RpeResult>,
    /// Mean orientation NEES (`None` without covariances).
    pub nees_ori: Option<f64>,
    /// Mean position NEES (`None` without covariances).
    pub nees_pos: Option<f64>,
    /// Estimates without a covariance at their time (0 without covariances).
    pub nees_unmatched: usize,
    /// Covariance blocks skipped as not positive definite (orientation + position).
    pub nees_singular: usize,
    /// Per-pose errors, in time order.
    pub per_pose: Vec<PoseError>,
}

/// The one JSON object printed by `sim-fleet eval --json`.
#[derive(Serialize)]
struct EvalJson<'a> {
    ate_ori_deg: Option<f64>,
    ate_pos_m: Option<f64>,
    nees_ori: Option<f64>,
    nees_pos: Option<f64>,
    rpe: &'a [RpeResult],
    align: Alignment,
    pairs: usize,
    #[serde(skip_serializing_if = "Option::is_none")]
    bins: Option<&'a [bins::Bin]>,
}

/// Evaluates `est` against `gt`: association ([`associate`] with
/// [`DEFAULT_MAX_DT_S`]) then [`evaluate_pairs`].
pub fn evaluate(
    gt: &[StampedPose],
    est: &[StampedPose],
    covs: Option<&[StampedCovariance]>,
    align: Alignment,
    segments: &[f64],
) -> EvalReport {
    evaluate_pairs(&associate(est, gt, DEFAULT_MAX_DT_S), covs, align, segments)
}

/// ATE (with `mode` alignment), RPE over `segments` (m) and, with
/// covariances, NEES (unaligned) of associated `(est, gt)` pairs.
pub fn evaluate_pairs(
    pairs: &[PosePair],
    covs: Option<&[StampedCovariance]>,
    mode: Alignment,
    segments: &[f64],
) -> EvalReport {
    let t_align = align(pairs, mode);
    let ate = ate_with(pairs, &t_align);
    let has_pairs = ate.n > 0;
    let nees_result = covs.map(|c| nees(pairs, c));
    let per_pose = pairs
        .iter()
        .map(|(est, gt)| {
            let aligned = apply_alignment(&t_align, est);
            let (d_theta, d_p) = pose_error(&aligned, gt);
            let cov = covs.and_then(|c| find_covariance(c, est.t));
            let (raw_theta, raw_p) = pose_error(est, gt);
            let sigma = |m: &nalgebra::Matrix3<f64>, scale: f64| {
                let d = m.diagonal();
                [0, 1, 2].map(|k| d[k].max(0.0).sqrt() * scale)
            };
            PoseError {
                t: est.t,
                est_pos: array(&aligned.pos),
                gt_pos: array(&gt.pos),
                pos_err: array(&d_p),
                ori_err_deg: array(&d_theta.map(f64::to_degrees)),
                pos_sigma: cov.map(|c| sigma(&c.pos, 1.0)),
                ori_sigma_deg: cov.map(|c| sigma(&c.ori, 1f64.to_degrees())),
                nees_ori: cov.and_then(|c| nees_of(&raw_theta, &c.ori)),
                nees_pos: cov.and_then(|c| nees_of(&raw_p, &c.pos)),
            }
        })
        .collect();
    EvalReport {
        align: mode,
        align_rot_xyzw: xyzw_from_rot(&t_align.rot),
        align_trans: array(&t_align.trans),
        pairs: ate.n,
        ate_ori_deg: has_pairs.then_some(ate.ori_deg),
        ate_pos_m: has_pairs.then_some(ate.pos_m),
        rpe: rpe(pairs, segments),
        nees_ori: nees_result.as_ref().and_then(|n| n.ori_mean),
        nees_pos: nees_result.as_ref().and_then(|n| n.pos_mean),
        nees_unmatched: nees_result.as_ref().map_or(0, |n| n.unmatched),
        nees_singular: nees_result
            .as_ref()
            .map_or(0, |n| n.singular_ori + n.singular_pos),
        per_pose,
    }
}

fn array(v: &Vector3<f64>) -> [f64; 3] {
    [v.x, v.y, v.z]
}

impl EvalReport {
    /// The accuracy part of a run summary (ATE, NEES, RPE); the rest is `None`.
    pub fn metric_set(&self) -> MetricSet {
        MetricSet {
            ate_ori_deg: self.ate_ori_deg,
            ate_pos_m: self.ate_pos_m,
            nees_ori: self.nees_ori,
            nees_pos: self.nees_pos,
            rpe: Some(self.rpe.clone()),
            ..MetricSet::default()
        }
    }

    /// The JSON object of `--json`: `ate_ori_deg`, `ate_pos_m`, `nees_ori`,
    /// `nees_pos`, `rpe`, `align`, `pairs` (unknown values are `null`).
    pub fn to_json(&self) -> serde_json::Result<String> {
        self.to_json_with(None)
    }

    /// [`EvalReport::to_json`], with the `bins` of `--bins-s` if given.
    pub fn to_json_with(&self, bins: Option<&[bins::Bin]>) -> serde_json::Result<String> {
        serde_json::to_string(&EvalJson {
            ate_ori_deg: self.ate_ori_deg,
            ate_pos_m: self.ate_pos_m,
            nees_ori: self.nees_ori,
            nees_pos: self.nees_pos,
            rpe: &self.rpe,
            align: self.align,
            pairs: self.pairs,
            bins,
        })
    }

    /// The human-readable table printed by `sim-fleet eval`.
    pub fn table(&self) -> String {
        let mut s = String::new();
        let _ = writeln!(s, "pairs: {}   alignment: {}", self.pairs, self.align);
        let _ = writeln!(
            s,
            "ATE   orientation {} deg   position {} m",
            opt(self.ate_ori_deg, 3),
            opt(self.ate_pos_m, 4)
        );
        let _ = writeln!(
            s,
            "RPE   {:>9} {:>7} {:>14} {:>16} {:>12} {:>14}",
            "segment_m", "count", "ori_mean_deg", "ori_median_deg", "pos_mean_m", "pos_median_m"
        );
        for r in &self.rpe {
            let _ = writeln!(
                s,
                "      {:>9.1} {:>7} {:>14} {:>16} {:>12} {:>14}",
                r.segment_m,
                r.count,
                opt(r.ori_deg_mean, 3),
                opt(r.ori_deg_median, 3),
                opt(r.pos_m_mean, 4),
                opt(r.pos_m_median, 4)
            );
        }
        if self.nees_ori.is_some() || self.nees_pos.is_some() || self.nees_unmatched > 0 {
            let _ = writeln!(
                s,
                "NEES  orientation {}   position {}   (3 DoF, single-run 95% bounds {}..{}; {} without covariance, {} singular blocks)",
                opt(self.nees_ori, 3),
                opt(self.nees_pos, 3),
                CHI2_3DOF_95_LOW,
                CHI2_3DOF_95_HIGH,
                self.nees_unmatched,
                self.nees_singular
            );
        }
        s
    }
}

/// A number with `digits` decimals, or `-` when unknown.
fn opt(v: Option<f64>, digits: usize) -> String {
    v.map_or_else(|| "-".to_string(), |x| format!("{x:.digits$}"))
}

/// Runs `sim-fleet eval`: reads the files, evaluates, prints, writes plots.
pub fn run_eval(args: &EvalArgs) -> anyhow::Result<()> {
    if let Some(bad) = args.segments.iter().find(|s| !(s.is_finite() && **s > 0.0)) {
        bail!("RPE segment lengths must be positive, got {bad}");
    }
    if let Some(b) = args.bins_s.filter(|b| !(b.is_finite() && *b > 0.0)) {
        bail!("--bins-s must be a positive number of seconds, got {b}");
    }
    let gt = read_trajectory(&args.gt).context("reading the ground truth")?;
    let est = read_trajectory(&args.est).context("reading the estimate")?;
    let covs = match &args.cov {
        Some(path) => Some(read_covariances(path).context("reading the covariances")?),
        None => None,
    };
    let pairs = associate(&est, &gt, args.max_dt);
    if pairs.is_empty() {
        bail!(
            "no estimated pose matches the ground truth in time: estimate {} spans {}, ground truth {} spans {} (max dt {} s)",
            args.est.display(),
            span(&est),
            args.gt.display(),
            span(&gt),
            args.max_dt
        );
    }
    let report = evaluate_pairs(&pairs, covs.as_deref(), args.align, &args.segments);
    if covs.is_some() && report.nees_unmatched == report.pairs {
        tracing::warn!("no covariance matches an estimate time within 1e-6 s: no NEES");
    }
    let timing = match &args.timing {
        Some(path) => Some(bins::read_timing(path)?),
        None => None,
    };
    let bins = match args.bins_s {
        Some(b) => {
            Some(bins::bins(&report.per_pose, timing.as_ref(), b).map_err(anyhow::Error::msg)?)
        }
        None => None,
    };
    let imu = match &args.imu_state {
        Some(path) => Some(read_imu_states(path).context("reading the IMU states")?),
        None => None,
    };
    let imu_report = imu.as_deref().map(imu_state::evaluate);
    if args.json {
        let text = report.to_json_with(bins.as_deref())?;
        match &imu_report {
            Some(r) => {
                let mut value: serde_json::Value = serde_json::from_str(&text)?;
                value["imu_state"] = serde_json::to_value(r)?;
                println!("{value}");
            }
            None => println!("{text}"),
        }
    } else {
        print!("{}", report.table());
        if let Some(r) = &imu_report {
            print!("{}", r.table());
        }
        if let Some(b) = &bins {
            print!("{}", bins::table(b));
        }
    }
    if !args.no_plots {
        let dir = args
            .plots_dir
            .clone()
            .unwrap_or_else(|| default_plots_dir(&args.est));
        let mut files = crate::plots::write_plots(&report, &dir)?;
        if let Some(records) = &imu {
            files.extend(crate::plots::write_imu_plots(records, &dir)?);
        }
        tracing::info!("wrote {} plots into {}", files.len(), dir.display());
    }
    Ok(())
}

/// `<folder of est>/<est stem>_plots`.
pub fn default_plots_dir(est: &Path) -> PathBuf {
    let stem = est
        .file_stem()
        .map_or_else(|| "estimate".into(), |s| s.to_string_lossy());
    est.parent()
        .unwrap_or_else(|| Path::new(""))
        .join(format!("{stem}_plots"))
}

/// `[first, last] s (n poses)` of a trajectory.
fn span(traj: &[StampedPose]) -> String {
    match (traj.first(), traj.last()) {
        (Some(a), Some(b)) => format!("[{:.3}, {:.3}] s ({} poses)", a.t, b.t, traj.len()),
        _ => "nothing (empty)".to_string(),
    }
}

pub mod bins;
pub mod imu_state;

#[cfg(test)]
mod tests;
