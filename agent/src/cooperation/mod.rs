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

pub mod loop_closure;
pub mod matcher;

use crate::estimator::peer_window::PeerWindow;
use crate::estimator::updater_common::{CommonTrack, PeerObservation};
use crate::estimator::updater_common_slam::SlamConstraint;
use crate::peer_history::{time_key, PeerHistory};
use common::descriptor::Descriptor;
use common::epipolar::{fundamental_eight_point, sampson_distance};
use common::estimator_options::CooperationOptions;
use loop_closure::{describe, detect, FrameFeatures, KeyframeDb, LoopParams};
use matcher::{epipolar_inliers, match_descriptors, MatchRules};
use nalgebra::Vector2;
use std::collections::{BTreeMap, BTreeSet, HashMap};
use std::sync::Arc;
use vocabulary::{MatchParams, Vocabulary};

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
    /// Measurements used: `(time key, peer track)`; constraints use the window
    /// key and the track with the top bit set.
    used: BTreeSet<(u64, u64)>,
}

/// The measurements behind one of our tracks in this frame.
#[derive(Clone, Debug, Default)]
struct Consumed {
    keys: Vec<(u32, u64, u64)>,
}

/// Everything the cooperative updates of one frame need.
#[derive(Clone, Debug, Default)]
pub struct Evidence {
    /// The CI participants (peer windows) the observations refer to.
    pub participants: Vec<PeerWindow>,
    /// Our VIO tracks with peers' measurements (common VIO features).
    pub vio: Vec<CommonTrack>,
    /// Our SLAM features with peers' measurements (common SLAM, case i).
    pub slam: Vec<CommonTrack>,
    /// Our SLAM features that are peers' SLAM landmarks (constraint update).
    pub constraints: Vec<SlamConstraint>,
    /// Whether a participant is a historical keyframe window.
    pub historical: Vec<bool>,
    consumed: BTreeMap<(u8, u64), Consumed>,
}

const CONSTRAINT_FLAG: u64 = 1 << 63;

