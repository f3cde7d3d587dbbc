//! Content checks of an [`Envelope`]: what a receiver can rely on after
//! [`super::decode`], and what [`super::encode`] refuses to send.

use thiserror::Error;

use super::body::{Body, CameraPose, DescriptorBatch, Heartbeat, StateSnapshot, TrackFrame};
use super::envelope::Envelope;
use super::history::{HistoryReplay, HistoryRequest, HistoryWindow, WindowFrame, WindowPart};
use super::packed_cov::PackedCovariance;
use crate::camera::{CameraError, CameraModel};

/// Longest fleet id in bytes.
pub const MAX_FLEET_ID_BYTES: usize = 64;

/// Characters a fleet id may not contain: it is a segment of the key expression
/// `fleet/<fleet-id>/<robot-id>/<kind>`, where these have meanings.
pub const FLEET_ID_FORBIDDEN_CHARS: &[char] = &['/', '*', '$', '?', '#'];

/// Largest accepted deviation of a clone quaternion's norm from 1.
pub const QUATERNION_NORM_TOLERANCE: f64 = 1e-3;

/// Size and count limits of a message; the defaults suit every scenario of the
/// workspace with a wide margin.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct Limits {
    /// Largest encoded message (header included) in bytes; checked before
    /// anything else when decoding. Default 1 MiB.
    pub max_message_bytes: usize,
    /// Most features in a [`TrackFrame`]. Default 4096.
    pub max_features: usize,
    /// Most entries in a [`DescriptorBatch`]. Default 4096.
    pub max_descriptor_entries: usize,
    /// Most clones in a [`StateSnapshot`]. Default 64.
    pub max_clones: usize,
    /// Most landmarks in a [`StateSnapshot`]. Default 1024.
    pub max_landmarks: usize,
}

impl Default for Limits {
    fn default() -> Self {
        Self {
            max_message_bytes: 1 << 20,
            max_features: 4096,
            max_descriptor_entries: 4096,
            max_clones: 64,
            max_landmarks: 1024,
        }
    }
}

