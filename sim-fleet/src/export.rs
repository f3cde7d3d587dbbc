//! `sim-fleet export-euroc`: one robot of a scenario as a sequence in the EuRoC
//! ASL layout, with rendered images ([`simulator::euroc_export`]).

use anyhow::{bail, Context, Result};
use simulator::euroc_export::export_euroc;
use simulator::{Fleet, Scenario};
use std::path::PathBuf;

/// Arguments of `sim-fleet export-euroc`.
#[derive(clap::Args, Debug)]
pub struct ExportArgs {
    /// Scenario file (YAML); its `render:` settings are used, and rendering is
    /// switched on if the scenario leaves it off.
    pub scenario: PathBuf,
    /// Robot index in the scenario.
    #[arg(long, default_value_t = 0)]
    pub robot: usize,
    /// Seed of every random draw (default: the scenario's).
    #[arg(long)]
    pub seed: Option<u64>,
    /// Export only the first this many seconds of the robot's flight.
    #[arg(long)]
    pub duration_s: Option<f64>,
    /// The sequence folder to write (`mav0` is made in it).
    #[arg(long)]
    pub out: PathBuf,
}

/// Writes the sequence; prints what was written.
pub fn run_export(args: &ExportArgs) -> Result<()> {
    let mut scenario = Scenario::load(&args.scenario)
        .with_context(|| format!("loading {}", args.scenario.display()))?;
    scenario.render.enabled = true;
    let seed = args.seed.unwrap_or(scenario.seed);
    let fleet = Fleet::build(&scenario, seed)?;
    let truth = fleet
        .truths
        .get(args.robot)
        .with_context(|| format!("the scenario has no robot {}", args.robot))?;
    let t_end = match args.duration_s {
        Some(d) if d.is_finite() && d > 0.0 => truth.start_time() + d,
        Some(d) => bail!("--duration-s {d}: must be a positive number of seconds"),
        None => f64::INFINITY,
    };
    let origin = format!("sim-fleet export-euroc {}", args.scenario.display());
    let n = export_euroc(&fleet, args.robot, t_end, &args.out, &origin)?;
    println!(
        "{}: {} images, {} IMU samples of robot {} (seed {seed})",
        args.out.join("mav0").display(),
        n.images,
        n.imu,
        args.robot
    );
    Ok(())
}
