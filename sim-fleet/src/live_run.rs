//! `sim-fleet live-run`: a fleet on live sensors, on one machine. Each robot
//! of a scenario is rendered as a EuRoC sequence ([`simulator::euroc_export`],
//! kept and reused), published as ROS 2 topics over Zenoh by its own `agent
//! publish-euroc`, and run by its own `agent --config` with `input.source:
//! live`, the agents talking over Zenoh on loopback. Each agent is given its
//! start pose from the truth, optionally moved by a seeded draw of its σ; the
//! estimates are scored against the truth without alignment.

use anyhow::{bail, Context, Result};
use common::metrics::{associate, ate, nees, Alignment, DEFAULT_MAX_DT_S};
use common::trajectory::{read_covariances, read_euroc_csv, read_tum, StampedPose};
use nalgebra::Vector3;
use rand_distr::{Distribution, Normal};
use serde::{Deserialize, Serialize};
use simulator::rng::{stream_rng, Stream};
use simulator::{Fleet, Scenario};
use std::path::{Path, PathBuf};
use std::process::{Child, Command, Stdio};
use std::time::{Duration, Instant};

/// Arguments of `sim-fleet live-run`.
#[derive(clap::Args, Debug)]
pub struct LiveRunArgs {
    /// Scenario file (YAML); rendering is switched on.
    pub scenario: PathBuf,
    /// Seed of the simulation and of the start draws (default: the scenario's).
    #[arg(long)]
    pub seed: Option<u64>,
    /// Estimator variant of every agent.
    #[arg(long, default_value = "dc-full-history")]
    pub variant: String,
    /// Playback speed of the sensors (1 = real time).
    #[arg(long, default_value_t = 1.0)]
    pub speed: f64,
    /// Only the first this many seconds of each robot's flight.
    #[arg(long)]
    pub duration_s: Option<f64>,
    /// The IMU axis whose heading each start gives (`x`, `y`, `z`, optionally
    /// with a leading `-`): take one far from the vertical (EuRoC's IMU has `x`
    /// up).
    #[arg(long, default_value = "y")]
    pub heading_axis: String,
    /// The start position's σ each agent is given, m (each axis).
    #[arg(long, default_value_t = 0.05)]
    pub start_sigma_pos_m: f64,
    /// The start orientation's σ each agent is given, deg (each axis).
    #[arg(long, default_value_t = 1.0)]
    pub start_sigma_ori_deg: f64,
    /// Move each start from the truth by a draw of those σ (position on each
    /// axis, heading about the vertical), seeded by the seed and the robot:
    /// robots set down on spots known that well.
    #[arg(long)]
    pub perturb_start: bool,
    /// Where the rendered sequences are kept (`seq<r>/`), and reused when they
    /// were made of the same scenario, seed and duration (default:
    /// `OUT/sequences`).
    #[arg(long)]
    pub sequences: Option<PathBuf>,
    /// The `agent` binary, built with `--features vision` (default: `agent`
    /// next to this program).
    #[arg(long)]
    pub agent_bin: Option<PathBuf>,
    /// Output folder: `robot<r>/` per agent (its configuration, outputs and
    /// log) and `live_summary.json`.
    #[arg(long, default_value = "out/live-fleet")]
    pub out: PathBuf,
}

/// What a sequence folder was made of: a folder that says otherwise is made
/// anew.
#[derive(Debug, PartialEq, Serialize, Deserialize)]
struct Made {
    scenario: PathBuf,
    seed: u64,
    duration_s: Option<f64>,
}

/// One robot's result.
#[derive(Debug, Serialize)]
pub struct LiveRobot {
    /// Robot index.
    pub robot: usize,
    /// The trajectory's name.
    pub name: String,
    /// Estimates written.
    pub estimates: usize,
    /// ATE without alignment, deg and m.
    pub ate_ori_deg: f64,
    /// ATE without alignment, m.
    pub ate_pos_m: f64,
    /// Mean NEES of orientation and position.
    pub nees_ori: Option<f64>,
    /// Mean NEES of position.
    pub nees_pos: Option<f64>,
    /// Loop closures to the peers' histories.
    pub loop_closures: Option<u64>,
    /// Common-feature updates.
    pub common_feature_updates: Option<u64>,
    /// Bytes per second the agent sent to its peers.
    pub bytes_per_s_sent: Option<f64>,
    /// How far the start given was from the truth, m and deg of heading.
    pub start_offset: (f64, f64),
    /// The agent's `sensors:` line: samples received, undecodable, dropped,
    /// and how long after its image each estimate came.
    pub sensors: String,
}

