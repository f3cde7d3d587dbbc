//! [`Frontend`]: the KLT tracker with its per-frame steps (see the module
//! documentation of [`super`]).

use super::cv::{mat_of, pixels_of, points_of};
use super::detect::detect_new;
use super::orb::OrbDescriber;
use super::patch_refine::{ImageView, RefineLimits, Refusal, Template};
use super::ransac::epipolar_inliers;
use super::{FirstPatch, FrontendOptions, Histogram};
use common::camera::CameraModel;
use common::descriptor::Descriptor;
use common::image::GrayImage;
use common::measurement::{FeatureFrame, FeatureObservation};
use nalgebra::Vector2;
use opencv::core::{
    Mat, Point2f, Ptr, Size, TermCriteria, TermCriteria_Type, Vector, BORDER_CONSTANT,
    BORDER_REFLECT_101,
};
use opencv::imgproc::CLAHE;
use opencv::prelude::*;
use opencv::{imgproc, video};
use std::collections::{HashMap, HashSet};
use std::time::Instant;
use thiserror::Error;

/// KLT stops after this many iterations per level ...
const KLT_MAX_ITERATIONS: i32 = 30;
/// ... or when a step is shorter than this, pixels.
const KLT_EPSILON_PX: f64 = 0.01;
/// KLT refuses windows whose gradient matrix has a smaller eigenvalue (per
/// pixel, OpenCV's normalization): flat patches cannot be tracked.
const KLT_MIN_EIGENVALUE: f64 = 1e-4;

/// Why a frame could not be processed.
#[derive(Debug, Error)]
pub enum FrontendError {
    /// The options are out of range.
    #[error("frontend options: {0}")]
    Options(String),
    /// The image does not have the camera's size.
    #[error("image is {got_w}x{got_h} pixels, the camera's are {want_w}x{want_h}")]
    ImageSize {
        /// Width of the image.
        got_w: u32,
        /// Height of the image.
        got_h: u32,
        /// Width of the camera.
        want_w: u32,
        /// Height of the camera.
        want_h: u32,
    },
    /// The frame time is NaN or infinite.
    #[error("frame time {0} is not finite")]
    NonFiniteTime(f64),
    /// Frames must come in time order.
    #[error("frame at t={t} is not after the previous one at t={previous}")]
    TimeBackwards {
        /// Its time.
        t: f64,
        /// The previous frame's time.
        previous: f64,
    },
    /// OpenCV failed.
    #[error("OpenCV: {0}")]
    OpenCv(#[from] opencv::Error),
}

/// What happened to the features of one frame.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct FrontendStats {
    /// Tracks carried over from the previous frame.
    pub tracked: usize,
    /// Tracks KLT lost (status, image bounds).
    pub lost_klt: usize,
    /// Tracks that failed the forward-backward check.
    pub lost_forward_backward: usize,
    /// Tracks rejected by the fundamental-matrix RANSAC.
    pub lost_ransac: usize,
    /// Tracks whose refinement against their first patch was refused: ended
    /// (`FirstPatch::Drop`) or given a new first patch (`Reanchor`).
    pub refused_patch: usize,
    /// New tracks.
    pub detected: usize,
    /// Wall-clock cost of the frame, ms.
    pub ms: f64,
    /// Of which: preprocessing, pyramid, KLT, RANSAC and the refinement
    /// against the first patches, ms.
    pub track_ms: f64,
    /// Of which: the refinement against the first patches, ms.
    pub refine_ms: f64,
    /// Detection of new features, ms.
    pub detect_ms: f64,
    /// ORB descriptors, ms.
    pub describe_ms: f64,
}

/// One processed frame.
#[derive(Clone, Debug)]
pub struct FrontendOutput {
    /// The features, as the estimator takes them (ids increasing).
    pub frame: FeatureFrame,
    /// Ids of the tracks that started in this frame.
    pub new_ids: Vec<u64>,
    /// Every track got a fresh descriptor in this frame.
    pub keyframe: bool,
    /// Counts and cost.
    pub stats: FrontendStats,
}

#[derive(Clone, Copy, Debug)]
struct Track {
    id: u64,
    uv: Vector2<f64>,
    descriptor: Descriptor,
}

/// The previous image (as a KLT pyramid) and its tracks.
struct Previous {
    t: f64,
    pyramid: Vector<Mat>,
    tracks: Vec<Track>,
}

