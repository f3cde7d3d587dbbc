//! `sim-fleet simulate`: every robot's measurements to MCAP, its ground truth to
//! TUM, simulator statistics, and a `summary.json` (estimator fields stay `null`).

use anyhow::{Context, Result};
use common::summary::{MetricSet, RobotSummary, RunSummary};
use common::trajectory::{write_tum, StampedPose};
use simulator::{Fleet, Scenario, SimEvent};
use std::collections::HashMap;
use std::path::{Path, PathBuf};
use std::time::Instant;

/// Arguments of `sim-fleet simulate`.
#[derive(clap::Args, Debug)]
pub struct SimulateArgs {
    /// Scenario file (YAML).
    pub scenario: PathBuf,
    /// Seed of every random draw (default: the scenario's).
    #[arg(long)]
    pub seed: Option<u64>,
    /// Output folder.
    #[arg(long, default_value = "out/simulate")]
    pub out: PathBuf,
    /// Skip writing the MCAP measurement files (statistics and ground truth only).
    #[arg(long)]
    pub no_mcap: bool,
}

/// What one robot's stream contained.
#[derive(Debug, Default, Clone)]
pub struct StreamStats {
    /// IMU samples.
    pub imu_samples: u64,
    /// Camera frames.
    pub frames: u64,
    /// Mean features per frame.
    pub features_per_frame: f64,
    /// Mean length of finished tracks, in frames.
    pub mean_track_length: f64,
    /// Simulated seconds (first to last IMU sample).
    pub sim_s: f64,
    /// Ground truth at each camera frame.
    pub truth: Vec<StampedPose>,
}

/// Gathers [`StreamStats`] from events as they pass.
#[derive(Debug, Default)]
pub struct StatsCollector {
    stats: StreamStats,
    t_first: Option<f64>,
    t_last: f64,
    features: u64,
    open: HashMap<u64, u64>,
    finished: u64,
    finished_len: u64,
}

impl StatsCollector {
    /// Accounts for one event.
    pub fn observe(&mut self, ev: &SimEvent) {
        match ev {
            SimEvent::Imu(imu) => {
                self.stats.imu_samples += 1;
                self.t_first.get_or_insert(imu.t);
                self.t_last = imu.t;
            }
            SimEvent::Camera(c) => {
                self.stats.frames += 1;
                self.features += c.frame.features.len() as u64;
                let mut next = HashMap::with_capacity(c.frame.features.len());
                for f in &c.frame.features {
                    next.insert(f.id, self.open.get(&f.id).copied().unwrap_or(0) + 1);
                }
                for (id, len) in &self.open {
                    if !next.contains_key(id) {
                        self.finished += 1;
                        self.finished_len += len;
                    }
                }
                self.open = next;
                self.stats.truth.push(StampedPose {
                    t: c.truth.t,
                    rot: c.truth.rot,
                    pos: c.truth.pos,
                });
            }
        }
    }

    /// The statistics of everything observed (open tracks count as finished).
    pub fn finish(mut self) -> StreamStats {
        let finished = self.finished + self.open.len() as u64;
        let finished_len = self.finished_len + self.open.values().sum::<u64>();
        let s = &mut self.stats;
        s.features_per_frame = self.features as f64 / s.frames.max(1) as f64;
        s.mean_track_length = finished_len as f64 / finished.max(1) as f64;
        s.sim_s = self.t_last - self.t_first.unwrap_or(self.t_last);
        self.stats
    }
}

fn simulate_robot(fleet: &Fleet, robot: usize, dir: &Path, mcap: bool) -> Result<StreamStats> {
    std::fs::create_dir_all(dir).with_context(|| format!("creating {}", dir.display()))?;
    let mut collector = StatsCollector::default();
    let events = fleet.stream(robot)?.inspect(|e| collector.observe(e));
    if mcap {
        simulator::mcap_io::write_stream(&dir.join("measurements.mcap"), events)?;
    } else {
        events.for_each(drop);
    }
    let stats = collector.finish();
    write_tum(dir.join("groundtruth.txt"), &stats.truth)?;
    Ok(stats)
}

/// Runs `sim-fleet simulate`.
pub fn run_simulate(args: &SimulateArgs) -> Result<()> {
    let wall = Instant::now();
    let scenario = Scenario::load(&args.scenario)?;
    let seed = args.seed.unwrap_or(scenario.seed);
    let fleet = Fleet::build(&scenario, seed)?;
    tracing::info!(
        scenario = %scenario.name,
        seed,
        robots = fleet.robot_count(),
        landmarks = fleet.world.landmarks.len(),
        "world built in {:.2} s",
        wall.elapsed().as_secs_f64()
    );
    let results: Vec<Result<StreamStats>> = std::thread::scope(|s| {
        let handles: Vec<_> = (0..fleet.robot_count())
            .map(|r| {
                let dir = args.out.join(format!("robot{r}"));
                let fleet = &fleet;
                s.spawn(move || simulate_robot(fleet, r, &dir, !args.no_mcap))
            })
            .collect();
        handles
            .into_iter()
            .map(|h| {
                h.join()
                    .unwrap_or_else(|_| Err(anyhow::anyhow!("simulation thread panicked")))
            })
            .collect()
    });
    let mut robots = Vec::new();
    let mut sim_s: f64 = 0.0;
    for (r, res) in results.into_iter().enumerate() {
        let st = res.with_context(|| format!("robot {r}"))?;
        println!(
            "robot {r} ({}): {:.1} s simulated, {} IMU samples, {} frames, {:.1} features/frame, mean track {:.1} frames",
            scenario.robot_name(r),
            st.sim_s,
            st.imu_samples,
            st.frames,
            st.features_per_frame,
            st.mean_track_length
        );
        sim_s = sim_s.max(st.sim_s);
        robots.push(RobotSummary {
            id: r as u32,
            trajectory: scenario.robot_name(r),
            metrics: MetricSet {
                frames: Some(st.frames),
                ..MetricSet::default()
            },
        });
    }
    let metrics: Vec<MetricSet> = robots.iter().map(|r| r.metrics.clone()).collect();
    let summary = RunSummary {
        scenario: scenario.name.clone(),
        variant: None,
        seed,
        transport: None,
        wall_s: Some(wall.elapsed().as_secs_f64()),
        sim_s: Some(sim_s),
        mean: MetricSet::mean_of(&metrics),
        robots,
    };
    std::fs::create_dir_all(&args.out)?;
    let path = args.out.join("summary.json");
    summary.write_json(&path)?;
    println!(
        "{} landmarks in the shared world; outputs in {} ({:.2} s)",
        fleet.world.landmarks.len(),
        args.out.display(),
        wall.elapsed().as_secs_f64()
    );
    Ok(())
}