/// The heading of the IMU axis `axis_i` of `pose`, rad.
fn heading(pose: &StampedPose, axis_i: &Vector3<f64>) -> f64 {
    let a = pose.rot * axis_i;
    a.y.atan2(a.x)
}

fn agent_binary(given: Option<&Path>) -> Result<PathBuf> {
    if let Some(b) = given {
        return Ok(b.to_path_buf());
    }
    let me = std::env::current_exe().context("locating this program")?;
    let dir = me.parent().context("this program has no folder")?;
    [dir.join("agent"), dir.join("..").join("agent")]
        .into_iter()
        .find(|p| p.is_file())
        .with_context(|| {
            format!(
                "no `agent` binary next to {} (cargo build --release -p agent --features vision, \
                 or --agent-bin)",
                me.display()
            )
        })
}

/// Renders robot `r`'s sequence into `dir`, unless it is there already.
fn sequence(fleet: &Fleet, r: usize, made: &Made, dir: &Path) -> Result<()> {
    let marker = dir.join("made.json");
    let same = std::fs::read(&marker)
        .ok()
        .and_then(|b| serde_json::from_slice::<Made>(&b).ok())
        .is_some_and(|m| &m == made);
    if same {
        return Ok(());
    }
    if dir.exists() {
        std::fs::remove_dir_all(dir).with_context(|| format!("removing {}", dir.display()))?;
    }
    let truth = &fleet.truths[r];
    let t_end = made
        .duration_s
        .map_or(f64::INFINITY, |d| truth.start_time() + d);
    let origin = format!("sim-fleet live-run {}", made.scenario.display());
    let n = simulator::euroc_export::export_euroc(fleet, r, t_end, dir, &origin)?;
    tracing::info!(
        "robot {r}: {} images, {} IMU samples rendered",
        n.images,
        n.imu
    );
    std::fs::write(&marker, serde_json::to_vec_pretty(made)?)?;
    Ok(())
}

/// Agent `r`'s configuration.
#[allow(clippy::too_many_arguments)]
fn config(
    args: &LiveRunArgs,
    r: usize,
    n: usize,
    seq: &Path,
    out: &Path,
    ports: &[u16],
    start: (&Vector3<f64>, f64),
    fleet_id: &str,
) -> String {
    let peers: Vec<usize> = (0..n).filter(|&q| q != r).collect();
    let connect: Vec<String> = peers
        .iter()
        .map(|&q| format!("tcp/127.0.0.1:{}", ports[q]))
        .collect();
    let (p, yaw_deg) = start;
    format!(
        "# Written by sim-fleet live-run.
robot_id: {r}
fleet_id: {fleet_id}
output_dir: {out}
status_period_s: 0
transport:
  kind: zenoh
  zenoh:
    config: loopback
    listen: [tcp/127.0.0.1:{me}]
    connect: [{connect}]
input:
  source: live
  live:
    calibration: {seq}
    zenoh:
      config: loopback
      listen: [tcp/127.0.0.1:{sensors}]
    imu_key: robot{r}/imu0
    image_key: robot{r}/cam0/image_raw
    start:
      position_m: [{}, {}, {}]
      yaw_deg: {yaw_deg}
      heading_axis: {axis}
      sigma_ori_deg: {sigma_ori}
      sigma_pos_m: {sigma_pos}
    idle_timeout_s: 3
estimator:
  variant: {variant}
clock:
  mode: realtime
  peers: {peers:?}
",
        p.x,
        p.y,
        p.z,
        out = out.display(),
        me = ports[r],
        connect = connect.join(", "),
        seq = seq.display(),
        sensors = ports[n + r],
        axis = args.heading_axis,
        sigma_ori = args.start_sigma_ori_deg,
        sigma_pos = args.start_sigma_pos_m,
        variant = args.variant,
    )
}

/// Waits for `child` at most `limit`, killing it past that.
fn wait(mut child: Child, what: &str, limit: Duration) -> Result<()> {
    let start = Instant::now();
    loop {
        if let Some(status) = child.try_wait()? {
            if !status.success() {
                bail!("{what} exited with {status}");
            }
            return Ok(());
        }
        if start.elapsed() > limit {
            let _ = child.kill();
            bail!("{what} did not end within {limit:?}");
        }
        std::thread::sleep(Duration::from_millis(100));
    }
}

