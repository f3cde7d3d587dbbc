//! `sim-fleet montecarlo`: one scenario over many seeds and estimator variants,
//! every robot run standalone ([`agent::runner::run_robot`]), in parallel, then
//! aggregated into means and spreads ([`aggregate`]) and a Markdown table
//! ([`table`]).
//!
//! A job is one (seed, variant, robot). Worker threads take jobs from a shared
//! queue (an atomic index into the job list, seed-major so that each seed's
//! [`Fleet`] is built once, shared by its robots and variants, and dropped
//! after its last job). Results are sorted by (variant, seed, robot) before they
//! are aggregated, so the aggregated accuracy and consistency metrics do not
//! depend on `--jobs` or on the scheduling (the timing metrics do, of course).
//!
//! An estimator error or panic fails that robot run only: it is recorded in
//! `failures`, counted as diverged, and the study goes on. Errors writing the
//! outputs stop the study.

pub mod aggregate;
mod fleet_job;
pub mod stats;
pub mod table;

use agent::frontend::FrontendOptions;
use agent::runner::{options_for, run_robot, Variant};
use aggregate::{aggregate_variant, RobotOutcome, RunFailure, StudySummary, DIVERGED_ATE_POS_M};
use common::summary::{MetricSet, RobotSummary, RunSummary, SummaryError};
use common::trajectory::{write_covariances, write_imu_states, write_tum, TrajectoryError};
use indicatif::{ProgressBar, ProgressStyle};
use simulator::scenario::ScenarioError;
use simulator::{Fleet, Scenario};
use std::any::Any;
use std::num::NonZeroUsize;
use std::panic::{catch_unwind, AssertUnwindSafe};
use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicBool, AtomicUsize, Ordering};
use std::sync::{Arc, Mutex, PoisonError};
use std::time::Instant;
use thiserror::Error;

/// Arguments of `sim-fleet montecarlo`.
#[derive(clap::Args, Debug, Clone)]
pub struct MontecarloArgs {
    /// Scenario file (YAML).
    pub scenario: PathBuf,
    /// Runs (seeds) per variant.
    #[arg(long, value_parser = clap::value_parser!(u64).range(1..))]
    pub runs: u64,
    /// Estimator variants, comma separated: indp (MSCKF only), indp-slam.
    #[arg(long, value_delimiter = ',', default_value = "indp,indp-slam")]
    pub variants: Vec<Variant>,
    /// First seed: the runs use seeds seed-start .. seed-start + runs - 1.
    #[arg(long, default_value_t = 1)]
    pub seed_start: u64,
    /// Parallel jobs (default: the available parallelism).
    #[arg(long)]
    pub jobs: Option<NonZeroUsize>,
    /// Output folder.
    #[arg(long)]
    pub out: PathBuf,
    /// A variant of the study to set the others against, seed by seed: the
    /// ratios of their means with 95 % intervals follow the table.
    #[arg(long)]
    pub baseline: Option<Variant>,
    /// What the cooperative variants' agents keep of their peers.
    #[command(flatten)]
    pub history: crate::fleet_run::HistoryArgs,
    /// A scenario that renders images (`render: {enabled: true}`): the image
    /// frontend's settings for every agent (YAML, the keys of
    /// an agent configuration's `images.frontend:` block) over the defaults.
    #[arg(long, value_name = "YAML")]
    pub frontend: Option<PathBuf>,
}

