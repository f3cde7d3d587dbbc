//! `agent dataset`: a real sequence through the frontend and the estimator,
//! with the outputs of every agent run (TUM trajectories for `sim-fleet eval`
//! and `evo`, covariances, `timing.csv`, `summary.json`) and the MCAP log.

use crate::agent_log::AgentLog;
use crate::config::EstimatorSection;
use crate::dataset::sensor_yaml::ImuNoiseSpec;
use crate::dataset::EurocDataset;
use crate::dataset_run::{
    run_stream, score, DatasetRecord, DatasetRun, DatasetScore, StreamSensors,
};
use crate::estimator::static_init::StaticInitOptions;
use crate::estimator::EstimatorOptions;
use crate::frontend::FrontendOptions;
use crate::run_files::{set_aside_unfinished, RunFiles, FLUSH_PERIOD};
use crate::runner::Variant;
use anyhow::{anyhow, bail, Context, Result};
use common::summary::{MetricSet, RobotSummary, RunSummary};
use common::trajectory::StampedPose;
use std::path::{Path, PathBuf};
use std::time::Instant;

/// Arguments of `agent dataset`.
#[derive(clap::Args, Debug)]
pub struct DatasetArgs {
    /// The sequence folder (holding `mav0`, or `mav0` itself).
    #[arg(long)]
    pub euroc: PathBuf,
    /// Ground truth (EuRoC CSV) to score against, if not the sequence's own.
    #[arg(long)]
    pub groundtruth: Option<PathBuf>,
    /// Output folder.
    #[arg(long, default_value = "out/dataset")]
    pub out: PathBuf,
    /// Log every this many images (with their tracks) to `agent.mcap`.
    #[arg(long, default_value_t = 5)]
    pub mcap_image_every: usize,
    /// Estimator settings (YAML): the keys of an agent configuration's
    /// `estimator:` block (`variant: indp | indp-slam`, `max_clones`,
    /// `try_zupt`, `zupt_max_disparity_px`, ...), over the defaults and the
    /// IMU noise of `imu0/sensor.yaml`.
    #[arg(long, value_name = "YAML")]
    pub estimator: Option<PathBuf>,
    /// Image frontend settings (YAML): the keys of an agent configuration's
    /// `images.frontend:` block (`num_features`, `histogram: none | equalize
    /// | clahe`, `klt_window_px`, ...), over the defaults.
    #[arg(long, value_name = "YAML")]
    pub frontend: Option<PathBuf>,
}

/// A YAML file with the keys of one block of an agent configuration
/// (`block`, named in the error when it does not parse).
fn read_block<T: serde::de::DeserializeOwned>(path: &Path, block: &str) -> Result<T> {
    let text =
        std::fs::read_to_string(path).with_context(|| format!("reading {}", path.display()))?;
    serde_yaml::from_str(&text)
        .with_context(|| format!("{}: not an `{block}:` block", path.display()))
}

/// The image frontend's options: the defaults, or those of `frontend` (a
/// file with the keys of an agent configuration's `images.frontend:` block;
/// an unknown key or a value out of range is an error naming it).
pub fn frontend_options(frontend: Option<&Path>) -> Result<FrontendOptions> {
    crate::rendered_run::frontend_options(frontend).map_err(|e| anyhow!(e))
}

/// The estimator's options for a sequence and its variant: the defaults for
/// tracked images (EuRoC's IMU datasheet, SLAM updates at 2 px), the IMU
/// noise of `imu0/sensor.yaml` when it gives one, then the overrides of
/// `estimator` (a file with the keys of an agent configuration's
/// `estimator:` block).
pub fn dataset_options(
    imu_noise: Option<ImuNoiseSpec>,
    estimator: Option<&Path>,
) -> Result<(EstimatorOptions, Variant)> {
    let mut o = EstimatorOptions::for_tracked_images();
    if let Some(n) = imu_noise {
        n.apply(&mut o);
    }
    let mut variant = Variant::IndpSlam;
    if let Some(path) = estimator {
        let section: EstimatorSection = read_block(path, "estimator")?;
        variant = section.variant.parse()?;
        if variant.cooperative() || variant.centralized() {
            bail!(
                "{}: variant `{}` needs peers; one sequence runs `indp` or `indp-slam`",
                path.display(),
                variant.name()
            );
        }
        variant.apply(&mut o);
        section.apply(&mut o);
    }
    o.validate()
        .map_err(|e| anyhow!("estimator settings: {e}"))?;
    Ok((o, variant))
}