/// The cooperation state of one robot.
#[derive(Debug)]
pub struct Cooperation {
    opts: CooperationOptions,
    vocabulary: Option<Arc<Vocabulary>>,
    peers: BTreeMap<u32, PeerState>,
    links: BTreeMap<u64, Vec<Link>>,
    /// Counters.
    pub stats: CooperationStats,
    /// Pixel-to-normalized scale of the epipolar thresholds (our focal length).
    focal_px: f64,
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
            stats: CooperationStats::default(),
            focal_px: focal_px.max(1.0),
        }
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

    /// Step 1: links our current frame's tracks to the peers' (see the module
    /// documentation). `frame_seq` seeds the RANSAC.
    pub fn match_frame(&mut self, frame: &FrameFeatures, peers: &Peers, frame_seq: u64) {
        if frame.ids.is_empty() {
            return;
        }
        let threshold = self.opts.epipolar_threshold_px / self.focal_px;
        let rules = MatchRules {
            max_distance: self.opts.max_descriptor_distance_bits,
            ratio: self.opts.match_ratio,
        };
        if self.opts.common_vio || self.opts.common_slam {
            for (&peer, h) in peers {
                self.match_window(peer, h, frame, &rules, threshold, frame_seq);
            }
        }
        if self.opts.historical {
            self.match_history(frame, peers, threshold, frame_seq);
        }
    }

    /// Matches our frame to the peer's newest frame.
    fn match_window(
        &mut self,
        peer: u32,
        h: &PeerHistory,
        frame: &FrameFeatures,
        rules: &MatchRules,
        threshold: f64,
        seq: u64,
    ) {
        let Some(newest) = h.recent.back() else {
            return;
        };
        let latest_kf = h.keyframes.values().next_back();
        let known: HashMap<u64, Descriptor> = latest_kf
            .into_iter()
            .flat_map(|k| k.descriptors.iter().map(|e| (e.id, e.descriptor())))
            .chain(
                h.recent_descriptors
                    .iter()
                    .map(|(id, (_, bits))| (*id, Descriptor(*bits))),
            )
            .collect();
        // Pairs linked before and seen in both frames: their geometry is
        // already verified, only the new tracks need descriptor matching.
        let peer_xy: HashMap<u64, Vector2<f64>> =
            newest.features.iter().map(|p| (p.id, p.xy())).collect();
        let (mut linked1, mut linked2) = (Vec::new(), Vec::new());
        let mut linked_theirs = std::collections::HashSet::new();
        let mut unlinked: Vec<usize> = Vec::new();
        for (a, id) in frame.ids.iter().enumerate() {
            let mut found = false;
            for l in self.links_of(*id) {
                if l.peer == peer && l.source == LinkSource::Window {
                    if let Some(x) = peer_xy.get(&l.peer_track) {
                        linked1.push(frame.xy[a]);
                        linked2.push(*x);
                        linked_theirs.insert(l.peer_track);
                        found = true;
                    }
                }
            }
            if !found {
                unlinked.push(a);
            }
        }
        let (mut ids, mut desc, mut xy) = (vec![], vec![], vec![]);
        for p in &newest.features {
            if linked_theirs.contains(&p.id) {
                continue;
            }
            if let Some(d) = known.get(&p.id) {
                ids.push(p.id);
                desc.push(*d);
                xy.push(p.xy());
            }
        }
        let ours: Vec<Descriptor> = unlinked.iter().map(|a| frame.descriptors[*a]).collect();
        let pairs: Vec<(usize, usize)> = match_descriptors(&ours, &desc, rules)
            .into_iter()
            .map(|(i, j)| (unlinked[i], j))
            .collect();
        if pairs.is_empty() {
            return;
        }
        let x1: Vec<Vector2<f64>> = pairs.iter().map(|(a, _)| frame.xy[*a]).collect();
        let x2: Vec<Vector2<f64>> = pairs.iter().map(|(_, b)| xy[*b]).collect();
        let keep = if linked1.len() >= self.opts.min_window_inliers {
            // The geometry of the verified pairs (one least-squares solve) checks
            // the new ones; no RANSAC.
            match fundamental_eight_point(&linked1, &linked2) {
                Ok(f) => x1
                    .iter()
                    .zip(&x2)
                    .map(|(a, b)| sampson_distance(&f, a, b) <= threshold)
                    .collect(),
                Err(_) => return,
            }
        } else {
            let all1: Vec<Vector2<f64>> = linked1.iter().chain(&x1).copied().collect();
            let all2: Vec<Vector2<f64>> = linked2.iter().chain(&x2).copied().collect();
            let seed = seq.wrapping_mul(1_000_003) ^ u64::from(peer);
            let Some(inl) =
                epipolar_inliers(&all1, &all2, threshold, self.opts.min_window_inliers, seed)
            else {
                return;
            };
            inl[linked1.len()..].to_vec()
        };
        self.stats.window_matches += 1;
        for ((a, b), keep) in pairs.into_iter().zip(keep) {
            if keep {
                let link = Link {
                    peer,
                    peer_track: ids[b],
                    source: LinkSource::Window,
                };
                self.add_link(frame.ids[a], link);
            }
        }
    }

    /// Indexes new peer keyframes and links our frame to the verified ones.
    fn match_history(&mut self, frame: &FrameFeatures, peers: &Peers, threshold: f64, seq: u64) {
        let Some(voc) = self.vocabulary.clone() else {
            return;
        };
        let (bow, index) = describe(&voc, frame);
        let params = LoopParams {
            candidates: self.opts.loop_candidates,
            min_score: self.opts.loop_min_score,
            matching: MatchParams {
                ratio: self.opts.match_ratio as f32,
                max_distance: self.opts.max_descriptor_distance_bits,
            },
            threshold,
            min_inliers: self.opts.min_loop_inliers,
            seed: seq,
        };
        for (&peer, h) in peers {
            let state = self.peers.entry(peer).or_default();
            let db = state
                .keyframes
                .get_or_insert_with(|| KeyframeDb::new(Arc::clone(&voc)));
            db.index_new(h);
            let found = detect(db, h, frame, &bow, &index, &params);
            let candidates = params.candidates.min(db.len());
            let verified = found.len();
            self.stats.loop_closures += verified as u64;
            self.stats.loop_rejected += candidates.saturating_sub(verified) as u64;
            for lc in found {
                for (ours, theirs) in lc.pairs {
                    let link = Link {
                        peer,
                        peer_track: theirs,
                        source: LinkSource::Keyframe(lc.keyframe),
                    };
                    self.add_link(ours, link);
                }
            }
        }
    }

    /// Step 2: the peers' unused measurements behind the links of our tracks
    /// `vio_ids` (about to leave the window) and of our SLAM features `slam_ids`.
    pub fn evidence(&self, vio_ids: &[u64], slam_ids: &[u64], peers: &Peers) -> Evidence {
        let mut ev = Evidence::default();
        let mut index: BTreeMap<(u32, LinkSource), Option<usize>> = BTreeMap::new();
        let mut taken: BTreeSet<(u32, u64, u64)> = BTreeSet::new();
        let classes: [(&[u64], bool); 2] = [(vio_ids, false), (slam_ids, true)];
        for (ids, slam) in classes {
            for &id in ids {
                let mut obs = Vec::new();
                let mut consumed = Consumed::default();
                let mut constraint = None;
                for link in &self.chosen_links(id, slam, peers) {
                    let Some(h) = peers.get(&link.peer) else {
                        continue;
                    };
                    let Some(p) = *index
                        .entry((link.peer, link.source))
                        .or_insert_with(|| participant(&mut ev, link, h))
                    else {
                        continue;
                    };
                    let used = self.peers.get(&link.peer).map(|s| &s.used);
                    let is_used = |k: &(u64, u64)| used.is_some_and(|u| u.contains(k));
                    if slam && self.opts.slam_constraint && constraint.is_none() {
                        let w = &ev.participants[p];
                        if let Some(j) = w.landmarks.iter().position(|l| l.id == link.peer_track) {
                            let key = (w.key, link.peer_track | CONSTRAINT_FLAG);
                            if !is_used(&key) && taken.insert((link.peer, key.0, key.1)) {
                                constraint = Some(SlamConstraint {
                                    id,
                                    participant: p,
                                    landmark: j,
                                });
                                consumed.keys.push((link.peer, key.0, key.1));
                            }
                            continue;
                        }
                    }
                    for (pose, t_s, xy) in measurements(h, link, &ev.participants[p]) {
                        let key = (time_key(t_s), link.peer_track);
                        if is_used(&key) || !taken.insert((link.peer, key.0, key.1)) {
                            continue;
                        }
                        consumed.keys.push((link.peer, key.0, key.1));
                        obs.push(PeerObservation {
                            participant: p,
                            pose,
                            xy,
                        });
                    }
                }
                if let Some(c) = constraint {
                    ev.constraints.push(c);
                }
                if !obs.is_empty() {
                    let track = CommonTrack { id, peer_obs: obs };
                    if slam {
                        ev.slam.push(track);
                    } else {
                        ev.vio.push(track);
                    }
                }
                if !consumed.keys.is_empty() {
                    ev.consumed.insert((u8::from(slam), id), consumed);
                }
            }
        }
        ev
    }

    /// The links of our track `id` whose measurements this class may use: every
    /// window link, and per peer the `max_keyframes_per_track` keyframe links
    /// whose windows the peer was most certain of (smallest position variance;
    /// at least two measurements of the peer's track). A landmark the peer kept
    /// in view, or saw on several passes, is in several of its keyframe
    /// windows; each window is one more CI participant, which inflates our
    /// covariance once more, so only the most informative are used.
    fn chosen_links(&self, id: u64, slam: bool, peers: &Peers) -> Vec<Link> {
        let mut out: Vec<Link> = Vec::new();
        let mut window: Vec<(usize, Link)> = Vec::new();
        let mut historical: Vec<(u32, f64, Link)> = Vec::new();
        for link in self.links_of(id) {
            if !self.allowed(link, slam) {
                continue;
            }
            // Measurements of the peer's track not used yet.
            let used = self.peers.get(&link.peer).map(|s| &s.used);
            let fresh =
                |t_s: f64| !used.is_some_and(|u| u.contains(&(time_key(t_s), link.peer_track)));
            match link.source {
                LinkSource::Window => {
                    let count = peers.get(&link.peer).map_or(0, |h| {
                        h.recent
                            .iter()
                            .filter(|f| {
                                fresh(f.t_s) && f.features.iter().any(|p| p.id == link.peer_track)
                            })
                            .count()
                    });
                    if count > 0 {
                        window.push((count, *link));
                    }
                }
                LinkSource::Keyframe(k) => {
                    let Some(kf) = peers.get(&link.peer).and_then(|h| h.keyframes.get(&k)) else {
                        continue;
                    };
                    let count = kf
                        .frames
                        .iter()
                        .filter(|f| {
                            fresh(f.t_s) && f.observations.iter().any(|o| o.id == link.peer_track)
                        })
                        .count();
                    if count >= 2 {
                        historical.push((link.peer, position_variance(&kf.snapshot), *link));
                    }
                }
            }
        }
        // Most certain window first; ties to the newest keyframe (larger key).
        historical.sort_by(|a, b| a.0.cmp(&b.0).then(a.1.total_cmp(&b.1)).then(b.2.cmp(&a.2)));
        let mut per_peer: BTreeMap<u32, usize> = BTreeMap::new();
        for (peer, _, link) in historical {
            let n = per_peer.entry(peer).or_default();
            if *n < self.opts.max_keyframes_per_track {
                *n += 1;
                out.push(link);
            }
        }
        // The peers that saw the feature longest, at most `max_peers_per_track`:
        // the update's size, and its cost, stay bounded however many robots
        // share a place.
        window.sort_by(|a, b| b.0.cmp(&a.0).then(a.1.cmp(&b.1)));
        let room = self
            .opts
            .max_peers_per_track
            .saturating_sub(out.len().min(1));
        out.extend(window.into_iter().take(room.max(1)).map(|(_, l)| l));
        out
    }

    /// Whether a link may be used for this class under the options.
    fn allowed(&self, link: &Link, slam: bool) -> bool {
        let class = if slam {
            self.opts.common_slam
        } else {
            self.opts.common_vio
        };
        match link.source {
            LinkSource::Window => class,
            LinkSource::Keyframe(_) => self.opts.historical,
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
                self.peers.entry(peer).or_default().used.insert((a, b));
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
    }

    /// Forgets the links of our tracks that ended, and used marks older than
    /// what any peer still keeps.
    pub fn retain_tracks(&mut self, alive: impl Fn(u64) -> bool, peers: &Peers) {
        self.links.retain(|id, _| alive(*id));
        let historical = self.opts.historical;
        for (peer, s) in self.peers.iter_mut() {
            let Some(h) = peers.get(peer) else {
                continue;
            };
            // The oldest measurement time a link can still reach, s.
            let recent = h.recent.front().map(|f| f.t_s);
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
            s.used = s.used.split_off(&(time_key(oldest - 1.0), 0));
        }
    }
}