/// Why a message's content is invalid.
#[derive(Clone, Debug, PartialEq, Error)]
pub enum ValidationError {
    /// A float is NaN or infinite.
    #[error("{field} is not finite: {value}")]
    NonFinite {
        /// Path of the field, e.g. `snapshot.clones[3].p_m[2]`.
        field: String,
        /// Its value.
        value: f64,
    },
    /// The fleet id is empty.
    #[error("fleet_id is empty")]
    EmptyFleetId,
    /// The fleet id is too long.
    #[error("fleet_id is {len} bytes long, at most {max} are allowed")]
    FleetIdTooLong {
        /// Its length in bytes.
        len: usize,
        /// [`MAX_FLEET_ID_BYTES`].
        max: usize,
    },
    /// The fleet id contains a key-expression character or a control character.
    #[error("fleet_id contains {ch:?}, which cannot appear in a key-expression segment")]
    FleetIdCharacter {
        /// The offending character.
        ch: char,
    },
    /// A list is longer than its limit.
    #[error("{field} has {count} elements, the limit is {max}")]
    TooMany {
        /// Which list.
        field: &'static str,
        /// Its length.
        count: usize,
        /// The limit in [`Limits`].
        max: usize,
    },
    /// A matrix to pack as a covariance is not square.
    #[error("a covariance must be square, got {rows}x{cols}")]
    CovarianceNotSquare {
        /// Rows.
        rows: usize,
        /// Columns.
        cols: usize,
    },
    /// The covariance dimension does not match the number of clones.
    #[error(
        "covariance dim is {dim}, but {clones} clones need 6 x {clones} = {expected} \
         (or 8 more with the camera intrinsics)"
    )]
    CovarianceDim {
        /// The declared dimension.
        dim: u32,
        /// Number of clones.
        clones: usize,
        /// `6 · clones`.
        expected: usize,
    },
    /// The packed triangle has the wrong number of entries.
    #[error("covariance of dim {dim} needs {expected} packed entries, got {len}")]
    CovarianceLength {
        /// The declared dimension.
        dim: u32,
        /// `dim (dim + 1) / 2`.
        expected: usize,
        /// `lower.len()`.
        len: usize,
    },
    /// A variance (diagonal entry) is zero or negative.
    #[error("{field} is a variance and must be positive, got {value}")]
    NonPositiveVariance {
        /// Path of the entry, e.g. `snapshot.covariance[13][13]`.
        field: String,
        /// Its value.
        value: f64,
    },
    /// A clone quaternion is not of unit norm.
    #[error(
        "snapshot.clones[{index}].q_xyzw has norm {norm}, \
         which is not within {QUATERNION_NORM_TOLERANCE} of 1"
    )]
    QuaternionNorm {
        /// Index of the clone.
        index: usize,
        /// The quaternion's norm.
        norm: f64,
    },
    /// Clone timestamps decrease.
    #[error(
        "snapshot.clones[{index}].t_s = {t_s} is before the previous clone's {previous_t_s}: \
         clones must be oldest first"
    )]
    ClonesOutOfOrder {
        /// Index of the later clone.
        index: usize,
        /// Its timestamp.
        t_s: f64,
        /// The timestamp of the clone before it.
        previous_t_s: f64,
    },
    /// The snapshot's pixel noise is not a positive number of pixels up to
    /// [`MAX_PIXEL_SIGMA_PX`].
    #[error(
        "snapshot.pixel_sigma_px must be positive and at most {MAX_PIXEL_SIGMA_PX} px, got {0}"
    )]
    PixelSigma(f64),
    /// The snapshot's camera model is unusable.
    #[error("snapshot.camera: {0}")]
    Camera(#[from] CameraError),
    /// A requested time range is empty (its start is not before its end).
    #[error("history_request.ranges[{index}] is empty: after {after_s} s, up to {up_to_s} s")]
    EmptyRange {
        /// Index of the range.
        index: usize,
        /// Its start.
        after_s: f64,
        /// Its end.
        up_to_s: f64,
    },
    /// A replayed window's snapshot is not a keyframe snapshot.
    #[error("history.window.snapshot is not a keyframe snapshot")]
    ReplayNotKeyframe,
    /// A replayed window's frame is not at one of its clone times, or out of order.
    #[error(
        "history.window.frames[{index}].t_s = {t_s} is not the time of a later clone \
         of the window"
    )]
    ReplayFrameTime {
        /// Index of the frame.
        index: usize,
        /// Its time.
        t_s: f64,
    },
    /// A replay carries both a whole window and a part of one.
    #[error("history carries both a window and a part: at most one")]
    ReplayWindowAndPart,
    /// A replayed part's frames are not in increasing time order.
    #[error(
        "history.part.frames[{index}].t_s = {t_s} is not after the frame before it: \
         frames must be oldest first"
    )]
    PartFramesOutOfOrder {
        /// Index of the frame.
        index: usize,
        /// Its time.
        t_s: f64,
    },
}

/// Largest pixel noise a snapshot may declare, pixels (a camera that bad
/// tracks nothing; a larger value is a corrupt message).
pub const MAX_PIXEL_SIGMA_PX: f64 = 100.0;

/// Most ranges in one [`HistoryRequest`].
pub const MAX_REQUEST_RANGES: usize = 64;

/// Most robots a [`HistoryReplay`] names (as asking, or as answered).
pub const MAX_REPLAY_ROBOTS: usize = 1024;

/// Most windows a [`HistoryReplay`] lists as answered (an hour of keyframe
/// windows at one per 0.25 s).
pub const MAX_ANSWERED_WINDOWS: usize = 16_384;

/// Most windows a [`HistoryRequest`] lists as held short of some parts (a
/// request that would list more asks for the rest whole).
pub const MAX_HELD_WINDOWS: usize = 4096;

