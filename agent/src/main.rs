//! `agent`: runs one robot of the fleet.
use agent::agent_log::AgentLog;
use agent::agent_output::{metrics_of, write_outputs};
use agent::config::{AgentConfig, InputSource};
use agent::node::{run_live_node, run_node, LiveSetup, RobotSetup};
use agent::runner::{options_for, run_robot, write_run_outputs, Variant};
use anyhow::{Context, Result};
use clap::{Parser, Subcommand};
use common::summary::{MetricSet, RobotSummary, RunSummary};
use signal_hook::consts::{SIGINT, SIGTERM};
use simulator::{Fleet, Scenario};
use std::path::PathBuf;
use std::sync::atomic::AtomicBool;
use std::sync::Arc;
use std::time::Instant;

/// One robot's agent of the distributed multi-robot VIO fleet.
#[derive(Parser, Debug)]
#[command(name = "agent", version, about, long_about = None)]
struct Cli {
    /// Run as one agent of a fleet, as the configuration file (YAML) says.
    #[arg(long, value_name = "FILE")]
    config: Option<PathBuf>,
    /// Print `progress <tick> <ticks> <frames> <lag_s>` lines on stdout (for the
    /// fleet launcher).
    #[arg(long)]
    progress: bool,
    #[command(subcommand)]
    command: Option<Command>,
}

#[derive(Subcommand, Debug)]
enum Command {
    /// Run one robot of a simulated scenario standalone (no peers) and score it.
    Run(RunArgs),
    /// Run on a real sequence in the EuRoC ASL layout (EuRoC MAV, TUM-VI):
    /// images through the frontend, IMU into the estimator, static start.
    #[cfg(feature = "vision")]
    Dataset(agent::dataset_cli::DatasetArgs),
    /// Run on the robot's live IMU and camera, ROS 2 topics over Zenoh
    /// (`zenoh-bridge-ros2dds`, `rmw_zenoh`): images through the frontend, IMU
    /// into the estimator, static start; ends when the sensors stop.
    #[cfg(feature = "vision")]
    Live(Box<agent::live_cli::LiveArgs>),
    /// Publish a sequence in the EuRoC ASL layout as ROS 2 IMU and image
    /// topics over Zenoh, paced as recorded: live sensors for `agent live`.
    PublishEuroc(PublishEurocArgs),
    /// Robustness probe: join a fleet as another robot and send it malformed
    /// payloads and a message of a foreign fleet (they must be dropped and
    /// counted, and the agents must keep running), and optionally flood it with
    /// valid messages as fast as the transport takes them.
    Probe(ProbeArgs),
    /// Print the Zenoh `access_control` block that binds robot ids to certificate
    /// names (JSON), for a Zenoh router between sites. Agents in peer mode make
    /// their own from `transport: zenoh: robot_certificates:`.
    Acl(AclArgs),
    /// Make the fleet's TLS certificates for the `quic` and `tls` Zenoh configurations: a CA
    /// (reused if the folder has one) and a key and certificate per robot or router.
    Certs(CertsArgs),
    /// Show what history store files hold (`history.store_dir`): format,
    /// mission, fleet, robot, windows and how many are whole, their time span,
    /// size, and any damage. A folder shows each file in it, the ones set
    /// aside as unreadable too.
    Store(StoreArgs),
}

#[derive(clap::Args, Debug)]
struct PublishEurocArgs {
    /// The sequence folder (holding `mav0`, or `mav0` itself).
    #[arg(long)]
    euroc: PathBuf,
    /// The session and the sensors' keys.
    #[command(flatten)]
    zenoh: agent::ros_input::ZenohArgs,
    /// Playback speed (1: as recorded).
    #[arg(long, default_value_t = 1.0)]
    speed: f64,
    /// IMU published before the first image, s (a static start needs a
    /// still window before it).
    #[arg(long, default_value_t = 2.0)]
    imu_lead_s: f64,
    /// Wait this long for a subscriber to both keys, s.
    #[arg(long, default_value_t = 30.0)]
    wait_subscriber_s: f64,
}

#[derive(clap::Args, Debug)]
struct StoreArgs {
    /// History files or store folders.
    #[arg(required = true)]
    paths: Vec<PathBuf>,
    /// Print JSON (one object per file) instead of a table.
    #[arg(long)]
    json: bool,
}

