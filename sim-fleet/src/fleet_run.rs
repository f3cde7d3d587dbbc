//! `sim-fleet run`: one agent **process** per robot (Zenoh or iceoryx2; threads of
//! this process for the in-process transport), supervised, with progress, and
//! their outputs collected into `DIR/summary.json`.
//!
//! Layout of `DIR`: `scenario.yaml` (the scenario as run, with derived robots),
//! `robot<i>/config.yaml` (each agent's configuration: a user can start the same
//! agent by hand with `agent --config`), `robot<i>/agent.log` (its log), the
//! agent's outputs in `robot<i>/`, and `summary.json`.

use agent::config::{
    AgentConfig, ClockConfig, ClockMode, EstimatorSection, FaultsConfig, HistoryConfig,
    InputConfig, InputSource, PublishConfig, TransportSection,
};
use agent::history_retention::Retention;
use agent::node::{run_node, NodeReport, RobotSetup};
use agent::runner::{write_run_outputs, Variant};
use agent::transport::fleet_certs::{issue, write_zenoh_configs, Member, Request, SecureLink};
use agent::transport::zenoh_acl::RobotCertificates;
use agent::transport::{InprocHub, TransportKind, ZenohSettings};
use anyhow::{bail, Context, Result};
use common::summary::{fill_peer_windows_published, MetricSet, RobotSummary, RunSummary};
use indicatif::{ProgressBar, ProgressStyle};
use simulator::scenario::RobotSpec;
use simulator::Scenario;
use std::collections::BTreeMap;
use std::io::{BufRead, BufReader};
use std::path::{Path, PathBuf};
use std::process::{Child, Command, Stdio};
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

/// Arguments of `sim-fleet run`.
#[derive(clap::Args, Debug, Clone)]
pub struct RunArgs {
    /// Scenario file (YAML).
    pub scenario: PathBuf,
    /// Number of robots; beyond the scenario's list, more are derived by flying
    /// the scenario's trajectories again, each copy starting later (see
    /// `--derived-delay-s`).
    #[arg(long)]
    pub robots: Option<usize>,
    /// Transport between the agents.
    #[arg(long, default_value = "zenoh", value_parser = ["zenoh", "iceoryx2", "inproc"])]
    pub transport: String,
    /// Lockstep on the fleet clock (the default): deterministic, bit-identical
    /// across transports.
    #[arg(long, conflicts_with = "realtime")]
    pub lockstep: bool,
    /// Real time, paced to the wall clock times RATE (1 = real time).
    #[arg(long, value_name = "RATE")]
    pub realtime: Option<f64>,
    /// Seed (default: the scenario's).
    #[arg(long)]
    pub seed: Option<u64>,
    /// Estimator variant: indp, indp-slam, dc-cmsckf, dc-cmsckf-cslam,
    /// dc-full-window, dc-full-history (the agents), ce-cmsckf, ce-cmsckf-cslam
    /// (the centralized estimator, in this process).
    #[arg(long, default_value = "dc-full-history")]
    pub variant: String,
    /// Output folder.
    #[arg(long, default_value = "out/fleet")]
    pub out: PathBuf,
    /// Fleet id (default: `fleet-<process id>`, so concurrent runs never mix).
    #[arg(long)]
    pub fleet_id: Option<String>,
    /// Zenoh configuration: a built-in name (loopback, lan, explicit-peers, tls, quic)
    /// or a json5 file. With `loopback`, each agent gets its own 127.0.0.1 port
    /// and connects to all the others.
    #[arg(long, default_value = "loopback")]
    pub zenoh_config: String,
    /// Zenoh over mutual TLS on loopback, robot ids bound to the certificates
    /// (`robot_certificates`): a CA and a certificate per robot are made in
    /// `OUT/tls/` (as `agent certs` makes them) and each agent gets the built-in `tls`
    /// configuration with its own files. Zenoh 1.10.2's TLS link loses messages under
    /// load (eclipse-zenoh/zenoh#2557; every lockstep run measured lost some): prefer
    /// `--quic`.
    #[arg(long, conflicts_with = "zenoh_config")]
    pub tls: bool,
    /// As `--tls`, over QUIC (UDP) with the built-in `quic` configuration: the same
    /// certificates and binding, without the TLS link's message loss under load.
    #[arg(long, conflicts_with_all = ["zenoh_config", "tls"])]
    pub quic: bool,
    /// Start of each derived copy relative to the previous copy, s.
    #[arg(long, default_value_t = 3.0)]
    pub derived_delay_s: f64,
    /// The agent binary (default: `agent` next to this program).
    #[arg(long)]
    pub agent_bin: Option<PathBuf>,
    /// Only write the scenario and the agents' configurations, and print the
    /// commands that would run them.
    #[arg(long)]
    pub dry_run: bool,
    /// Keep each agent's histories on disk in `DIR/robot<i>` (read back when
    /// an agent starts, so a run after this one, or an agent restarted, starts
    /// with what it held).
    #[arg(long, value_name = "DIR")]
    pub history_store: Option<PathBuf>,
    /// What the agents keep of their peers.
    #[command(flatten)]
    pub history: HistoryArgs,
}

