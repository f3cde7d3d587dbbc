//! `sim-fleet compare`: plots of several runs of one fleet side by side (e.g.
//! `indp-slam` against `dc-full-history` on the same seed): per robot, the
//! top-down trajectories against the truth, and the position error of each run
//! with its ±3σ bounds. Runs are output folders of `sim-fleet run` or one seed's
//! folder of `sim-fleet montecarlo` (`robot<i>/estimate.txt`, `groundtruth.txt`,
//! `covariance.txt`).

use crate::eval::{evaluate, EvalReport};
use crate::plots::{draw_xy, range, DrawResult};
use anyhow::{bail, Context, Result};
use common::metrics::{Alignment, DEFAULT_RPE_SEGMENTS_M};
use common::trajectory::{read_covariances, read_trajectory};
use plotters::prelude::*;
use std::path::{Path, PathBuf};

/// Arguments of `sim-fleet compare`.
#[derive(clap::Args, Debug, Clone)]
pub struct CompareArgs {
    /// A run as `LABEL=FOLDER` (repeat; the first is drawn first).
    #[arg(long = "run", required = true, value_parser = parse_run)]
    pub runs: Vec<(String, PathBuf)>,
    /// Output folder of the SVG plots.
    #[arg(long)]
    pub out: PathBuf,
}

fn parse_run(s: &str) -> Result<(String, PathBuf), String> {
    let (label, dir) = s
        .split_once('=')
        .ok_or_else(|| format!("expected LABEL=FOLDER, got `{s}`"))?;
    Ok((label.to_string(), PathBuf::from(dir)))
}

const COLORS: [RGBColor; 4] = [
    RGBColor(200, 30, 30),
    RGBColor(30, 60, 200),
    RGBColor(30, 140, 30),
    RGBColor(160, 60, 160),
];

/// The robot folders of a run, in robot order.
fn robot_dirs(run: &Path) -> Vec<PathBuf> {
    (0..)
        .map(|i| run.join(format!("robot{i}")))
        .take_while(|d| d.join("estimate.txt").is_file())
        .collect()
}

fn evaluate_dir(dir: &Path) -> Result<EvalReport> {
    let gt = read_trajectory(dir.join("groundtruth.txt"))
        .with_context(|| format!("reading {}", dir.join("groundtruth.txt").display()))?;
    let est = read_trajectory(dir.join("estimate.txt"))
        .with_context(|| format!("reading {}", dir.join("estimate.txt").display()))?;
    let covs = read_covariances(dir.join("covariance.txt")).ok();
    Ok(evaluate(
        &gt,
        &est,
        covs.as_deref(),
        Alignment::None,
        &DEFAULT_RPE_SEGMENTS_M,
    ))
}

fn trajectories(path: &Path, robot: usize, reports: &[(String, EvalReport)]) -> DrawResult {
    let root = SVGBackend::new(path, (900, 900)).into_drawing_area();
    root.fill(&WHITE)?;
    let xy = |p: [f64; 3]| (p[0], p[1]);
    let gt = reports
        .first()
        .map(|(_, r)| r.per_pose.iter().map(|p| xy(p.gt_pos)).collect())
        .unwrap_or_default();
    let estimates = reports
        .iter()
        .enumerate()
        .map(|(k, (label, r))| {
            let ate = r
                .ate_pos_m
                .map_or_else(|| "-".into(), |a| format!("{a:.3}"));
            (
                format!("{label} (ATE {ate} m)"),
                r.per_pose.iter().map(|p| xy(p.est_pos)).collect(),
                COLORS[k % COLORS.len()],
            )
        })
        .collect();
    draw_xy(
        &root,
        &format!("robot {robot}: trajectory x-y"),
        gt,
        estimates,
    )?;
    root.present()?;
    Ok(())
}