#[derive(clap::Args, Debug)]
struct CertsArgs {
    /// The folder for the files (`ca.pem`, `ca-key.pem`, `<name>-cert.pem`,
    /// `<name>-key.pem`).
    #[arg(long)]
    out: PathBuf,
    /// A robot: `ID=HOST[,HOST...]`, the addresses or DNS names its peers connect
    /// to. Its certificate's name is `--common-name` with ID in place of `{id}`.
    #[arg(long = "robot", value_name = "ID=HOSTS")]
    robots: Vec<String>,
    /// Another member by its exact name, e.g. a Zenoh router: `NAME=HOST[,HOST...]`.
    #[arg(long = "named", value_name = "NAME=HOSTS")]
    named: Vec<String>,
    /// Robot N's certificate common name (as `robot_certificates: common_name`).
    #[arg(long, default_value = "robot{id}")]
    common_name: String,
    /// Days the certificates are valid.
    #[arg(long, default_value_t = 365)]
    days: u32,
    /// Days a new CA is valid.
    #[arg(long, default_value_t = 3650)]
    ca_days: u32,
    /// A new CA's common name.
    #[arg(long, default_value = "fleet-ca")]
    ca_name: String,
    /// Also write `<name>.json5` per member: the built-in Zenoh configuration of
    /// `--link` pointing at the files in `--out` (for agents on this machine).
    #[arg(long)]
    zenoh_configs: bool,
    /// The secure link the `--zenoh-configs` files use: `tls` (TCP) or `quic` (UDP).
    #[arg(long, value_enum, default_value = "tls", requires = "zenoh_configs")]
    link: agent::transport::fleet_certs::SecureLink,
}

#[derive(clap::Args, Debug)]
struct AclArgs {
    /// The fleet id.
    #[arg(long)]
    fleet: String,
    /// The fleet's robot ids, comma-separated.
    #[arg(long, value_delimiter = ',', required = true)]
    robots: Vec<u32>,
    /// Robot N's certificate common name: this text with N in place of `{id}`.
    #[arg(long, default_value = "robot{id}")]
    common_name: String,
    /// Other routers' certificate names whose forwarded messages this router
    /// accepts as they come (each checks its own senders), comma-separated.
    #[arg(long, value_delimiter = ',')]
    trusted_routers: Vec<String>,
    /// The block for robot N's agent instead of a router's.
    #[arg(long)]
    agent: Option<u32>,
}

#[derive(clap::Args, Debug)]
struct ProbeArgs {
    /// An agent's configuration: the fleet and transport to join.
    #[arg(long)]
    config: PathBuf,
    /// The robot id the probe uses (must not be a fleet member's).
    #[arg(long, default_value_t = 999)]
    as_robot: u32,
    /// Malformed payloads to send.
    #[arg(long, default_value_t = 3)]
    malformed: u32,
    /// Fleet id of the foreign message to send (none if not given).
    #[arg(long)]
    foreign_fleet: Option<String>,
    /// How long to wait for a peer before sending, s.
    #[arg(long, default_value_t = 10.0)]
    wait_s: f64,
    /// Then flood for this long, s: valid track frames and descriptor batches
    /// of the largest size a message may have, and keyframe windows, half of
    /// them stamped far in the future (they wait for a fleet clock that never
    /// comes), half at time 0.
    #[arg(long, default_value_t = 0.0)]
    flood_s: f64,
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
    /// Hybrid run: this real IMU recording (EuRoC CSV, in the trajectory
    /// file's clock) replaces the simulated IMU; the camera stays simulated.
    #[arg(long, value_name = "CSV")]
    real_imu: Option<PathBuf>,
    /// EuRoC ground truth with bias columns, for the real IMU's biases at the
    /// start (default: the robot's trajectory file when it is a .csv).
    #[arg(long, value_name = "CSV")]
    real_imu_biases: Option<PathBuf>,
    /// Render camera images and make the features with the image frontend
    /// (needs the `vision` feature).
    #[arg(long)]
    render: bool,
    /// With `--render`: image frontend settings (YAML), the keys of an agent
    /// configuration's `images.frontend:` block (`first_patch: off`, ...),
    /// over the defaults.
    #[arg(long, value_name = "YAML", requires = "render")]
    frontend: Option<PathBuf>,
}

fn main() -> std::process::ExitCode {
    common::exit_report::exit_code(run_main())
}