/// The agents' history settings a run may override (`history:` of an agent's
/// configuration).
#[derive(clap::Args, Debug, Clone, Copy, Default)]
pub struct HistoryArgs {
    /// Memory bound of each agent's history of one peer, MiB (default: the
    /// agent's, 64).
    #[arg(long, value_name = "MIB")]
    pub history_mib_per_peer: Option<f64>,
    /// Which keyframe windows a full history drops first: `informed` (the
    /// agent's default: the least certain view of a place seen more than once,
    /// then the least certain window) or `oldest`.
    #[arg(long, value_name = "POLICY")]
    pub history_retention: Option<Retention>,
    /// Switch history catch-up off: agents never ask again for the keyframe
    /// windows a late start, an outage or lost messages kept from them.
    #[arg(long)]
    pub no_catch_up: bool,
    /// A link outage over fleet seconds FROM:TO (e.g. `20:60`): every message
    /// sent in it is dropped on arrival; in lockstep runs the heartbeats pass,
    /// so the fleet clock runs on.
    #[arg(long, value_name = "FROM:TO", value_parser = parse_outage)]
    pub link_outage: Option<[f64; 2]>,
    /// A lossy link: the fraction in [0, 1] of the peers' messages each agent
    /// loses on arrival, drawn from the run's seed (in lockstep runs the
    /// heartbeats pass, so the fleet clock runs on).
    #[arg(long, value_name = "FRACTION", value_parser = parse_fraction)]
    pub link_loss: Option<f64>,
}

/// A number in `[0, 1]`.
fn parse_fraction(s: &str) -> std::result::Result<f64, String> {
    let v: f64 = s.trim().parse().map_err(|e| format!("`{s}`: {e}"))?;
    if !(0.0..=1.0).contains(&v) {
        return Err(format!("`{s}`: expected a fraction in [0, 1]"));
    }
    Ok(v)
}

/// `FROM:TO` in seconds, `FROM < TO`.
fn parse_outage(s: &str) -> std::result::Result<[f64; 2], String> {
    let (a, b) = s
        .split_once(':')
        .ok_or_else(|| format!("`{s}`: expected FROM:TO in seconds, e.g. 20:60"))?;
    let num = |v: &str| {
        v.trim()
            .parse::<f64>()
            .map_err(|e| format!("`{v}` in `{s}`: {e}"))
    };
    let (from, to) = (num(a)?, num(b)?);
    if !(from.is_finite() && to.is_finite() && from < to) {
        return Err(format!("`{s}`: FROM must be below TO, both finite"));
    }
    Ok([from, to])
}

impl HistoryArgs {
    /// `base` with these overrides.
    pub fn apply(&self, base: HistoryConfig) -> HistoryConfig {
        HistoryConfig {
            max_mib_per_peer: self.history_mib_per_peer.unwrap_or(base.max_mib_per_peer),
            retention: self.history_retention.unwrap_or(base.retention),
            catch_up: base.catch_up && !self.no_catch_up,
            ..base
        }
    }

    /// The faults these flags inject (the agents mix the run's seed into the
    /// loss draws, so each Monte-Carlo run loses different messages).
    pub fn faults(&self) -> FaultsConfig {
        FaultsConfig {
            outage_fleet_s: self.link_outage,
            loss_fraction: self.link_loss.unwrap_or(0.0),
            loss_seed: 0,
        }
    }
}

