//! One robot of a scenario that renders images, through the image frontend into
//! the estimator (the rendered counterpart of [`crate::runner::run_robot`]),
//! with the quality of the tracks measured against the rendered truth.
//!
//! Track accuracy: when a track starts, its pixel is cast into the rendered
//! room from the true camera pose, which gives the true 3-D point behind it;
//! every later observation of the track is compared with that point projected
//! through the true pose and calibration. The error is what KLT drift,
//! interpolation and image noise add to the ideal measurement (the detection's
//! own position is exact by construction).

use crate::estimator::EstimatorOptions;
use crate::frontend::{Frontend, FrontendOptions, FrontendOutput};
use crate::runner::{run_robot_with, RobotRun, RunError};
use common::calibration::CameraCalibration;
use nalgebra::Vector3;
use simulator::camera_sim::CameraEvent;
use simulator::render::Renderer;
use simulator::truth::RobotTruth;
use simulator::world::camera_pose;
use simulator::Fleet;
use std::collections::HashMap;

/// Summary of the frontend over a run.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct TrackQuality {
    /// Images processed.
    pub frames: usize,
    /// Mean features per frame.
    pub features_per_frame: f64,
    /// Mean frontend cost per frame, ms (wall clock).
    pub ms_per_frame: f64,
    /// Track observations compared with the truth.
    pub observations: usize,
    /// Reprojection error of the tracked pixels, px: mean, median, 95th percentile.
    pub reprojection_mean_px: f64,
    /// Median, px.
    pub reprojection_median_px: f64,
    /// 95th percentile, px.
    pub reprojection_p95_px: f64,
    /// Fraction of observations more than 3 px off (tracking failures).
    pub outlier_fraction: f64,
}

impl TrackQuality {
    /// The tracks' mean error, px, or `None` when no track was scored.
    pub fn mean_error_px(&self) -> Option<f64> {
        let m = self.reprojection_mean_px;
        (self.observations > 0 && m.is_finite()).then_some(m)
    }
}

/// The tracks' error against the rendered truth in one image.
///
/// The common part, the mean of the error vectors, is a shift every track
/// shares, as a small camera rotation would make it, where errors in all
/// directions average out (on rendered V1_01 seed 2 a common
/// -0.14 px along x over 50-60 s came with a 0.4 deg move of the yaw).
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct FrameTrackError {
    /// Camera time of the image, s.
    pub t_s: f64,
    /// Observations compared with the truth (tracks older than this image).
    pub observations: usize,
    /// Mean length of the error vectors, px.
    pub mean_px: f64,
    /// Mean error vector (truth minus track), px: x, then y.
    pub common_px: [f64; 2],
    /// Observations more than 3 px off.
    pub over_3px: usize,
}

impl FrameTrackError {
    /// The CSV header of [`FrameTrackError::csv_row`].
    pub const CSV_HEADER: &'static str =
        "t_s,observations,mean_px,common_x_px,common_y_px,over_3px";

    /// One CSV row.
    pub fn csv_row(&self) -> String {
        format!(
            "{:.6},{},{:.4},{:.4},{:.4},{}",
            self.t_s,
            self.observations,
            self.mean_px,
            self.common_px[0],
            self.common_px[1],
            self.over_3px
        )
    }
}

/// A rendered run: the estimator's run and the frontend's track quality.
#[derive(Clone, Debug, Default)]
pub struct ImageRun {
    /// The estimator's outputs.
    pub run: RobotRun,
    /// The frontend's tracks.
    pub tracks: TrackQuality,
    /// The tracks' error in each image that had tracks to score.
    pub per_frame: Vec<FrameTrackError>,
}

/// `track_errors.csv`: [`FrameTrackError::CSV_HEADER`], then a row per image.
pub fn track_errors_csv(per_frame: &[FrameTrackError]) -> String {
    let mut text = String::from(FrameTrackError::CSV_HEADER);
    for f in per_frame {
        text.push('\n');
        text.push_str(&f.csv_row());
    }
    text.push('\n');
    text
}