fn run_main() -> Result<()> {
    tracing_subscriber::fmt()
        .with_env_filter(
            tracing_subscriber::EnvFilter::try_from_default_env()
                .unwrap_or_else(|_| tracing_subscriber::EnvFilter::new("info")),
        )
        .with_writer(std::io::stderr)
        .with_ansi(std::io::IsTerminal::is_terminal(&std::io::stderr()))
        .init();
    let cli = Cli::parse();
    match (&cli.command, &cli.config) {
        (Some(Command::Run(args)), _) => run(args),
        (Some(Command::Probe(args)), _) => probe(args),
        (Some(Command::Acl(args)), _) => print_acl(args),
        (Some(Command::Certs(args)), _) => make_certs(args),
        (Some(Command::Store(args)), _) => show_store(args),
        #[cfg(feature = "vision")]
        (Some(Command::Dataset(args)), _) => agent::dataset_cli::run_dataset_command(args),
        #[cfg(feature = "vision")]
        (Some(Command::Live(args)), _) => agent::live_cli::run_live_command(args, stop_flag()?),
        (Some(Command::PublishEuroc(args)), _) => publish_euroc(args),
        (None, Some(config)) => run_agent(config, cli.progress),
        (None, None) => {
            println!("agent {} (see --help)", env!("CARGO_PKG_VERSION"));
            Ok(())
        }
    }
}

fn make_certs(args: &CertsArgs) -> Result<()> {
    use agent::transport::fleet_certs::{issue, write_zenoh_configs, Member, Request};
    let split = |spec: &str| -> Result<(String, Vec<String>)> {
        let (name, hosts) = spec
            .split_once('=')
            .with_context(|| format!("{spec:?}: expected NAME=HOST[,HOST...]"))?;
        Ok((
            name.to_owned(),
            hosts.split(',').map(str::to_owned).collect(),
        ))
    };
    let mut members = Vec::new();
    for spec in &args.robots {
        let (id, hosts) = split(spec)?;
        let id: u32 = id
            .parse()
            .with_context(|| format!("{spec:?}: the robot id {id:?} is not a number"))?;
        let name = args.common_name.replace("{id}", &id.to_string());
        members.push(Member { name, hosts });
    }
    for spec in &args.named {
        let (name, hosts) = split(spec)?;
        members.push(Member { name, hosts });
    }
    let request = Request {
        ca_name: args.ca_name.clone(),
        ca_days: args.ca_days,
        days: args.days,
        members,
    };
    let issued = issue(&args.out, &request)?;
    if !issued.new_ca {
        println!("signed with the CA already in {}", args.out.display());
    }
    let mut files = issued.files;
    if args.zenoh_configs {
        let names: Vec<String> = request.members.into_iter().map(|m| m.name).collect();
        files.extend(write_zenoh_configs(&args.out, &names, args.link)?);
    }
    for f in &files {
        println!("{}", f.display());
    }
    Ok(())
}

fn print_acl(args: &AclArgs) -> Result<()> {
    use agent::transport::zenoh_acl::{access_control, AclRole, RobotCertificates};
    agent::transport::settings::validate_fleet_id(&args.fleet)?;
    let certs = RobotCertificates {
        robots: args.robots.clone(),
        common_name: args.common_name.clone(),
        trusted_routers: args.trusted_routers.clone(),
    };
    let role = args.agent.map_or(AclRole::Router, AclRole::Agent);
    let acl = access_control(&args.fleet, &certs, role)?;
    println!("{}", serde_json::to_string_pretty(&acl)?);
    Ok(())
}

