//! `sim-fleet`: simulate a fleet, evaluate estimates, run Monte-Carlo studies (and,
//! launch a fleet of agents).
use anyhow::Result;
use clap::{Parser, Subcommand};
use sim_fleet::anees::{run_anees, AneesArgs};
use sim_fleet::compare::{run_compare, CompareArgs};
use sim_fleet::convert::{run_convert, ConvertArgs};
use sim_fleet::eval::{run_eval, EvalArgs};
use sim_fleet::export::{run_export, ExportArgs};
use sim_fleet::fleet_run::{run_fleet, RunArgs};
use sim_fleet::live_run::{run_live, LiveRunArgs};
use sim_fleet::montecarlo::{run_montecarlo, MontecarloArgs};
use sim_fleet::paired::{run_paired, PairedArgs};
use sim_fleet::simulate::{run_simulate, SimulateArgs};

/// Fleet tools of the distributed multi-robot VIO system.
#[derive(Parser, Debug)]
#[command(name = "sim-fleet", version, about)]
struct Cli {
    #[command(subcommand)]
    command: Command,
}

#[derive(Subcommand, Debug)]
enum Command {
    /// Simulate every robot of a scenario: IMU and feature measurements (MCAP),
    /// ground truth (TUM) and a run summary.
    Simulate(SimulateArgs),
    /// Evaluate an estimate against ground truth: ATE, RPE, NEES and plots.
    Eval(EvalArgs),
    /// Run every robot of a scenario standalone over many seeds and estimator
    /// variants, in parallel, and aggregate the metrics (means, spreads, divergences).
    Montecarlo(MontecarloArgs),
    /// Compare two variants of Monte-Carlo studies seed by seed: means, the
    /// mean difference and the ratio of the means with 95 % intervals.
    Paired(PairedArgs),
    /// Launch one agent process per robot (Zenoh or iceoryx2; threads for
    /// inproc), supervise them and collect their outputs into DIR/summary.json.
    Run(RunArgs),
    /// Plot several runs of one fleet side by side: trajectories against the
    /// truth, position errors with ±3σ.
    Compare(CompareArgs),
    /// Convert a sequence in the EuRoC ASL layout (EuRoC MAV, TUM-VI) to an
    /// MCAP file: IMU, images and ground truth, on the fleet clock.
    ConvertEuroc(ConvertArgs),
    /// Write one robot of a scenario as a sequence in the EuRoC ASL layout, with
    /// rendered images, its IMU and its ground truth: a moving sequence with a
    /// known truth for `agent dataset`, `agent publish-euroc` and other VIO systems.
    ExportEuroc(ExportArgs),
    /// A fleet on live sensors, on this machine: each robot rendered as a
    /// EuRoC sequence, published over Zenoh as ROS 2 topics and run by an
    /// agent with `input.source: live`; scored against the truth.
    LiveRun(LiveRunArgs),
    /// NEES averaged over runs at each epoch against the two-sided 95 % band
    /// of a consistent filter: orientation, position, tilt and yaw.
    Anees(AneesArgs),
}

fn main() -> std::process::ExitCode {
    common::exit_report::exit_code(run_main())
}

fn run_main() -> Result<()> {
    let cli = Cli::parse();
    // Monte-Carlo studies run whole fleets in this process: their agents' peer
    // events would drown the table, so agents log warnings only there.
    let default_filter = match cli.command {
        Command::Montecarlo(_) => "info,agent=warn",
        _ => "info",
    };
    tracing_subscriber::fmt()
        .with_env_filter(
            tracing_subscriber::EnvFilter::try_from_default_env()
                .unwrap_or_else(|_| tracing_subscriber::EnvFilter::new(default_filter)),
        )
        .with_writer(std::io::stderr)
        .with_ansi(std::io::IsTerminal::is_terminal(&std::io::stderr()))
        .init();
    match cli.command {
        Command::Simulate(args) => run_simulate(&args),
        Command::Eval(args) => run_eval(&args),
        Command::Montecarlo(args) => run_montecarlo(&args),
        Command::Paired(args) => run_paired(&args),
        Command::Run(args) => run_fleet(&args),
        Command::Compare(args) => run_compare(&args),
        Command::ConvertEuroc(args) => run_convert(&args),
        Command::ExportEuroc(args) => run_export(&args),
        Command::LiveRun(args) => run_live(&args),
        Command::Anees(args) => run_anees(&args),
    }
}
