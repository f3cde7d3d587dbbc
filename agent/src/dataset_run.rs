//! A real sequence ([`EurocDataset`]) through the image frontend into the
//! estimator, started by the static initializer (the platform must stand still
//! at the start, as in EuRoC and TUM-VI): no ground truth is used to run, only
//! to score.

use crate::dataset::EurocDataset;
use crate::estimator::frame_output::{BodyTwist, StampedTwist};
use crate::estimator::static_init::{static_start_sigmas, StaticInitOptions, StaticInitResult};
use crate::estimator::{Estimator, EstimatorOptions, FrameRecord};
use crate::frontend::{Frontend, FrontendError, FrontendOptions, FrontendOutput};
use crate::run_files::{RunRecord, RunRow};
use common::calibration::CameraCalibration;
use common::metrics::PosePair;
use common::summary::MetricSet;
use common::trajectory::{interpolate_pose, StampedCovariance, StampedPose};
use nalgebra::{Matrix3, Rotation3, Vector3};
use simulator::SimEvent;
use std::collections::{HashMap, HashSet};
use thiserror::Error;

/// Why a sequence could not be run (an image that cannot be read is skipped,
/// [`DatasetRun::skipped_images`]).
#[derive(Debug, Error)]
pub enum DatasetRunError {
    /// The frontend failed.
    #[error(transparent)]
    Frontend(#[from] FrontendError),
}

/// Everything a run on real data produced. Its size grows with the estimates
/// (pose, covariance, truth and counts) and the tracks (an id and a count
/// each), not with the features of every image.
#[derive(Debug, Default)]
pub struct DatasetRun {
    /// The static initializer's result, once it succeeded.
    pub init: Option<StaticInitResult>,
    /// The frontend's figures over every image (also before the start).
    pub frontend: FrontendTally,
    /// The estimates, with the ground truth at their times when it is known.
    pub record: DatasetRecord,
    /// Inputs the estimator rejected, with the reason.
    pub rejected: crate::runner::Rejections,
    /// Images that could not be read (missing, damaged) or are not the
    /// camera's size, with the reason: their frames are lost, the run goes on.
    pub skipped_images: crate::runner::Rejections,
}

/// Skipped images logged one by one; the rest are only counted.
const SKIPPED_IMAGES_LOGGED: usize = 10;

impl DatasetRun {
    /// Records an image whose frame is lost, and logs the first few.
    fn skip_image(&mut self, why: String) {
        let n = self.skipped_images.len();
        if n < SKIPPED_IMAGES_LOGGED {
            tracing::warn!("image skipped: {why}");
        } else if n == SKIPPED_IMAGES_LOGGED {
            tracing::warn!("more images skipped: counted, not logged");
        }
        self.skipped_images.push(why);
    }
}

/// What the frontend did over a sequence, gathered image by image.
#[derive(Debug, Default)]
pub struct FrontendTally {
    /// Images through the frontend.
    pub images: usize,
    /// Features over all images.
    pub features: usize,
    /// Fewest features in one image.
    pub min_features: Option<usize>,
    /// The first image's track ids.
    first_ids: HashSet<u64>,
    /// The last image's track ids.
    last_ids: HashSet<u64>,
    /// Images each track was seen in.
    lengths: HashMap<u64, u32>,
    /// Frontend time over all images, ms.
    pub ms: f64,
}

impl FrontendTally {
    /// Counts one image's output.
    pub fn add(&mut self, out: &FrontendOutput) {
        let ids: HashSet<u64> = out.frame.features.iter().map(|o| o.id).collect();
        for id in &ids {
            *self.lengths.entry(*id).or_default() += 1;
        }
        if self.images == 0 {
            self.first_ids.clone_from(&ids);
        }
        self.images += 1;
        self.features += out.frame.features.len();
        self.min_features = Some(self.min_features.map_or(out.frame.features.len(), |m| {
            m.min(out.frame.features.len())
        }));
        self.last_ids = ids;
        self.ms += out.stats.ms;
    }

    /// Tracks of the first image still tracked in the last one.
    pub fn tracks_first_to_last(&self) -> usize {
        self.first_ids.intersection(&self.last_ids).count()
    }