/// The scenario with `n` robots: the first `n` of the list, then copies of
/// the list flown again, copy `c` starting `c * delay_s` later. Trajectory paths
/// become absolute so the file works from any folder.
pub fn derive_scenario(base: &Scenario, n: usize, delay_s: f64) -> Scenario {
    let mut sc = base.clone();
    let list: Vec<RobotSpec> = (0..base.robots.len())
        .filter_map(|i| {
            let mut r = base.robots.get(i)?.clone();
            r.trajectory = base.trajectory_path(i)?;
            r.trajectory = std::fs::canonicalize(&r.trajectory).unwrap_or(r.trajectory);
            r.name = Some(base.robot_name(i));
            Some(r)
        })
        .collect();
    sc.robots = (0..n)
        .filter_map(|i| {
            let copy = i / list.len().max(1);
            let mut r = list.get(i % list.len().max(1))?.clone();
            if copy > 0 {
                r.start_time_s += copy as f64 * delay_s;
                r.name = r.name.map(|name| format!("{name}+{copy}"));
            }
            Some(r)
        })
        .collect();
    sc
}

/// Free TCP ports on 127.0.0.1, outside the range outgoing connections take.
fn free_ports(n: usize) -> Result<Vec<u16>> {
    common::loopback_ports::free_loopback_ports(n).context("finding free loopback ports")
}

/// Certificates for robots `0..n` on loopback in `dir` (made anew: a previous run's
/// are removed), each robot's copy of the built-in configuration of `link` pointing
/// at its files, and the binding of the ids to the certificates.
fn fleet_tls(dir: &Path, n: usize, link: SecureLink) -> Result<(Vec<PathBuf>, RobotCertificates)> {
    if dir.exists() {
        std::fs::remove_dir_all(dir).with_context(|| format!("removing {}", dir.display()))?;
    }
    let certs = RobotCertificates {
        robots: (0..n as u32).collect(),
        common_name: "robot{id}".to_owned(),
        trusted_routers: Vec::new(),
    };
    let request = Request {
        ca_name: "fleet-ca".to_owned(),
        ca_days: 30,
        days: 30,
        members: (certs.robots.iter())
            .map(|&id| Member {
                name: certs.name_of(id),
                hosts: vec!["127.0.0.1".to_owned()],
            })
            .collect(),
    };
    issue(dir, &request)?;
    let names: Vec<String> = request.members.into_iter().map(|m| m.name).collect();
    let configs = write_zenoh_configs(dir, &names, link)?;
    Ok((configs, certs))
}

