//! What agents send each other (thesis Section 5.3): feature tracks, ORB
//! descriptors, state snapshots and a heartbeat, in a versioned envelope.
//!
//! The transport moves opaque bytes; this module owns their meaning.

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
}

impl MessageKind {
    /// Every kind, in wire order.
    pub const ALL: [MessageKind; 4] = [
        MessageKind::Tracks,
        MessageKind::Descriptors,
        MessageKind::Snapshot,
        MessageKind::Heartbeat,
    ];

    /// The key-expression segment of this kind.
    pub fn as_str(self) -> &'static str {
        match self {
            MessageKind::Tracks => "tracks",
            MessageKind::Descriptors => "descriptors",
            MessageKind::Snapshot => "snapshot",
            MessageKind::Heartbeat => "heartbeat",
        }
    }

    /// The kind named by a key-expression segment.
    pub fn from_segment(s: &str) -> Option<MessageKind> {
        MessageKind::ALL.into_iter().find(|k| k.as_str() == s)
    }
}