fn position_errors(path: &Path, robot: usize, reports: &[(String, EvalReport)]) -> DrawResult {
    let root = SVGBackend::new(path, (1000, 900)).into_drawing_area();
    root.fill(&WHITE)?;
    let t0 = reports
        .iter()
        .filter_map(|(_, r)| r.per_pose.first().map(|p| p.t))
        .fold(f64::INFINITY, f64::min);
    let t_range = range(
        reports
            .iter()
            .flat_map(|(_, r)| r.per_pose.iter().map(|p| p.t - t0)),
    );
    for (axis, panel) in root.split_evenly((3, 1)).iter().enumerate() {
        let y = range(reports.iter().flat_map(|(_, r)| {
            r.per_pose.iter().flat_map(move |p| {
                let s = p.pos_sigma.map_or(0.0, |s| 3.0 * s[axis]);
                [p.pos_err[axis], s, -s]
            })
        }));
        let name = ["x", "y", "z"][axis];
        let mut chart = ChartBuilder::on(panel)
            .caption(
                format!("robot {robot}: position error {name} and ±3σ"),
                ("sans-serif", 18),
            )
            .margin(8)
            .x_label_area_size(35)
            .y_label_area_size(70)
            .build_cartesian_2d(t_range.clone(), y)?;
        chart
            .configure_mesh()
            .label_style(("sans-serif", 15))
            .x_desc("time [s]")
            .y_desc(format!("{name} [m]"))
            .draw()?;
        for (k, (label, r)) in reports.iter().enumerate() {
            let c = COLORS[k % COLORS.len()];
            let err: Vec<(f64, f64)> = r
                .per_pose
                .iter()
                .map(|p| (p.t - t0, p.pos_err[axis]))
                .collect();
            chart
                .draw_series(LineSeries::new(err, c.stroke_width(2)))?
                .label(label.clone())
                .legend(move |(x, y)| PathElement::new(vec![(x, y), (x + 20, y)], c));
            for sign in [1.0, -1.0] {
                let bound: Vec<(f64, f64)> = r
                    .per_pose
                    .iter()
                    .filter_map(|p| p.pos_sigma.map(|s| (p.t - t0, sign * 3.0 * s[axis])))
                    .collect();
                chart.draw_series(LineSeries::new(bound, c.mix(0.45)))?;
            }
        }
        chart
            .configure_series_labels()
            .background_style(WHITE.mix(0.8))
            .border_style(BLACK)
            .draw()?;
    }
    root.present()?;
    Ok(())
}

/// Runs `sim-fleet compare`.
pub fn run_compare(args: &CompareArgs) -> Result<()> {
    let mut per_run = Vec::new();
    for (label, dir) in &args.runs {
        let robots = robot_dirs(dir);
        if robots.is_empty() {
            bail!("{}: no robot<i>/estimate.txt in it", dir.display());
        }
        let reports: Vec<EvalReport> = robots
            .iter()
            .map(|d| evaluate_dir(d))
            .collect::<Result<_>>()?;
        per_run.push((label.clone(), reports));
    }
    let robots = per_run.iter().map(|(_, r)| r.len()).min().unwrap_or(0);
    std::fs::create_dir_all(&args.out)
        .with_context(|| format!("creating {}", args.out.display()))?;
    for i in 0..robots {
        let reports: Vec<(String, EvalReport)> = per_run
            .iter()
            .map(|(l, r)| (l.clone(), r[i].clone()))
            .collect();
        let p = args.out.join(format!("robot{i}_trajectory_xy.svg"));
        trajectories(&p, i, &reports).map_err(|e| anyhow::anyhow!("{}: {e}", p.display()))?;
        let p = args.out.join(format!("robot{i}_error_pos.svg"));
        position_errors(&p, i, &reports).map_err(|e| anyhow::anyhow!("{}: {e}", p.display()))?;
        for (l, r) in &reports {
            println!(
                "robot {i} {l:>16}: ATE {:.3} deg / {:.3} m, NEES {} / {}",
                r.ate_ori_deg.unwrap_or(f64::NAN),
                r.ate_pos_m.unwrap_or(f64::NAN),
                r.nees_ori.map_or("-".into(), |v| format!("{v:.2}")),
                r.nees_pos.map_or("-".into(), |v| format!("{v:.2}")),
            );
        }
    }
    println!("plots in {}", args.out.display());
    Ok(())
}
