//! What this robot takes from its peers in a frame (thesis Section 5.3), as pure
//! data in, data out: no transport, no I/O.
//!
//! 1. [`Cooperation::match_frame`]: our current features are matched to each
//!    peer's newest frame (features several robots see now) and, for historical
//!    features, to the peers' keyframe databases (loop closures). Verified
//!    matches become **links** from our track to a peer's track, kept while our
//!    track lives.
//! 2. [`Cooperation::evidence`]: for the tracks the estimator is about to use,
//!    the peers' measurements behind their links that were never used, with the
//!    peer windows they belong to (the CI participants), and the peers' SLAM
//!    landmarks for the constraint update.
//! 3. [`Cooperation::mark_used`]: each peer measurement is used in one update
//!    only.

mod evidence;
mod linking;
pub mod loop_closure;
pub mod matcher;
pub mod peer_frames;
mod used_marks;
mod window_cache;

pub use evidence::Evidence;

use crate::estimator::frame_alignment::FrameAlignment;
use crate::estimator::peer_frame_states::{frame_var, FrameSeed};
use crate::estimator::state::{PeerFrameMean, Var};
use crate::peer_history::PeerHistory;
use common::estimator_options::CooperationOptions;
use loop_closure::KeyframeDb;
use peer_frames::PeerFrame;
use std::collections::{BTreeMap, BTreeSet};
use std::sync::Arc;
use used_marks::UsedMarks;
use vocabulary::Vocabulary;
use window_cache::WindowCache;

/// The vocabulary for random binary descriptors (the simulator's landmarks),
/// trained once per process from a fixed seed: every agent of a simulated fleet
/// has the same one without a file.
pub fn builtin_vocabulary() -> Option<Arc<Vocabulary>> {
    static VOCABULARY: std::sync::OnceLock<Option<Arc<Vocabulary>>> = std::sync::OnceLock::new();
    VOCABULARY
        .get_or_init(|| {
            vocabulary::synthetic::random_descriptor_vocabulary(
                1,
                200,
                100,
                &vocabulary::TrainParams::default(),
            )
            .map(Arc::new)
            .map_err(|e| tracing::warn!("no built-in vocabulary: {e}"))
            .ok()
        })
        .clone()
}

/// The peers' data as received: their histories by robot id.
pub type Peers = BTreeMap<u32, PeerHistory>;

/// Where a linked peer track's measurements are.
#[derive(Clone, Copy, Debug, PartialEq, Eq, PartialOrd, Ord)]
pub enum LinkSource {
    /// The peer's current window (its newest snapshot).
    Window,
    /// One of the peer's stored keyframe windows (its key).
    Keyframe(u64),
}

/// Our track is the same feature as a peer's track.
#[derive(Clone, Copy, Debug, PartialEq, Eq, PartialOrd, Ord)]
pub struct Link {
    /// The peer.
    pub peer: u32,
    /// The peer's track id.
    pub peer_track: u64,
    /// Where its measurements are.
    pub source: LinkSource,
}

/// What cooperation did so far.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct CooperationStats {
    /// Frames matched to a peer's current frame (epipolar check passed).
    pub window_matches: u64,
    /// Verified loop closures to peer keyframes.
    pub loop_closures: u64,
    /// Loop-closure candidates that failed the epipolar check.
    pub loop_rejected: u64,
    /// Links made.
    pub links: u64,
}

/// Per-peer state.
#[derive(Debug, Default)]
struct PeerState {
    keyframes: Option<KeyframeDb>,
    /// Where each of the peer's frames (by `StateSnapshot::frame_epoch`: a
    /// new one at each start that could not keep the old) is in ours
    /// (`align_peer_frames`).
    frames: BTreeMap<u64, PeerFrame>,
    /// Measurements used ([`used_marks`]).
    used: UsedMarks,
}

/// Marks a used constraint in [`PeerState::used`] (the track id with the top bit set).
const CONSTRAINT_FLAG: u64 = 1 << 63;