/// Runs `sim-fleet live-run`.
pub fn run_live(args: &LiveRunArgs) -> Result<()> {
    if !(args.speed.is_finite() && args.speed > 0.0) {
        bail!("--speed {}: must be > 0", args.speed);
    }
    if let Some(d) = args.duration_s.filter(|d| !(d.is_finite() && *d > 0.0)) {
        bail!("--duration-s {d}: must be a positive number of seconds");
    }
    for (name, v) in [
        ("--start-sigma-pos-m", args.start_sigma_pos_m),
        ("--start-sigma-ori-deg", args.start_sigma_ori_deg),
    ] {
        if !(v.is_finite() && v > 0.0) {
            bail!("{name} {v}: must be > 0");
        }
    }
    let axis_i = agent::config::StartPose {
        position_m: [0.0; 3],
        yaw_deg: 0.0,
        heading_axis: args.heading_axis.clone(),
        sigma_ori_deg: 1.0,
        sigma_pos_m: 1.0,
    }
    .heading_axis_i()
    .map_err(anyhow::Error::msg)?;
    let bin = agent_binary(args.agent_bin.as_deref())?;
    let mut scenario = Scenario::load(&args.scenario)
        .with_context(|| format!("loading {}", args.scenario.display()))?;
    scenario.render.enabled = true;
    let seed = args.seed.unwrap_or(scenario.seed);
    let fleet = Fleet::build(&scenario, seed)?;
    let n = fleet.robot_count();
    if n < 2 {
        bail!("the scenario has {n} robot: a fleet needs two or more");
    }
    let out = &args.out;
    std::fs::create_dir_all(out).with_context(|| format!("creating {}", out.display()))?;
    let out = out.canonicalize()?;
    let sequences = args
        .sequences
        .clone()
        .unwrap_or_else(|| out.join("sequences"));
    let made = Made {
        scenario: args.scenario.canonicalize()?,
        seed,
        duration_s: args.duration_s,
    };
    let ports = common::loopback_ports::free_loopback_ports(2 * n)?;
    let fleet_id = format!("live-{}", std::process::id());
    let mut truths = Vec::with_capacity(n);
    let mut agents = Vec::with_capacity(n);
    let mut offsets = Vec::with_capacity(n);
    for r in 0..n {
        let seq = sequences.join(format!("seq{r}"));
        sequence(&fleet, r, &made, &seq)?;
        let seq = seq.canonicalize()?;
        let gt = read_euroc_csv(seq.join("mav0/state_groundtruth_estimate0/data.csv"))?;
        let first = *gt.first().context("an empty ground truth")?;
        let (mut pos, mut yaw) = (first.pos, heading(&first, &axis_i).to_degrees());
        if args.perturb_start {
            // The error a robot's start is given with: its own stream.
            let mut rng = stream_rng(seed, Stream::InitialState(r));
            let p = Normal::new(0.0, args.start_sigma_pos_m)?;
            pos += Vector3::from_fn(|_, _| p.sample(&mut rng));
            yaw += Normal::new(0.0, args.start_sigma_ori_deg)?.sample(&mut rng);
        }
        offsets.push((
            (pos - first.pos).norm(),
            yaw - heading(&first, &axis_i).to_degrees(),
        ));
        let dir = out.join(format!("robot{r}"));
        if dir.exists() {
            std::fs::remove_dir_all(&dir)?;
        }
        std::fs::create_dir_all(&dir)?;
        let cfg = dir.join("config.yaml");
        let text = config(args, r, n, &seq, &dir, &ports, (&pos, yaw), &fleet_id);
        std::fs::write(&cfg, text)?;
        let child = Command::new(&bin)
            .arg("--config")
            .arg(&cfg)
            .stdout(Stdio::from(std::fs::File::create(dir.join("agent.out"))?))
            .stderr(Stdio::from(std::fs::File::create(dir.join("agent.log"))?))
            .spawn()
            .with_context(|| format!("starting {}", bin.display()))?;
        agents.push(child);
        truths.push((seq, gt));
    }
    let publishers: Vec<Child> = (0..n)
        .map(|r| {
            Command::new(&bin)
                .arg("publish-euroc")
                .arg("--euroc")
                .arg(&truths[r].0)
                .args(["--listen", "tcp/127.0.0.1:0", "--connect"])
                .arg(format!("tcp/127.0.0.1:{}", ports[n + r]))
                .arg("--imu-key")
                .arg(format!("robot{r}/imu0"))
                .arg("--image-key")
                .arg(format!("robot{r}/cam0/image_raw"))
                .arg("--speed")
                .arg(args.speed.to_string())
                .stdout(Stdio::null())
                .stderr(Stdio::from(std::fs::File::create(
                    out.join(format!("robot{r}/publish.log")),
                )?))
                .spawn()
                .context("starting agent publish-euroc")
        })
        .collect::<Result<_>>()?;
    let longest = (fleet.truths.iter())
        .map(|t| t.end_time() - t.start_time())
        .fold(0.0, f64::max);
    let limit = Duration::from_secs_f64(
        args.duration_s.unwrap_or(longest).min(longest) / args.speed + 120.0,
    );
    for (r, p) in publishers.into_iter().enumerate() {
        wait(p, &format!("robot {r}'s publish-euroc"), limit)?;
    }
    for (r, a) in agents.into_iter().enumerate() {
        wait(a, &format!("robot {r}'s agent (see its agent.log)"), limit)?;
    }
    let robots = (0..n)
        .map(|r| {
            score(
                &out,
                r,
                &truths[r].1,
                fleet.scenario.robot_name(r),
                offsets[r],
            )
        })
        .collect::<Result<Vec<_>>>()?;
    print_table(&robots, args);
    let summary = serde_json::json!({
        "scenario": fleet.scenario.name,
        "seed": seed,
        "variant": args.variant,
        "speed": args.speed,
        "perturb_start": args.perturb_start,
        "robots": robots,
    });
    std::fs::write(
        out.join("live_summary.json"),
        serde_json::to_vec_pretty(&summary)?,
    )?;
    println!("summary: {}", out.join("live_summary.json").display());
    Ok(())
}