/// `Ok` if `value` is finite, else a [`ValidationError::NonFinite`] naming it
/// (the name is only built on failure).
fn finite(value: f64, field: impl FnOnce() -> String) -> Result<(), ValidationError> {
    if value.is_finite() {
        Ok(())
    } else {
        Err(ValidationError::NonFinite {
            field: field(),
            value,
        })
    }
}

/// Checks every entry of a float array.
fn all_finite<T: Copy + Into<f64>>(
    values: &[T],
    field: impl Fn() -> String,
) -> Result<(), ValidationError> {
    for (k, &v) in values.iter().enumerate() {
        finite(v.into(), || format!("{}[{k}]", field()))?;
    }
    Ok(())
}

fn count(field: &'static str, count: usize, max: usize) -> Result<(), ValidationError> {
    if count > max {
        Err(ValidationError::TooMany { field, count, max })
    } else {
        Ok(())
    }
}

fn positive_variance(value: f64, field: impl FnOnce() -> String) -> Result<(), ValidationError> {
    // NaN was rejected before; `!(v > 0)` would also catch it.
    if value > 0.0 {
        Ok(())
    } else {
        Err(ValidationError::NonPositiveVariance {
            field: field(),
            value,
        })
    }
}

impl Envelope {
    /// Checks the content against `limits` (see [`super::decode_with`] for the list).
    pub fn validate(&self, limits: &Limits) -> Result<(), ValidationError> {
        validate_fleet_id(&self.fleet_id)?;
        finite(self.stamp_s, || "stamp_s".into())?;
        match &self.body {
            Body::Tracks(t) => validate_tracks(t, limits),
            Body::Descriptors(d) => validate_descriptors(d, limits),
            Body::Snapshot(s) => validate_snapshot(s, limits),
            Body::Heartbeat(h) => validate_heartbeat(h),
            Body::HistoryRequest(r) => validate_history_request(r),
            Body::HistoryReplay(r) => validate_history_replay(r, limits),
        }
    }
}

fn validate_fleet_id(id: &str) -> Result<(), ValidationError> {
    if id.is_empty() {
        return Err(ValidationError::EmptyFleetId);
    }
    if id.len() > MAX_FLEET_ID_BYTES {
        return Err(ValidationError::FleetIdTooLong {
            len: id.len(),
            max: MAX_FLEET_ID_BYTES,
        });
    }
    match id
        .chars()
        .find(|c| c.is_control() || FLEET_ID_FORBIDDEN_CHARS.contains(c))
    {
        Some(ch) => Err(ValidationError::FleetIdCharacter { ch }),
        None => Ok(()),
    }
}

fn validate_tracks(t: &TrackFrame, limits: &Limits) -> Result<(), ValidationError> {
    finite(t.t_s, || "tracks.t_s".into())?;
    count("tracks.features", t.features.len(), limits.max_features)?;
    for (i, f) in t.features.iter().enumerate() {
        all_finite(&f.uv_px, || format!("tracks.features[{i}].uv_px"))?;
        all_finite(&f.xy_norm, || format!("tracks.features[{i}].xy_norm"))?;
    }
    Ok(())
}

fn validate_descriptors(d: &DescriptorBatch, limits: &Limits) -> Result<(), ValidationError> {
    finite(d.t_s, || "descriptors.t_s".into())?;
    count(
        "descriptors.entries",
        d.entries.len(),
        limits.max_descriptor_entries,
    )
}

fn validate_clone(i: usize, c: &CameraPose) -> Result<(), ValidationError> {
    finite(c.t_s, || format!("snapshot.clones[{i}].t_s"))?;
    all_finite(&c.q_xyzw, || format!("snapshot.clones[{i}].q_xyzw"))?;
    all_finite(&c.p_m, || format!("snapshot.clones[{i}].p_m"))?;
    let norm = c.q_xyzw.iter().map(|v| v * v).sum::<f64>().sqrt();
    if (norm - 1.0).abs() > QUATERNION_NORM_TOLERANCE {
        return Err(ValidationError::QuaternionNorm { index: i, norm });
    }
    Ok(())
}

