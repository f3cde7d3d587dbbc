//! `sim-fleet live-run`: a fleet on live sensors, on one machine. Each robot
//! of a scenario is rendered as a EuRoC sequence ([`simulator::euroc_export`],
//! kept and reused), published as ROS 2 topics over Zenoh by its own `agent
//! publish-euroc`, and run by its own `agent --config` with `input.source:
//! live`, the agents talking over Zenoh on loopback. Each agent is given its
//! start pose from the truth, optionally moved by a seeded draw of its σ; the
//! estimates are scored against the truth without alignment. With
//! `--own-frames` no agent is told where it is: each starts at the origin of
//! a frame of its own, finds its peers' frames from its loop closures, and is
//! scored in its frame (its alignments against the true ones).

use agent::estimator::frame_alignment::{rot_z, FrameAlignment};
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
    #[arg(long, conflicts_with = "own_frames")]
    pub perturb_start: bool,
    /// Each robot in a frame of its own: its agent starts at the origin with
    /// heading 0 (position σ 1 mm and heading σ 0.05 deg: the start defines
    /// the frame; the tilt keeps `--start-sigma-ori-deg`) and aligns
    /// its peers' frames from its loop closures (`estimator.align_peer_frames`,
    /// which needs `--variant dc-full-history`); it is scored in that frame.
    #[arg(long)]
    pub own_frames: bool,
    /// Image frontend settings of every agent (YAML): the keys of an agent
    /// configuration's `images.frontend:` block, e.g.
    /// `deploy/config/held-tracks/frontend.yaml`.
    #[arg(long, value_name = "YAML")]
    pub frontend: Option<PathBuf>,
    /// Estimator settings of every agent (YAML): keys of an agent
    /// configuration's `estimator:` block, e.g.
    /// `deploy/config/held-tracks/estimator.yaml`; a key this command sets
    /// too (`variant`, `align_peer_frames`) must agree with it.
    #[arg(long, value_name = "YAML")]
    pub estimator: Option<PathBuf>,
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
    /// With `--own-frames`: the peers' frames it aligned, against the true
    /// ones.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub peer_frames: Option<LivePeerFrames>,
}

/// How well one agent found its peers' frames (`--own-frames`).
#[derive(Debug, Serialize)]
pub struct LivePeerFrames {
    /// Peer frames aligned (a peer started again counts once per start).
    pub aligned: usize,
    /// Of the peers, how many it found a frame of.
    pub peers_aligned: usize,
    /// Its peers.
    pub peers: usize,
    /// Largest yaw error of an alignment, deg.
    pub max_yaw_err_deg: Option<f64>,
    /// Largest translation error of an alignment, m.
    pub max_pos_err_m: Option<f64>,
}

/// Where a robot's own frame is in the world: the truth at its first
/// sample, `(position m, heading of the start's axis rad)`.
type OwnFrame = (Vector3<f64>, f64);

/// `pose` (in the world) in the frame `frame`.
fn in_own_frame(pose: &StampedPose, frame: &OwnFrame) -> StampedPose {
    let back = rot_z(-frame.1);
    StampedPose {
        t: pose.t,
        rot: back * pose.rot,
        pos: back * (pose.pos - frame.0),
    }
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
    // In a frame of its own the start defines the frame: its position and
    // heading are known exactly, and the peers' frames must be found.
    let (sigma_pos, sigma_yaw, align) = match args.own_frames {
        true => (
            0.001,
            "\n      sigma_yaw_deg: 0.05",
            "\n  align_peer_frames: true",
        ),
        false => (args.start_sigma_pos_m, "", ""),
    };
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
      sigma_ori_deg: {sigma_ori}{sigma_yaw}
      sigma_pos_m: {sigma_pos}
    idle_timeout_s: 3
estimator:
  variant: {variant}{align}
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
        variant = args.variant,
    )
}

/// What `--frontend` and `--estimator` add to every agent's configuration.
#[derive(Debug, Default)]
struct AgentSettings {
    /// The `images.frontend:` block.
    frontend: Option<serde_yaml::Mapping>,
    /// Keys of the `estimator:` block.
    estimator: Option<serde_yaml::Mapping>,
}

impl AgentSettings {
    fn read(args: &LiveRunArgs) -> Result<Self> {
        let read = |path: &Option<PathBuf>| -> Result<Option<serde_yaml::Mapping>> {
            let Some(path) = path else { return Ok(None) };
            let text = std::fs::read_to_string(path)
                .with_context(|| format!("reading {}", path.display()))?;
            // An empty file (or one of comments only) adds nothing.
            let value: Option<serde_yaml::Value> = serde_yaml::from_str(&text)
                .with_context(|| format!("parsing {}", path.display()))?;
            match value {
                None => Ok(Some(serde_yaml::Mapping::new())),
                Some(serde_yaml::Value::Mapping(m)) => Ok(Some(m)),
                Some(_) => bail!("{}: expected a mapping of settings", path.display()),
            }
        };
        Ok(Self {
            frontend: read(&args.frontend)?,
            estimator: read(&args.estimator)?,
        })
    }