/// The KLT + ORB frontend of one camera.
pub struct Frontend {
    opts: FrontendOptions,
    camera: CameraModel,
    orb: OrbDescriber,
    clahe: Option<Ptr<CLAHE>>,
    prev: Option<Previous>,
    next_id: u64,
    frames: u64,
    /// Each live track's first patch (`first_patch` set).
    templates: HashMap<u64, Template>,
}

impl std::fmt::Debug for Frontend {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("Frontend")
            .field("opts", &self.opts)
            .field("frames", &self.frames)
            .field("next_id", &self.next_id)
            .finish_non_exhaustive()
    }
}

impl Frontend {
    /// A frontend for images of `camera` (its size, and its intrinsics for the
    /// RANSAC's undistortion).
    pub fn new(opts: FrontendOptions, camera: CameraModel) -> Result<Self, FrontendError> {
        opts.validate().map_err(FrontendError::Options)?;
        camera
            .validate()
            .map_err(|e| FrontendError::Options(format!("camera: {e}")))?;
        let clahe = match opts.histogram {
            Histogram::Clahe => Some(imgproc::create_clahe(2.0, Size::new(8, 8))?),
            _ => None,
        };
        Ok(Self {
            orb: OrbDescriber::new()?,
            opts,
            camera,
            clahe,
            prev: None,
            next_id: 1,
            frames: 0,
            templates: HashMap::new(),
        })
    }

    /// The options.
    pub fn options(&self) -> &FrontendOptions {
        &self.opts
    }

    /// Tracks the previous frame's features into `image` (camera time `t`, s),
    /// rejects outliers, tops the tracks up with new features and describes them.
    pub fn process(&mut self, t: f64, image: &GrayImage) -> Result<FrontendOutput, FrontendError> {
        let started = Instant::now();
        self.check(t, image)?;
        let img = self.preprocess(image)?;
        let pyramid = self.pyramid(&img)?;
        let mut stats = FrontendStats::default();
        let mut tracks = match self.prev.take() {
            Some(prev) => self.track(&prev, &pyramid, &mut stats)?,
            None => Vec::new(),
        };
        let refining = Instant::now();
        self.hold_to_first_patches(&img, &mut tracks, &mut stats)?;
        stats.refine_ms = ms_since(refining);
        stats.tracked = tracks.len();
        stats.track_ms = ms_since(started);
        let keyframe = self.frames % self.opts.keyframe_interval == 0;
        let new_ids = self.top_up(&img, keyframe, &mut tracks, &mut stats)?;
        self.take_first_patches(&img, &tracks, &new_ids)?;
        stats.detected = new_ids.len();
        self.frames += 1;
        let features = tracks
            .iter()
            .map(|tr| FeatureObservation {
                id: tr.id,
                uv: tr.uv,
                descriptor: tr.descriptor,
            })
            .collect();
        self.prev = Some(Previous { t, pyramid, tracks });
        stats.ms = ms_since(started);
        Ok(FrontendOutput {
            frame: FeatureFrame {
                t,
                camera: 0,
                features,
            },
            new_ids,
            keyframe,
            stats,
        })
    }

    fn check(&self, t: f64, image: &GrayImage) -> Result<(), FrontendError> {
        if image.width() != self.camera.width || image.height() != self.camera.height {
            return Err(FrontendError::ImageSize {
                got_w: image.width(),
                got_h: image.height(),
                want_w: self.camera.width,
                want_h: self.camera.height,
            });
        }
        if !t.is_finite() {
            return Err(FrontendError::NonFiniteTime(t));
        }
        if let Some(prev) = &self.prev {
            if t <= prev.t {
                return Err(FrontendError::TimeBackwards {
                    t,
                    previous: prev.t,
                });
            }
        }
        Ok(())
    }

    /// Step 1: contrast normalization.
    fn preprocess(&mut self, image: &GrayImage) -> Result<Mat, FrontendError> {
        let raw = mat_of(image)?;
        let mut out = Mat::default();
        match (self.opts.histogram, self.clahe.as_mut()) {
            (Histogram::Equalize, _) => imgproc::equalize_hist(&raw, &mut out)?,
            (Histogram::Clahe, Some(clahe)) => clahe.apply(&raw, &mut out)?,
            _ => out = raw,
        }
        Ok(out)
    }