    /// Mean track length, images (over tracks that ended or reached the end).
    pub fn mean_track_length(&self) -> f64 {
        let total: u64 = self.lengths.values().map(|&n| u64::from(n)).sum();
        total as f64 / self.lengths.len().max(1) as f64
    }
}

/// The estimates of a run on real data and the ground truth at their times,
/// as [`RunFiles`](crate::run_files::RunFiles) streams them.
///
/// The estimate lives in the static start's frame (origin at the start, yaw
/// by convention); the ground truth in the motion capture's. The truth is
/// brought into the estimate's frame by the translation and the turn about
/// the vertical that put it on the first estimate it covers (as `evo
/// --align_origin`, but yaw only: the tilt error of the start stays an
/// error). Both frames have gravity along -z, so this is the whole
/// difference a static start cannot know.
#[derive(Debug, Default)]
pub struct DatasetRecord {
    /// A ground truth was given (`groundtruth.txt` is written).
    has_truth: bool,
    /// The estimate after each processed frame (IMU clock).
    pub estimate: Vec<StampedPose>,
    /// Its orientation and position covariance.
    pub covariance: Vec<StampedCovariance>,
    /// The truth at each estimate's time in the estimate's frame, where the
    /// ground truth covers it.
    pub truth: Vec<Option<StampedPose>>,
    /// Per-frame counts and costs.
    pub frames: Vec<FrameRecord>,
    /// The body twist of the last estimate, with its whole covariance
    /// (published beside the pose on live sensors).
    pub last_twist: Option<BodyTwist>,
    /// The body twist after each frame, with its standard deviations.
    pub twists: Vec<StampedTwist>,
    /// Motion capture frame to the estimate's: the turn about z and the
    /// translation, fixed at the first estimate the truth covers.
    to_estimate: Option<(Rotation3<f64>, Vector3<f64>)>,
}

impl DatasetRecord {
    /// An empty record; `has_truth` when a ground truth will be given.
    pub fn new(has_truth: bool) -> Self {
        DatasetRecord {
            has_truth,
            ..DatasetRecord::default()
        }
    }

    /// Records an estimate and the ground truth's pose at its time
    /// (`truth`, in the motion capture's frame), if known.
    pub fn push(
        &mut self,
        estimate: StampedPose,
        cov: StampedCovariance,
        frame: FrameRecord,
        truth: Option<StampedPose>,
    ) {
        let truth = truth.map(|g| {
            let (turn, shift) = *self.to_estimate.get_or_insert_with(|| {
                let yaw = yaw_of(&(estimate.rot * g.rot.transpose()));
                let turn = Rotation3::from_axis_angle(&Vector3::z_axis(), yaw);
                (turn, estimate.pos - turn * g.pos)
            });
            StampedPose {
                t: g.t,
                rot: turn * g.rot,
                pos: turn * g.pos + shift,
            }
        });
        self.estimate.push(estimate);
        self.covariance.push(cov);
        self.frames.push(frame);
        self.truth.push(truth);
    }

    /// The estimates the truth covers, paired with it.
    pub fn pairs(&self) -> Vec<PosePair> {
        self.estimate
            .iter()
            .zip(&self.truth)
            .filter_map(|(e, g)| g.map(|g| (*e, g)))
            .collect()
    }

    /// Accuracy against the truth (when known), consistency and cost.
    pub fn metrics(&self) -> MetricSet {
        crate::runner::record_metrics(&self.pairs(), &self.covariance, &self.frames)
    }
}

/// The rotation about z of `rot` (its yaw in the z-y-x convention), rad.
fn yaw_of(rot: &Matrix3<f64>) -> f64 {
    rot[(1, 0)].atan2(rot[(0, 0)])
}

impl RunRecord for DatasetRecord {
    fn has_truth(&self) -> bool {
        self.has_truth
    }

    fn rows(&self) -> usize {
        self.estimate.len()
    }

    fn row(&self, i: usize) -> RunRow<'_> {
        RunRow {
            truth: self.truth[i].as_ref(),
            estimate: &self.estimate[i],
            covariance: &self.covariance[i],
            frame: &self.frames[i],
        }
    }
}

