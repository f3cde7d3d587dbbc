//! Who is out there: peers appearing, vanishing and coming back, as the
//! transport's presence reports them and as their messages show; logged as JSON
//! lines (`peer_events.jsonl`) and counted.

use crate::transport::PresenceEvent;
use serde::Serialize;
use std::collections::BTreeMap;
use std::io::Write;

/// One logged event.
#[derive(Clone, Debug, PartialEq, Serialize)]
pub struct PeerEvent {
    /// Seconds since the agent started (wall clock).
    pub wall_s: f64,
    /// The agent's fleet time when it happened, s (`None` before the first tick).
    pub fleet_t_s: Option<f64>,
    /// The peer.
    pub peer: u32,
    /// `appeared`, `vanished`, `reappeared`, `finished`, `settled` (done
    /// catching up at the end), `left` (gone after announcing the end of its
    /// data), `released` (no longer waited for in lockstep) or `silent`.
    pub event: &'static str,
}

/// Presence of one peer.
#[derive(Clone, Copy, Debug, Default, PartialEq, Serialize)]
pub struct PeerPresence {
    /// Currently alive.
    pub alive: bool,
    /// Times it appeared (1 for a peer that never left).
    pub appearances: u32,
    /// Times it vanished without having announced the end of its data.
    pub losses: u32,
    /// It announced the end of its data (since it last appeared).
    pub finished: bool,
    /// It announced it is done catching up at the end (since it last appeared).
    pub settled: bool,
    /// When it last vanished, s since the agent started (wall clock).
    #[serde(skip)]
    pub vanished_wall_s: Option<f64>,
}

/// After a peer vanished, its messages bring it back only once this much wall
/// time has passed, s: those still under way when it went (a flooding peer
/// leaves thousands queued) are not news of it. Without this, a peer that
/// vanished and never finishes came back at once and kept the others
/// lingering for `clock.linger_timeout_s`. A peer that really comes back says
/// so by its presence at once, or by its messages after this.
pub const STALE_AFTER_VANISH_S: f64 = 2.0;

/// The presence of every peer and the event log.
#[derive(Debug, Default)]
pub struct PeerEvents {
    /// Per peer.
    pub peers: BTreeMap<u32, PeerPresence>,
    /// Every event, in order.
    pub log: Vec<PeerEvent>,
}

impl PeerEvents {
    /// Applies a presence report; returns the logged event.
    pub fn presence(
        &mut self,
        ev: PresenceEvent,
        wall_s: f64,
        fleet_t_s: Option<f64>,
    ) -> Option<PeerEvent> {
        let (peer, event) = match ev {
            PresenceEvent::Appeared(p) => {
                let st = self.peers.entry(p).or_default();
                if st.alive {
                    return None;
                }
                st.alive = true;
                st.appearances += 1;
                st.finished = false;
                st.settled = false;
                (
                    p,
                    if st.appearances > 1 {
                        "reappeared"
                    } else {
                        "appeared"
                    },
                )
            }
            PresenceEvent::Vanished(p) => {
                let st = self.peers.entry(p).or_default();
                if !st.alive {
                    return None;
                }
                st.alive = false;
                st.vanished_wall_s = Some(wall_s);
                // A peer that said it was done and then ends is not lost. Whether
                // it ends before we do is thread timing, so counting it made the
                // loss count vary between identical lockstep runs.
                if st.finished {
                    (p, "left")
                } else {
                    st.losses += 1;
                    (p, "vanished")
                }
            }
        };
        Some(self.push(peer, event, wall_s, fleet_t_s))
    }

    /// A message from `peer`: a peer heard from is alive even if its presence
    /// report has not come yet, unless it vanished less than
    /// [`STALE_AFTER_VANISH_S`] ago.
    pub fn heard(&mut self, peer: u32, wall_s: f64, fleet_t_s: Option<f64>) -> Option<PeerEvent> {
        if let Some(p) = self.peers.get(&peer) {
            let stale = p
                .vanished_wall_s
                .is_some_and(|v| wall_s - v < STALE_AFTER_VANISH_S);
            if p.alive || stale {
                return None;
            }
        }
        self.presence(PresenceEvent::Appeared(peer), wall_s, fleet_t_s)
    }