/// Every agent's configuration for a run.
pub fn agent_configs(
    args: &RunArgs,
    scenario_path: &Path,
    n: usize,
    out: &Path,
) -> Result<Vec<AgentConfig>> {
    let kind = match args.transport.as_str() {
        "zenoh" => TransportKind::Zenoh,
        "iceoryx2" => TransportKind::Iceoryx2,
        _ => TransportKind::Inproc,
    };
    let fleet_id = args
        .fleet_id
        .clone()
        .unwrap_or_else(|| format!("fleet-{}", std::process::id()));
    let ports = if kind == TransportKind::Zenoh && args.zenoh_config == "loopback" {
        free_ports(n)?
    } else {
        Vec::new()
    };
    let link = match (args.tls, args.quic) {
        (true, _) => Some(SecureLink::Tls),
        (_, true) => Some(SecureLink::Quic),
        _ => None,
    };
    let tls = match (link, kind) {
        (None, _) => None,
        (Some(link), TransportKind::Zenoh) => Some(fleet_tls(&out.join("tls"), n, link)?),
        (Some(link), _) => bail!("--{} needs --transport zenoh", link.scheme()),
    };
    let scheme = link.map_or("tcp", SecureLink::scheme);
    let clock = |me: u32| ClockConfig {
        mode: if args.realtime.is_some() {
            ClockMode::Realtime
        } else {
            ClockMode::Lockstep
        },
        realtime_rate: args.realtime.unwrap_or(1.0),
        peers: (0..n as u32).filter(|p| *p != me).collect(),
        ..ClockConfig::default()
    };
    // Absolute: the agents read their configurations from another folder.
    let store = match &args.history_store {
        Some(d) if d.is_relative() => Some(std::env::current_dir()?.join(d)),
        other => other.clone(),
    };
    let configs: Vec<AgentConfig> = (0..n)
        .map(|i| {
            let me = i as u32;
            let zenoh = ZenohSettings {
                config: match &tls {
                    Some((configs, _)) => configs[i].display().to_string(),
                    None => args.zenoh_config.clone(),
                },
                listen: ports
                    .get(i)
                    .map(|p| vec![format!("{scheme}/127.0.0.1:{p}")])
                    .unwrap_or_default(),
                connect: ports
                    .iter()
                    .enumerate()
                    .filter(|(j, _)| *j != i)
                    .map(|(_, p)| format!("{scheme}/127.0.0.1:{p}"))
                    .collect(),
                robot_certificates: tls.as_ref().map(|(_, certs)| certs.clone()),
            };
            AgentConfig {
                robot_id: me,
                fleet_id: fleet_id.clone(),
                output_dir: out.join(format!("robot{i}")),
                transport: TransportSection {
                    kind,
                    zenoh,
                    iceoryx2: Default::default(),
                },
                input: InputConfig {
                    source: InputSource::Simulator,
                    scenario: scenario_path.to_path_buf(),
                    robot_index: Some(i),
                    seed: args.seed,
                    mcap: None,
                    live: None,
                },
                estimator: EstimatorSection {
                    variant: args.variant.clone(),
                    ..EstimatorSection::default()
                },
                clock: clock(me),
                publish: PublishConfig::default(),
                history: {
                    // Room for every robot of the fleet, however large.
                    let h = args.history.apply(HistoryConfig::default());
                    HistoryConfig {
                        max_peers: h.max_peers.max(n),
                        store_dir: store.as_ref().map(|d| d.join(format!("robot{i}"))),
                        ..h
                    }
                },
                mcap_log: true,
                status_period_s: agent::config::DEFAULT_STATUS_PERIOD_S,
                images: Default::default(),
                faults: args.history.faults(),
            }
        })
        .collect();
    // The checks `agent --config` makes: in-process runs start no agent binary,
    // and a bad flag (a negative history bound) must not run unnoticed.
    for (i, c) in configs.iter().enumerate() {
        c.validate()
            .map_err(|e| anyhow::anyhow!("agent {i}'s configuration: {e}"))?;
    }
    Ok(configs)
}

fn agent_binary(args: &RunArgs) -> Result<PathBuf> {
    if let Some(b) = &args.agent_bin {
        return Ok(b.clone());
    }
    let me = std::env::current_exe().context("locating this program")?;
    let dir = me.parent().context("this program has no folder")?;
    let candidates = [dir.join("agent"), dir.join("..").join("agent")];
    candidates
        .iter()
        .find(|p| p.is_file())
        .cloned()
        .with_context(|| {
            format!(
                "no `agent` binary next to {} (build it: cargo build --release -p agent, or pass --agent-bin)",
                me.display()
            )
        })
}

/// Runs `sim-fleet run`.
pub fn run_fleet(args: &RunArgs) -> Result<()> {
    if let Some(r) = args.realtime {
        if !(r.is_finite() && r > 0.0) {
            bail!("--realtime must be a rate > 0 (got {r})");
        }
    }
    let base = Scenario::load(&args.scenario)?;
    let n = args.robots.unwrap_or(base.robots.len());
    if n == 0 {
        bail!("--robots must be at least 1");
    }
    let scenario = derive_scenario(&base, n, args.derived_delay_s);
    std::fs::create_dir_all(&args.out)
        .with_context(|| format!("creating {}", args.out.display()))?;
    let out = std::fs::canonicalize(&args.out)?;
    let scenario_path = out.join("scenario.yaml");
    std::fs::write(&scenario_path, serde_yaml::to_string(&scenario)?)
        .with_context(|| format!("writing {}", scenario_path.display()))?;
    let configs = agent_configs(args, &scenario_path, n, &out)?;
    let mut config_paths = Vec::new();
    for cfg in &configs {
        std::fs::create_dir_all(&cfg.output_dir)?;
        let p = cfg.output_dir.join("config.yaml");
        std::fs::write(&p, serde_yaml::to_string(cfg)?)
            .with_context(|| format!("writing {}", p.display()))?;
        config_paths.push(p);
    }
    let wall = Instant::now();
    if args.dry_run {
        let bin = agent_binary(args).unwrap_or_else(|_| PathBuf::from("agent"));
        for p in &config_paths {
            println!("{} --config {}", bin.display(), p.display());
        }
        return Ok(());
    }
    let variant: Variant = args.variant.parse()?;
    if variant.centralized() {
        return run_centralized(&scenario, args, variant, &out, wall);
    }
    let stop = Arc::new(AtomicBool::new(false));
    for sig in [signal_hook::consts::SIGINT, signal_hook::consts::SIGTERM] {
        signal_hook::flag::register_conditional_shutdown(sig, 1, Arc::clone(&stop))?;
        signal_hook::flag::register(sig, Arc::clone(&stop))?;
    }
    let bar = ProgressBar::new(0);
    if let Ok(style) = ProgressStyle::with_template(
        "{spinner} [{elapsed_precise}] {bar:40} {pos}/{len} ticks  {msg}",
    ) {
        bar.set_style(style);
    }
    let failures = if args.transport == "inproc" {
        run_threads(&configs, &stop, &bar)?
    } else {
        run_processes(args, &configs, &config_paths, &stop, &bar)?
    };
    bar.finish_and_clear();
    let summary = collect(&scenario, args, &configs, wall.elapsed().as_secs_f64());
    summary.write_json(out.join("summary.json"))?;
    print_summary(&summary, &out, scenario.sensors.camera.rate_hz);
    if !failures.is_empty() {
        bail!("agents failed: {}", failures.join("; "));
    }
    Ok(())
}