/// Runs robot `robot` of a fleet that renders images (`render.enabled`);
/// `on_image` sees every image with the frontend's output (e.g. to log it).
pub fn run_robot_rendered(
    fleet: &Fleet,
    robot: usize,
    opts: EstimatorOptions,
    frontend: FrontendOptions,
    mut on_image: impl FnMut(&CameraEvent, &FrontendOutput),
) -> Result<ImageRun, RunError> {
    if !fleet.renders() {
        return Err(RunError::Frames {
            t: f64::NAN,
            reason: "the scenario does not render images (render.enabled: false)".into(),
        });
    }
    let mut scorer =
        TrackScorer::new(fleet, robot).ok_or(simulator::SimError::NoSuchRobot(robot))?;
    let mut fe = Frontend::new(frontend, fleet.initial_calibration(robot).camera).map_err(|e| {
        RunError::Frames {
            t: f64::NAN,
            reason: e.to_string(),
        }
    })?;
    let run = run_robot_with(fleet, robot, opts, |c| {
        let t = c.frame.t;
        let fail = |reason: String| RunError::Frames { t, reason };
        let image = c.image.as_ref().ok_or_else(|| fail("no image".into()))?;
        let out = fe.process(t, image).map_err(|e| fail(e.to_string()))?;
        on_image(&c, &out);
        scorer.score(&c, &out);
        Ok(Some(out.frame))
    })?;
    Ok(ImageRun {
        run,
        tracks: scorer.quality(),
        per_frame: scorer.per_frame,
    })
}

/// Scores a frontend's tracks against the rendered truth, image by image (see
/// the module documentation).
pub struct TrackScorer<'a> {
    renderer: &'a Renderer,
    truth: &'a RobotTruth,
    calib: &'a CameraCalibration,
    landmarks: HashMap<u64, Vector3<f64>>,
    errors: Vec<f64>,
    frames: usize,
    features: usize,
    ms: f64,
    /// The tracks' error in each image that had tracks to score.
    pub per_frame: Vec<FrameTrackError>,
}

impl<'a> TrackScorer<'a> {
    /// A scorer for robot `robot`'s images; `None` when the fleet does not
    /// render or has no such robot.
    pub fn new(fleet: &'a Fleet, robot: usize) -> Option<Self> {
        Some(Self {
            renderer: fleet.renderer(robot)?,
            truth: fleet.truths.get(robot)?,
            calib: fleet.true_calibration(robot)?,
            landmarks: HashMap::new(),
            errors: Vec::new(),
            frames: 0,
            features: 0,
            ms: 0.0,
            per_frame: Vec::new(),
        })
    }

    /// Scores the frontend's output `out` for the camera event `c`: a new
    /// track's pixel is cast into the room, an older one compared with its
    /// point's projection.
    pub fn score(&mut self, c: &CameraEvent, out: &FrontendOutput) {
        self.frames += 1;
        self.features += out.frame.features.len();
        self.ms += out.stats.ms;
        let Some(pose) = camera_pose(self.truth, self.calib, c.truth.t) else {
            return;
        };
        let to_c = pose.inverse();
        let ids: std::collections::HashSet<u64> = out.new_ids.iter().copied().collect();
        let mut frame = FrameTrackError {
            t_s: c.frame.t,
            ..FrameTrackError::default()
        };
        for f in &out.frame.features {
            if ids.contains(&f.id) {
                if let Some(p) = self.renderer.raycast(&pose, &f.uv) {
                    self.landmarks.insert(f.id, p);
                }
            } else if let Some(p) = self.landmarks.get(&f.id) {
                if let Some(uv) = self.calib.camera.project(&to_c.transform_point(p)) {
                    let e = uv - f.uv;
                    let len = e.norm();
                    self.errors.push(len);
                    frame.observations += 1;
                    frame.mean_px += len;
                    frame.common_px[0] += e.x;
                    frame.common_px[1] += e.y;
                    frame.over_3px += usize::from(len > 3.0);
                }
            }
        }
        if frame.observations > 0 {
            let n = frame.observations as f64;
            frame.mean_px /= n;
            frame.common_px = frame.common_px.map(|c| c / n);
            self.per_frame.push(frame);
        }
        let alive: std::collections::HashSet<u64> =
            out.frame.features.iter().map(|f| f.id).collect();
        self.landmarks.retain(|id, _| alive.contains(id));
    }

    /// The summary so far.
    pub fn quality(&self) -> TrackQuality {
        quality(self.frames, self.features, self.ms, self.errors.clone())
    }
}

fn quality(frames: usize, features: usize, ms: f64, mut errors: Vec<f64>) -> TrackQuality {
    errors.sort_by(f64::total_cmp);
    let n = errors.len();
    let pick = |q: f64| common::metrics::percentile_sorted(&errors, q).unwrap_or(f64::NAN);
    let per = |v: f64| {
        if frames > 0 {
            v / frames as f64
        } else {
            f64::NAN
        }
    };
    TrackQuality {
        frames,
        features_per_frame: per(features as f64),
        ms_per_frame: per(ms),
        observations: n,
        reprojection_mean_px: if n > 0 {
            errors.iter().sum::<f64>() / n as f64
        } else {
            f64::NAN
        },
        reprojection_median_px: pick(0.5),
        reprojection_p95_px: pick(0.95),
        outlier_fraction: if n > 0 {
            errors.iter().filter(|e| **e > 3.0).count() as f64 / n as f64
        } else {
            f64::NAN
        },
    }
}