    fn pyramid(&self, img: &Mat) -> Result<Vector<Mat>, FrontendError> {
        let mut pyramid = Vector::<Mat>::new();
        let win = Size::new(self.opts.klt_window_px, self.opts.klt_window_px);
        video::build_optical_flow_pyramid(
            img,
            &mut pyramid,
            win,
            self.opts.klt_pyramid_levels,
            true,
            BORDER_REFLECT_101,
            BORDER_CONSTANT,
            true,
        )?;
        Ok(pyramid)
    }

    /// Steps 2 and 3: KLT with the forward-backward check, then the epipolar
    /// RANSAC.
    fn track(
        &self,
        prev: &Previous,
        pyramid: &Vector<Mat>,
        stats: &mut FrontendStats,
    ) -> Result<Vec<Track>, FrontendError> {
        if prev.tracks.is_empty() {
            return Ok(Vec::new());
        }
        let start: Vec<Vector2<f64>> = prev.tracks.iter().map(|t| t.uv).collect();
        let starts = points_of(&start);
        let (fwd, ok_f) = self.klt(&prev.pyramid, pyramid, &starts, None)?;
        // Back from where the points landed, starting at where they came from:
        // a good track converges at once, a bad one drifts away.
        let (back, ok_b) = self.klt(pyramid, &prev.pyramid, &points_of(&fwd), Some(&starts))?;
        let (w, h) = (f64::from(self.camera.width), f64::from(self.camera.height));
        let mut kept = Vec::with_capacity(start.len());
        let mut prev_uv = Vec::with_capacity(start.len());
        for i in 0..start.len() {
            let p = fwd[i];
            let inside = p.x >= 0.0 && p.y >= 0.0 && p.x <= w - 1.0 && p.y <= h - 1.0;
            if !ok_f[i] || !inside {
                stats.lost_klt += 1;
            } else if !ok_b[i] || (back[i] - start[i]).norm() > self.opts.max_forward_backward_px {
                stats.lost_forward_backward += 1;
            } else {
                kept.push(Track {
                    uv: p,
                    ..prev.tracks[i]
                });
                prev_uv.push(start[i]);
            }
        }
        let cur_uv: Vec<Vector2<f64>> = kept.iter().map(|t| t.uv).collect();
        let inliers = epipolar_inliers(
            &self.camera,
            &prev_uv,
            &cur_uv,
            self.opts.ransac_threshold_px,
        )?;
        let before = kept.len();
        let kept: Vec<Track> = kept
            .into_iter()
            .zip(inliers)
            .filter_map(|(t, ok)| ok.then_some(t))
            .collect();
        stats.lost_ransac = before - kept.len();
        Ok(kept)
    }

    /// Step 3, second part: each tracked pixel refined against its track's
    /// first patch (`first_patch`); a refused one ends or starts over.
    fn hold_to_first_patches(
        &mut self,
        img: &Mat,
        tracks: &mut Vec<Track>,
        stats: &mut FrontendStats,
    ) -> Result<(), FrontendError> {
        if self.opts.first_patch == FirstPatch::Off || tracks.is_empty() {
            return Ok(());
        }
        let Some(view) = view_of(img)? else {
            return Ok(());
        };
        let limits = RefineLimits::default();
        let drop = self.opts.first_patch == FirstPatch::Drop;
        let mut refused = 0;
        let mut scratch = Vec::new();
        tracks.retain_mut(|tr| {
            let Some(tpl) = self.templates.get_mut(&tr.id) else {
                // No first patch (it started too near the border or on a
                // flat patch): the frame-to-frame pixel.
                return true;
            };
            let why = match tpl.refine(&view, tr.uv, &limits, &mut scratch) {
                Ok(uv) => {
                    tr.uv = uv;
                    return true;
                }
                Err(why) => why,
            };
            refused += 1;
            match (why, drop) {
                // Near the border: the frame-to-frame pixel until the patch is
                // inside again or the track leaves.
                (Refusal::Outside, _) => true,
                // The first patch and the frame-to-frame pixel disagree, or
                // the patch changed: the track ends ...
                (_, true) => false,
                // ... or starts over from where KLT put it.
                (_, false) => {
                    match Template::extract(&view, tr.uv, limits.half_px) {
                        Some(tpl) => self.templates.insert(tr.id, tpl),
                        None => self.templates.remove(&tr.id),
                    };
                    true
                }
            }
        });
        stats.refused_patch = refused;
        Ok(())
    }