/// A centralized variant: one joint estimator for the whole fleet in this
/// process (no agents, no transport); each robot's outputs in `DIR/robot<i>/`.
fn run_centralized(
    scenario: &Scenario,
    args: &RunArgs,
    variant: Variant,
    out: &Path,
    wall: Instant,
) -> Result<()> {
    let seed = args.seed.unwrap_or(scenario.seed);
    let fleet = simulator::Fleet::build(scenario, seed)?;
    let runs = agent::central::run::run_central(&fleet, variant)?;
    let mut robots = Vec::with_capacity(runs.len());
    let mut sim_s: f64 = 0.0;
    for (i, run) in runs.iter().enumerate() {
        write_run_outputs(run, &out.join(format!("robot{i}")))?;
        if let (Some(a), Some(b)) = (run.estimate.first(), run.estimate.last()) {
            sim_s = sim_s.max(b.t - a.t);
        }
        robots.push(RobotSummary {
            id: i as u32,
            trajectory: scenario.robot_name(i),
            metrics: run.metrics(),
        });
    }
    let sets: Vec<MetricSet> = robots.iter().map(|r| r.metrics.clone()).collect();
    let summary = RunSummary {
        scenario: scenario.name.clone(),
        variant: Some(variant.name().to_string()),
        seed,
        transport: None,
        wall_s: Some(wall.elapsed().as_secs_f64()),
        sim_s: Some(sim_s),
        mean: MetricSet::mean_of(&sets),
        robots,
    };
    summary.write_json(out.join("summary.json"))?;
    print_summary(&summary, out, scenario.sensors.camera.rate_hz);
    Ok(())
}

/// Progress of every agent, for the bar.
#[derive(Default)]
struct Board {
    ticks: BTreeMap<usize, (u64, u64)>,
    done: usize,
    max_lag_s: f64,
}

impl Board {
    fn show(&self, bar: &ProgressBar, n: usize) {
        let (pos, len) = self
            .ticks
            .values()
            .fold((0, 0), |(p, l), (a, b)| (p + a, l + b));
        bar.set_length(len);
        bar.set_position(pos);
        bar.set_message(format!(
            "{}/{} agents done, max lag {:.2} s",
            self.done, n, self.max_lag_s
        ));
    }
}