    /// `config` (an agent configuration) with the settings added. The agent
    /// checks the keys when it loads the file.
    fn apply(&self, config: &str) -> Result<String> {
        if self.frontend.is_none() && self.estimator.is_none() {
            return Ok(config.to_owned());
        }
        let mut doc: serde_yaml::Mapping = serde_yaml::from_str(config)?;
        if let Some(keys) = &self.estimator {
            let block = doc
                .entry("estimator".into())
                .or_insert_with(|| serde_yaml::Mapping::new().into());
            let block = block
                .as_mapping_mut()
                .context("the configuration's `estimator` is not a mapping")?;
            for (k, v) in keys {
                match block.get(k) {
                    Some(ours) if ours != v => bail!(
                        "--estimator sets `{}` to {}, but this run sets it to {}",
                        yaml_inline(k),
                        yaml_inline(v),
                        yaml_inline(ours)
                    ),
                    _ => {
                        block.insert(k.clone(), v.clone());
                    }
                }
            }
        }
        if let Some(frontend) = &self.frontend {
            let mut images = serde_yaml::Mapping::new();
            images.insert("frontend".into(), frontend.clone().into());
            doc.insert("images".into(), images.into());
        }
        Ok(format!(
            "# Written by sim-fleet live-run.\n{}",
            serde_yaml::to_string(&doc)?
        ))
    }
}

/// A YAML value on one line, for messages.
fn yaml_inline(v: &serde_yaml::Value) -> String {
    serde_yaml::to_string(v).map_or_else(|_| format!("{v:?}"), |s| s.trim().to_owned())
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
        sigma_yaw_deg: None,
        sigma_pos_m: 1.0,
    }
    .heading_axis_i()
    .map_err(anyhow::Error::msg)?;
    let bin = agent_binary(args.agent_bin.as_deref())?;
    let settings = AgentSettings::read(args)?;
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
    // The settings checked against what this run sets before anything is
    // rendered: robot 0's configuration, its start aside.
    let start = (&Vector3::zeros(), 0.0);
    settings.apply(&config(
        args, 0, n, &sequences, &out, &ports, start, &fleet_id,
    ))?;
    let mut truths = Vec::with_capacity(n);
    let mut agents = Vec::with_capacity(n);
    let mut offsets = Vec::with_capacity(n);
    let mut frames: Vec<OwnFrame> = Vec::with_capacity(n);
    for r in 0..n {
        let seq = sequences.join(format!("seq{r}"));
        sequence(&fleet, r, &made, &seq)?;
        let seq = seq.canonicalize()?;
        let gt = read_euroc_csv(seq.join("mav0/state_groundtruth_estimate0/data.csv"))?;
        let first = *gt.first().context("an empty ground truth")?;
        let frame = (first.pos, heading(&first, &axis_i));
        frames.push(frame);
        let (mut pos, mut yaw) = (first.pos, frame.1.to_degrees());
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
        let start = match args.own_frames {
            true => (Vector3::zeros(), 0.0),
            false => (pos, yaw),
        };
        let text = config(
            args,
            r,
            n,
            &seq,
            &dir,
            &ports,
            (&start.0, start.1),
            &fleet_id,
        );
        let text = settings.apply(&text)?;
        std::fs::write(&cfg, text)?;
        let child = Command::new(&bin)
            .arg("--config")
            .arg(&cfg)
            .stdout(Stdio::from(std::fs::File::create(dir.join("agent.out"))?))
            .stderr(Stdio::from(std::fs::File::create(dir.join("agent.log"))?))
            .spawn()
            .with_context(|| format!("starting {}", bin.display()))?;
        agents.push(child);
        let gt = match args.own_frames {
            true => gt.iter().map(|p| in_own_frame(p, &frame)).collect(),
            false => gt,
        };
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
            let mut robot = score(
                &out,
                r,
                &truths[r].1,
                fleet.scenario.robot_name(r),
                offsets[r],
            )?;
            if args.own_frames {
                robot.peer_frames = score_peer_frames(&out, r, &frames)?;
            }
            Ok(robot)
        })
        .collect::<Result<Vec<_>>>()?;
    print_table(&robots, args);
    let summary = serde_json::json!({
        "scenario": fleet.scenario.name,
        "seed": seed,
        "variant": args.variant,
        "speed": args.speed,
        "perturb_start": args.perturb_start,
        "own_frames": args.own_frames,
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
        peer_frames: None,
    })
}

