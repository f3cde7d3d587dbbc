//! The peer windows built for recent frames, kept for the next ones.
//!
//! A peer's window is a CI participant in many consecutive frames: its newest
//! window until its next snapshot, a keyframe window for as long as we revisit
//! that place. Building one unpacks the covariance, covers its `f32` rounding
//! and checks it with a Cholesky factorization (`PeerWindow::from_snapshot`),
//! about 5 % of an agent's CPU on the EuRoC fleet when redone every frame.
//!
//! An entry is reused only for a snapshot equal to the one it was built from,
//! so a cached window is exactly the window `from_snapshot` would build (the
//! estimates stay bit for bit the same), and a peer that sends a different
//! snapshot under the same key gets its new one.

use super::FrameUse;
use crate::estimator::frame_alignment::{window_in_frame, window_in_state_frame};
use crate::estimator::peer_window::PeerWindow;
use common::messages::StateSnapshot;

/// Windows kept: the frame's participants (2 by default) and the historical
/// windows that take turns with them.
const CAPACITY: usize = 8;

/// One built window (or a refusal) with the snapshot it came from.
#[derive(Debug)]
struct Entry {
    peer: u32,
    key: u64,
    historical: bool,
    snapshot: StateSnapshot,
    /// How the window was taken into our frame.
    frame: FrameUse,
    window: Option<PeerWindow>,
    last_used: u64,
}

/// The most recently used peer windows, at most [`CAPACITY`].
#[derive(Debug, Default)]
pub(super) struct WindowCache {
    entries: Vec<Entry>,
    clock: u64,
}

impl WindowCache {
    /// Peer `peer`'s window `key` from `snap` (`historical` when it is a stored
    /// keyframe window), taken into our frame as `frame` says: the cached one
    /// when `snap` and `frame` are what it was built from (a frame our state
    /// holds moves with every update: its windows are built again), else
    /// built now (and kept in place of the least recently used).
    pub(super) fn window(
        &mut self,
        peer: u32,
        key: u64,
        historical: bool,
        snap: &StateSnapshot,
        frame: FrameUse,
    ) -> Option<PeerWindow> {
        self.clock += 1;
        let clock = self.clock;
        if let Some(e) = self.entries.iter_mut().find(|e| {
            e.peer == peer
                && e.key == key
                && e.historical == historical
                && e.frame == frame
                && e.snapshot == *snap
        }) {
            e.last_used = clock;
            return e.window.clone();
        }
        let window = PeerWindow::from_snapshot(peer, key, snap).map(|w| match &frame {
            FrameUse::Same => w,
            FrameUse::Fused(a) => window_in_frame(&w, a),
            FrameUse::InState(var, a) => window_in_state_frame(&w, a, *var),
        });
        let entry = Entry {
            peer,
            key,
            historical,
            snapshot: snap.clone(),
            frame,
            window: window.clone(),
            last_used: clock,
        };
        // The same window sent again with other content replaces its entry.
        let slot = self
            .entries
            .iter()
            .position(|e| e.peer == peer && e.key == key && e.historical == historical)
            .or_else(|| {
                (self.entries.len() >= CAPACITY)
                    .then(|| {
                        self.entries
                            .iter()
                            .enumerate()
                            .min_by_key(|(_, e)| e.last_used)
                            .map(|(i, _)| i)
                    })
                    .flatten()
            });
        match slot {
            Some(i) => self.entries[i] = entry,
            None => self.entries.push(entry),
        }
        window
    }

    /// Number of windows kept.
    #[cfg(test)]
    pub(super) fn len(&self) -> usize {
        self.entries.len()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A peer's snapshot of `clones` clones at frame `frame`.
    fn snapshot_for_tests(clones: usize, frame: u64) -> StateSnapshot {
        match common::messages::samples::snapshot(frame, clones, 2, true).body {
            common::messages::Body::Snapshot(s) => s,
            other => panic!("not a snapshot: {other:?}"),
        }
    }

    #[test]
    fn a_cached_window_is_the_window_built_from_the_same_snapshot() {
        let mut cache = WindowCache::default();
        let snap = snapshot_for_tests(3, 40);
        let built = PeerWindow::from_snapshot(2, 7, &snap);
        assert!(built.is_some());
        assert_eq!(cache.window(2, 7, false, &snap, FrameUse::Same), built);
        assert_eq!(cache.window(2, 7, false, &snap, FrameUse::Same), built);
        assert_eq!(cache.len(), 1);
    }

    #[test]
    fn a_different_snapshot_under_the_same_key_is_built_again() {
        let mut cache = WindowCache::default();
        let first = snapshot_for_tests(3, 40);
        let second = snapshot_for_tests(3, 41);
        assert_eq!(
            cache.window(2, 7, false, &first, FrameUse::Same),
            PeerWindow::from_snapshot(2, 7, &first)
        );
        let again = cache.window(2, 7, false, &second, FrameUse::Same);
        assert_eq!(again, PeerWindow::from_snapshot(2, 7, &second));
        assert_ne!(again, PeerWindow::from_snapshot(2, 7, &first));
        assert_eq!(cache.len(), 1, "the new content replaces the old entry");
    }

    #[test]
    fn a_new_alignment_of_the_peer_builds_its_window_again_in_our_frame() {
        let mut cache = WindowCache::default();
        let snap = snapshot_for_tests(3, 40);
        let raw = PeerWindow::from_snapshot(2, 7, &snap).expect("usable");
        let a = crate::estimator::frame_alignment::FrameAlignment {
            yaw_rad: 0.3,
            t_m: nalgebra::Vector3::new(1.0, 2.0, 0.0),
            cov: nalgebra::Matrix4::identity() * 1e-4,
        };
        assert_eq!(
            cache.window(2, 7, false, &snap, FrameUse::Same),
            Some(raw.clone())
        );
        let moved = cache.window(2, 7, false, &snap, FrameUse::Fused(a));
        assert_eq!(moved, Some(window_in_frame(&raw, &a)));
        assert_eq!(cache.len(), 1);
        let mut b = a;
        b.yaw_rad = 0.31;
        assert_eq!(
            cache.window(2, 7, false, &snap, FrameUse::Fused(b)),
            Some(window_in_frame(&raw, &b))
        );
    }

    #[test]
    fn the_cache_keeps_the_most_recently_used_windows_only() {
        let mut cache = WindowCache::default();
        let snap = snapshot_for_tests(2, 40);
        for key in 0..(CAPACITY as u64 + 5) {
            let _ = cache.window(1, key, true, &snap, FrameUse::Same);
            let _ = cache.window(1, 0, true, &snap, FrameUse::Same);
        }
        assert_eq!(cache.len(), CAPACITY);
        assert!(
            cache.entries.iter().any(|e| e.key == 0),
            "kept: used every time"
        );
    }
}
