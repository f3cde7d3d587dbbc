//! Everything that arrives from peers passes here: decoded with bounds, checked
//! (fleet, sender, kind, sequence), counted, and either accepted or dropped with
//! a reason. Nothing a peer sends can stop the agent.

use crate::transport::Received;
use common::messages::{decode, Envelope, MessageKind};
use serde::Serialize;
use std::collections::{BTreeMap, BTreeSet};

/// Traffic of one message kind.
#[derive(Clone, Copy, Debug, Default, PartialEq, Serialize)]
pub struct KindCounts {
    /// Messages sent.
    pub sent: u64,
    /// Bytes sent (encoded payloads).
    pub sent_bytes: u64,
    /// Messages received and accepted.
    pub received: u64,
    /// Bytes received and accepted.
    pub received_bytes: u64,
}

/// Why a received payload was dropped.
#[derive(Clone, Copy, Debug, PartialEq, Eq, PartialOrd, Ord, Serialize)]
#[serde(rename_all = "snake_case")]
pub enum DropReason {
    /// It did not decode (corrupt, truncated, unknown version, invalid content).
    Malformed,
    /// It belongs to another fleet.
    ForeignFleet,
    /// The envelope names a different sender than the transport delivered it from.
    SenderMismatch,
    /// The body kind differs from the channel it came on.
    KindMismatch,
    /// It claims to come from this agent.
    FromSelf,
    /// Its sender would be one peer more than the agent keeps (`history.max_peers`).
    TooManyPeers,
    /// Its sender's messages waiting for the fleet clock already fill that peer's
    /// memory bound: it sends faster than the fleet runs.
    Backlog,
    /// Its sender exceeded `history.max_peer_mib_per_s` (dropped undecoded).
    RateLimit,
}

/// A byte budget per peer that refills at a fixed rate (a token bucket holding
/// at most one second's worth): what a flooding peer sends beyond it is dropped
/// before it costs a decode.
#[derive(Debug)]
pub struct PeerRates {
    bytes_per_s: f64,
    /// Per peer: bytes still allowed, and when that was computed (s).
    buckets: BTreeMap<u32, (f64, f64)>,
}

impl PeerRates {
    /// `bytes_per_s` per peer, with a burst of one second's worth.
    pub fn new(bytes_per_s: f64) -> Self {
        Self {
            bytes_per_s,
            buckets: BTreeMap::new(),
        }
    }

    /// Whether `peer` may send `bytes` more at wall time `now_s`; if so they
    /// are taken from its budget. Only admitted peers should be asked (the map
    /// grows with the peers asked about).
    pub fn admit(&mut self, peer: u32, bytes: usize, now_s: f64) -> bool {
        let cap = self.bytes_per_s;
        let (left, at) = self.buckets.entry(peer).or_insert((cap, now_s));
        *left = (*left + (now_s - *at).max(0.0) * cap).min(cap);
        *at = now_s;
        let b = bytes as f64;
        if b > *left {
            return false;
        }
        *left -= b;
        true
    }
}

/// Traffic statistics of one agent.
#[derive(Clone, Debug, Default, Serialize)]
pub struct NetStats {
    /// Per kind.
    pub kinds: BTreeMap<MessageKind, KindCounts>,
    /// Per peer: accepted messages received, per kind.
    pub received_from: BTreeMap<u32, BTreeMap<MessageKind, u64>>,
    /// Dropped payloads by reason.
    pub dropped: BTreeMap<DropReason, u64>,
    /// Messages missing in a peer's sequence numbers (lost in transit).
    pub sequence_gaps: u64,
    /// The first few drop explanations, for the log.
    #[serde(skip)]
    pub drop_samples: Vec<String>,
}

impl NetStats {
    /// Counts a message sent.
    pub fn sent(&mut self, kind: MessageKind, bytes: usize) {
        let k = self.kinds.entry(kind).or_default();
        k.sent += 1;
        k.sent_bytes += bytes as u64;
    }

    /// Total bytes sent.
    pub fn bytes_sent(&self) -> u64 {
        self.kinds.values().map(|k| k.sent_bytes).sum()
    }

