//! A real sequence ([`EurocDataset`]) through the image frontend into the
//! estimator, started by the static initializer (the platform must stand still
//! at the start, as in EuRoC and TUM-VI): no ground truth is used to run, only
//! to score.

use crate::dataset::{DatasetError, EurocDataset};
use crate::estimator::static_init::{static_start_sigmas, StaticInitOptions, StaticInitResult};
use crate::estimator::{Estimator, EstimatorOptions, FrameOutput};
use crate::frontend::{Frontend, FrontendError, FrontendOptions, FrontendOutput};
use common::trajectory::{StampedCovariance, StampedPose};
use nalgebra::{Matrix3, Vector3};
use simulator::SimEvent;
use thiserror::Error;

/// Why a sequence could not be run.
#[derive(Debug, Error)]
pub enum DatasetRunError {
    /// Reading the data failed.
    #[error(transparent)]
    Data(#[from] DatasetError),
    /// The frontend failed.
    #[error(transparent)]
    Frontend(#[from] FrontendError),
}

/// Everything a run on real data produced.
#[derive(Debug, Default)]
pub struct DatasetRun {
    /// The static initializer's result, once it succeeded.
    pub init: Option<StaticInitResult>,
    /// The frontend's output for every image (also before the start).
    pub frames: Vec<FrontendOutput>,
    /// The estimate after each processed frame (IMU clock; the initializer's
    /// frame: origin at the start, yaw by convention).
    pub estimate: Vec<StampedPose>,
    /// Its covariance.
    pub covariance: Vec<StampedCovariance>,
    /// The estimator's per-frame outputs.
    pub outputs: Vec<FrameOutput>,
    /// Inputs the estimator rejected, with the reason.
    pub rejected: Vec<String>,
}

/// Runs the whole sequence: IMU samples and frontend frames into the
/// estimator, which starts at the first image where the static initializer
/// succeeds; `on_frame` sees every image with its frontend output (for logs).
pub fn run_dataset(
    ds: &EurocDataset,
    opts: EstimatorOptions,
    frontend: FrontendOptions,
    init: &StaticInitOptions,
    mut on_frame: impl FnMut(&simulator::camera_sim::CameraEvent, &FrontendOutput),
) -> Result<DatasetRun, DatasetRunError> {
    let mut est = Estimator::new(opts, ds.calibration.clone());
    let mut fe = Frontend::new(frontend, ds.calibration.camera.clone())?;
    let mut run = DatasetRun::default();
    for ev in ds.events() {
        match ev? {
            SimEvent::Imu(s) => {
                if let Err(e) = est.feed_imu(s) {
                    run.rejected.push(e.to_string());
                }
            }
            SimEvent::Camera(c) => {
                let Some(image) = c.image.as_ref() else {
                    continue;
                };
                let out = fe.process(c.frame.t, image)?;
                if run.init.is_none() {
                    // Only the IMU up to this image counts: the window ends here.
                    if let Ok(res) = est.initialize_static(init, &static_start_sigmas()) {
                        run.init = Some(res);
                    }
                } else if let Err(e) = est.feed_frame(out.frame.clone()) {
                    run.rejected.push(e.to_string());
                }
                on_frame(&c, &out);
                run.frames.push(out);
            }
        }
        for o in est.poll() {
            match o {
                Ok(o) => {
                    run.estimate.push(StampedPose {
                        t: o.t,
                        rot: o.rot,
                        pos: o.pos,
                    });
                    run.covariance.push(StampedCovariance {
                        t: o.t,
                        ori: o.cov_ori,
                        pos: o.cov_pos,
                    });
                    run.outputs.push(o);
                }
                Err(e) => run.rejected.push(e.to_string()),
            }
        }
    }
    Ok(run)
}

/// How a run on real data went, against the ground truth when there is one.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct DatasetScore {
    /// Images through the frontend.
    pub images: usize,
    /// Mean features per image.
    pub features_per_image: f64,
    /// Fewest features in one image.
    pub min_features: usize,
    /// Tracks of the first image still tracked in the last one.
    pub tracks_first_to_last: usize,
    /// Mean track length, images (over tracks that ended or reached the end).
    pub mean_track_length: f64,
    /// Tilt (roll and pitch) error of the static start vs the ground truth, deg.
    pub init_tilt_error_deg: Option<f64>,
    /// Tilt error of the last estimate vs the ground truth, deg.
    pub final_tilt_error_deg: Option<f64>,
    /// Estimates made.
    pub estimates: usize,
}

/// Angle between the "up" directions of two `R_ItoG`, deg: the roll and pitch
/// error, blind to yaw (which a static start cannot know).
pub fn tilt_error_deg(rot: &Matrix3<f64>, truth: &Matrix3<f64>) -> f64 {
    let up = rot.transpose() * Vector3::z();
    let up_true = truth.transpose() * Vector3::z();
    up.angle(&up_true).to_degrees()
}

/// Scores a run.
pub fn score(run: &DatasetRun, ds: &EurocDataset) -> DatasetScore {
    let counts: Vec<usize> = run.frames.iter().map(|f| f.frame.features.len()).collect();
    let ids = |k: usize| -> std::collections::HashSet<u64> {
        run.frames
            .get(k)
            .map(|f| f.frame.features.iter().map(|o| o.id).collect())
            .unwrap_or_default()
    };
    let first = ids(0);
    let last = ids(run.frames.len().saturating_sub(1));
    let mut lengths: std::collections::HashMap<u64, usize> = std::collections::HashMap::new();
    for f in &run.frames {
        for o in &f.frame.features {
            *lengths.entry(o.id).or_default() += 1;
        }
    }
    let tilt = |t: f64, rot: &Matrix3<f64>| ds.truth_at(t).map(|gt| tilt_error_deg(rot, &gt.rot));
    DatasetScore {
        images: run.frames.len(),
        features_per_image: counts.iter().sum::<usize>() as f64 / counts.len().max(1) as f64,
        min_features: counts.iter().copied().min().unwrap_or(0),
        tracks_first_to_last: first.intersection(&last).count(),
        mean_track_length: lengths.values().sum::<usize>() as f64 / lengths.len().max(1) as f64,
        init_tilt_error_deg: run.init.as_ref().and_then(|i| tilt(i.t, &i.rot_i_to_g)),
        final_tilt_error_deg: run.estimate.last().and_then(|p| tilt(p.t, &p.rot)),
        estimates: run.estimate.len(),
    }
}
