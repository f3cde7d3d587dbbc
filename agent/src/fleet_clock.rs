//! The fleet clock: camera ticks on a shared time grid, and the two ways an agent
//! advances along it.
//!
//! * **Lockstep**: an agent starts tick `k` only once every peer it waits for has
//!   finished tick `k - 1` (announced by a heartbeat sent after that tick's
//!   messages). Peers' messages are handed to the agent only up to the end of tick
//!   `k - 1`, so what an agent knows at each tick does not depend on process
//!   scheduling or on the transport: runs are bit-identical.
//! * **Real time**: ticks are paced to the wall clock times a rate.
//!
//! Pure state machines: the caller passes the time in.

use std::collections::BTreeMap;
use std::time::{Duration, Instant};

/// The shared grid of camera ticks: tick `k` covers fleet times up to
/// `t0 + (k + 1/2) dt`, so a frame near `t0 + k dt` belongs to tick `k` even
/// with a small time offset.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct TickGrid {
    /// Fleet time of tick 0, s.
    pub t0_s: f64,
    /// Tick period (the camera period), s.
    pub dt_s: f64,
}

impl TickGrid {
    /// The last fleet time that belongs to tick `k`.
    pub fn end_of(&self, k: u64) -> f64 {
        self.t0_s + (k as f64 + 0.5) * self.dt_s
    }

    /// Number of ticks needed to cover fleet times up to `t_end`.
    pub fn ticks_until(&self, t_end: f64) -> u64 {
        let k = ((t_end - self.t0_s) / self.dt_s - 0.5).ceil();
        if k.is_finite() && k > 0.0 {
            k as u64 + 1
        } else {
            1
        }
    }
}

/// What the lockstep barrier knows of one peer.
#[derive(Clone, Debug, PartialEq)]
pub struct PeerProgress {
    /// The last tick the peer announced as done.
    pub done_tick: Option<u64>,
    /// The peer announced it has no more data.
    pub finished: bool,
    /// The peer is no longer waited for (vanished, finished or silent too long).
    pub released: bool,
    /// When the peer was last heard from (caller's clock, s).
    pub last_heard_s: f64,
}

/// The lockstep barrier over the peers an agent waits for.
#[derive(Clone, Debug, Default)]
pub struct Lockstep {
    peers: BTreeMap<u32, PeerProgress>,
}

impl Lockstep {
    /// A barrier over `peers`, all last heard at `now_s`.
    pub fn new(peers: &[u32], now_s: f64) -> Self {
        Self {
            peers: peers
                .iter()
                .map(|p| {
                    (
                        *p,
                        PeerProgress {
                            done_tick: None,
                            finished: false,
                            released: false,
                            last_heard_s: now_s,
                        },
                    )
                })
                .collect(),
        }
    }

    /// Any message from `peer` shows it is alive.
    pub fn heard(&mut self, peer: u32, now_s: f64) {
        if let Some(p) = self.peers.get_mut(&peer) {
            p.last_heard_s = now_s;
        }
    }

    /// A heartbeat: `peer` finished tick `done_tick`, or all of its data.
    pub fn progress(&mut self, peer: u32, done_tick: Option<u64>, finished: bool, now_s: f64) {
        if let Some(p) = self.peers.get_mut(&peer) {
            p.last_heard_s = now_s;
            if let Some(t) = done_tick {
                p.done_tick = Some(p.done_tick.map_or(t, |d| d.max(t)));
            }
            if finished {
                p.finished = true;
                p.released = true;
            }
        }
    }

    /// `peer` is gone (liveliness lost): stop waiting for it. It is not waited for
    /// again if it comes back (it restarts from its first tick, behind the fleet).
    pub fn release(&mut self, peer: u32) -> bool {
        match self.peers.get_mut(&peer) {
            Some(p) if !p.released => {
                p.released = true;
                true
            }
            _ => false,
        }
    }

    /// The peers that have not yet finished tick `k` (nor been released).
    pub fn waiting_for(&self, k: u64) -> Vec<u32> {
        self.peers
            .iter()
            .filter(|(_, p)| !p.released && p.done_tick.is_none_or(|d| d < k))
            .map(|(id, _)| *id)
            .collect()
    }