/// `agent store`: a line (or a JSON object) per history file.
fn show_store(args: &StoreArgs) -> Result<()> {
    use agent::history_store::inspect;
    let mut files = Vec::new();
    for p in &args.paths {
        if p.is_dir() {
            let mut found: Vec<PathBuf> = std::fs::read_dir(p)
                .with_context(|| format!("reading {}", p.display()))?
                .filter_map(|e| e.ok().map(|e| e.path()))
                .filter(|f| {
                    f.file_name()
                        .is_some_and(|n| n.to_string_lossy().contains(".fvhs"))
                })
                .filter(|f| !f.to_string_lossy().ends_with(".tmp"))
                .collect();
            found.sort();
            files.extend(found);
        } else {
            files.push(p.clone());
        }
    }
    let summaries: Vec<_> = files.iter().map(|f| inspect(f)).collect();
    if args.json {
        println!("{}", serde_json::to_string_pretty(&summaries)?);
        return Ok(());
    }
    println!(
        "{:<36} {:>6} {:>6}  {:<28} {:<16} {:>7} {:>7} {:>6} {:>19} {:>8}  problem",
        "file",
        "format",
        "robot",
        "mission",
        "fleet",
        "records",
        "windows",
        "whole",
        "span s",
        "MB"
    );
    let dash = || "-".to_string();
    for s in &summaries {
        let name = s
            .path
            .file_name()
            .map_or_else(dash, |n| n.to_string_lossy().into_owned());
        println!(
            "{:<36} {:>6} {:>6}  {:<28} {:<16} {:>7} {:>7} {:>6} {:>19} {:>8.2}  {}",
            name,
            s.format.map_or_else(dash, |v| v.to_string()),
            s.robot.map_or_else(dash, |v| v.to_string()),
            s.mission.clone().unwrap_or_else(dash),
            s.fleet_id.clone().unwrap_or_else(dash),
            s.records,
            s.windows,
            s.whole,
            s.span_s
                .map_or_else(dash, |(a, b)| format!("{a:.1}-{b:.1}")),
            s.bytes as f64 / 1e6,
            s.problem.clone().unwrap_or_else(dash),
        );
    }
    Ok(())
}

/// A flag SIGINT and SIGTERM set (a second signal exits at once).
fn stop_flag() -> Result<Arc<AtomicBool>> {
    let stop = Arc::new(AtomicBool::new(false));
    for sig in [SIGINT, SIGTERM] {
        signal_hook::flag::register_conditional_shutdown(sig, 1, Arc::clone(&stop))?;
        signal_hook::flag::register(sig, Arc::clone(&stop))?;
    }
    Ok(stop)
}

fn publish_euroc(args: &PublishEurocArgs) -> Result<()> {
    use agent::ros_input::{publish_sequence, PublishOptions};
    let stop = stop_flag()?;
    let ds = agent::dataset::EurocDataset::open(&args.euroc, None)
        .with_context(|| format!("opening {}", args.euroc.display()))?;
    let opts = PublishOptions {
        speed: args.speed,
        imu_lead_s: args.imu_lead_s,
        wait_subscriber: std::time::Duration::try_from_secs_f64(args.wait_subscriber_s)
            .with_context(|| format!("--wait-subscriber-s {}", args.wait_subscriber_s))?,
    };
    let keys = args.zenoh.keys();
    let sent = publish_sequence(&ds, &args.zenoh.settings(), &keys, &opts, &stop)?;
    println!(
        "published {} IMU messages on {} and {} images on {} ({} images unreadable)",
        sent.imu, keys.imu, sent.images, keys.image, sent.images_skipped
    );
    Ok(())
}

/// Where an agent's data come from.
enum Input {
    /// A simulated robot, or a recording of one.
    Recorded(Box<RobotSetup>),
    /// The robot's own sensors.
    Live(Box<LiveSetup>),
}

