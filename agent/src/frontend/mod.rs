//! The image frontend: camera images in,
//! [`FeatureFrame`](common::measurement::FeatureFrame)s out, the same type
//! the simulator produces, so the estimator and the peers cannot tell the
//! difference.
//!
//! One frame (`Frontend::process`, built with the cargo feature `vision`, on
//! OpenCV):
//! 1. optional histogram equalization or CLAHE;
//! 2. pyramidal KLT from the previous image, kept only when tracking back
//!    lands within `max_forward_backward_px` of the start (forward-backward
//!    check);
//! 3. outlier rejection with a fundamental-matrix RANSAC on the undistorted
//!    points (ideal pixels `K · n`, so the threshold is in pixels), then
//!    each track refined against the patch it started with
//!    ([`patch_refine`]; `first_patch: off` skips it), so frame-to-frame
//!    errors do not add up;
//! 4. new features on a grid (FAST or Shi-Tomasi), away from the image border
//!    and at least `min_distance_px` from every feature, until
//!    `num_features` are tracked;
//! 5. ORB descriptors for the new tracks, and for every track at keyframes
//!    (every `keyframe_interval` frames), for the peers and the vocabulary.
//!
//! The options are plain data (always compiled, so configurations parse in
//! any build); the OpenCV part is behind the feature.

#[cfg(feature = "vision")]
mod cv;
#[cfg(feature = "vision")]
mod detect;
#[cfg(feature = "vision")]
mod orb;
#[cfg(feature = "vision")]
mod patch_refine;
#[cfg(feature = "vision")]
mod ransac;
#[cfg(feature = "vision")]
mod tracker;

#[cfg(feature = "vision")]
pub use tracker::{Frontend, FrontendError, FrontendOutput, FrontendStats};

use serde::{Deserialize, Serialize};

/// Which corner detector makes new features.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum Detector {
    /// FAST-9 corners with non-maximum suppression (OpenVINS's default).
    Fast,
    /// Shi-Tomasi minimum-eigenvalue corners (`goodFeaturesToTrack`).
    ShiTomasi,
}

/// Contrast normalization before tracking.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum Histogram {
    /// The image as it is.
    None,
    /// Global histogram equalization.
    Equalize,
    /// Contrast-limited adaptive equalization (8x8 tiles, clip limit 2).
    Clahe,
}

/// What a track does when its refinement against its first patch is refused.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum FirstPatch {
    /// No refinement: frame-to-frame KLT alone (OpenVINS's tracker, and the
    /// default until stop 94).
    Off,
    /// Refined; when refused the track keeps its frame-to-frame pixel and
    /// takes the patch there as its new first patch.
    Reanchor,
    /// Refined; when refused the track ends (the default: on the rendered
    /// reference flights its tracks are 0.09 px off the truth against the KLT
    /// alone's 0.6, README "Tracks held to their first patch"). A patch
    /// reaching past the image border keeps the frame-to-frame pixel in both
    /// modes.
    Drop,
}

/// Frontend settings (defaults follow OpenVINS's KLT frontend on EuRoC).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct FrontendOptions {
    /// Tracks to keep alive: new features are detected while fewer are tracked.
    pub num_features: usize,
    /// Detection grid columns: new features are spread over the cells.
    pub grid_cols: usize,
    /// Detection grid rows.
    pub grid_rows: usize,
    /// Smallest distance between two features, pixels.
    pub min_distance_px: f64,
    /// No new feature closer than this to the image border, pixels (ORB needs
    /// about 16 around a keypoint).
    pub border_px: u32,
    /// Corner detector.
    pub detector: Detector,
    /// FAST intensity threshold, gray levels.
    pub fast_threshold: i32,
    /// Contrast normalization.
    pub histogram: Histogram,
    /// KLT window side, pixels.
    pub klt_window_px: i32,
    /// KLT pyramid levels above the full image.
    pub klt_pyramid_levels: i32,
    /// Largest forward-backward KLT disagreement, pixels.
    pub max_forward_backward_px: f64,
    /// Fundamental-matrix RANSAC threshold on undistorted points, pixels.
    pub ransac_threshold_px: f64,
    /// Every this many frames is a keyframe: every track gets a fresh descriptor.
    pub keyframe_interval: u64,
    /// Refinement of each track against the patch it started with
    /// (`patch_refine`): `drop` (the default), `reanchor` or `off`.
    pub first_patch: FirstPatch,
}

impl Default for FrontendOptions {
    fn default() -> Self {
        Self {
            num_features: 200,
            grid_cols: 5,
            grid_rows: 5,
            min_distance_px: 10.0,
            border_px: 20,
            detector: Detector::Fast,
            fast_threshold: 20,
            histogram: Histogram::Equalize,
            klt_window_px: 15,
            klt_pyramid_levels: 4,
            max_forward_backward_px: 1.0,
            ransac_threshold_px: 1.0,
            keyframe_interval: 10,
            first_patch: FirstPatch::Drop,
        }
    }
}

impl FrontendOptions {
    /// Checks the ranges; the message names the bad key.
    pub fn validate(&self) -> Result<(), String> {
        if self.num_features == 0 || self.num_features > 10_000 {
            return Err(format!(
                "num_features must be 1..=10000, got {}",
                self.num_features
            ));
        }
        if self.grid_cols == 0 || self.grid_rows == 0 || self.grid_cols * self.grid_rows > 10_000 {
            return Err("grid_cols and grid_rows must be positive (at most 10000 cells)".into());
        }
        let positive = [
            ("min_distance_px", self.min_distance_px),
            ("max_forward_backward_px", self.max_forward_backward_px),
            ("ransac_threshold_px", self.ransac_threshold_px),
        ];
        for (k, v) in positive {
            if !(v.is_finite() && v > 0.0) {
                return Err(format!("{k} must be positive, got {v}"));
            }
        }
        if !(3..=101).contains(&self.klt_window_px) || self.klt_window_px % 2 == 0 {
            return Err(format!(
                "klt_window_px must be odd in 3..=101, got {}",
                self.klt_window_px
            ));
        }
        if !(0..=8).contains(&self.klt_pyramid_levels) {
            return Err(format!(
                "klt_pyramid_levels must be 0..=8, got {}",
                self.klt_pyramid_levels
            ));
        }
        if !(1..=255).contains(&self.fast_threshold) {
            return Err(format!(
                "fast_threshold must be 1..=255, got {}",
                self.fast_threshold
            ));
        }
        if self.keyframe_interval == 0 {
            return Err("keyframe_interval must be at least 1".into());
        }
        Ok(())
    }
}