/// How a peer's windows are taken into our frame.
#[derive(Clone, Copy, Debug, PartialEq)]
pub(crate) enum FrameUse {
    /// As they are: one fleet frame.
    Same,
    /// Through its confirmed alignment, whose covariance each window takes in.
    Fused(FrameAlignment),
    /// Through the frame our state holds (`peer_frame_state_s`), at its mean.
    InState(Var, PeerFrameMean),
}

/// The cooperation state of one robot.
#[derive(Debug)]
pub struct Cooperation {
    opts: CooperationOptions,
    vocabulary: Option<Arc<Vocabulary>>,
    peers: BTreeMap<u32, PeerState>,
    links: BTreeMap<u64, Vec<Link>>,
    /// Our tracks whose peers' measurements were used this frame: their
    /// keyframe links are checked for exhaustion in `retain_tracks`.
    used_tracks: BTreeSet<u64>,
    /// Counters.
    pub stats: CooperationStats,
    /// Pixel-to-normalized scale of the epipolar thresholds (our focal length).
    focal_px: f64,
    /// The peer windows of recent frames' updates.
    windows: WindowCache,
    /// Peer frames confirmed since the estimator last took them
    /// (`peer_frame_state_s`).
    seeds: Vec<FrameSeed>,
    /// Loop-closure measurements of frames the state holds, since the
    /// estimator last took them (`held_frame_measurement_period_s` and
    /// `held_frame_measurement_window_s`).
    held_measurements: Vec<FrameSeed>,
    /// Frames the state held and let go: used as fixed alignments since.
    frozen: BTreeSet<(u32, u64)>,
    /// The peer frames our state holds, with their marginal covariances, as
    /// of the estimator's last [`Cooperation::set_state_frames`].
    state_frames: BTreeMap<(u32, u64), FrameAlignment>,
}

impl Cooperation {
    /// Cooperation with `opts`; historical loop closures need a vocabulary.
    pub fn new(
        opts: CooperationOptions,
        vocabulary: Option<Arc<Vocabulary>>,
        focal_px: f64,
    ) -> Self {
        Self {
            opts,
            vocabulary,
            peers: BTreeMap::new(),
            links: BTreeMap::new(),
            used_tracks: BTreeSet::new(),
            stats: CooperationStats::default(),
            focal_px: focal_px.max(1.0),
            windows: WindowCache::default(),
            seeds: Vec::new(),
            held_measurements: Vec::new(),
            frozen: BTreeSet::new(),
            state_frames: BTreeMap::new(),
        }
    }

    /// The peer frames confirmed since the last call, for the estimator to
    /// take into its state (`peer_frame_state_s`).
    pub fn take_frame_seeds(&mut self) -> Vec<FrameSeed> {
        std::mem::take(&mut self.seeds)
    }

    /// Loop-closure measurements of frames the state holds, since the last
    /// call (`cooperation.held_frame_measurement_period_s`), for the estimator's
    /// `updater_frame`.
    pub fn take_held_frame_measurements(&mut self) -> Vec<FrameSeed> {
        std::mem::take(&mut self.held_measurements)
    }

    /// Whether peer `peer`'s frame `epoch`, once confirmed, is held by the
    /// state (`peer_frame_state_s`), not yet let go.
    pub(crate) fn holds_in_state(&self, peer: u32, epoch: u64) -> bool {
        self.opts.peer_frame_hold_s() > 0.0 && !self.frozen.contains(&(peer, epoch))
    }

    /// When peer `peer`'s frame `epoch` was confirmed (fleet clock), s.
    pub fn frame_aligned_at(&self, peer: u32, epoch: u64) -> Option<f64> {
        self.peers
            .get(&peer)
            .and_then(|s| s.frames.get(&epoch))
            .and_then(|f| f.aligned_at_s)
    }