/// One agent of a fleet: estimator, peers over the configured transport,
/// outputs in the configured folder. SIGINT/SIGTERM stop it cleanly (a second
/// signal exits at once).
fn run_agent(config: &std::path::Path, progress: bool) -> Result<()> {
    let cfg = AgentConfig::load(config)?;
    let stop = stop_flag()?;
    // The robot's input first: a bad scenario or calibration fails before
    // the agent shows itself to its peers.
    let input = match cfg.input.source {
        InputSource::Live => Input::Live(Box::new(LiveSetup::load(&cfg)?)),
        InputSource::Simulator | InputSource::Mcap => {
            Input::Recorded(Box::new(RobotSetup::load(&cfg)?))
        }
    };
    let settings = cfg.transport_settings();
    let transport = agent::transport::open(&settings, None)
        .with_context(|| format!("robot {}: opening the transport", cfg.robot_id))?;
    let name = transport.name();
    tracing::info!(
        robot = cfg.robot_id,
        fleet = %cfg.fleet_id,
        transport = name,
        source = ?cfg.input.source,
        "agent starting"
    );
    // This process is one agent: its CPU time (the transport's threads too) is
    // the agent's cost, rather than the node thread's alone.
    let cpu_start = cpu_time::ProcessTime::try_now().ok();
    let show = |p: agent::node::Progress| {
        if progress {
            println!(
                "progress {} {} {} {:.3}",
                p.tick, p.ticks_total, p.frames, p.lag_s
            );
        }
    };
    let mut report = match &input {
        Input::Recorded(setup) => run_node(&cfg, setup, transport, &stop, show)?,
        Input::Live(setup) => run_live_node(&cfg, setup, transport, &stop, show)?,
    };
    if let Some(line) = &report.sensors {
        println!("sensors: {line}");
    }
    if let Some(d) = cpu_start.and_then(|t| t.try_elapsed().ok()) {
        report.cpu_s = Some(d.as_secs_f64());
    }
    std::fs::create_dir_all(&cfg.output_dir)
        .with_context(|| format!("creating {}", cfg.output_dir.display()))?;
    write_outputs(&report, cfg.robot_id, name, &cfg.output_dir)
        .with_context(|| format!("writing outputs to {}", cfg.output_dir.display()))?;
    let m = metrics_of(&report);
    tracing::info!(
        robot = cfg.robot_id,
        frames = report.run.frames.len(),
        ate_ori_deg = m.ate_ori_deg.unwrap_or(f64::NAN),
        ate_pos_m = m.ate_pos_m.unwrap_or(f64::NAN),
        bytes_per_s_sent = m.bytes_per_s_sent.unwrap_or(f64::NAN),
        received = m.messages_received.unwrap_or(0),
        dropped = m.messages_dropped.unwrap_or(0),
        interrupted = report.interrupted,
        "agent done"
    );
    if progress {
        println!("done {}", cfg.output_dir.display());
    }
    Ok(())
}

fn probe(args: &ProbeArgs) -> Result<()> {
    use agent::transport::PresenceEvent;
    use common::messages::{encode, AgentState, Body, Envelope, Heartbeat, MessageKind};
    use std::time::{Duration, Instant};
    let cfg = AgentConfig::load(&args.config)?;
    let mut settings = cfg.transport_settings();
    settings.robot_id = args.as_robot;
    // Join through the agent's own endpoint, listening on any free port of the same
    // protocol (a TLS-only configuration refuses `tcp/`).
    let scheme = (settings.zenoh.listen.first())
        .and_then(|e| e.split_once('/'))
        .map_or("tcp", |(scheme, _)| scheme)
        .to_owned();
    settings.zenoh.connect = settings.zenoh.listen.clone();
    settings.zenoh.listen = vec![format!("{scheme}/127.0.0.1:0")];
    let mut t = agent::transport::open(&settings, None)?;
    let deadline = Instant::now() + Duration::from_secs_f64(args.wait_s);
    // Wait for the agent of the configuration itself (its presence means its
    // subscriber is known), then a moment for the routes to settle.
    let mut seen = false;
    while !seen && Instant::now() < deadline {
        seen = t
            .presence()
            .contains(&PresenceEvent::Appeared(cfg.robot_id));
        let _ = t.receive(Duration::from_millis(20))?;
    }
    anyhow::ensure!(
        seen,
        "robot {} of fleet `{}` did not appear",
        cfg.robot_id,
        cfg.fleet_id
    );
    std::thread::sleep(Duration::from_millis(200));
    for k in 0..args.malformed {
        // A wrong magic, a truncated header, and random-looking bytes.
        let junk: Vec<u8> = match k % 3 {
            0 => b"not a fleet message".to_vec(),
            1 => vec![b'F', b'V'],
            _ => (0..64u32)
                .map(|i| (i.wrapping_mul(2654435761) >> 13) as u8)
                .collect(),
        };
        t.publish(MessageKind::Tracks, &junk)?;
    }
    if let Some(fleet) = &args.foreign_fleet {
        let env = Envelope {
            fleet_id: fleet.clone(),
            robot_id: args.as_robot,
            seq: 0,
            stamp_s: 0.0,
            sent_wall_ns: 0,
            body: Body::Heartbeat(Heartbeat {
                state: AgentState::Running,
                frames_done: 0,
                last_frame_index: None,
                last_t_s: None,
                newest_window_end_s: None,
            }),
        };
        t.publish(MessageKind::Heartbeat, &encode(&env)?)?;
    }
    let (mut flood_msgs, mut flood_bytes) = (0u64, 0usize);
    let started = Instant::now();
    let mut seq = 0u64;
    while started.elapsed().as_secs_f64() < args.flood_s {
        for (kind, body) in flood_round(seq) {
            let env = Envelope {
                fleet_id: cfg.fleet_id.clone(),
                robot_id: args.as_robot,
                seq,
                stamp_s: if seq % 2 == 0 { 0.0 } else { 1e6 },
                sent_wall_ns: 0,
                body,
            };
            let bytes = encode(&env)?;
            t.publish(kind, &bytes)?;
            flood_msgs += 1;
            flood_bytes += bytes.len();
        }
        seq += 1;
    }
    // Give the transport time to deliver before leaving.
    std::thread::sleep(Duration::from_millis(500));
    t.close(Duration::from_secs(2))?;
    println!(
        "sent {} malformed and {} foreign-fleet messages to fleet `{}`",
        args.malformed,
        u32::from(args.foreign_fleet.is_some()),
        cfg.fleet_id
    );
    if args.flood_s > 0.0 {
        let s = started.elapsed().as_secs_f64();
        println!(
            "flooded it with {flood_msgs} valid messages, {:.1} MB in {s:.1} s ({:.1} MB/s)",
            flood_bytes as f64 / 1e6,
            flood_bytes as f64 / 1e6 / s
        );
    }
    Ok(())
}

