//! The envelope around every message: who sent it, in which order, when.

use serde::{Deserialize, Serialize};

use super::body::Body;
use super::MessageKind;

/// One message from one agent: sender, sequence number, send time and body.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct Envelope {
    /// The fleet the sender belongs to (non-empty, at most
    /// [`super::MAX_FLEET_ID_BYTES`] bytes, a valid key-expression segment);
    /// receivers drop messages of other fleets.
    pub fleet_id: String,
    /// The sender's robot id.
    pub robot_id: u32,
    /// Per sender and per kind, incremented by one for each message sent, from 0;
    /// a gap tells the receiver that messages were lost.
    pub seq: u64,
    /// Send time in seconds on the sender's clock (the fleet clock in simulation).
    pub stamp_s: f64,
    /// Wall-clock send time, nanoseconds since the Unix epoch (0: unknown). Only
    /// for latency statistics between hosts with synchronized clocks; never used
    /// by the estimator.
    pub sent_wall_ns: u64,
    /// The content.
    pub body: Body,
}

impl Envelope {
    /// The kind of the body (the last segment of the message's key expression).
    pub fn kind(&self) -> MessageKind {
        self.body.kind()
    }
}
