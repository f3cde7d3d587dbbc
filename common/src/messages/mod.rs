//! What agents send each other (thesis Section 5.3): feature tracks, ORB
//! descriptors, state snapshots and a heartbeat, in a versioned envelope.
//!
//! The transport moves opaque bytes; this module owns their meaning.
//!
//! * [`Envelope`]: fleet id, robot id, sequence number, send time and a [`Body`]:
//!   [`TrackFrame`] (every frame), [`DescriptorBatch`] (new tracks, keyframes),
//!   [`StateSnapshot`] (the sliding window with covariance), [`Heartbeat`], and
//!   for history catch-up [`HistoryRequest`] and [`HistoryReplay`] ([`history`]).
//! * [`encode`] / [`decode`] ([`decode_with`] for other [`Limits`]): the wire
//!   format, `b"FVIO"`, a little-endian `u16` [`WIRE_VERSION`], then bincode 2
//!   (serde, standard configuration). Decoding is bounded and validates the
//!   content; encoding refuses what peers would reject.
//! * [`samples`]: realistic messages of each kind and their size budgets.
//!
//! # Camera poses, not IMU poses
//! A snapshot carries the pose of the **camera** of each clone, `(R_CtoG,
//! p_CinG)`, and the covariance of those camera poses. The sender's filter
//! estimates IMU poses together with the camera-IMU extrinsics, intrinsics and
//! time offset, all correlated. Mapping its IMU poses through its current
//! extrinsics (with the Jacobian of that map, extrinsic blocks included, applied
//! to its covariance) folds the calibration, and its uncertainty, into what is
//! sent. A peer that relates its own observations to the sender's camera then
//! needs neither the sender's calibration nor the calibration's covariance and
//! cross-covariance, which would otherwise have to be sent and kept consistent.
//! The intrinsics do travel ([`CameraModelWire`], point values), but only to
//! interpret the raw pixels of [`TrackPoint::uv_px`]; the undistorted
//! [`TrackPoint::xy_norm`] already applies them. So does the sender's pixel
//! noise ([`StateSnapshot::pixel_sigma_px`]): a peer weighs the sender's
//! tracks at it, through the sender's lens.
//!
//! # Covariance in `f32`
//! [`PackedCovariance`] stores the lower triangle in `f32`: for the usual
//! 11-clone window (66x66, 2211 entries) that is 8.8 KB per snapshot instead of
//! 17.7 KB in `f64`, the bulk of the snapshot. `f32` has a 24-bit significand,
//! so every entry keeps a relative precision of 2⁻²⁴ ≈ 6e-8 (7 significant
//! digits) over the normal range 1e-38 … 3e38, far wider than the variances that
//! occur ((1e-6 rad)² … (1e3 m)²); uncertainties are known to a few percent at
//! best. What rounding can lose is a correlation within about 1e-7 of ±1, i.e.
//! the smallest eigenvalues of a nearly singular matrix, which may come out
//! slightly negative (15 % of the EuRoC fleet's windows, stop 47): a receiver
//! takes [`PackedCovariance::to_dmatrix_at_least_sent`], which raises each
//! variance by the rounding bound of its row so that the matrix is at least
//! the sender's, and checks a Cholesky factorization before trusting it.
//! Poses, positions and times stay `f64`: metres over a building with
//! sub-millimetre resolution, and seconds over hours with microseconds, are
//! beyond `f32`.

mod body;
mod bounded_vec;
mod codec;
mod envelope;
pub mod history;
mod packed_cov;
pub mod samples;
mod validate;

pub use body::{
    AgentState, Body, CameraModelWire, CameraPose, DescriptorBatch, DescriptorEntry,
    DistortionWire, Heartbeat, Landmark, StateSnapshot, TrackFrame, TrackPoint,
};
pub use codec::{
    decode, decode_with, encode, encode_with, DecodeError, EncodeError, DECODE_CLAIM_LIMIT_BYTES,
    HEADER_LEN, MAGIC, SUPPORTED_VERSIONS, WIRE_VERSION,
};
pub use envelope::Envelope;
pub use history::{
    AnsweredWindow, HeldWindow, HistoryReplay, HistoryRequest, HistoryWindow, RequestRef,
    TimeRange, WindowFrame, WindowObservation, WindowPart,
};
pub use packed_cov::{cover_f32_rounding, PackedCovariance};
pub use validate::{
    Limits, ValidationError, FLEET_ID_FORBIDDEN_CHARS, INTRINSICS_DIM, MAX_ANSWERED_WINDOWS,
    MAX_FLEET_ID_BYTES, MAX_HELD_WINDOWS, MAX_PIXEL_SIGMA_PX, MAX_REPLAY_ROBOTS,
    MAX_REQUEST_RANGES, QUATERNION_NORM_TOLERANCE,
};

use serde::{Deserialize, Serialize};

/// The kind of a message: the last segment of its key expression
/// (`fleet/<fleet-id>/<robot-id>/<kind>`).
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, PartialOrd, Ord, Serialize, Deserialize)]
pub enum MessageKind {
    /// Per camera frame: the active feature tracks.
    Tracks,
    /// 256-bit descriptors of new tracks and of keyframes.
    Descriptors,
    /// Sliding-window state with covariance (and keyframe windows for histories).
    Snapshot,
    /// Presence and progress (the fleet clock in lockstep runs).
    Heartbeat,
    /// A request for a peer's keyframe windows (history catch-up).
    HistoryRequest,
    /// Keyframe windows sent again on request.
    HistoryReplay,
}

impl MessageKind {
    /// Every kind, in wire order.
    pub const ALL: [MessageKind; 6] = [
        MessageKind::Tracks,
        MessageKind::Descriptors,
        MessageKind::Snapshot,
        MessageKind::Heartbeat,
        MessageKind::HistoryRequest,
        MessageKind::HistoryReplay,
    ];

    /// The key-expression segment of this kind.
    pub fn as_str(self) -> &'static str {
        match self {
            MessageKind::Tracks => "tracks",
            MessageKind::Descriptors => "descriptors",
            MessageKind::Snapshot => "snapshot",
            MessageKind::Heartbeat => "heartbeat",
            MessageKind::HistoryRequest => "history_request",
            MessageKind::HistoryReplay => "history",
        }
    }

    /// The kind named by a key-expression segment.
    pub fn from_segment(s: &str) -> Option<MessageKind> {
        MessageKind::ALL.into_iter().find(|k| k.as_str() == s)
    }
}