    /// The state let go of peer `peer`'s frame `epoch` with estimate `a` (its
    /// marginal): from now on a fixed alignment, refined by loop closures.
    pub fn freeze_frame(&mut self, peer: u32, epoch: u64, a: FrameAlignment) {
        if let Some(f) = self
            .peers
            .get_mut(&peer)
            .and_then(|s| s.frames.get_mut(&epoch))
        {
            *f = f.clone().with_alignment(a);
            self.frozen.insert((peer, epoch));
        }
        // Frames dropped since (at most 8 a peer are kept) are forgotten here
        // too: the epochs come from the network.
        let peers = &self.peers;
        self.frozen
            .retain(|(p, e)| peers.get(p).is_some_and(|s| s.frames.contains_key(e)));
    }

    /// Whether peer `peer`'s frame `epoch` is still kept (a frame the state
    /// holds is marginalized once the cooperation dropped it).
    pub fn keeps_frame(&self, peer: u32, epoch: u64) -> bool {
        self.peers
            .get(&peer)
            .is_some_and(|s| s.frames.contains_key(&epoch))
    }

    /// Forgets peer `peer`'s frame `epoch` (one the state could not take):
    /// the next loop closures measure it anew.
    pub fn forget_frame(&mut self, peer: u32, epoch: u64) {
        if let Some(s) = self.peers.get_mut(&peer) {
            s.frames.remove(&epoch);
        }
    }

    /// The peer frames our state holds now: the windows of this frame are
    /// taken into our frame at these means.
    pub fn set_state_frames(&mut self, frames: BTreeMap<(u32, u64), FrameAlignment>) {
        self.state_frames = frames;
    }

    /// Each peer's keyframe database (historical loop closures): approximate
    /// bytes, and bytes per keyframe window it holds.
    pub fn keyframe_db_bytes(&self) -> BTreeMap<u32, (usize, f64)> {
        self.peers
            .iter()
            .filter_map(|(p, s)| {
                let db = s.keyframes.as_ref()?;
                Some((*p, (db.bytes(), db.bytes_per_keyframe())))
            })
            .collect()
    }

    /// Whether the peers' frames are being aligned: the matcher then needs our
    /// camera's pose (`FrameFeatures::camera`).
    pub fn aligns_peer_frames(&self) -> bool {
        self.opts.align_peer_frames
    }

    /// How peer `peer`'s windows in its frame `epoch` are taken into our
    /// frame; `None`: not at all (not aligned yet).
    pub(crate) fn frame_of(&self, peer: u32, epoch: u64) -> Option<FrameUse> {
        if !self.opts.align_peer_frames {
            return Some(FrameUse::Same);
        }
        if self.holds_in_state(peer, epoch) {
            return self.state_frames.get(&(peer, epoch)).map(|a| {
                FrameUse::InState(
                    frame_var(peer, epoch),
                    PeerFrameMean {
                        yaw_rad: a.yaw_rad,
                        t_m: a.t_m,
                        measurements: 0,
                    },
                )
            });
        }
        self.peers
            .get(&peer)
            .and_then(|s| s.frames.get(&epoch))
            .and_then(PeerFrame::alignment)
            .map(|a| FrameUse::Fused(*a))
    }

    /// Each peer's frames as we know them, by epoch: the confirmed alignment
    /// (if any), and the measurements taken and refused (none yet: a peer
    /// we have closed no loop to).
    pub fn peer_frames(&self) -> BTreeMap<u32, BTreeMap<u64, PeerFrame>> {
        self.peers
            .iter()
            .map(|(p, s)| {
                let frames = s
                    .frames
                    .iter()
                    .map(|(e, f)| {
                        // A frame our state holds: its estimate is the state's.
                        let f = match self.state_frames.get(&(*p, *e)) {
                            Some(a) => {
                                let mut held = f.clone().with_alignment(*a);
                                held.in_filter = true;
                                held
                            }
                            None => f.clone(),
                        };
                        (*e, f)
                    })
                    .collect();
                (*p, frames)
            })
            .collect()
    }

    /// The links of our track `id`.
    pub fn links_of(&self, id: u64) -> &[Link] {
        self.links.get(&id).map_or(&[], Vec::as_slice)
    }

    fn add_link(&mut self, ours: u64, link: Link) {
        let list = self.links.entry(ours).or_default();
        if !list.contains(&link) {
            list.push(link);
            self.stats.links += 1;
        }
    }

