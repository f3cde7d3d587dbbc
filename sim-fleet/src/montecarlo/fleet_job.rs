//! One Monte-Carlo run of a cooperative variant: the whole fleet of a seed at
//! once. Distributed variants run their agents as threads over the in-process
//! transport in lockstep (the same code as `sim-fleet run --transport inproc`,
//! bit-identical to Zenoh and iceoryx2); each robot's outputs land in
//! `DIR/robot<i>/`.

use crate::fleet_run::{agent_configs, run_inproc, HistoryArgs, RunArgs};
use agent::frontend::FrontendOptions;
use agent::runner::Variant;
use common::summary::{fill_peer_windows_published, MetricSet};
use simulator::Scenario;
use std::path::Path;
use std::sync::atomic::AtomicBool;
use std::sync::Arc;

/// Runs `variant` on the fleet of `seed` (the agents' histories as `history`
/// says, their image frontends with `frontend` when the scenario renders);
/// each robot's metrics and the simulated seconds, or why it failed.
pub fn run(
    scenario_path: &Path,
    scenario: &Scenario,
    seed: u64,
    (variant, history): (Variant, HistoryArgs),
    frontend: &FrontendOptions,
    dir: &Path,
) -> Result<(Vec<(usize, MetricSet)>, f64), String> {
    if variant.centralized() {
        return run_centralized(scenario, seed, variant, dir);
    }
    let args = RunArgs {
        scenario: scenario_path.to_path_buf(),
        robots: None,
        transport: "inproc".into(),
        lockstep: true,
        realtime: None,
        seed: Some(seed),
        variant: variant.name().into(),
        out: dir.to_path_buf(),
        fleet_id: Some(format!("mc-{}-{seed}", variant.name())),
        zenoh_config: "loopback".into(),
        tls: false,
        quic: false,
        derived_delay_s: 3.0,
        agent_bin: None,
        dry_run: false,
        // Each Monte-Carlo run starts with empty histories.
        history_store: None,
        history,
    };
    let n = scenario.robots.len();
    let mut configs = agent_configs(&args, scenario_path, n, dir).map_err(|e| format!("{e:#}"))?;
    for c in &mut configs {
        // Monte-Carlo runs keep the text outputs; the MCAP log and the status
        // lines are for one run.
        c.mcap_log = false;
        c.status_period_s = 0.0;
        c.images.frontend = frontend.clone();
    }
    let stop = Arc::new(AtomicBool::new(false));
    let reports = run_inproc(&configs, &stop, None).map_err(|e| format!("{e:#}"))?;
    let mut robots = Vec::with_capacity(n);
    let mut sim_s: f64 = 0.0;
    for (i, r) in reports.into_iter().enumerate() {
        let report = r.map_err(|e| format!("robot {i}: {e}"))?;
        if let (Some(a), Some(b)) = (report.run.estimate.first(), report.run.estimate.last()) {
            sim_s = sim_s.max(b.t - a.t);
        }
        robots.push((i, agent::agent_output::metrics_of(&report)));
    }
    fill_peer_windows_published(robots.iter_mut().map(|(_, m)| m));
    Ok((robots, sim_s))
}

/// The centralized estimator on the fleet of `seed`, in this thread; each
/// robot's outputs in `DIR/robot<i>/`.
fn run_centralized(
    scenario: &Scenario,
    seed: u64,
    variant: Variant,
    dir: &Path,
) -> Result<(Vec<(usize, MetricSet)>, f64), String> {
    let fleet = simulator::Fleet::build(scenario, seed).map_err(|e| e.to_string())?;
    let runs = agent::central::run::run_central(&fleet, variant).map_err(|e| e.to_string())?;
    let mut robots = Vec::with_capacity(runs.len());
    let mut sim_s: f64 = 0.0;
    for (i, run) in runs.iter().enumerate() {
        agent::runner::write_run_outputs(run, &dir.join(format!("robot{i}")))
            .map_err(|e| format!("robot {i}: {e}"))?;
        if let (Some(a), Some(b)) = (run.estimate.first(), run.estimate.last()) {
            sim_s = sim_s.max(b.t - a.t);
        }
        robots.push((i, run.metrics()));
    }
    Ok((robots, sim_s))
}