/// Why a Monte-Carlo study could not run or write its results.
#[derive(Debug, Error)]
pub enum MontecarloError {
    /// The scenario could not be loaded.
    #[error(transparent)]
    Scenario(#[from] ScenarioError),
    /// The arguments are inconsistent.
    #[error("{0}")]
    Args(String),
    /// A folder or file could not be created or written.
    #[error("cannot write {}", path.display())]
    Io {
        /// The path.
        path: PathBuf,
        /// The cause.
        #[source]
        source: std::io::Error,
    },
    /// A trajectory or covariance file could not be written.
    #[error(transparent)]
    Trajectory(#[from] TrajectoryError),
    /// A run summary could not be written.
    #[error(transparent)]
    Summary(#[from] SummaryError),
    /// The study summary could not be serialized.
    #[error("cannot serialize the study summary")]
    Json(#[from] serde_json::Error),
    /// A worker thread died outside of a job.
    #[error("a Monte-Carlo worker thread panicked")]
    WorkerPanicked,
    /// No robot run succeeded.
    #[error("all {count} robot runs failed; the first (variant {variant}, seed {seed}, robot {robot}): {error}")]
    AllFailed {
        /// Robot runs.
        count: usize,
        /// Variant of the first failure.
        variant: String,
        /// Its seed.
        seed: u64,
        /// Its robot.
        robot: u32,
        /// Its error.
        error: String,
    },
}

/// One unit of work: seed `seeds[seed]` with `variants[variant]`, for robot
/// `robot` standalone, or (`None`) the whole fleet at once (cooperative
/// variants: agents over the in-process transport in lockstep, or the
/// centralized estimator).
#[derive(Clone, Copy, Debug)]
struct Job {
    seed: usize,
    variant: usize,
    robot: Option<usize>,
}

/// What a job produced.
enum JobResult {
    /// The runs finished and their files are written.
    Done {
        /// Each robot's metrics.
        robots: Vec<(usize, MetricSet)>,
        /// Simulated seconds of the estimates.
        sim_s: f64,
    },
    /// The estimator (or the fleet of its seed) failed or panicked.
    Failed(String),
    /// The outputs could not be written: the study stops.
    Fatal(MontecarloError),
}

struct JobOutput {
    job: Job,
    result: JobResult,
    wall_s: f64,
}

/// A seed's fleet, built by the first job that needs it.
enum FleetState {
    Pending,
    Ready(Arc<Fleet>),
    Failed(String),
    Released,
}

struct SeedSlot {
    state: Mutex<FleetState>,
    /// Jobs of this seed not finished yet.
    remaining: AtomicUsize,
}

/// Everything the workers share.
struct Study<'a> {
    scenario: &'a Scenario,
    scenario_path: &'a Path,
    seeds: &'a [u64],
    variants: &'a [Variant],
    history: crate::fleet_run::HistoryArgs,
    /// The image frontend's settings, for a scenario that renders images.
    frontend: FrontendOptions,
    out: &'a Path,
    slots: Vec<SeedSlot>,
    abort: AtomicBool,
}

impl Study<'_> {
    fn seed_dir(&self, variant: usize, seed: usize) -> PathBuf {
        seed_dir(self.out, self.variants[variant], self.seeds[seed])
    }

    /// The fleet of seed index `i`, built on first use.
    fn fleet(&self, i: usize) -> Result<Arc<Fleet>, String> {
        let slot = &self.slots[i];
        let mut state = slot.state.lock().unwrap_or_else(PoisonError::into_inner);
        match &*state {
            FleetState::Ready(fleet) => Ok(Arc::clone(fleet)),
            FleetState::Failed(e) => Err(e.clone()),
            FleetState::Released => Err(format!(
                "internal error: fleet of seed {} released before its last job",
                self.seeds[i]
            )),
            FleetState::Pending => match Fleet::build(self.scenario, self.seeds[i]) {
                Ok(fleet) => {
                    let fleet = Arc::new(fleet);
                    *state = FleetState::Ready(Arc::clone(&fleet));
                    Ok(fleet)
                }
                Err(e) => {
                    let msg = format!("building the fleet of seed {}: {e}", self.seeds[i]);
                    *state = FleetState::Failed(msg.clone());
                    Err(msg)
                }
            },
        }
    }

    /// Marks one job of seed index `i` finished; the last one drops the fleet.
    fn release(&self, i: usize) {
        let slot = &self.slots[i];
        if slot.remaining.fetch_sub(1, Ordering::AcqRel) == 1 {
            *slot.state.lock().unwrap_or_else(PoisonError::into_inner) = FleetState::Released;
        }
    }

    fn run(&self, job: Job) -> JobOutput {
        let wall = Instant::now();
        let result = match catch_unwind(AssertUnwindSafe(|| self.run_inner(job))) {
            Ok(result) => result,
            Err(panic) => JobResult::Failed(format!("panicked: {}", panic_message(&*panic))),
        };
        self.release(job.seed);
        JobOutput {
            job,
            result,
            wall_s: wall.elapsed().as_secs_f64(),
        }
    }

    fn run_inner(&self, job: Job) -> JobResult {
        let Some(robot) = job.robot else {
            return self.run_fleet_job(job);
        };
        let fleet = match self.fleet(job.seed) {
            Ok(fleet) => fleet,
            Err(e) => return JobResult::Failed(e),
        };
        let variant = self.variants[job.variant];
        let opts = options_for(&fleet.scenario.estimator, &fleet, robot, variant);
        // Rendered images go through the image frontend; its tracks are
        // scored against the rendered truth.
        let ran = if fleet.renders() {
            agent::rendered_run::run(&fleet, robot, opts, self.frontend.clone())
                .map(|r| (r.run, r.track_error_mean_px, Some(r.track_errors_csv)))
        } else {
            run_robot(&fleet, robot, opts).map(|run| (run, None, None))
        };
        let (run, track_error_px, track_errors_csv) = match ran {
            Ok(ran) => ran,
            Err(e) => return JobResult::Failed(e.to_string()),
        };
        drop(fleet);
        if !run.rejected.is_empty() {
            tracing::debug!(
                variant = variant.name(),
                seed = self.seeds[job.seed],
                robot,
                "{} inputs rejected, the first: {}",
                run.rejected.len(),
                run.rejected.first().map_or("", String::as_str)
            );
        }
        let dir = self
            .seed_dir(job.variant, job.seed)
            .join(format!("robot{robot}"));
        let written = create_dir(&dir).and_then(|()| {
            write_tum(dir.join("estimate.txt"), &run.estimate)?;
            write_tum(dir.join("groundtruth.txt"), &run.truth)?;
            write_covariances(dir.join("covariance.txt"), &run.covariance)?;
            if !run.imu_states.is_empty() {
                write_imu_states(dir.join("imu_state.txt"), &run.imu_states)?;
            }
            if let Some(csv) = &track_errors_csv {
                let path = dir.join("track_errors.csv");
                std::fs::write(&path, csv)
                    .map_err(|source| MontecarloError::Io { path, source })?;
            }
            Ok(())
        });
        if let Err(e) = written {
            return JobResult::Fatal(e);
        }
        let sim_s = match (run.estimate.first(), run.estimate.last()) {
            (Some(a), Some(b)) => b.t - a.t,
            _ => 0.0,
        };
        let metrics = MetricSet {
            track_error_px,
            ..run.metrics()
        };
        JobResult::Done {
            robots: vec![(robot, metrics)],
            sim_s,
        }
    }

    /// A cooperative variant: the whole fleet of the seed at once.
    fn run_fleet_job(&self, job: Job) -> JobResult {
        let variant = self.variants[job.variant];
        let seed = self.seeds[job.seed];
        let dir = self.seed_dir(job.variant, job.seed);
        if let Err(e) = create_dir(&dir) {
            return JobResult::Fatal(e);
        }
        match fleet_job::run(
            self.scenario_path,
            self.scenario,
            seed,
            (variant, self.history),
            &self.frontend,
            &dir,
        ) {
            Ok((robots, sim_s)) => JobResult::Done { robots, sim_s },
            Err(e) => JobResult::Failed(e),
        }
    }
}

/// The band test of robot `id` over the runs of `variant` that wrote their
/// outputs (`DIR/anees/<variant>/robot<id>.csv` and `.svg`), one epoch per camera frame
/// (`frame_s`);
/// `None` when no run did, or (with a warning: the study's other results
/// stand) when their files cannot be read back.
fn anees_of(
    out: &Path,
    variant: Variant,
    seeds: &[u64],
    id: u32,
    frame_s: f64,
) -> Option<crate::anees::AneesSummary> {
    let dirs: Vec<PathBuf> = seeds
        .iter()
        .map(|&s| seed_dir(out, variant, s).join(format!("robot{id}")))
        .filter(|d| d.join("covariance.txt").is_file())
        .collect();
    if dirs.is_empty() {
        return None;
    }
    let warn = |e: &dyn std::fmt::Display| {
        tracing::warn!(variant = variant.name(), robot = id, "NEES band test: {e}");
    };
    let (summary, epochs) = crate::anees::study(&dirs, frame_s)
        .map_err(|e| warn(&e))
        .ok()?;
    let file = out
        .join("anees")
        .join(variant.name())
        .join(format!("robot{id}"));
    if let Err(e) = crate::anees::write_csv(&file.with_extension("csv"), &epochs) {
        warn(&e);
    }
    if let Err(e) =
        crate::plots::write_anees_plot(&file.with_extension("svg"), &epochs, summary.runs)
    {
        warn(&e);
    }
    Some(summary)
}

/// `DIR/runs/<variant>/seed<k>`.
/// The image frontend's settings of `frontend` (the defaults without it).
/// Refuses, before any run, what a scenario that renders images cannot do
/// here: a build without the image frontend (the agents of the cooperative
/// variants need it too), a centralized variant (no image frontend), or
/// frontend settings for a scenario that renders nothing.
fn check_rendering(
    scenario: &Scenario,
    variants: &[Variant],
    frontend: Option<&Path>,
) -> Result<FrontendOptions, MontecarloError> {
    if !scenario.render.enabled {
        return match frontend {
            Some(f) => Err(MontecarloError::Args(format!(
                "--frontend {} needs a scenario that renders images (render: {{enabled: true}})",
                f.display()
            ))),
            None => Ok(FrontendOptions::default()),
        };
    }
    let settings =
        agent::rendered_run::frontend_options(frontend).map_err(MontecarloError::Args)?;
    if let Some(v) = variants.iter().find(|v| v.centralized()) {
        return Err(MontecarloError::Args(format!(
            "{} has no image frontend and the scenario renders images (render.enabled)",
            v.name()
        )));
    }
    if !agent::rendered_run::AVAILABLE {
        return Err(MontecarloError::Args(
            agent::runner::RunError::NoImageFrontend.to_string(),
        ));
    }
    Ok(settings)
}

fn seed_dir(out: &Path, variant: Variant, seed: u64) -> PathBuf {
    out.join("runs")
        .join(variant.name())
        .join(format!("seed{seed}"))
}

fn create_dir(dir: &Path) -> Result<(), MontecarloError> {
    std::fs::create_dir_all(dir).map_err(|source| MontecarloError::Io {
        path: dir.to_path_buf(),
        source,
    })
}

fn panic_message(panic: &(dyn Any + Send)) -> String {
    if let Some(s) = panic.downcast_ref::<&str>() {
        (*s).to_string()
    } else if let Some(s) = panic.downcast_ref::<String>() {
        s.clone()
    } else {
        "unknown panic payload".to_string()
    }
}

/// The seeds `start .. start + runs - 1`.
fn seed_range(start: u64, runs: u64) -> Result<Vec<u64>, MontecarloError> {
    let end = start.checked_add(runs).ok_or_else(|| {
        MontecarloError::Args(format!("seeds {start} + {runs} runs overflow u64"))
    })?;
    Ok((start..end).collect())
}

/// Runs every job on up to `threads` workers; the outputs in any order.
fn run_jobs(
    study: &Study,
    jobs: &[Job],
    threads: usize,
    bar: &ProgressBar,
) -> Result<Vec<JobOutput>, MontecarloError> {
    let next = AtomicUsize::new(0);
    let per_worker: Vec<std::thread::Result<Vec<JobOutput>>> = std::thread::scope(|s| {
        let handles: Vec<_> = (0..threads)
            .map(|_| {
                s.spawn(|| {
                    let mut outputs = Vec::new();
                    while !study.abort.load(Ordering::Relaxed) {
                        let Some(&job) = jobs.get(next.fetch_add(1, Ordering::Relaxed)) else {
                            break;
                        };
                        let output = study.run(job);
                        match &output.result {
                            JobResult::Done { .. } => {}
                            JobResult::Failed(e) => bar.suspend(|| {
                                tracing::warn!(
                                    variant = study.variants[job.variant].name(),
                                    seed = study.seeds[job.seed],
                                    robot = ?job.robot,
                                    "run failed: {e}"
                                )
                            }),
                            JobResult::Fatal(_) => study.abort.store(true, Ordering::Relaxed),
                        }
                        outputs.push(output);
                        bar.inc(1);
                    }
                    outputs
                })
            })
            .collect();
        handles.into_iter().map(|h| h.join()).collect()
    });
    let mut outputs = Vec::with_capacity(jobs.len());
    for worker in per_worker {
        outputs.extend(worker.map_err(|_| MontecarloError::WorkerPanicked)?);
    }
    Ok(outputs)
}

fn progress_bar(len: usize) -> ProgressBar {
    let bar = ProgressBar::new(len as u64);
    if let Ok(style) = ProgressStyle::with_template(
        "{elapsed_precise} [{wide_bar}] {pos}/{len} robot runs, ETA {eta}",
    ) {
        bar.set_style(style.progress_chars("=> "));
    }
    bar
}

/// Runs the study of `args`; returns its summary (also written to
/// `DIR/summary.json`) and its table (`DIR/table.md`, followed by the ratios
/// to the baseline with `--baseline`, which also writes `DIR/baseline.json`).
pub fn montecarlo(args: &MontecarloArgs) -> Result<(StudySummary, String), MontecarloError> {
    let wall = Instant::now();
    let scenario = Scenario::load(&args.scenario)?;
    let seeds = seed_range(args.seed_start, args.runs)?;
    let variants = &args.variants;
    if variants.is_empty() {
        return Err(MontecarloError::Args("no variant given".into()));
    }
    for (i, v) in variants.iter().enumerate() {
        if variants[..i].contains(v) {
            return Err(MontecarloError::Args(format!(
                "variant {} is listed twice",
                v.name()
            )));
        }
    }
    if let Some(b) = args.baseline.filter(|b| !variants.contains(b)) {
        return Err(MontecarloError::Args(format!(
            "the baseline {} is not one of the study's variants",
            b.name()
        )));
    }
    let frontend = check_rendering(&scenario, variants, args.frontend.as_deref())?;
    let robots = scenario.robots.len();
    let jobs: Vec<Job> = (0..seeds.len())
        .flat_map(|seed| {
            variants.iter().enumerate().flat_map(move |(variant, v)| {
                let per_robot: Vec<Option<usize>> = if v.cooperative() {
                    vec![None]
                } else {
                    (0..robots).map(Some).collect()
                };
                per_robot.into_iter().map(move |robot| Job {
                    seed,
                    variant,
                    robot,
                })
            })
        })
        .collect();
    let jobs_per_seed = jobs.len() / seeds.len().max(1);
    let threads = args
        .jobs
        .or_else(|| std::thread::available_parallelism().ok())
        .map_or(1, NonZeroUsize::get)
        .min(jobs.len())
        .max(1);
    create_dir(&args.out)?;
    tracing::info!(
        scenario = %scenario.name,
        runs = seeds.len(),
        variants = ?variants.iter().map(|v| v.name()).collect::<Vec<_>>(),
        robots,
        threads,
        "{} robot runs",
        jobs.len()
    );
    let study = Study {
        scenario: &scenario,
        scenario_path: &args.scenario,
        seeds: &seeds,
        variants,
        history: args.history,
        frontend,
        out: &args.out,
        slots: seeds
            .iter()
            .map(|_| SeedSlot {
                state: Mutex::new(FleetState::Pending),
                remaining: AtomicUsize::new(jobs_per_seed),
            })
            .collect(),
        abort: AtomicBool::new(false),
    };
    let bar = progress_bar(jobs.len());
    let robot_runs: usize = seeds.len() * variants.len() * robots;
    let outputs = run_jobs(&study, &jobs, threads, &bar);
    bar.finish_and_clear();
    let mut outputs = outputs?;
    outputs.sort_by_key(|o| (o.job.variant, o.job.seed, o.job.robot));
    if let Some(pos) = outputs
        .iter()
        .position(|o| matches!(o.result, JobResult::Fatal(_)))
    {
        if let JobResult::Fatal(e) = outputs.swap_remove(pos).result {
            return Err(e);
        }
    }

    let robot_ids: Vec<(u32, String)> = (0..robots)
        .map(|r| (r as u32, scenario.robot_name(r)))
        .collect();
    let mut failures = Vec::new();
    let mut aggregates = Vec::with_capacity(variants.len());
    // The band test's epoch: one camera frame.
    let frame_s = 1.0 / scenario.sensors.camera.rate_hz;
    for (vi, variant) in variants.iter().enumerate() {
        let mut runs = Vec::with_capacity(seeds.len());
        for (si, &seed) in seeds.iter().enumerate() {
            let of_run: Vec<&JobOutput> = outputs
                .iter()
                .filter(|o| (o.job.variant, o.job.seed) == (vi, si))
                .collect();
            let mut summary = RunSummary {
                scenario: scenario.name.clone(),
                variant: Some(variant.name().to_string()),
                seed,
                transport: None,
                wall_s: Some(of_run.iter().map(|o| o.wall_s).sum()),
                sim_s: None,
                robots: Vec::with_capacity(robots),
                mean: MetricSet::default(),
            };
            let mut outcomes = Vec::with_capacity(robots);
            for o in of_run {
                let produced: Vec<(usize, RobotOutcome)> = match &o.result {
                    JobResult::Done {
                        robots: list,
                        sim_s,
                    } => {
                        summary.sim_s = Some(summary.sim_s.unwrap_or(0.0).max(*sim_s));
                        list.iter()
                            .map(|(r, m)| {
                                (
                                    *r,
                                    RobotOutcome {
                                        metrics: m.clone(),
                                        error: None,
                                    },
                                )
                            })
                            .collect()
                    }
                    JobResult::Failed(error) => {
                        let failed: Vec<usize> = match o.job.robot {
                            Some(r) => vec![r],
                            None => (0..robots).collect(),
                        };
                        failed
                            .into_iter()
                            .map(|r| {
                                failures.push(RunFailure {
                                    variant: variant.name().to_string(),
                                    seed,
                                    robot: r as u32,
                                    error: error.clone(),
                                });
                                (
                                    r,
                                    RobotOutcome {
                                        metrics: MetricSet::default(),
                                        error: Some(error.clone()),
                                    },
                                )
                            })
                            .collect()
                    }
                    // Returned above; never aggregated.
                    JobResult::Fatal(_) => Vec::new(),
                };
                for (r, outcome) in produced {
                    summary.robots.push(RobotSummary {
                        id: r as u32,
                        trajectory: scenario.robot_name(r),
                        metrics: outcome.metrics.clone(),
                    });
                    outcomes.push(outcome);
                }
            }
            let metrics: Vec<MetricSet> =
                summary.robots.iter().map(|r| r.metrics.clone()).collect();
            summary.mean = MetricSet::mean_of(&metrics);
            let dir = seed_dir(&args.out, *variant, seed);
            create_dir(&dir)?;
            summary.write_json(dir.join("summary.json"))?;
            runs.push(outcomes);
        }
        let mut aggregate = aggregate_variant(&robot_ids, &runs);
        for robot in &mut aggregate.robots {
            robot.anees = anees_of(&args.out, *variant, &seeds, robot.id, frame_s);
        }
        aggregates.push((variant.name().to_string(), aggregate));
    }
    if failures.len() == robot_runs {
        if let Some(first) = failures.first() {
            return Err(MontecarloError::AllFailed {
                count: robot_runs,
                variant: first.variant.clone(),
                seed: first.seed,
                robot: first.robot,
                error: first.error.clone(),
            });
        }
    }
    let study = StudySummary {
        scenario: scenario.name.clone(),
        runs: seeds.len(),
        seeds,
        diverged_ate_pos_m: DIVERGED_ATE_POS_M,
        wall_s: Some(wall.elapsed().as_secs_f64()),
        variants: aggregates,
        failures,
    };
    let path = args.out.join("summary.json");
    let text = serde_json::to_string_pretty(&study)?;
    std::fs::write(&path, text + "\n").map_err(|source| MontecarloError::Io { path, source })?;
    let mut table = table::render_table(&study);
    if let Some(b) = &args.baseline {
        let comparison = crate::paired::against_baseline(&study, b.name())
            .map_err(|e| MontecarloError::Args(e.to_string()))?;
        table.push_str(&comparison.render());
        let path = args.out.join("baseline.json");
        let text = serde_json::to_string_pretty(&comparison)?;
        std::fs::write(&path, text + "\n")
            .map_err(|source| MontecarloError::Io { path, source })?;
    }
    let path = args.out.join("table.md");
    std::fs::write(&path, &table).map_err(|source| MontecarloError::Io { path, source })?;
    Ok((study, table))
}

/// Runs `sim-fleet montecarlo`: the study, then the table on stdout.
pub fn run_montecarlo(args: &MontecarloArgs) -> anyhow::Result<()> {
    let (study, table) = montecarlo(args)?;
    print!("{table}");
    if !study.failures.is_empty() {
        tracing::warn!(
            "{} robot runs failed (listed under `failures` in {})",
            study.failures.len(),
            args.out.join("summary.json").display()
        );
    }
    println!(
        "outputs in {} ({:.1} s)",
        args.out.display(),
        study.wall_s.unwrap_or(0.0)
    );
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_seeds_run_from_the_start_seed_and_an_overflowing_range_is_an_error() {
        assert_eq!(seed_range(1, 3).unwrap(), vec![1, 2, 3]);
        assert_eq!(seed_range(7, 1).unwrap(), vec![7]);
        assert!(matches!(
            seed_range(u64::MAX, 2),
            Err(MontecarloError::Args(_))
        ));
    }

    #[test]
    fn a_panic_message_is_recovered_from_str_and_string_payloads() {
        let from_str = catch_unwind(|| panic!("static")).unwrap_err();
        assert_eq!(panic_message(&*from_str), "static");
        let from_string = catch_unwind(|| panic!("seed {}", 3)).unwrap_err();
        assert_eq!(panic_message(&*from_string), "seed 3");
        let other = catch_unwind(|| std::panic::panic_any(42_u8)).unwrap_err();
        assert_eq!(panic_message(&*other), "unknown panic payload");
    }

    #[test]
    fn the_run_folders_are_named_by_variant_and_seed() {
        assert_eq!(
            seed_dir(Path::new("mc"), Variant::IndpSlam, 12),
            Path::new("mc/runs/indp-slam/seed12")
        );
    }
}