fn validate_covariance(cov: &PackedCovariance, clones: usize) -> Result<(), ValidationError> {
    let poses = clones.saturating_mul(6);
    let expected = cov.dim as usize;
    if expected != poses && expected != poses.saturating_add(INTRINSICS_DIM) {
        return Err(ValidationError::CovarianceDim {
            dim: cov.dim,
            clones,
            expected: poses,
        });
    }
    let expected_len = PackedCovariance::packed_len(expected);
    if cov.lower.len() != expected_len {
        return Err(ValidationError::CovarianceLength {
            dim: cov.dim,
            expected: expected_len,
            len: cov.lower.len(),
        });
    }
    let mut k = 0;
    for row in 0..expected {
        for col in 0..=row {
            let v = f64::from(cov.lower[k]);
            finite(v, || format!("snapshot.covariance[{row}][{col}]"))?;
            if row == col {
                positive_variance(v, || format!("snapshot.covariance[{row}][{row}]"))?;
            }
            k += 1;
        }
    }
    Ok(())
}

/// Size of the intrinsics block a snapshot covariance may end with.
pub const INTRINSICS_DIM: usize = 8;

fn validate_snapshot(s: &StateSnapshot, limits: &Limits) -> Result<(), ValidationError> {
    finite(s.t_s, || "snapshot.t_s".into())?;
    if !(s.pixel_sigma_px > 0.0 && s.pixel_sigma_px <= MAX_PIXEL_SIGMA_PX) {
        return Err(ValidationError::PixelSigma(s.pixel_sigma_px));
    }
    CameraModel::from(&s.camera).validate()?;
    count("snapshot.clones", s.clones.len(), limits.max_clones)?;
    count(
        "snapshot.landmarks",
        s.landmarks.len(),
        limits.max_landmarks,
    )?;
    for (i, c) in s.clones.iter().enumerate() {
        validate_clone(i, c)?;
    }
    for (i, pair) in s.clones.windows(2).enumerate() {
        if pair[1].t_s < pair[0].t_s {
            return Err(ValidationError::ClonesOutOfOrder {
                index: i + 1,
                t_s: pair[1].t_s,
                previous_t_s: pair[0].t_s,
            });
        }
    }
    validate_covariance(&s.covariance, s.clones.len())?;
    for (i, l) in s.landmarks.iter().enumerate() {
        all_finite(&l.p_m, || format!("snapshot.landmarks[{i}].p_m"))?;
        all_finite(&l.cov_upper, || {
            format!("snapshot.landmarks[{i}].cov_upper")
        })?;
        for (k, name) in [(0, "xx"), (3, "yy"), (5, "zz")] {
            positive_variance(f64::from(l.cov_upper[k]), || {
                format!("snapshot.landmarks[{i}].cov_upper.{name}")
            })?;
        }
    }
    Ok(())
}

fn validate_heartbeat(h: &Heartbeat) -> Result<(), ValidationError> {
    if let Some(t) = h.last_t_s {
        finite(t, || "heartbeat.last_t_s".into())?;
    }
    if let Some(t) = h.newest_window_end_s {
        finite(t, || "heartbeat.newest_window_end_s".into())?;
    }
    Ok(())
}

fn validate_history_request(r: &HistoryRequest) -> Result<(), ValidationError> {
    count("history_request.ranges", r.ranges.len(), MAX_REQUEST_RANGES)?;
    for (i, range) in r.ranges.iter().enumerate() {
        if let Some(a) = range.after_s {
            finite(a, || format!("history_request.ranges[{i}].after_s"))?;
        }
        if let Some(b) = range.up_to_s {
            finite(b, || format!("history_request.ranges[{i}].up_to_s"))?;
        }
        if let (Some(after_s), Some(up_to_s)) = (range.after_s, range.up_to_s) {
            if after_s >= up_to_s {
                return Err(ValidationError::EmptyRange {
                    index: i,
                    after_s,
                    up_to_s,
                });
            }
        }
    }
    count("history_request.held", r.held.len(), MAX_HELD_WINDOWS)?;
    for (i, h) in r.held.iter().enumerate() {
        finite(h.end_s, || format!("history_request.held[{i}].end_s"))?;
    }
    Ok(())
}