/// Runs the command ([`StreamRun::run`] over the sequence).
pub fn run_dataset_command(args: &DatasetArgs) -> Result<()> {
    let wall = Instant::now();
    let ds = EurocDataset::open(&args.euroc, args.groundtruth.as_deref())
        .with_context(|| format!("opening {}", args.euroc.display()))?;
    let (opts, variant) = dataset_options(ds.imu_noise, args.estimator.as_deref())?;
    let frontend = frontend_options(args.frontend.as_deref())?;
    tracing::info!(
        "{}: IMU noise {} {:?}",
        variant.name(),
        if ds.imu_noise.is_some() {
            "of imu0/sensor.yaml"
        } else {
            "by default (EuRoC's)"
        },
        opts.imu
    );
    let sensors = StreamSensors {
        calibration: &ds.calibration,
        groundtruth: ds.groundtruth.as_deref(),
    };
    let run = StreamRun {
        out: &args.out,
        name: sequence_name(&ds.root),
        sensors,
        opts,
        variant,
        frontend,
        mcap_image_every: args.mcap_image_every,
        wall,
    };
    run.run(ds.events(), |_| {})?;
    Ok(())
}

/// One stream of real sensor data through the frontend and the estimator,
/// with the outputs of every agent run: `agent dataset` and `agent live`.
pub struct StreamRun<'a> {
    /// Output folder.
    pub out: &'a Path,
    /// The run's name in `summary.json`.
    pub name: String,
    /// The camera and the ground truth, if known.
    pub sensors: StreamSensors<'a>,
    /// Estimator settings.
    pub opts: EstimatorOptions,
    /// Estimator variant (`indp` or `indp-slam`).
    pub variant: Variant,
    /// Image frontend settings.
    pub frontend: FrontendOptions,
    /// Log every this many images (with their tracks) to `agent.mcap`.
    pub mcap_image_every: usize,
    /// When the command started.
    pub wall: Instant,
}

impl StreamRun<'_> {
    /// Runs `events`: writes `estimate.txt`, `covariance.txt`, `timing.csv`
    /// and, when the ground truth is known, `groundtruth.txt` as the stream
    /// goes (a run killed keeps what it estimated), then `agent.mcap` and
    /// `summary.json`, and prints the frontend's, the start's and the
    /// estimate's figures. `on_estimate` sees the record after each new
    /// estimate (to publish it).
    pub fn run<E: std::fmt::Display>(
        self,
        events: impl Iterator<Item = Result<simulator::SimEvent, E>>,
        mut on_estimate: impl FnMut(&DatasetRecord),
    ) -> Result<DatasetScore> {
        let out = self.out;
        std::fs::create_dir_all(out).with_context(|| format!("creating {}", out.display()))?;
        if let Some(aside) =
            set_aside_unfinished(out).with_context(|| format!("readying {}", out.display()))?
        {
            tracing::warn!(
                "an earlier run here did not finish: its files are kept in {}",
                aside.display()
            );
        }
        let has_truth = self.sensors.groundtruth.is_some();
        let mut log = AgentLog::create(&out.join("agent.mcap"))?;
        let mut files = RunFiles::create(out, has_truth, FLUSH_PERIOD)
            .with_context(|| format!("writing {}", out.display()))?;
        let every = self.mcap_image_every.max(1);
        let mut k = 0usize;
        let run = run_stream(
            &self.sensors,
            events,
            self.opts,
            self.frontend,
            &StaticInitOptions::default(),
            |c, fo| {
                if k % every == 0 {
                    if let Some(img) = &c.image {
                        let _ = log.image(c.frame.t, img);
                        let _ = log.tracks(&fo.frame, &fo.new_ids);
                    }
                }
                k += 1;
            },
            |record| {
                files.append(record);
                on_estimate(record);
            },
        )?;
        if run.frontend.images == 0 {
            if let Some(first) = run.skipped_images.first() {
                bail!(
                    "none of the {} images could be used; the first: {first}",
                    run.skipped_images.len()
                );
            }
        }
        let rec = &run.record;
        files
            .finish(rec)
            .with_context(|| format!("writing {}", out.display()))?;
        let truth: Vec<StampedPose> = rec.truth.iter().flatten().copied().collect();
        log.run_poses(&rec.estimate, &rec.covariance, &rec.twists, &truth, &[])?;
        log.finish()?;

        let s = score(&run, self.sensors.groundtruth);
        print_figures(&run, &s, truth.len());
        let metrics = rec.metrics();
        let sim_s =
            rec.estimate.last().map_or(0.0, |p| p.t) - rec.estimate.first().map_or(0.0, |p| p.t);
        let summary = RunSummary {
            scenario: self.name.clone(),
            variant: Some(self.variant.name().into()),
            seed: 0,
            transport: None,
            wall_s: Some(self.wall.elapsed().as_secs_f64()),
            sim_s: Some(sim_s),
            mean: MetricSet::mean_of(std::slice::from_ref(&metrics)),
            robots: vec![RobotSummary {
                id: 0,
                trajectory: self.name,
                metrics,
            }],
        };
        summary.write_json(out.join("summary.json"))?;
        Ok(s)
    }
}