    /// Total bytes received and accepted.
    pub fn bytes_received(&self) -> u64 {
        self.kinds.values().map(|k| k.received_bytes).sum()
    }

    /// Counts a dropped payload, keeping the first explanations for the log.
    pub fn drop(&mut self, reason: DropReason, why: String) {
        *self.dropped.entry(reason).or_default() += 1;
        if self.drop_samples.len() < 20 {
            self.drop_samples.push(why);
        }
    }
}

/// Decodes and checks received payloads.
#[derive(Debug)]
pub struct Inbox {
    fleet_id: String,
    robot_id: u32,
    /// Peers admitted so far; at most `max_peers`, first come first served, so
    /// one sender forging many robot ids cannot grow what the agent keeps.
    peers: BTreeSet<u32>,
    max_peers: usize,
    /// Next expected sequence number per (peer, kind).
    next_seq: BTreeMap<(u32, MessageKind), u64>,
}

impl Inbox {
    /// The inbox of robot `robot_id` in fleet `fleet_id`, admitting at most
    /// `max_peers` distinct peers.
    pub fn new(fleet_id: &str, robot_id: u32, max_peers: usize) -> Self {
        Self {
            fleet_id: fleet_id.to_string(),
            robot_id,
            peers: BTreeSet::new(),
            max_peers,
            next_seq: BTreeMap::new(),
        }
    }

    /// Whether a message from `peer` can still be admitted: the peer is known,
    /// or there is room for one more. Asked before decoding, so that forged
    /// robot ids beyond the limit cost nothing.
    pub fn has_room_for(&self, peer: u32) -> bool {
        self.peers.contains(&peer) || self.peers.len() < self.max_peers
    }