/// Robot `r`'s alignments of its peers' frames (its `transport_stats.json`)
/// against the true ones: peer `q`'s frame in `r`'s is `p_r = R_z(ψ_q − ψ_r)
/// p_q + R_z(−ψ_r) (o_q − o_r)`, `(o, ψ)` each frame in the world. `None`
/// when its variant does not align frames (it works alone).
fn score_peer_frames(out: &Path, r: usize, frames: &[OwnFrame]) -> Result<Option<LivePeerFrames>> {
    let path = out.join(format!("robot{r}/transport_stats.json"));
    let stats: serde_json::Value = serde_json::from_slice(
        &std::fs::read(&path).with_context(|| format!("reading {}", path.display()))?,
    )
    .with_context(|| format!("parsing {}", path.display()))?;
    if stats["peer_frames"].is_null() {
        return Ok(None);
    }
    let mut out = LivePeerFrames {
        aligned: 0,
        peers_aligned: 0,
        peers: frames.len().saturating_sub(1),
        max_yaw_err_deg: None,
        max_pos_err_m: None,
    };
    let (o_r, psi_r) = frames[r];
    let alignment = |yaw_rad: f64, t_m: Vector3<f64>| FrameAlignment {
        yaw_rad,
        t_m,
        cov: nalgebra::Matrix4::zeros(),
    };
    for (q, &(o_q, psi_q)) in frames.iter().enumerate().filter(|(q, _)| *q != r) {
        let truth = alignment(psi_q - psi_r, rot_z(-psi_r) * (o_q - o_r));
        let list = stats["peer_frames"][q.to_string()].as_array().cloned();
        let mut found = false;
        for f in list.unwrap_or_default() {
            let (Some(yaw_deg), Some(t)) = (f["yaw_deg"].as_f64(), f["t_m"].as_array()) else {
                continue;
            };
            let t: Vec<f64> = t.iter().filter_map(serde_json::Value::as_f64).collect();
            let [x, y, z] = t[..] else { continue };
            let e = truth.difference(&alignment(yaw_deg.to_radians(), Vector3::new(x, y, z)));
            out.aligned += 1;
            found = true;
            let max = |m: Option<f64>, v: f64| Some(m.map_or(v, |m: f64| m.max(v)));
            out.max_yaw_err_deg = max(out.max_yaw_err_deg, e[0].abs().to_degrees());
            out.max_pos_err_m = max(out.max_pos_err_m, e.fixed_rows::<3>(1).norm());
        }
        out.peers_aligned += usize::from(found);
    }
    Ok(Some(out))
}

fn print_table(robots: &[LiveRobot], args: &LiveRunArgs) {
    let opt = |v: Option<f64>| v.map_or("-".to_owned(), |v| format!("{v:.2}"));
    println!(
        "{} at {}x real time, starts {}:",
        args.variant,
        args.speed,
        match (args.own_frames, args.perturb_start) {
            (true, _) => "each in a frame of its own",
            (false, true) => "moved from the truth by a draw of their sigma",
            (false, false) => "at the truth",
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
        if let Some(f) = &r.peer_frames {
            let opt3 = |v: Option<f64>| v.map_or("-".to_owned(), |v| format!("{v:.3}"));
            println!(
                "      peer frames: {} of {} peers aligned, at most {} deg and {} m off",
                f.peers_aligned,
                f.peers,
                opt3(f.max_yaw_err_deg),
                opt3(f.max_pos_err_m)
            );
        }
    }
    let n = robots.len().max(1) as f64;
    println!(
        "mean  ATE {:.3} deg / {:.4} m",
        robots.iter().map(|r| r.ate_ori_deg).sum::<f64>() / n,
        robots.iter().map(|r| r.ate_pos_m).sum::<f64>() / n
    );
}

#[cfg(test)]
mod tests {
    use super::*;

    fn mapping(yaml: &str) -> serde_yaml::Mapping {
        serde_yaml::from_str(yaml).unwrap()
    }

    const CONFIG: &str =
        "# Written by sim-fleet live-run.\nrobot_id: 0\nestimator:\n  variant: indp-slam\n";

    #[test]
    fn no_settings_leave_the_configuration_as_written() {
        assert_eq!(AgentSettings::default().apply(CONFIG).unwrap(), CONFIG);
    }

    #[test]
    fn settings_join_the_estimator_block_and_make_the_frontend_block() {
        let settings = AgentSettings {
            frontend: Some(mapping("first_patch: drop")),
            estimator: Some(mapping("variant: indp-slam\nup_msckf_sigma_px: 0.5")),
        };
        let text = settings.apply(CONFIG).unwrap();
        assert!(
            text.starts_with("# Written by sim-fleet live-run.\n"),
            "{text}"
        );
        let doc: serde_yaml::Value = serde_yaml::from_str(&text).unwrap();
        assert_eq!(doc["robot_id"].as_u64(), Some(0));
        assert_eq!(doc["estimator"]["variant"].as_str(), Some("indp-slam"));
        assert_eq!(doc["estimator"]["up_msckf_sigma_px"].as_f64(), Some(0.5));
        assert_eq!(
            doc["images"]["frontend"]["first_patch"].as_str(),
            Some("drop")
        );
    }

    #[test]
    fn a_setting_against_the_runs_own_is_refused_by_name() {
        let settings = AgentSettings {
            frontend: None,
            estimator: Some(mapping("variant: dc-full-history")),
        };
        let err = settings.apply(CONFIG).unwrap_err().to_string();
        assert_eq!(
            err,
            "--estimator sets `variant` to dc-full-history, but this run sets it to indp-slam"
        );
    }
}