/// One round of the probe's flood: a track frame and a new-track descriptor
/// batch as large as a message may be (fresh track ids each round), and a
/// keyframe window with its keyframe descriptors.
fn flood_round(k: u64) -> Vec<(common::messages::MessageKind, common::messages::Body)> {
    use common::messages::{
        Body, CameraModelWire, CameraPose, DescriptorBatch, DescriptorEntry, MessageKind,
        PackedCovariance, StateSnapshot, TrackFrame, TrackPoint,
    };
    // Every round a new keyframe window (keyed by its newest clone's time).
    let t = if k % 2 == 0 {
        2.0 * k as f64
    } else {
        1e6 + k as f64
    };
    let n = 4000u64;
    let id = |i: u64| k * n + i;
    let xy = |i: u64| ((i % 61) as f64 * 0.01 - 0.3, (i % 37) as f64 * 0.01 - 0.2);
    let features = (0..n)
        .map(|i| {
            let (x, y) = xy(i);
            TrackPoint::new(
                id(i),
                &nalgebra::Vector2::new(370.0 + 450.0 * x, 240.0 + 450.0 * y),
                &nalgebra::Vector2::new(x, y),
            )
        })
        .collect();
    let descriptors = |count: u64| -> Vec<DescriptorEntry> {
        (0..count)
            .map(|i| DescriptorEntry {
                id: id(i),
                bits: [id(i).wrapping_mul(0x9e37_79b9_7f4a_7c15); 4],
            })
            .collect()
    };
    let clones: Vec<CameraPose> = (0..11)
        .map(|c| {
            CameraPose::new(
                t + 0.1 * c as f64,
                &nalgebra::Matrix3::identity(),
                &nalgebra::Vector3::new(k as f64, 0.0, 1.0),
            )
        })
        .collect();
    let covariance = PackedCovariance::from_dmatrix(&(nalgebra::DMatrix::identity(66, 66) * 1e-4))
        .unwrap_or_default();
    vec![
        (
            MessageKind::Tracks,
            Body::Tracks(TrackFrame {
                frame_index: k,
                t_s: t,
                features,
            }),
        ),
        (
            MessageKind::Descriptors,
            Body::Descriptors(DescriptorBatch {
                frame_index: k,
                t_s: t,
                keyframe: false,
                entries: descriptors(n),
            }),
        ),
        (
            MessageKind::Descriptors,
            Body::Descriptors(DescriptorBatch {
                frame_index: k,
                t_s: t,
                keyframe: true,
                entries: descriptors(500),
            }),
        ),
        (
            MessageKind::Snapshot,
            Body::Snapshot(StateSnapshot {
                frame_index: k,
                t_s: t + 1.0,
                keyframe: true,
                frame_epoch: 0,
                camera: CameraModelWire::default(),
                pixel_sigma_px: 1.0,
                covariance,
                clones,
                landmarks: Vec::new(),
            }),
        ),
    ]
}