    /// The first patches of the tracks that started in this frame, and none
    /// for the tracks that ended.
    fn take_first_patches(
        &mut self,
        img: &Mat,
        tracks: &[Track],
        new_ids: &[u64],
    ) -> Result<(), FrontendError> {
        if self.opts.first_patch == FirstPatch::Off {
            return Ok(());
        }
        let alive: HashSet<u64> = tracks.iter().map(|t| t.id).collect();
        self.templates.retain(|id, _| alive.contains(id));
        let Some(view) = view_of(img)? else {
            return Ok(());
        };
        let half = RefineLimits::default().half_px;
        let new: HashSet<u64> = new_ids.iter().copied().collect();
        for tr in tracks.iter().filter(|t| new.contains(&t.id)) {
            if let Some(tpl) = Template::extract(&view, tr.uv, half) {
                self.templates.insert(tr.id, tpl);
            }
        }
        Ok(())
    }

    /// Pyramidal Lucas-Kanade from `from` to `to`, optionally from initial
    /// guesses: the points and whether each was found.
    fn klt(
        &self,
        from: &Vector<Mat>,
        to: &Vector<Mat>,
        points: &Vector<Point2f>,
        guess: Option<&Vector<Point2f>>,
    ) -> Result<(Vec<Vector2<f64>>, Vec<bool>), FrontendError> {
        let mut next = guess.cloned().unwrap_or_default();
        let flags = if guess.is_some() {
            video::OPTFLOW_USE_INITIAL_FLOW
        } else {
            0
        };
        let mut status = Vector::<u8>::new();
        let mut err = Vector::<f32>::new();
        let criteria = TermCriteria::new(
            TermCriteria_Type::COUNT as i32 + TermCriteria_Type::EPS as i32,
            KLT_MAX_ITERATIONS,
            KLT_EPSILON_PX,
        )?;
        video::calc_optical_flow_pyr_lk(
            from,
            to,
            points,
            &mut next,
            &mut status,
            &mut err,
            Size::new(self.opts.klt_window_px, self.opts.klt_window_px),
            self.opts.klt_pyramid_levels,
            criteria,
            flags,
            KLT_MIN_EIGENVALUE,
        )?;
        let found = status.iter().map(|s| s != 0).collect();
        Ok((pixels_of(&next), found))
    }

    /// Steps 4 and 5: new features where tracks are missing, then one ORB pass
    /// over the new points and, at keyframes, the tracked ones (a new point ORB
    /// cannot describe is not kept; a tracked one keeps its descriptor).
    /// Returns the new ids.
    fn top_up(
        &mut self,
        img: &Mat,
        keyframe: bool,
        tracks: &mut Vec<Track>,
        stats: &mut FrontendStats,
    ) -> Result<Vec<u64>, FrontendError> {
        let started = Instant::now();
        let want = self.opts.num_features.saturating_sub(tracks.len());
        let existing: Vec<Vector2<f64>> = tracks.iter().map(|t| t.uv).collect();
        let fresh = detect_new(img, &existing, want, &self.opts)?;
        stats.detect_ms = ms_since(started);
        let started = Instant::now();
        let mut points = fresh.clone();
        if keyframe {
            points.extend(existing);
        }
        let gray = img.data_bytes()?;
        let width = usize::try_from(img.cols()).unwrap_or(0);
        let mut descriptors = self.orb.describe(img, gray, width, &points)?.into_iter();
        let new_descriptors: Vec<Option<Descriptor>> =
            descriptors.by_ref().take(fresh.len()).collect();
        for (tr, d) in tracks.iter_mut().zip(descriptors) {
            tr.descriptor = d.unwrap_or(tr.descriptor);
        }
        let mut ids = Vec::new();
        for (uv, d) in fresh.into_iter().zip(new_descriptors) {
            let Some(descriptor) = d else { continue };
            let id = self.next_id;
            self.next_id += 1;
            tracks.push(Track { id, uv, descriptor });
            ids.push(id);
        }
        stats.describe_ms = ms_since(started);
        Ok(ids)
    }
}

/// A view of an 8-bit single-channel `Mat` (`None` for another type).
fn view_of(img: &Mat) -> Result<Option<ImageView<'_>>, FrontendError> {
    let width = usize::try_from(img.cols()).unwrap_or(0);
    let height = usize::try_from(img.rows()).unwrap_or(0);
    Ok(ImageView::new(img.data_bytes()?, width, height))
}

fn ms_since(t: Instant) -> f64 {
    t.elapsed().as_secs_f64() * 1e3
}