/// Prints what the frontend, the start and the estimator did.
fn print_figures(run: &DatasetRun, s: &DatasetScore, truth_rows: usize) {
    let rec = &run.record;
    if let Some(first) = run.skipped_images.first() {
        println!(
            "{} images could not be used and were skipped (their frames are lost); the first: {first}",
            run.skipped_images.len()
        );
    }
    println!(
        "{} images: {:.0} features/image (min {}), {} tracks from the first image to the last, mean track {:.1} images, frontend {:.2} ms/image",
        s.images,
        s.features_per_image,
        s.min_features,
        s.tracks_first_to_last,
        s.mean_track_length,
        run.frontend.ms / s.images.max(1) as f64
    );
    match &run.init {
        Some(i) => println!(
            "static start at t={:.3}: tilt error vs ground truth {} deg; last estimate {} deg; {} estimates",
            i.t,
            s.init_tilt_error_deg.map_or("n/a".into(), |e| format!("{e:.3}")),
            s.final_tilt_error_deg.map_or("n/a".into(), |e| format!("{e:.3}")),
            s.estimates
        ),
        None => println!("the static initializer never succeeded (the platform must stand still at the start)"),
    }
    let metrics = rec.metrics();
    let f = |v: Option<f64>, digits: usize| v.map_or("n/a".into(), |v| format!("{v:.digits$}"));
    println!(
        "estimator: {:.2} ms/frame (p95 {}), {} frames standing still; against the truth put on the first estimate: ATE {} deg / {} m, NEES ori {} pos {}; position-and-yaw aligned: ATE {} deg / {} m ({} of {} estimates covered)",
        metrics.ms_per_frame_mean.unwrap_or(0.0),
        f(metrics.ms_per_frame_p95, 2),
        rec.frames.iter().filter(|f| f.zero_velocity).count(),
        f(metrics.ate_ori_deg, 3),
        f(metrics.ate_pos_m, 3),
        f(metrics.nees_ori, 2),
        f(metrics.nees_pos, 2),
        f(metrics.ate_posyaw_ori_deg, 3),
        f(metrics.ate_posyaw_pos_m, 3),
        truth_rows,
        rec.estimate.len()
    );
    for r in run.rejected.iter().take(5) {
        tracing::warn!("rejected: {r}");
    }
}

/// The sequence's name: the folder holding `mav0` (`V1_01_easy`).
fn sequence_name(mav0: &std::path::Path) -> String {
    let named = if mav0.file_name().is_some_and(|n| n == "mav0") {
        mav0.parent().unwrap_or(mav0)
    } else {
        mav0
    };
    named
        .file_name()
        .map_or_else(|| "dataset".into(), |n| n.to_string_lossy().into_owned())
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::frontend::Histogram;

    #[test]
    fn a_frontend_file_overrides_the_defaults_and_a_bad_one_is_refused_by_name() {
        assert_eq!(
            frontend_options(None).ok(),
            Some(FrontendOptions::default())
        );
        let dir = tempfile::tempdir().expect("tempdir");
        let yaml = dir.path().join("frontend.yaml");
        std::fs::write(&yaml, "histogram: none\nnum_features: 150\n").expect("write");
        let o = frontend_options(Some(&yaml)).expect("options");
        assert_eq!((o.histogram, o.num_features), (Histogram::None, 150));
        assert_eq!(o.klt_window_px, FrontendOptions::default().klt_window_px);
        std::fs::write(&yaml, "num_feature: 150\n").expect("write");
        let e = format!(
            "{:#}",
            frontend_options(Some(&yaml)).expect_err("unknown key")
        );
        assert!(e.contains("num_feature"), "{e}");
        std::fs::write(&yaml, "klt_window_px: 16\n").expect("write");
        let e = format!(
            "{:#}",
            frontend_options(Some(&yaml)).expect_err("even window")
        );
        assert!(e.contains("klt_window_px"), "{e}");
    }
}
