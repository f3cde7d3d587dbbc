//! `agent`: runs one robot of the fleet.
use agent::runner::{options_for, run_robot, Variant};
use anyhow::{Context, Result};
use clap::{Parser, Subcommand};
use common::summary::{MetricSet, RobotSummary, RunSummary};
use common::trajectory::{write_covariances, write_tum};
use simulator::{Fleet, Scenario};
use std::io::Write;
use std::path::PathBuf;
use std::time::Instant;

/// One robot's agent of the distributed multi-robot VIO fleet.
#[derive(Parser, Debug)]
#[command(name = "agent", version, about, long_about = None)]
struct Cli {
    #[command(subcommand)]
    command: Option<Command>,
}

#[derive(Subcommand, Debug)]
enum Command {
    /// Run one robot of a simulated scenario standalone (no peers) and score it.
    Run(RunArgs),
}

#[derive(clap::Args, Debug)]
struct RunArgs {
    /// Scenario file (YAML).
    #[arg(long)]
    scenario: PathBuf,
    /// Robot index in the scenario.
    #[arg(long, default_value_t = 0)]
    robot: usize,
    /// Seed (default: the scenario's).
    #[arg(long)]
    seed: Option<u64>,
    /// Estimator variant: indp (MSCKF only) or indp-slam.
    #[arg(long, default_value = "indp-slam")]
    variant: String,
    /// Output folder.
    #[arg(long, default_value = "out/agent")]
    out: PathBuf,
}

fn main() -> Result<()> {
    tracing_subscriber::fmt()
        .with_env_filter(
            tracing_subscriber::EnvFilter::try_from_default_env()
                .unwrap_or_else(|_| tracing_subscriber::EnvFilter::new("info")),
        )
        .with_writer(std::io::stderr)
        .init();
    match Cli::parse().command {
        Some(Command::Run(args)) => run(&args),
        None => {
            println!("agent {} (see --help)", env!("CARGO_PKG_VERSION"));
            Ok(())
        }
    }
}

fn run(args: &RunArgs) -> Result<()> {
    let wall = Instant::now();
    let scenario = Scenario::load(&args.scenario)?;
    let seed = args.seed.unwrap_or(scenario.seed);
    let variant: Variant = args.variant.parse()?;
    let fleet = Fleet::build(&scenario, seed)?;
    let opts = options_for(&scenario.estimator, &fleet, variant);
    let run = run_robot(&fleet, args.robot, opts)?;
    for r in run.rejected.iter().take(5) {
        tracing::warn!("rejected: {r}");
    }
    let out = &args.out;
    std::fs::create_dir_all(out).with_context(|| format!("creating {}", out.display()))?;
    write_tum(out.join("estimate.txt"), &run.estimate)?;
    write_tum(out.join("groundtruth.txt"), &run.truth)?;
    write_covariances(out.join("covariance.txt"), &run.covariance)?;
    let mut timing = std::io::BufWriter::new(std::fs::File::create(out.join("timing.csv"))?);
    writeln!(timing, "t,propagate_ms,msckf_ms,slam_update_ms,slam_init_ms,marginalize_ms,total_ms,msckf_features,msckf_rejected,msckf_failed,slam_features,slam_updated,slam_rejected,slam_initialized,slam_init_failed")?;
    for f in &run.frames {
        let t = &f.timing;
        writeln!(
            timing,
            "{:.6},{:.4},{:.4},{:.4},{:.4},{:.4},{:.4},{},{},{},{},{},{},{},{}",
            f.t,
            t.propagate_ms,
            t.msckf_ms,
            t.slam_update_ms,
            t.slam_init_ms,
            t.marginalize_ms,
            t.total_ms,
            f.msckf_features,
            f.msckf.rejected_chi2,
            f.msckf.failed,
            f.slam_features,
            f.slam.updated,
            f.slam.rejected_chi2,
            f.slam.initialized,
            f.slam.init_failed
        )?;
    }
    timing.flush()?;
    let metrics = run.metrics();
    println!(
        "robot {} ({}), {}, seed {seed}: ATE {:.3} deg / {:.3} m, NEES ori {:.2} pos {:.2}, {:.2} ms/frame (p95 {:.2}), {} frames",
        args.robot,
        scenario.robot_name(args.robot),
        variant.name(),
        metrics.ate_ori_deg.unwrap_or(f64::NAN),
        metrics.ate_pos_m.unwrap_or(f64::NAN),
        metrics.nees_ori.unwrap_or(f64::NAN),
        metrics.nees_pos.unwrap_or(f64::NAN),
        metrics.ms_per_frame_mean.unwrap_or(f64::NAN),
        metrics.ms_per_frame_p95.unwrap_or(f64::NAN),
        run.frames.len()
    );
    let sim_s = run.estimate.last().map(|p| p.t).unwrap_or(0.0)
        - run.estimate.first().map(|p| p.t).unwrap_or(0.0);
    let summary = RunSummary {
        scenario: scenario.name.clone(),
        variant: Some(variant.name().to_string()),
        seed,
        transport: None,
        wall_s: Some(wall.elapsed().as_secs_f64()),
        sim_s: Some(sim_s),
        mean: MetricSet::mean_of(std::slice::from_ref(&metrics)),
        robots: vec![RobotSummary {
            id: args.robot as u32,
            trajectory: scenario.robot_name(args.robot),
            metrics,
        }],
    };
    summary.write_json(out.join("summary.json"))?;
    Ok(())
}