fn validate_history_replay(r: &HistoryReplay, limits: &Limits) -> Result<(), ValidationError> {
    count("history.for_robots", r.for_robots.len(), MAX_REPLAY_ROBOTS)?;
    count("history.completes", r.completes.len(), MAX_REPLAY_ROBOTS)?;
    count("history.answered", r.answered.len(), MAX_ANSWERED_WINDOWS)?;
    for (i, a) in r.answered.iter().enumerate() {
        finite(a.end_s, || format!("history.answered[{i}].end_s"))?;
    }
    match (&r.window, &r.part) {
        (Some(_), Some(_)) => Err(ValidationError::ReplayWindowAndPart),
        (Some(w), None) => validate_history_window(w, limits),
        (None, Some(p)) => validate_window_part(p, limits),
        (None, None) => Ok(()),
    }
}

/// A replayed part: at most one frame per possible clone, oldest first, and
/// at most a keyframe's descriptors. Which clones the frames belong to is
/// checked by the requester against the window it holds.
fn validate_window_part(p: &WindowPart, limits: &Limits) -> Result<(), ValidationError> {
    finite(p.end_s, || "history.part.end_s".into())?;
    count("history.part.frames", p.frames.len(), limits.max_clones)?;
    count(
        "history.part.descriptors",
        p.descriptors.len(),
        limits.max_descriptor_entries,
    )?;
    let mut previous = f64::NEG_INFINITY;
    for (i, f) in p.frames.iter().enumerate() {
        finite(f.t_s, || format!("history.part.frames[{i}].t_s"))?;
        if f.t_s <= previous {
            return Err(ValidationError::PartFramesOutOfOrder {
                index: i,
                t_s: f.t_s,
            });
        }
        previous = f.t_s;
        validate_window_frame(
            "history.part.frames",
            "history.part.frames.observations",
            i,
            f,
            limits,
        )?;
    }
    Ok(())
}

/// The measurements of a replayed frame: bounded and finite.
/// `frames` names the frames (`history.window.frames`), `observations` their
/// observations for a count error.
fn validate_window_frame(
    frames: &str,
    observations: &'static str,
    i: usize,
    f: &WindowFrame,
    limits: &Limits,
) -> Result<(), ValidationError> {
    count(observations, f.observations.len(), limits.max_features)?;
    for (k, o) in f.observations.iter().enumerate() {
        all_finite(&o.xy_norm, || {
            format!("{frames}[{i}].observations[{k}].xy_norm")
        })?;
    }
    Ok(())
}

/// A replayed window: a valid keyframe snapshot, and at most one frame per
/// clone, each at a clone's time, oldest first.
fn validate_history_window(w: &HistoryWindow, limits: &Limits) -> Result<(), ValidationError> {
    validate_snapshot(&w.snapshot, limits)?;
    if !w.snapshot.keyframe {
        return Err(ValidationError::ReplayNotKeyframe);
    }
    count(
        "history.window.frames",
        w.frames.len(),
        w.snapshot.clones.len(),
    )?;
    count(
        "history.window.descriptors",
        w.descriptors.len(),
        limits.max_descriptor_entries,
    )?;
    // Clones are oldest first (checked above): each frame must take a later
    // clone than the frame before it.
    let mut clones = w.snapshot.clones.iter();
    for (i, f) in w.frames.iter().enumerate() {
        finite(f.t_s, || format!("history.window.frames[{i}].t_s"))?;
        if !clones.any(|c| c.t_s == f.t_s) {
            return Err(ValidationError::ReplayFrameTime {
                index: i,
                t_s: f.t_s,
            });
        }
        validate_window_frame(
            "history.window.frames",
            "history.window.frames.observations",
            i,
            f,
            limits,
        )?;
    }
    Ok(())
}