/// Runs the whole sequence: IMU samples and frontend frames into the
/// estimator, which starts at the first image where the static initializer
/// succeeds. `on_frame` sees every image with its frontend output (for logs),
/// `on_estimate` the record after each new estimate (to write it out).
pub fn run_dataset(
    ds: &EurocDataset,
    opts: EstimatorOptions,
    frontend: FrontendOptions,
    init: &StaticInitOptions,
    on_frame: impl FnMut(&simulator::camera_sim::CameraEvent, &FrontendOutput),
    on_estimate: impl FnMut(&DatasetRecord),
) -> Result<DatasetRun, DatasetRunError> {
    let sensors = StreamSensors {
        calibration: &ds.calibration,
        groundtruth: ds.groundtruth.as_deref(),
    };
    run_stream(
        &sensors,
        ds.events(),
        opts,
        frontend,
        init,
        on_frame,
        on_estimate,
    )
}

/// The camera of a sensor stream and the ground truth to score it against.
#[derive(Clone, Copy, Debug)]
pub struct StreamSensors<'a> {
    /// The camera's calibration.
    pub calibration: &'a CameraCalibration,
    /// The ground truth (`R_ItoG`, `p_IinG` on the sensors' clock), if known.
    pub groundtruth: Option<&'a [StampedPose]>,
}