fn run_processes(
    args: &RunArgs,
    configs: &[AgentConfig],
    paths: &[PathBuf],
    stop: &AtomicBool,
    bar: &ProgressBar,
) -> Result<Vec<String>> {
    let bin = agent_binary(args)?;
    let board = Arc::new(Mutex::new(Board::default()));
    let n = configs.len();
    let mut children: Vec<(usize, Child)> = Vec::new();
    let mut readers = Vec::new();
    for (i, (cfg, path)) in configs.iter().zip(paths).enumerate() {
        let log = std::fs::File::create(cfg.output_dir.join("agent.log"))?;
        let mut child = Command::new(&bin)
            .arg("--config")
            .arg(path)
            .arg("--progress")
            .stdout(Stdio::piped())
            .stderr(Stdio::from(log))
            .spawn()
            .with_context(|| format!("starting {}", bin.display()))?;
        if let Some(stdout) = child.stdout.take() {
            let board = Arc::clone(&board);
            readers.push(std::thread::spawn(move || {
                for line in BufReader::new(stdout).lines().map_while(Result::ok) {
                    let parts: Vec<&str> = line.split_whitespace().collect();
                    if let ["progress", tick, total, _frames, lag] = parts.as_slice() {
                        if let (Ok(t), Ok(l), Ok(lag)) =
                            (tick.parse(), total.parse(), lag.parse::<f64>())
                        {
                            if let Ok(mut b) = board.lock() {
                                b.ticks.insert(i, (t, l));
                                b.max_lag_s = b.max_lag_s.max(lag);
                            }
                        }
                    }
                }
            }));
        }
        children.push((i, child));
    }
    let mut failures = Vec::new();
    let mut signalled = false;
    while !children.is_empty() {
        if stop.load(Ordering::Relaxed) && !signalled {
            signalled = true;
            for (_, c) in &children {
                // SIGTERM, so that agents flush their outputs.
                let _ = Command::new("kill")
                    .args(["-TERM", &c.id().to_string()])
                    .status();
            }
        }
        let mut still = Vec::new();
        for (i, mut c) in children {
            match c.try_wait() {
                Ok(Some(status)) => {
                    if !status.success() {
                        failures.push(format!(
                            "robot {i} exited with {status} (see {})",
                            configs[i].output_dir.join("agent.log").display()
                        ));
                    }
                    if let Ok(mut b) = board.lock() {
                        b.done += 1;
                    }
                }
                Ok(None) => still.push((i, c)),
                Err(e) => failures.push(format!("robot {i}: {e}")),
            }
        }
        children = still;
        if let Ok(b) = board.lock() {
            b.show(bar, n);
        }
        std::thread::sleep(Duration::from_millis(100));
    }
    for r in readers {
        let _ = r.join();
    }
    Ok(failures)
}

fn run_threads(
    configs: &[AgentConfig],
    stop: &Arc<AtomicBool>,
    bar: &ProgressBar,
) -> Result<Vec<String>> {
    let results = run_inproc(configs, stop, Some(bar))?;
    Ok(results
        .into_iter()
        .enumerate()
        .filter_map(|(i, r)| r.err().map(|e| format!("robot {i}: {e}")))
        .collect())
}

/// Runs the agents of `configs` as threads of this process over one in-process
/// hub, writing each agent's outputs; returns each agent's report, or why it
/// failed. With `bar`, shows their progress.
pub fn run_inproc(
    configs: &[AgentConfig],
    stop: &Arc<AtomicBool>,
    bar: Option<&ProgressBar>,
) -> Result<Vec<std::result::Result<NodeReport, String>>> {
    let hub = InprocHub::new();
    let board = Arc::new(Mutex::new(Board::default()));
    let n = configs.len();
    let mut handles = Vec::new();
    for (i, cfg) in configs.iter().enumerate() {
        let cfg = cfg.clone();
        let transport = agent::transport::open(&cfg.transport_settings(), Some(&hub))?;
        let stop = Arc::clone(stop);
        let board = Arc::clone(&board);
        handles.push(std::thread::spawn(move || -> Result<NodeReport> {
            let setup = RobotSetup::load(&cfg)?;
            let report = run_node(&cfg, &setup, transport, &stop, |p| {
                if let Ok(mut b) = board.lock() {
                    b.ticks.insert(i, (p.tick, p.ticks_total));
                    b.max_lag_s = b.max_lag_s.max(p.lag_s);
                }
            })?;
            agent::agent_output::write_outputs(&report, cfg.robot_id, "inproc", &cfg.output_dir)?;
            if let Ok(mut b) = board.lock() {
                b.done += 1;
            }
            Ok(report)
        }));
    }
    while handles.iter().any(|h| !h.is_finished()) {
        if let (Some(bar), Ok(b)) = (bar, board.lock()) {
            b.show(bar, n);
        }
        std::thread::sleep(Duration::from_millis(20));
    }
    Ok(handles
        .into_iter()
        .map(|h| match h.join() {
            Ok(Ok(r)) => Ok(r),
            Ok(Err(e)) => Err(format!("{e:#}")),
            Err(_) => Err("panicked".to_string()),
        })
        .collect())
}