/// Images (with their tracks) logged by `agent run --render`: one in this many.
#[cfg(feature = "vision")]
const LOG_IMAGE_EVERY: usize = 5;

/// A rendered run through the image frontend, with the tracks' accuracy
/// printed, their error per image in `OUT/track_errors.csv`, and every 5th
/// image logged.
#[cfg(feature = "vision")]
fn rendered(
    fleet: &Fleet,
    robot: usize,
    opts: agent::estimator::EstimatorOptions,
    frontend: Option<&std::path::Path>,
    log: &mut AgentLog,
    out: &std::path::Path,
) -> Result<(agent::runner::RobotRun, Option<f64>)> {
    let frontend = agent::dataset_cli::frontend_options(frontend)?;
    let mut k = 0usize;
    let r = agent::image_runner::run_robot_rendered(fleet, robot, opts, frontend, |c, out| {
        if k % LOG_IMAGE_EVERY == 0 {
            if let Some(img) = &c.image {
                let _ = log.image(c.frame.t, img);
                let _ = log.tracks(&out.frame, &out.new_ids);
            }
        }
        k += 1;
    })?;
    let q = &r.tracks;
    println!(
        "frontend: {} images, {:.0} features/image, {:.2} ms/image; tracks against the rendered truth: mean {:.3} px, median {:.3} px, p95 {:.3} px, {:.2}% over 3 px ({} observations)",
        q.frames,
        q.features_per_frame,
        q.ms_per_frame,
        q.reprojection_mean_px,
        q.reprojection_median_px,
        q.reprojection_p95_px,
        100.0 * q.outlier_fraction,
        q.observations
    );
    let csv = out.join("track_errors.csv");
    let text = agent::image_runner::track_errors_csv(&r.per_frame);
    std::fs::write(&csv, text).with_context(|| format!("writing {}", csv.display()))?;
    Ok((r.run, q.mean_error_px()))
}

#[cfg(not(feature = "vision"))]
fn rendered(
    _: &Fleet,
    _: usize,
    _: agent::estimator::EstimatorOptions,
    _: Option<&std::path::Path>,
    _: &mut AgentLog,
    _: &std::path::Path,
) -> Result<(agent::runner::RobotRun, Option<f64>)> {
    Err(agent::runner::RunError::NoImageFrontend.into())
}

fn run(args: &RunArgs) -> Result<()> {
    let wall = Instant::now();
    let mut scenario = Scenario::load(&args.scenario)?;
    scenario.render.enabled |= args.render;
    let seed = args.seed.unwrap_or(scenario.seed);
    let variant: Variant = args.variant.parse()?;
    let fleet = Fleet::build(&scenario, seed)?;
    let opts = options_for(&scenario.estimator, &fleet, args.robot, variant);
    let out = &args.out;
    std::fs::create_dir_all(out).with_context(|| format!("creating {}", out.display()))?;
    let mut log = AgentLog::create(&out.join("agent.mcap"))?;
    let (run, track_error_px) = if let Some(imu) = &args.real_imu {
        let default_biases = scenario
            .trajectory_path(args.robot)
            .filter(|p| p.extension().is_some_and(|e| e == "csv"));
        let biases = args.real_imu_biases.clone().or(default_biases);
        let run =
            agent::hybrid::run_robot_hybrid(&fleet, args.robot, opts, imu, biases.as_deref())?;
        (run, None)
    } else if fleet.renders() {
        rendered(
            &fleet,
            args.robot,
            opts,
            args.frontend.as_deref(),
            &mut log,
            out,
        )?
    } else {
        (run_robot(&fleet, args.robot, opts)?, None)
    };
    let truth_twists: Vec<_> = run
        .twists
        .iter()
        .filter_map(|tw| {
            let s = fleet.truths.get(args.robot)?.state(tw.t)?;
            Some(agent::runner::truth_twist(tw.t, &s))
        })
        .collect();
    log.run_poses(
        &run.estimate,
        &run.covariance,
        &run.twists,
        &run.truth,
        &truth_twists,
    )?;
    log.finish()?;
    for r in run.rejected.iter().take(5) {
        tracing::warn!("rejected: {r}");
    }
    write_run_outputs(&run, out).with_context(|| format!("writing {}", out.display()))?;
    let metrics = MetricSet {
        track_error_px,
        ..run.metrics()
    };
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