    /// Step 3: marks the measurements behind the used tracks as used. `vio` and
    /// `slam` are our tracks whose peer measurements went into an update;
    /// `constraints` our SLAM features whose constraint did.
    pub fn mark_used(&mut self, ev: &Evidence, vio: &[u64], slam: &[u64], constraints: &[u64]) {
        let mut mark = |slam_class: bool, id: u64, only_constraint: Option<bool>| {
            let Some(c) = ev.consumed.get(&(u8::from(slam_class), id)) else {
                return;
            };
            for &(peer, a, b) in &c.keys {
                let is_constraint = b & CONSTRAINT_FLAG != 0;
                if only_constraint.is_some_and(|want| want != is_constraint) {
                    continue;
                }
                self.peers.entry(peer).or_default().used.insert(a, b);
            }
        };
        for &id in vio {
            mark(false, id, None);
        }
        for &id in slam {
            mark(true, id, Some(false));
        }
        for &id in constraints {
            mark(true, id, Some(true));
        }
        self.used_tracks
            .extend(vio.iter().chain(slam).chain(constraints).copied());
        self.forget(&ev.exhausted);
    }

    /// Forgets the links the evidence step found used up (see
    /// `chosen_links`): a SLAM feature kept in view is looked up every frame,
    /// and `drop_exhausted_links` only looks at the tracks used this frame.
    fn forget(&mut self, exhausted: &[(u64, Link)]) {
        for (id, link) in exhausted {
            if let Some(list) = self.links.get_mut(id) {
                list.retain(|l| l != link);
            }
        }
    }

    /// Forgets the keyframe links of the tracks used this frame that can
    /// never be chosen again (see `chosen_links`): their window is gone, or
    /// it is whole and holds fewer than two unused measurements of the peer's
    /// track. A landmark kept in view over many passes of a long mission is
    /// linked to more and more windows of its place, and every frame would
    /// look through the used-up ones first (measured: links per track from
    /// 12 to 28 over 20 minutes, the evidence from 0.23 to 0.50 ms a frame).
    fn drop_exhausted_links(&mut self, peers: &Peers) {
        for id in std::mem::take(&mut self.used_tracks) {
            let Some(list) = self.links.get(&id) else {
                continue;
            };
            let keep: Vec<bool> = list
                .iter()
                .map(|l| match l.source {
                    LinkSource::Window => true,
                    LinkSource::Keyframe(k) => peers
                        .get(&l.peer)
                        .and_then(|h| h.keyframes.get(&k))
                        .is_some_and(|kf| !kf.is_whole() || self.fresh_in_keyframe(l, kf) >= 2),
                })
                .collect();
            if keep.iter().all(|k| *k) {
                continue;
            }
            if let Some(list) = self.links.get_mut(&id) {
                let mut flags = keep.into_iter();
                list.retain(|_| flags.next().unwrap_or(true));
            }
        }
    }

    /// Forgets the links of our tracks that ended, and used marks older than
    /// what any peer still keeps.
    pub fn retain_tracks(&mut self, alive: impl Fn(u64) -> bool, peers: &Peers) {
        self.links.retain(|id, _| alive(*id));
        self.drop_exhausted_links(peers);
        let historical = self.opts.historical;
        for (peer, s) in self.peers.iter_mut() {
            let Some(h) = peers.get(peer) else {
                continue;
            };
            // The oldest measurement time a link can still reach, s.
            let recent = h.recent().front().map(|f| f.t_s);
            let kf = h
                .keyframes
                .values()
                .next()
                .and_then(|k| k.snapshot.clones.first().map(|c| c.t_s))
                .filter(|_| historical);
            let oldest = match (recent, kf) {
                (Some(a), Some(b)) => a.min(b),
                (a, b) => match a.or(b) {
                    Some(t) => t,
                    None => continue,
                },
            };
            s.used.prune(h, oldest, recent);
        }
    }
}

#[cfg(test)]
mod tests;