/// Reads every agent's `summary.json` into the run's summary.
fn collect(
    scenario: &Scenario,
    args: &RunArgs,
    configs: &[AgentConfig],
    wall_s: f64,
) -> RunSummary {
    let mut robots = Vec::new();
    let mut sim_s: Option<f64> = None;
    let mut seed = args.seed.unwrap_or(scenario.seed);
    for (i, cfg) in configs.iter().enumerate() {
        match RunSummary::read_json(cfg.output_dir.join("summary.json")) {
            Ok(s) => {
                seed = s.seed;
                sim_s = Some(sim_s.unwrap_or(0.0).max(s.sim_s.unwrap_or(0.0)));
                robots.extend(s.robots);
            }
            Err(e) => {
                tracing::warn!("robot {i}: no summary ({e})");
                robots.push(RobotSummary {
                    id: i as u32,
                    trajectory: scenario.robot_name(i),
                    metrics: MetricSet::default(),
                });
            }
        }
    }
    fill_peer_windows_published(robots.iter_mut().map(|r| &mut r.metrics));
    let sets: Vec<MetricSet> = robots.iter().map(|r| r.metrics.clone()).collect();
    RunSummary {
        scenario: scenario.name.clone(),
        variant: Some(args.variant.clone()),
        seed,
        transport: Some(args.transport.clone()),
        wall_s: Some(wall_s),
        sim_s,
        mean: MetricSet::mean_of(&sets),
        robots,
    }
}

/// The peers' keyframe windows a robot held whole at the end, of those its
/// peers published (`whole/published`), or `-` when unknown.
pub fn peer_windows(m: &MetricSet) -> String {
    match (m.peer_windows_whole, m.peer_windows_published) {
        (Some(w), Some(p)) => format!("{w}/{p}"),
        _ => "-".into(),
    }
}

fn print_summary(s: &RunSummary, out: &Path, camera_rate_hz: f64) {
    print!("{}", summary_table(s, camera_rate_hz));
    println!("summary: {}", out.join("summary.json").display());
}

