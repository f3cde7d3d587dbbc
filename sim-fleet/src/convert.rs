//! `sim-fleet convert-euroc`: a sequence in the EuRoC ASL layout (EuRoC MAV,
//! TUM-VI) to one MCAP file in the layout `sim-fleet simulate` writes: `/imu`,
//! `/camera/image` (`foxglove.CompressedImage`, PNG), `/groundtruth` and empty
//! `/features` frames (an agent's image frontend makes them). Foxglove opens
//! it, and an agent replays it (`input.source: mcap`) with a scenario whose
//! robot flies the same ground-truth file.
//!
//! Times are moved onto the fleet clock the way scenarios re-time
//! trajectories: the ground truth's first pose is at `--start-time-s`
//! (default 0); without a ground truth, the first IMU sample is.

use agent::dataset::{DatasetError, EurocDataset};
use agent::hybrid::read_euroc_biases;
use anyhow::{Context, Result};
use simulator::imu::Biases;
use simulator::SimEvent;
use std::path::PathBuf;

/// Arguments of `sim-fleet convert-euroc`.
#[derive(clap::Args, Debug)]
pub struct ConvertArgs {
    /// The sequence folder (holding `mav0`, or `mav0` itself).
    pub dataset: PathBuf,
    /// Ground truth (EuRoC CSV), if not the sequence's own.
    #[arg(long)]
    pub groundtruth: Option<PathBuf>,
    /// Fleet time of the ground truth's first pose, s.
    #[arg(long, default_value_t = 0.0)]
    pub start_time_s: f64,
    /// The MCAP file to write.
    #[arg(long)]
    pub out: PathBuf,
}

/// Converts; prints what was written.
pub fn run_convert(args: &ConvertArgs) -> Result<()> {
    let ds = EurocDataset::open(&args.dataset, args.groundtruth.as_deref())
        .with_context(|| format!("opening {}", args.dataset.display()))?;
    let t0 = match &ds.groundtruth {
        Some(gt) => gt.first().map(|p| p.t),
        None => ds.imu.first().map(|s| s.t),
    }
    .context("the sequence has no IMU samples")?;
    let shift = args.start_time_s - t0;
    let biases = match args.groundtruth.as_deref().or(gt_file(&ds).as_deref()) {
        Some(p) => read_euroc_biases(p)?,
        None => Vec::new(),
    };
    let bias_at = |t: f64| -> Biases {
        biases
            .iter()
            .min_by(|a, b| (a.0 - t).abs().total_cmp(&(b.0 - t).abs()))
            .map(|b| b.1)
            .unwrap_or_default()
    };
    let mut failure: Option<DatasetError> = None;
    let events = ds.events().map_while(|ev| match ev {
        Ok(SimEvent::Imu(s)) => Some(SimEvent::Imu(common::measurement::ImuSample {
            t: s.t + shift,
            ..s
        })),
        Ok(SimEvent::Camera(mut c)) => {
            c.truth.biases = bias_at(c.frame.t);
            c.frame.t += shift;
            c.truth.t += shift;
            Some(SimEvent::Camera(c))
        }
        Err(e) => {
            failure = Some(e);
            None
        }
    });
    if let Some(dir) = args.out.parent().filter(|d| !d.as_os_str().is_empty()) {
        std::fs::create_dir_all(dir).with_context(|| format!("creating {}", dir.display()))?;
    }
    let messages = simulator::mcap_io::write_stream(&args.out, events)?;
    if let Some(e) = failure {
        return Err(e).context("reading the sequence (the MCAP file is incomplete)");
    }
    println!(
        "{}: {messages} messages ({} images, {} IMU samples), fleet time = sequence time {:+.9} s",
        args.out.display(),
        ds.images.len(),
        ds.imu.len(),
        shift
    );
    Ok(())
}

/// The sequence's own ground-truth file, if it has one.
fn gt_file(ds: &EurocDataset) -> Option<PathBuf> {
    ["state_groundtruth_estimate0/data.csv", "gt0/data.csv"]
        .iter()
        .map(|r| ds.root.join(r))
        .find(|p| p.is_file())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_micro_sequence_converts_and_reads_back_with_its_images_on_the_fleet_clock() {
        let data = PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("../../shared/data");
        let dir = tempfile::tempdir().unwrap();
        let out = dir.path().join("micro.mcap");
        run_convert(&ConvertArgs {
            dataset: data.join("euroc_v1_01_micro"),
            groundtruth: Some(data.join("trajectories/V1_01_easy.csv")),
            start_time_s: 0.0,
            out: out.clone(),
        })
        .unwrap();
        let events = simulator::mcap_io::read_stream(&out).unwrap();
        let cameras: Vec<_> = events
            .iter()
            .filter_map(|e| match e {
                SimEvent::Camera(c) => Some(c),
                SimEvent::Imu(_) => None,
            })
            .collect();
        assert_eq!(cameras.len(), 95);
        assert_eq!(events.len() - cameras.len(), 29120);
        let first = cameras[0];
        assert!(
            first.frame.t.abs() < 1e-6,
            "the first image is at the first ground-truth pose"
        );
        assert!((first.truth.t - first.frame.t).abs() < 1e-9);
        let img = first.image.as_ref().unwrap();
        assert_eq!((img.width(), img.height()), (752, 480));
        // EuRoC's ground-truth gyro bias estimate at the start.
        assert!((first.truth.biases.gyro.z - 0.0770299).abs() < 1e-6);
        assert!(run_convert(&ConvertArgs {
            dataset: dir.path().to_path_buf(),
            groundtruth: None,
            start_time_s: 0.0,
            out: dir.path().join("x.mcap"),
        })
        .is_err());
    }
}