/// Sum of the position variances of a window's camera poses, m².
fn position_variance(snap: &common::messages::StateSnapshot) -> f64 {
    (0..snap.clones.len())
        .flat_map(|i| (3..6).map(move |j| 6 * i + j))
        .filter_map(|d| snap.covariance.get(d, d))
        .sum()
}

/// The participant behind `link`: its index in `ev.participants` (added now if
/// new), or `None` when the peer's window is not usable.
fn participant(ev: &mut Evidence, link: &Link, h: &PeerHistory) -> Option<usize> {
    let (snap, historical) = match link.source {
        LinkSource::Window => (h.latest.as_ref()?, false),
        LinkSource::Keyframe(k) => (&h.keyframes.get(&k)?.snapshot, true),
    };
    let key = time_key(snap.clones.last().map_or(snap.t_s, |c| c.t_s));
    if let Some(i) = ev
        .participants
        .iter()
        .position(|w| w.peer == link.peer && w.key == key)
    {
        return Some(i);
    }
    let w = PeerWindow::from_snapshot(link.peer, key, snap)?;
    ev.participants.push(w);
    ev.historical.push(historical);
    Some(ev.participants.len() - 1)
}

/// The linked peer track's measurements at the poses of window `w`:
/// `(pose index, camera time, normalized coordinates)`.
fn measurements(h: &PeerHistory, link: &Link, w: &PeerWindow) -> Vec<(usize, f64, Vector2<f64>)> {
    let mut out = Vec::new();
    match link.source {
        LinkSource::Window => {
            for f in &h.recent {
                let Some(pose) = w.pose_at(f.t_s) else {
                    continue;
                };
                if let Some(p) = f.features.iter().find(|p| p.id == link.peer_track) {
                    out.push((pose, f.t_s, p.xy()));
                }
            }
        }
        LinkSource::Keyframe(k) => {
            let Some(kf) = h.keyframes.get(&k) else {
                return out;
            };
            for f in &kf.frames {
                let Some(pose) = w.pose_at(f.t_s) else {
                    continue;
                };
                if let Some(o) = f.observations.iter().find(|o| o.id == link.peer_track) {
                    let xy = Vector2::new(f64::from(o.xy_norm[0]), f64::from(o.xy_norm[1]));
                    out.push((pose, f.t_s, xy));
                }
            }
        }
    }
    out
}

#[cfg(test)]
mod tests;