    /// Releases the peers still blocking tick `k` that were silent for longer than
    /// `timeout_s`; returns them.
    pub fn release_silent(&mut self, k: u64, now_s: f64, timeout_s: f64) -> Vec<u32> {
        let stale: Vec<u32> = self
            .waiting_for(k)
            .into_iter()
            .filter(|id| {
                self.peers
                    .get(id)
                    .is_some_and(|p| now_s - p.last_heard_s > timeout_s)
            })
            .collect();
        for id in &stale {
            self.release(*id);
        }
        stale
    }

    /// The progress of every peer.
    pub fn peers(&self) -> &BTreeMap<u32, PeerProgress> {
        &self.peers
    }

    /// Peers still running (not finished, not released).
    pub fn running(&self) -> Vec<u32> {
        self.peers
            .iter()
            .filter(|(_, p)| !p.released)
            .map(|(id, _)| *id)
            .collect()
    }
}

/// Real-time pacing: fleet time `t` is due at `start + (t - t_start) / rate`.
#[derive(Clone, Copy, Debug)]
pub struct Pacer {
    start: Instant,
    t_start_s: f64,
    rate: f64,
}

impl Pacer {
    /// Pacing from now, with fleet time `t_start_s` due now.
    pub fn new(t_start_s: f64, rate: f64) -> Self {
        Self {
            start: Instant::now(),
            t_start_s,
            rate: if rate > 0.0 { rate } else { 1.0 },
        }
    }

    /// When fleet time `t_s` is due.
    pub fn due(&self, t_s: f64) -> Instant {
        let wall = ((t_s - self.t_start_s) / self.rate).max(0.0);
        self.start + Duration::from_secs_f64(if wall.is_finite() { wall } else { 0.0 })
    }

    /// How far behind the wall clock fleet time `t_s` is being processed, s
    /// (negative: ahead).
    pub fn lag_s(&self, t_s: f64) -> f64 {
        let now = Instant::now();
        let due = self.due(t_s);
        if now >= due {
            (now - due).as_secs_f64()
        } else {
            -(due - now).as_secs_f64()
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn ticks_cover_frames_near_the_grid() {
        let g = TickGrid {
            t0_s: 10.0,
            dt_s: 0.1,
        };
        assert!((g.end_of(0) - 10.05).abs() < 1e-12);
        assert_eq!(g.ticks_until(10.0), 1);
        assert_eq!(g.ticks_until(10.1), 2);
        assert_eq!(g.ticks_until(10.149), 2);
        assert_eq!(g.ticks_until(10.151), 3);
        assert_eq!(g.ticks_until(f64::NAN), 1);
    }

    #[test]
    fn barrier_waits_for_every_live_peer() {
        let mut l = Lockstep::new(&[1, 2], 0.0);
        assert_eq!(l.waiting_for(0), vec![1, 2]);
        l.progress(1, Some(0), false, 0.1);
        assert_eq!(l.waiting_for(0), vec![2]);
        l.progress(2, Some(3), false, 0.1);
        assert!(l.waiting_for(0).is_empty());
        assert_eq!(l.waiting_for(1), vec![1]);
        // A late, older heartbeat does not move a peer back.
        l.progress(2, Some(1), false, 0.2);
        assert!(!l.waiting_for(3).contains(&2));
    }

    #[test]
    fn finished_vanished_and_silent_peers_are_released() {
        let mut l = Lockstep::new(&[1, 2, 3], 0.0);
        l.progress(1, None, true, 1.0);
        assert!(l.release(2));
        assert!(!l.release(2));
        assert_eq!(l.waiting_for(5), vec![3]);
        assert!(l.release_silent(5, 5.0, 10.0).is_empty());
        assert_eq!(l.release_silent(5, 10.5, 10.0), vec![3]);
        assert!(l.waiting_for(5).is_empty());
        assert!(l.running().is_empty());
        // Unknown peers are ignored.
        l.progress(9, Some(1), false, 1.0);
        assert!(!l.peers().contains_key(&9));
    }

    #[test]
    fn pacer_maps_fleet_time_to_wall_time() {
        let p = Pacer::new(100.0, 4.0);
        let d = p.due(102.0) - p.due(100.0);
        assert!((d.as_secs_f64() - 0.5).abs() < 1e-9);
        assert!(p.lag_s(1000.0) < 0.0);
    }
}
