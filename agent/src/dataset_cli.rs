//! `agent dataset`: a real sequence through the frontend and the estimator,
//! with TUM outputs (for `sim-fleet eval` and `evo`) and the MCAP log.

use crate::agent_log::AgentLog;
use crate::dataset::EurocDataset;
use crate::dataset_run::{run_dataset, score};
use crate::estimator::static_init::StaticInitOptions;
use crate::estimator::EstimatorOptions;
use crate::frontend::FrontendOptions;
use anyhow::{Context, Result};
use common::trajectory::{interpolate_pose, write_covariances, write_tum, StampedPose};
use std::path::PathBuf;

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
}

/// Runs the command: prints the frontend's and the start's figures and writes
/// `estimate.txt`, `covariance.txt`, `groundtruth.txt` (when known) and
/// `agent.mcap` into the output folder.
pub fn run_dataset_command(args: &DatasetArgs) -> Result<()> {
    let ds = EurocDataset::open(&args.euroc, args.groundtruth.as_deref())
        .with_context(|| format!("opening {}", args.euroc.display()))?;
    std::fs::create_dir_all(&args.out)
        .with_context(|| format!("creating {}", args.out.display()))?;
    let mut log = AgentLog::create(&args.out.join("agent.mcap"))?;
    let every = args.mcap_image_every.max(1);
    let mut k = 0usize;
    let run = run_dataset(
        &ds,
        EstimatorOptions::default(),
        FrontendOptions::default(),
        &StaticInitOptions::default(),
        |c, out| {
            if k % every == 0 {
                if let Some(img) = &c.image {
                    let _ = log.image(c.frame.t, img);
                    let _ = log.tracks(&out.frame, &out.new_ids);
                }
            }
            k += 1;
        },
    )?;
    // The truth at the estimate times, in the ground truth's own frame (the
    // estimate is in the static start's frame: align before comparing).
    let truth: Vec<StampedPose> = match &ds.groundtruth {
        Some(gt) => run
            .estimate
            .iter()
            .filter_map(|p| interpolate_pose(gt, p.t))
            .collect(),
        None => Vec::new(),
    };
    log.run_poses(&run.estimate, &run.covariance, &[])?;
    log.finish()?;
    write_tum(args.out.join("estimate.txt"), &run.estimate)?;
    write_covariances(args.out.join("covariance.txt"), &run.covariance)?;
    if !truth.is_empty() {
        write_tum(args.out.join("groundtruth.txt"), &truth)?;
    }
    let s = score(&run, &ds);
    let ms: f64 = run.frames.iter().map(|f| f.stats.ms).sum::<f64>() / s.images.max(1) as f64;
    println!(
        "{} images: {:.0} features/image (min {}), {} tracks from the first image to the last, mean track {:.1} images, {:.2} ms/image",
        s.images, s.features_per_image, s.min_features, s.tracks_first_to_last, s.mean_track_length, ms
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
    for r in run.rejected.iter().take(5) {
        tracing::warn!("rejected: {r}");
    }
    Ok(())
}