/// The run's table: a line of totals, a header, one line per robot and, when
/// known, the share of a core an agent needs in real time.
fn summary_table(s: &RunSummary, camera_rate_hz: f64) -> String {
    use std::fmt::Write as _;
    let f = |v: Option<f64>, d: usize| v.map_or("-".to_string(), |v| format!("{v:.d$}"));
    let mut t = String::new();
    // Writing to a String cannot fail.
    let _ = writeln!(
        t,
        "{} robots over {}, {} s of fleet time in {} s",
        s.robots.len(),
        s.transport.as_deref().unwrap_or("?"),
        f(s.sim_s, 1),
        f(s.wall_s, 1)
    );
    // The trajectory column fits the longest name (derived robots add `+k`).
    let w = s
        .robots
        .iter()
        .map(|r| r.trajectory.chars().count())
        .fold(21, usize::max);
    let _ = writeln!(
        t,
        "robot  {:<w$} ATE deg  ATE m   aligned m  NEES ori  NEES pos  KB/s sent  msgs in  dropped  peer windows  CPU %",
        "trajectory"
    );
    // CPU time per second of the robot's own data (its frames at the camera
    // rate): the share of a core the agent needs to keep up in real time.
    let data_s = |m: &MetricSet| m.frames.map(|n| n as f64 / camera_rate_hz);
    let share = |m: &MetricSet| {
        m.cpu_s
            .zip(data_s(m))
            .and_then(|(c, t)| (t > 0.0).then(|| c / t))
    };
    for r in &s.robots {
        let m = &r.metrics;
        let _ = writeln!(
            t,
            "{:<6} {:<w$} {:>7}  {:>6}  {:>9}  {:>8}  {:>8}  {:>9}  {:>7}  {:>7}  {:>12}  {:>5}",
            r.id,
            r.trajectory,
            f(m.ate_ori_deg, 3),
            f(m.ate_pos_m, 3),
            f(m.ate_posyaw_pos_m, 3),
            f(m.nees_ori, 2),
            f(m.nees_pos, 2),
            f(m.bytes_per_s_sent.map(|b| b / 1000.0), 1),
            m.messages_received.map_or("-".into(), |v| v.to_string()),
            m.messages_dropped.map_or("-".into(), |v| v.to_string()),
            peer_windows(m),
            f(share(m).map(|x| 100.0 * x), 1),
        );
    }
    // Over the fleet: all CPU time over all data time.
    let (cpu, data) = s.robots.iter().fold((0.0, 0.0), |(c, d), r| {
        match (r.metrics.cpu_s, data_s(&r.metrics)) {
            (Some(x), Some(y)) => (c + x, d + y),
            _ => (c, d),
        }
    });
    if let Some(x) = (data > 0.0 && cpu > 0.0).then(|| cpu / data) {
        let _ = writeln!(
            t,
            "real time needs {:.1} % of a core per agent: {:.0} agents per core (simulated sensors included)",
            100.0 * x,
            1.0 / x
        );
    }
    // Robots in their own frames: how each found its peers'.
    for r in &s.robots {
        let m = &r.metrics;
        if let Some(n) = m.peer_frames_aligned {
            let _ = writeln!(
                t,
                "robot {}: {n} peer frames aligned, the first {} s after its start; {} deg / {} m off (NEES {})",
                r.id,
                f(m.first_peer_frame_s, 1),
                f(m.peer_frame_yaw_err_deg, 3),
                f(m.peer_frame_pos_err_m, 3),
                f(m.peer_frame_nees, 2),
            );
        }
    }
    t
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn derived_robots_repeat_the_list_later() {
        let base: Scenario = serde_yaml::from_str(
            "name: t\nrobots:\n  - trajectory: /a.txt\n  - trajectory: /b.txt\n    start_time_s: 1.0\n",
        )
        .unwrap();
        let sc = derive_scenario(&base, 5, 3.0);
        assert_eq!(sc.robots.len(), 5);
        let starts: Vec<f64> = sc.robots.iter().map(|r| r.start_time_s).collect();
        assert_eq!(starts, vec![0.0, 1.0, 3.0, 4.0, 6.0]);
        assert_eq!(sc.robots[4].name.as_deref(), Some("a+2"));
        let two = derive_scenario(&base, 1, 3.0);
        assert_eq!(two.robots.len(), 1);
    }

    #[test]
    fn the_summary_columns_line_up_whatever_the_trajectory_names() {
        let robot = |id: u32, name: &str| common::summary::RobotSummary {
            id,
            trajectory: name.into(),
            metrics: MetricSet {
                ate_ori_deg: Some(0.25),
                ate_pos_m: Some(0.03),
                ..MetricSet::default()
            },
        };
        for names in [
            vec!["V1_01_easy", "V1_02_medium"],
            vec!["tum_corridor1_512_16_okvis", "tum_corridor1_512_16_okvis+1"],
        ] {
            let s = RunSummary {
                robots: names
                    .iter()
                    .enumerate()
                    .map(|(i, n)| robot(i as u32, n))
                    .collect(),
                ..RunSummary::default()
            };
            let table = summary_table(&s, 10.0);
            let lines: Vec<&str> = table.lines().skip(1).collect();
            assert_eq!(lines.len(), 1 + names.len(), "{table}");
            // The ATE column ends where the header's does on every robot's line,
            // and every line is as long as the header.
            let end_of = |line: &str, key: &str| line.find(key).map(|i| i + key.len());
            let deg_end = end_of(lines[0], "ATE deg");
            for line in &lines[1..] {
                assert_eq!(end_of(line, "0.250"), deg_end, "{table}");
                assert_eq!(line.chars().count(), lines[0].chars().count(), "{table}");
            }
        }
    }

    #[test]
    fn robots_that_aligned_their_peers_frames_get_a_line_each() {
        let m = MetricSet {
            peer_frames_aligned: Some(2),
            first_peer_frame_s: Some(2.44),
            peer_frame_yaw_err_deg: Some(0.3),
            peer_frame_pos_err_m: Some(0.061),
            peer_frame_nees: Some(3.1),
            ..MetricSet::default()
        };
        let s = RunSummary {
            robots: vec![common::summary::RobotSummary {
                id: 1,
                trajectory: "V1_02_medium".into(),
                metrics: m,
            }],
            ..RunSummary::default()
        };
        let table = summary_table(&s, 10.0);
        assert!(
            table.contains(
                "robot 1: 2 peer frames aligned, the first 2.4 s after its start; 0.300 deg / 0.061 m off (NEES 3.10)"
            ),
            "{table}"
        );
    }
}