/// Robot `r`'s estimates against its truth, and its agent's figures.
fn score(
    out: &Path,
    r: usize,
    gt: &[StampedPose],
    name: String,
    start_offset: (f64, f64),
) -> Result<LiveRobot> {
    let dir = out.join(format!("robot{r}"));
    let est = read_tum(dir.join("estimate.txt"))?;
    let covs = read_covariances(dir.join("covariance.txt"))?;
    let pairs = associate(&est, gt, DEFAULT_MAX_DT_S);
    if pairs.is_empty() {
        bail!(
            "robot {r}: no estimate to score (see {})",
            dir.join("agent.log").display()
        );
    }
    let a = ate(&pairs, Alignment::None);
    let n = nees(&pairs, &covs);
    let summary: serde_json::Value =
        serde_json::from_slice(&std::fs::read(dir.join("summary.json"))?)?;
    let m = &summary["robots"][0];
    let sensors = std::fs::read_to_string(dir.join("agent.out"))?
        .lines()
        .find_map(|l| l.strip_prefix("sensors: ").map(str::to_owned))
        .unwrap_or_default();
    Ok(LiveRobot {
        robot: r,
        name,
        estimates: est.len(),
        ate_ori_deg: a.ori_deg,
        ate_pos_m: a.pos_m,
        nees_ori: n.ori_mean,
        nees_pos: n.pos_mean,
        loop_closures: m["loop_closures"].as_u64(),
        common_feature_updates: m["common_feature_updates"].as_u64(),
        bytes_per_s_sent: m["bytes_per_s_sent"].as_f64(),
        start_offset,
        sensors,
    })
}

fn print_table(robots: &[LiveRobot], args: &LiveRunArgs) {
    let opt = |v: Option<f64>| v.map_or("-".to_owned(), |v| format!("{v:.2}"));
    println!(
        "{} at {}x real time, starts {}:",
        args.variant,
        args.speed,
        match args.perturb_start {
            true => "moved from the truth by a draw of their sigma",
            false => "at the truth",
        }
    );
    println!(
        "{:<5} {:<20} {:>9} {:>8} {:>8} {:>8} {:>9} {:>9} {:>8} {:>9}",
        "robot",
        "trajectory",
        "estimates",
        "ATE deg",
        "ATE m",
        "NEES ori",
        "NEES pos",
        "closures",
        "KB/s",
        "start m"
    );
    for r in robots {
        println!(
            "{:<5} {:<20} {:>9} {:>8.3} {:>8.4} {:>8} {:>9} {:>9} {:>8.1} {:>9.3}",
            r.robot,
            r.name,
            r.estimates,
            r.ate_ori_deg,
            r.ate_pos_m,
            opt(r.nees_ori),
            opt(r.nees_pos),
            r.loop_closures.map_or("-".into(), |c| c.to_string()),
            r.bytes_per_s_sent.unwrap_or(f64::NAN) / 1e3,
            r.start_offset.0
        );
        println!("      sensors: {}", r.sensors);
    }
    let n = robots.len().max(1) as f64;
    println!(
        "mean  ATE {:.3} deg / {:.4} m",
        robots.iter().map(|r| r.ate_ori_deg).sum::<f64>() / n,
        robots.iter().map(|r| r.ate_pos_m).sum::<f64>() / n
    );
}