    /// Logs any other event about `peer`.
    pub fn push(
        &mut self,
        peer: u32,
        event: &'static str,
        wall_s: f64,
        fleet_t_s: Option<f64>,
    ) -> PeerEvent {
        match event {
            "finished" => self.peers.entry(peer).or_default().finished = true,
            "settled" => self.peers.entry(peer).or_default().settled = true,
            _ => {}
        }
        let e = PeerEvent {
            wall_s,
            fleet_t_s,
            peer,
            event,
        };
        self.log.push(e.clone());
        e
    }

    /// Peers alive now.
    pub fn alive(&self) -> Vec<u32> {
        self.peers
            .iter()
            .filter(|(_, p)| p.alive)
            .map(|(id, _)| *id)
            .collect()
    }

    /// Writes the log as JSON lines.
    pub fn write_jsonl(&self, w: &mut impl Write) -> std::io::Result<()> {
        for e in &self.log {
            serde_json::to_writer(&mut *w, e)?;
            writeln!(w)?;
        }
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn appear_vanish_and_come_back() {
        let mut p = PeerEvents::default();
        let a = p.presence(PresenceEvent::Appeared(2), 0.1, None).unwrap();
        assert_eq!(a.event, "appeared");
        assert!(p.presence(PresenceEvent::Appeared(2), 0.2, None).is_none());
        assert!(p.heard(2, 0.3, None).is_none());
        assert_eq!(
            p.presence(PresenceEvent::Vanished(2), 1.0, Some(5.0))
                .unwrap()
                .event,
            "vanished"
        );
        assert!(p.alive().is_empty());
        assert_eq!(p.heard(2, 3.5, Some(6.0)).unwrap().event, "reappeared");
        assert_eq!(p.peers[&2].appearances, 2);
        assert_eq!(p.peers[&2].losses, 1);
        let mut out = Vec::new();
        p.write_jsonl(&mut out).unwrap();
        assert_eq!(String::from_utf8(out).unwrap().lines().count(), 3);
    }

    #[test]
    fn a_peer_gone_after_finishing_has_left_and_is_not_lost() {
        let mut p = PeerEvents::default();
        p.presence(PresenceEvent::Appeared(1), 0.0, None);
        p.push(1, "finished", 1.0, Some(80.0));
        let e = p
            .presence(PresenceEvent::Vanished(1), 1.1, Some(80.0))
            .unwrap();
        assert_eq!(e.event, "left");
        assert_eq!(p.peers[&1].losses, 0);
        // Back with new data, then gone without a word: that is a loss.
        assert_eq!(p.heard(1, 3.5, Some(81.0)).unwrap().event, "reappeared");
        assert!(!p.peers[&1].finished);
        let e = p
            .presence(PresenceEvent::Vanished(1), 4.0, Some(82.0))
            .unwrap();
        assert_eq!(e.event, "vanished");
        assert_eq!(p.peers[&1].losses, 1);
    }

    /// Messages still queued when a peer vanished do not bring it back; its
    /// presence does at once, and its messages do after the grace.
    #[test]
    fn messages_under_way_when_a_peer_vanished_do_not_bring_it_back() {
        let mut p = PeerEvents::default();
        p.presence(PresenceEvent::Appeared(999), 0.0, None);
        p.presence(PresenceEvent::Vanished(999), 10.0, Some(10.0));
        assert!(p.heard(999, 10.0003, Some(10.0)).is_none());
        assert!(p.heard(999, 11.9, Some(11.9)).is_none());
        assert!(p.alive().is_empty());
        assert_eq!(p.heard(999, 12.1, Some(12.1)).unwrap().event, "reappeared");
        // Gone again, and back by its presence at once.
        p.presence(PresenceEvent::Vanished(999), 13.0, Some(13.0));
        let back = p.presence(PresenceEvent::Appeared(999), 13.1, Some(13.1));
        assert_eq!(back.unwrap().event, "reappeared");
        assert_eq!(p.peers[&999].losses, 2);
    }
}