/// [`run_dataset`] over any stream of IMU samples and images in time order
/// (a recorded sequence, or live sensors): an event that failed to arrive
/// whole (an image that cannot be read or decoded) loses its frame and is
/// counted in [`DatasetRun::skipped_images`].
pub fn run_stream<E: std::fmt::Display>(
    sensors: &StreamSensors<'_>,
    events: impl Iterator<Item = Result<SimEvent, E>>,
    opts: EstimatorOptions,
    frontend: FrontendOptions,
    init: &StaticInitOptions,
    mut on_frame: impl FnMut(&simulator::camera_sim::CameraEvent, &FrontendOutput),
    mut on_estimate: impl FnMut(&DatasetRecord),
) -> Result<DatasetRun, DatasetRunError> {
    let mut est = Estimator::new(opts, sensors.calibration.clone());
    let mut fe = Frontend::new(frontend, sensors.calibration.camera.clone())?;
    let mut run = DatasetRun {
        record: DatasetRecord::new(sensors.groundtruth.is_some()),
        ..DatasetRun::default()
    };
    for ev in events {
        // Images are read as the stream goes: one missing or damaged image
        // loses its frame, as a camera driver dropping one would, and the
        // tracks bridge the gap.
        let ev = match ev {
            Ok(ev) => ev,
            Err(e) => {
                run.skip_image(e.to_string());
                continue;
            }
        };
        match ev {
            SimEvent::Imu(s) => {
                if let Err(e) = est.feed_imu(s) {
                    run.rejected.push(e.to_string());
                }
            }
            SimEvent::Camera(c) => {
                let Some(image) = c.image.as_ref() else {
                    continue;
                };
                let out = match fe.process(c.frame.t, image) {
                    Ok(out) => out,
                    Err(e @ FrontendError::ImageSize { .. }) => {
                        run.skip_image(format!("image at t={:.6} s: {e}", c.frame.t));
                        continue;
                    }
                    Err(e) => return Err(e.into()),
                };
                if run.init.is_none() {
                    // Only the IMU up to this image counts: the window ends here.
                    if let Ok(res) = est.initialize_static(init, &static_start_sigmas()) {
                        run.init = Some(res);
                    }
                } else if let Err(e) = est.feed_frame(out.frame.clone()) {
                    run.rejected.push(e.to_string());
                }
                on_frame(&c, &out);
                run.frontend.add(&out);
            }
        }
        let mut estimated = false;
        for o in est.poll() {
            match o {
                Ok(o) => {
                    let truth = sensors
                        .groundtruth
                        .and_then(|gt| interpolate_pose(gt, o.t()));
                    run.record.twists.push(o.twist.stamped(o.t()));
                    run.record.last_twist = Some(o.twist);
                    run.record.push(o.pose(), o.covariance(), o.record, truth);
                    estimated = true;
                }
                Err(e) => run.rejected.push(e.to_string()),
            }
        }
        if estimated {
            on_estimate(&run.record);
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

/// Scores a run against `groundtruth` (`R_ItoG`, `p_IinG`), when known.
pub fn score(run: &DatasetRun, groundtruth: Option<&[StampedPose]>) -> DatasetScore {
    let f = &run.frontend;
    let tilt = |t: f64, rot: &Matrix3<f64>| {
        groundtruth
            .and_then(|gt| interpolate_pose(gt, t))
            .map(|gt| tilt_error_deg(rot, &gt.rot))
    };
    DatasetScore {
        images: f.images,
        features_per_image: f.features as f64 / f.images.max(1) as f64,
        min_features: f.min_features.unwrap_or(0),
        tracks_first_to_last: f.tracks_first_to_last(),
        mean_track_length: f.mean_track_length(),
        init_tilt_error_deg: run.init.as_ref().and_then(|i| tilt(i.t, &i.rot_i_to_g)),
        final_tilt_error_deg: run.record.estimate.last().and_then(|p| tilt(p.t, &p.rot)),
        estimates: run.record.estimate.len(),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn pose(t: f64, yaw: f64, tilt: f64, pos: Vector3<f64>) -> StampedPose {
        StampedPose {
            t,
            rot: Rotation3::from_euler_angles(tilt, 0.0, yaw).into_inner(),
            pos,
        }
    }

    /// A truth turned by 40 deg about the vertical and moved by 3 m is put
    /// on the first estimate it covers; after that it follows the motion,
    /// and a tilt error stays an error.
    #[test]
    fn the_truth_is_put_on_the_first_estimate_it_covers_by_a_turn_about_z_and_a_shift() {
        let turn = Rotation3::from_axis_angle(&Vector3::z_axis(), 40f64.to_radians());
        let shift = Vector3::new(3.0, -1.0, 0.5);
        // The estimate's frame: the truth's turned and moved.
        let in_estimate = |p: &StampedPose| StampedPose {
            t: p.t,
            rot: turn * p.rot,
            pos: turn * p.pos + shift,
        };
        let mut rec = DatasetRecord::new(true);
        let cov = |t| StampedCovariance {
            t,
            ori: Matrix3::identity() * 1e-4,
            pos: Matrix3::identity() * 1e-2,
        };
        // No truth yet for the first estimate.
        rec.push(
            pose(0.0, 0.0, 0.0, Vector3::zeros()),
            cov(0.0),
            FrameRecord::default(),
            None,
        );
        for k in 1..20 {
            let t = 0.1 * k as f64;
            let truth = pose(t, 0.3 * t, 0.02, Vector3::new(t, 2.0 * t, 0.1));
            // The estimate: the truth in its frame, 0.01 rad more tilted.
            let mut est = in_estimate(&truth);
            est.rot = Rotation3::from_euler_angles(0.01, 0.0, 0.0).into_inner() * est.rot;
            rec.push(est, cov(t), FrameRecord::default(), Some(truth));
        }
        assert_eq!(rec.rows(), 20);
        assert!(rec.row(0).truth.is_none());
        let pairs = rec.pairs();
        assert_eq!(pairs.len(), 19);
        // The turn is read from orientations 0.01 rad apart in tilt: its yaw
        // is off by 0.01²/4, a few µm over these meters.
        assert!((pairs[0].0.pos - pairs[0].1.pos).norm() < 1e-12);
        for (e, g) in &pairs {
            assert!((e.pos - g.pos).norm() < 1e-4, "{e:?} {g:?}");
            let err = Rotation3::from_matrix_unchecked(g.rot.transpose() * e.rot).angle();
            assert!((err - 0.01).abs() < 1e-3, "{err}");
        }
        let m = rec.metrics();
        assert!(m.ate_pos_m.expect("ATE") < 1e-4);
        assert!((m.ate_ori_deg.expect("ATE") - 0.01f64.to_degrees()).abs() < 0.05);
    }

    /// Without a truth the record has rows and no truth: no `groundtruth.txt`.
    #[test]
    fn a_record_without_truth_writes_no_groundtruth() {
        let mut rec = DatasetRecord::new(false);
        for k in 0..5 {
            let t = k as f64;
            rec.push(
                pose(t, 0.0, 0.0, Vector3::new(t, 0.0, 0.0)),
                StampedCovariance {
                    t,
                    ori: Matrix3::identity(),
                    pos: Matrix3::identity(),
                },
                FrameRecord::default(),
                None,
            );
        }
        let dir = tempfile::tempdir().expect("tempdir");
        crate::run_files::write_all(&rec, dir.path()).expect("write");
        assert!(!dir.path().join("groundtruth.txt").exists());
        let est = common::trajectory::read_tum(dir.path().join("estimate.txt")).expect("read");
        assert_eq!(est.len(), 5);
        assert_eq!(rec.metrics().ate_pos_m, None);
    }
}