    /// The envelope of `msg` if it is acceptable; otherwise counts why not.
    pub fn accept(&mut self, msg: &Received, stats: &mut NetStats) -> Option<Envelope> {
        let env = match decode(&msg.bytes) {
            Ok(e) => e,
            Err(e) => {
                stats.drop(
                    DropReason::Malformed,
                    format!(
                        "{} bytes of {:?} from robot {}: {e}",
                        msg.bytes.len(),
                        msg.kind,
                        msg.from_robot
                    ),
                );
                return None;
            }
        };
        if env.fleet_id != self.fleet_id {
            stats.drop(
                DropReason::ForeignFleet,
                format!(
                    "{:?} of fleet `{}` (ours is `{}`) from robot {}",
                    env.kind(),
                    env.fleet_id,
                    self.fleet_id,
                    msg.from_robot
                ),
            );
            return None;
        }
        if env.robot_id == self.robot_id {
            stats.drop(
                DropReason::FromSelf,
                format!("{:?} claiming to be from this robot", env.kind()),
            );
            return None;
        }
        if env.robot_id != msg.from_robot {
            stats.drop(
                DropReason::SenderMismatch,
                format!(
                    "{:?} from robot {} claims robot {}",
                    env.kind(),
                    msg.from_robot,
                    env.robot_id
                ),
            );
            return None;
        }
        if env.kind() != msg.kind {
            stats.drop(
                DropReason::KindMismatch,
                format!("{:?} body on the {:?} channel", env.kind(), msg.kind),
            );
            return None;
        }
        if !self.peers.contains(&env.robot_id) {
            if self.peers.len() >= self.max_peers {
                stats.drop(
                    DropReason::TooManyPeers,
                    format!(
                        "{:?} from robot {}: already {} peers",
                        env.kind(),
                        env.robot_id,
                        self.max_peers
                    ),
                );
                return None;
            }
            self.peers.insert(env.robot_id);
        }
        let next = self.next_seq.entry((env.robot_id, env.kind())).or_insert(0);
        // A restarted peer numbers from 0 again: only forward jumps are losses.
        if env.seq > *next {
            stats.sequence_gaps += env.seq - *next;
        }
        *next = env.seq + 1;
        let k = stats.kinds.entry(env.kind()).or_default();
        k.received += 1;
        k.received_bytes += msg.bytes.len() as u64;
        *stats
            .received_from
            .entry(env.robot_id)
            .or_default()
            .entry(env.kind())
            .or_default() += 1;
        Some(env)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use common::messages::{encode, AgentState, Body, Heartbeat};

    fn heartbeat(fleet: &str, robot: u32, seq: u64) -> Vec<u8> {
        encode(&Envelope {
            fleet_id: fleet.into(),
            robot_id: robot,
            seq,
            stamp_s: 1.0,
            sent_wall_ns: 0,
            body: Body::Heartbeat(Heartbeat {
                state: AgentState::Running,
                frames_done: 3,
                last_frame_index: Some(2),
                last_t_s: Some(1.0),
                newest_window_end_s: None,
            }),
        })
        .unwrap()
    }

    fn received(from: u32, kind: MessageKind, bytes: Vec<u8>) -> Received {
        Received {
            from_robot: from,
            kind,
            bytes,
        }
    }

    #[test]
    fn bad_payloads_are_dropped_and_counted_by_reason() {
        let mut inbox = Inbox::new("a", 0, 8);
        let mut st = NetStats::default();
        let hb = MessageKind::Heartbeat;
        assert!(inbox
            .accept(&received(1, hb, vec![1, 2, 3]), &mut st)
            .is_none());
        assert!(inbox
            .accept(&received(1, hb, heartbeat("b", 1, 0)), &mut st)
            .is_none());
        assert!(inbox
            .accept(&received(1, hb, heartbeat("a", 2, 0)), &mut st)
            .is_none());
        assert!(inbox
            .accept(&received(0, hb, heartbeat("a", 0, 0)), &mut st)
            .is_none());
        assert!(inbox
            .accept(
                &received(1, MessageKind::Tracks, heartbeat("a", 1, 0)),
                &mut st
            )
            .is_none());
        for r in [
            DropReason::Malformed,
            DropReason::ForeignFleet,
            DropReason::SenderMismatch,
            DropReason::FromSelf,
            DropReason::KindMismatch,
        ] {
            assert_eq!(st.dropped.get(&r), Some(&1), "{r:?}");
        }
        assert!(inbox
            .accept(&received(1, hb, heartbeat("a", 1, 0)), &mut st)
            .is_some());
        assert_eq!(st.kinds[&hb].received, 1);
    }

    #[test]
    fn sequence_gaps_count_lost_messages() {
        let mut inbox = Inbox::new("a", 0, 8);
        let mut st = NetStats::default();
        let hb = MessageKind::Heartbeat;
        for seq in [0, 1, 4, 5, 0, 1] {
            inbox.accept(&received(1, hb, heartbeat("a", 1, seq)), &mut st);
        }
        assert_eq!(st.sequence_gaps, 2);
        assert_eq!(st.received_from[&1][&hb], 6);
    }

    #[test]
    fn peers_beyond_the_limit_are_dropped_and_the_admitted_stay() {
        let mut inbox = Inbox::new("a", 0, 2);
        let mut st = NetStats::default();
        let hb = MessageKind::Heartbeat;
        for robot in [1, 2, 3, 4, 1, 2] {
            inbox.accept(&received(robot, hb, heartbeat("a", robot, 0)), &mut st);
        }
        assert_eq!(st.dropped.get(&DropReason::TooManyPeers), Some(&2));
        assert!(inbox.has_room_for(1) && !inbox.has_room_for(3));
        assert_eq!(st.received_from.keys().copied().collect::<Vec<_>>(), [1, 2]);
        assert_eq!(st.kinds[&hb].received, 4);
    }

    #[test]
    fn a_peer_beyond_its_rate_is_refused_until_its_budget_refills() {
        let mut r = PeerRates::new(1000.0);
        // A burst of one second's worth, then nothing more at that instant.
        assert!(r.admit(1, 600, 0.0));
        assert!(r.admit(1, 400, 0.0));
        assert!(!r.admit(1, 1, 0.0));
        // Others have their own budget.
        assert!(r.admit(2, 1000, 0.0));
        // Half a second refills half.
        assert!(!r.admit(1, 600, 0.5));
        assert!(r.admit(1, 500, 0.5));
        // Never more than one second's worth, however long the pause.
        assert!(!r.admit(1, 1001, 100.0));
        assert!(r.admit(1, 1000, 100.0));
    }
}
