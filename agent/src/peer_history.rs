//! What an agent keeps of each peer (thesis Section 5.3.5): the peer's latest
//! window for real-time common features, its recent track frames and
//! descriptors, and the **keyframe windows** for historical loop closures.
//!
//! Policy, per peer:
//! * **latest**: the newest snapshot, and the track frames and new-track
//!   descriptors of the last `recent_tracks_s` seconds (a ring: older ones drop;
//!   frames the latest snapshot's window still spans stay, as after a standstill);
//! * **history**: every keyframe window (non-overlapping windows, about 1 Hz), kept
//!   with the track measurements made inside it (normalized coordinates only) and
//!   the keyframe's descriptors; historical states are never updated;
//! * **bound**: when a peer's history exceeds `max_mib_per_peer`, keyframe windows
//!   are dropped (counted), so memory per peer is bounded whatever the mission
//!   length: by default the oldest, or the least certain window of a place seen
//!   more than once ([`crate::history_retention`]). The recent frames and the
//!   recent descriptors each get an eighth of that bound on top
//!   ([`RECENT_SHARE`], never less than [`MIN_RECENT_BYTES`], or a small bound
//!   would store windows without their measurements), which a peer that sends
//!   at its own pace never reaches (20 frames in 2 s) and a peer that floods
//!   cannot exceed.

use crate::history_retention::{self, Place, Retention};
use common::messages::{
    DescriptorBatch, DescriptorEntry, HeldWindow, HistoryWindow, StateSnapshot, TrackFrame,
    WindowFrame, WindowObservation, WindowPart,
};
use std::collections::{BTreeMap, HashMap, VecDeque};

/// One track measurement kept in a history window (normalized coordinates),
/// as the wire carries it in a replayed window.
pub type HistoricalObservation = WindowObservation;

/// The measurements of one frame inside a keyframe window (its time matches
/// a clone of the window).
pub type HistoricalFrame = WindowFrame;

/// A stored non-overlapping window of a peer.
///
/// Its measurements are kept track by track: every loop-closure evidence
/// looks up the measurements of one track in many windows each camera frame,
/// and with them kept frame by frame that took a binary search in each frame
/// (the top of a profile of a 16-robot fleet and of an hour's flight, most of
/// it cache misses). Kept by track it is one search, and smaller: the track id
/// once per track, not once per measurement.
#[derive(Clone, Debug, PartialEq)]
pub struct KeyframeWindow {
    /// The window (camera poses, covariance, landmarks).
    pub snapshot: StateSnapshot,
    /// Camera times of the frames of measurements held (at the window's clone
    /// times), oldest first; at most [`MAX_WINDOW_FRAMES`].
    frame_times: Vec<f64>,
    /// The tracks measured, by id.
    tracks: Vec<WindowTrack>,
    /// Normalized coordinates of every measurement, track by track, each
    /// track's in frame order.
    xy: Vec<[f32; 2]>,
    /// The keyframe's descriptors (for the peer's vocabulary database).
    pub descriptors: Vec<DescriptorEntry>,
    /// Where its newest camera was and looked (`None` without a finite pose).
    pub place: Option<Place>,
    /// Sum of its cameras' position variances, m²: how certain the peer was.
    pub position_variance_m2: f64,
}

/// Most frames of measurements a window keeps (a frame per clone: 11 by
/// default); a peer's frames beyond are dropped.
pub const MAX_WINDOW_FRAMES: usize = 64;

/// One peer track of a keyframe window.
#[derive(Clone, Copy, Debug, PartialEq)]
struct WindowTrack {
    /// The peer's track id.
    id: u64,
    /// Its first measurement in [`KeyframeWindow::xy`].
    first: u32,
    /// The frames that measured it: bit `k` for `frame_times[k]`.
    frames: u64,
}

impl KeyframeWindow {
    /// The window of `snapshot` with the measurements and descriptors kept of it.
    pub fn new(
        snapshot: StateSnapshot,
        frames: Vec<HistoricalFrame>,
        descriptors: Vec<DescriptorEntry>,
    ) -> Self {
        let mut kf = Self {
            place: history_retention::place_of(&snapshot),
            position_variance_m2: history_retention::position_variance_m2(&snapshot),
            snapshot,
            frame_times: Vec::new(),
            tracks: Vec::new(),
            xy: Vec::new(),
            descriptors,
        };
        kf.set_frames(frames);
        kf
    }

    /// Keeps `frames` (in their order, at most [`MAX_WINDOW_FRAMES`]) track by
    /// track. A malformed frame that measured a track twice keeps the first.
    fn set_frames(&mut self, frames: Vec<HistoricalFrame>) {
        let frames = &frames[..frames.len().min(MAX_WINDOW_FRAMES)];
        let mut all: Vec<(u64, usize, [f32; 2])> = frames
            .iter()
            .enumerate()
            .flat_map(|(k, f)| f.observations.iter().map(move |o| (o.id, k, o.xy_norm)))
            .collect();
        // Stable: of a repeated id in one frame, the first stays first.
        all.sort_by_key(|&(id, k, _)| (id, k));
        all.dedup_by_key(|&mut (id, k, _)| (id, k));
        self.frame_times = frames.iter().map(|f| f.t_s).collect();
        self.tracks.clear();
        self.xy = Vec::with_capacity(all.len());
        for (id, k, xy) in all {
            match self.tracks.last_mut() {
                Some(t) if t.id == id => t.frames |= 1 << k,
                _ => self.tracks.push(WindowTrack {
                    id,
                    // At most 64 frames of a bounded number of measurements each.
                    first: u32::try_from(self.xy.len()).unwrap_or(u32::MAX),
                    frames: 1 << k,
                }),
            }
            self.xy.push(xy);
        }
        self.tracks.shrink_to_fit();
    }

    /// The track measurements, one frame per clone at most, oldest first,
    /// each frame's by track id.
    pub fn frames(&self) -> Vec<HistoricalFrame> {
        (0..self.frame_times.len())
            .map(|k| HistoricalFrame {
                t_s: self.frame_times[k],
                observations: self.observations_in(k).collect(),
            })
            .collect()
    }

    /// The camera times of the frames of measurements held, oldest first.
    pub fn frames_times(&self) -> impl Iterator<Item = f64> + '_ {
        self.frame_times.iter().copied()
    }

    /// The measurements of frame `k`, by track id.
    fn observations_in(&self, k: usize) -> impl Iterator<Item = HistoricalObservation> + '_ {
        let bit = 1u64 << k;
        self.tracks
            .iter()
            .filter(move |t| t.frames & bit != 0)
            .map(move |t| HistoricalObservation {
                id: t.id,
                xy_norm: self.xy[t.first as usize + (t.frames & (bit - 1)).count_ones() as usize],
            })
    }

    /// The measurements of the frame at camera time `t_s` (within 1 µs), by
    /// track id; empty without one.
    pub fn observations_at(&self, t_s: f64) -> Vec<HistoricalObservation> {
        self.frame_times
            .iter()
            .position(|t| (t - t_s).abs() < 1e-6)
            .map(|k| self.observations_in(k).collect())
            .unwrap_or_default()
    }

    /// The peer's track `id` as measured in this window: `(camera time,
    /// normalized coordinates)` of each frame that measured it, oldest first.
    pub fn measurements_of(&self, id: u64) -> impl Iterator<Item = (f64, [f32; 2])> + '_ {
        let track = self
            .tracks
            .binary_search_by_key(&id, |t| t.id)
            .ok()
            .map(|i| self.tracks[i]);
        let (first, mask) = track.map_or((0, 0), |t| (t.first as usize, t.frames));
        (0..self.frame_times.len())
            .filter(move |k| mask & (1 << k) != 0)
            .zip(first..)
            .map(move |(k, i)| (self.frame_times[k], self.xy[i]))
    }

    /// The window as a replay carries it.
    pub fn to_wire(&self) -> HistoryWindow {
        HistoryWindow {
            snapshot: self.snapshot.clone(),
            frames: self.frames(),
            descriptors: self.descriptors.clone(),
        }
    }

    /// A replayed window, as stored.
    pub fn from_wire(w: HistoryWindow) -> Self {
        Self::new(w.snapshot, w.frames, w.descriptors)
    }

    /// The newest clone's time (the snapshot's time without clones), s.
    pub fn end_s(&self) -> f64 {
        self.snapshot.end_s()
    }

    /// How much of the window arrived: frames with measurements, and whether
    /// the descriptors did (a lost message leaves a window short of one).
    pub fn completeness(&self) -> (usize, bool) {
        (self.frame_times.len(), !self.descriptors.is_empty())
    }

    /// Whether it holds everything a window can hold: a frame at every
    /// clone and the descriptors.
    pub fn is_whole(&self) -> bool {
        let (frames, descriptors) = self.completeness();
        descriptors && frames >= self.snapshot.clones.len()
    }

    /// Which of its parts this copy holds, as a request lists it.
    pub fn held(&self) -> HeldWindow {
        let frames_mask = self
            .snapshot
            .clones
            .iter()
            .take(64)
            .enumerate()
            .filter(|(_, c)| self.frame_times.contains(&c.t_s))
            .fold(0u64, |mask, (i, _)| mask | (1 << i));
        HeldWindow {
            end_s: self.end_s(),
            frames_mask,
            descriptors: !self.descriptors.is_empty(),
        }
    }

    /// The parts of this window that some holder in `held` lacks: each
    /// frame one of them misses, and the descriptors if one misses those.
    /// Empty (no frames, no descriptors) when there is nothing to send.
    pub fn part_for<'a>(&self, held: impl IntoIterator<Item = &'a HeldWindow>) -> WindowPart {
        let clone_index = |t_s: f64| self.snapshot.clones.iter().position(|c| c.t_s == t_s);
        let mut frames_wanted = vec![false; self.frame_times.len()];
        let mut descriptors = false;
        for h in held {
            for (wanted, t_s) in frames_wanted.iter_mut().zip(&self.frame_times) {
                *wanted |= clone_index(*t_s).is_none_or(|i| !h.holds_frame(i));
            }
            descriptors |= !h.descriptors;
        }
        WindowPart {
            end_s: self.end_s(),
            frames: self
                .frames()
                .into_iter()
                .zip(frames_wanted)
                .filter(|(_, wanted)| *wanted)
                .map(|(f, _)| f)
                .collect(),
            descriptors: if descriptors {
                self.descriptors.clone()
            } else {
                Vec::new()
            },
        }
    }

    /// Adds what `part` has that this copy lacks: frames at its clone times
    /// not held (kept oldest first), and descriptors if none are held.
    /// Returns whether anything was added.
    fn merge(&mut self, part: WindowPart) -> bool {
        let mut added = false;
        let mut frames = self.frames();
        for f in part.frames {
            let at_clone = self.snapshot.clones.iter().any(|c| c.t_s == f.t_s);
            if at_clone && !frames.iter().any(|g| g.t_s == f.t_s) {
                frames.push(f);
                added = true;
            }
        }
        if added {
            frames.sort_by(|a, b| a.t_s.total_cmp(&b.t_s));
            self.set_frames(frames);
        }
        if self.descriptors.is_empty() && !part.descriptors.is_empty() {
            self.descriptors = part.descriptors;
            added = true;
        }
        added
    }

    /// Approximate heap bytes held.
    pub fn bytes(&self) -> usize {
        let s = &self.snapshot;
        std::mem::size_of::<Self>()
            + s.clones.len() * std::mem::size_of::<common::messages::CameraPose>()
            + s.covariance.lower.len() * 4
            + s.landmarks.len() * std::mem::size_of::<common::messages::Landmark>()
            + self.frame_times.len() * std::mem::size_of::<f64>()
            + self.tracks.len() * std::mem::size_of::<WindowTrack>()
            + self.xy.len() * std::mem::size_of::<[f32; 2]>()
            + self.descriptors.len() * std::mem::size_of::<DescriptorEntry>()
    }
}

/// The share of `max_bytes` the recent frames, and again the recent
/// descriptors, may hold beyond the keyframe history: 1 / `RECENT_SHARE`.
pub const RECENT_SHARE: usize = 8;

/// The least room the recent frames, and again the recent descriptors, get:
/// 2 s of frames at 10 Hz with up to 270 tracks each. A keyframe window takes
/// its measurements from the recent frames; below this, a small history bound
/// would store windows without them (measured: a fifth of the bytes missing at
/// 0.15 MiB per peer with 100 tracks per frame).
pub const MIN_RECENT_BYTES: usize = 128 * 1024;

/// The bytes the recent frames, and again the recent descriptors, may hold
/// with a history bound of `max_bytes`.
pub fn recent_budget(max_bytes: usize) -> usize {
    (max_bytes / RECENT_SHARE).max(MIN_RECENT_BYTES)
}

/// Bytes one recent track frame holds.
fn frame_bytes(f: &TrackFrame) -> usize {
    std::mem::size_of::<TrackFrame>()
        + f.features.len() * std::mem::size_of::<common::messages::TrackPoint>()
}

/// Bytes one recent descriptor holds (key, time and bits, with the map's overhead).
const DESCRIPTOR_BYTES: usize = 48;

/// Everything kept of one peer.
#[derive(Clone, Debug, Default)]
pub struct PeerHistory {
    /// The newest snapshot (any kind).
    pub latest: Option<StateSnapshot>,
    /// Recent track frames, oldest first (see [`PeerHistory::recent`]).
    recent: VecDeque<TrackFrame>,
    /// Bytes held by `recent`.
    recent_bytes: usize,
    /// Descriptors of recently started tracks, by track id.
    pub recent_descriptors: HashMap<u64, (f64, [u64; 4])>,
    /// Keyframe windows by their newest clone time (bit pattern of the f64, which
    /// orders like the time for non-negative times; see [`time_key`]).
    pub keyframes: BTreeMap<u64, KeyframeWindow>,
    /// The key in `keyframes` of the newest stored window of each frame index:
    /// keyframe descriptors find their window without a scan of the history.
    by_frame_index: BTreeMap<u64, u64>,
    /// Keyframe descriptors that arrived before their snapshot, by frame index.
    pending_keyframe_descriptors: BTreeMap<u64, Vec<DescriptorEntry>>,
    /// Bytes held by `keyframes`.
    pub history_bytes: usize,
    /// Keyframe windows dropped by the memory bound.
    pub dropped_keyframes: u64,
    /// Keyframe windows stored in total.
    pub stored_keyframes: u64,
    /// Bytes of every keyframe window stored (dropped ones too): with
    /// [`PeerHistory::stored_span_s`], how fast a peer's history grows whatever
    /// the bound kept.
    pub stored_bytes: usize,
    /// Fleet time from the oldest to the newest clone of every window stored, s.
    pub stored_span: Option<(f64, f64)>,
    /// Windows stored or replaced so far: a change means there may be windows
    /// to index.
    pub revision: u64,
}

/// A sortable key of a fleet time (monotonic for finite times).
pub fn time_key(t_s: f64) -> u64 {
    let b = t_s.to_bits();
    if b >> 63 == 1 {
        !b
    } else {
        b | (1 << 63)
    }
}

/// What [`PeerHistory::add_replayed`] did with a window.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Replayed {
    /// It was missing: stored.
    New,
    /// A less complete copy was held: replaced.
    Completed,
    /// An equal or more complete copy is held: ignored.
    AlreadyHeld,
}

/// Limits of a [`PeerHistory`].
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct HistoryLimits {
    /// History bytes per peer before keyframe windows are dropped.
    pub max_bytes: usize,
    /// How long recent track frames and descriptors are kept, s.
    pub recent_s: f64,
    /// Which keyframe windows are dropped.
    pub retention: Retention,
}

impl PeerHistory {
    /// Recent track frames, oldest first.
    pub fn recent(&self) -> &VecDeque<TrackFrame> {
        &self.recent
    }

    /// Forgets the recent frames (a test's peer that has moved on).
    #[cfg(test)]
    pub(crate) fn clear_recent(&mut self) {
        self.recent.clear();
        self.recent_bytes = 0;
    }

    /// Adds a track frame; drops recent frames older than `recent_s`, unless
    /// the latest snapshot still has a clone at or before them. Beyond that,
    /// the oldest frames also go while the ring holds more than its share of
    /// the memory bound.
    pub fn add_tracks(&mut self, frame: TrackFrame, limits: &HistoryLimits) {
        let newest = frame.t_s;
        self.recent_bytes += frame_bytes(&frame);
        self.recent.push_back(frame);
        let budget = recent_budget(limits.max_bytes);
        // A standstill's frames get no clone (the zero-velocity update takes
        // their place), so a window can span more than `recent_s`; its oldest
        // frames must stay for the next keyframe window to be whole. Clones
        // only get newer, so the latest snapshot's oldest one bounds them all.
        let window_start = self
            .latest
            .as_ref()
            .and_then(|s| s.clones.iter().map(|c| c.t_s).min_by(f64::total_cmp))
            .unwrap_or(f64::INFINITY);
        let keep_from = (newest - limits.recent_s).min(window_start);
        while let Some(f) = self.recent.front() {
            if f.t_s >= keep_from && self.recent_bytes <= budget {
                break;
            }
            self.recent_bytes = self.recent_bytes.saturating_sub(frame_bytes(f));
            self.recent.pop_front();
        }
        self.recent_descriptors
            .retain(|_, (t, _)| *t >= newest - limits.recent_s);
    }

    /// Keeps the recent descriptors within their share of the memory bound:
    /// past it, the older half goes (all of them if they share one time).
    fn bound_recent_descriptors(&mut self, limits: &HistoryLimits) {
        let cap = recent_budget(limits.max_bytes) / DESCRIPTOR_BYTES;
        if self.recent_descriptors.len() <= cap {
            return;
        }
        let mut times: Vec<f64> = self.recent_descriptors.values().map(|(t, _)| *t).collect();
        let drop = times.len() - cap / 2;
        let (_, cutoff, _) = times.select_nth_unstable_by(drop.saturating_sub(1), f64::total_cmp);
        let cutoff = *cutoff;
        self.recent_descriptors.retain(|_, (t, _)| *t > cutoff);
        if self.recent_descriptors.len() > cap {
            self.recent_descriptors.clear();
        }
    }

    /// Adds descriptors: new-track descriptors go to the recent map, keyframe
    /// descriptors wait for (or join) their keyframe window.
    pub fn add_descriptors(&mut self, batch: DescriptorBatch, limits: &HistoryLimits) {
        if !batch.keyframe {
            for e in &batch.entries {
                self.recent_descriptors.insert(e.id, (batch.t_s, e.bits));
            }
            self.bound_recent_descriptors(limits);
            return;
        }
        let key = batch.frame_index;
        let window = self
            .by_frame_index
            .get(&key)
            .and_then(|k| self.keyframes.get_mut(k))
            .filter(|k| k.snapshot.frame_index == key);
        match window {
            Some(kf) => {
                // Descriptors that come after their snapshot (another topic,
                // reordered) change the window: its bytes count against the
                // bound, and the store and the loop-closure index see a new
                // revision.
                let before = kf.bytes();
                kf.descriptors = batch.entries;
                let after = kf.bytes();
                self.history_bytes = (self.history_bytes + after).saturating_sub(before);
                self.stored_bytes = (self.stored_bytes + after).saturating_sub(before);
                self.revision += 1;
                self.keep_within(limits);
            }
            None => {
                self.pending_keyframe_descriptors.insert(key, batch.entries);
                // Only the newest few can still find their snapshot.
                while self.pending_keyframe_descriptors.len() > 8 {
                    self.pending_keyframe_descriptors.pop_first();
                }
            }
        }
    }

    /// Adds a snapshot; a keyframe snapshot becomes a history window with the
    /// recent measurements at its clone times.
    pub fn add_snapshot(&mut self, snap: StateSnapshot, limits: &HistoryLimits) {
        if snap.keyframe {
            let mut frames = Vec::with_capacity(snap.clones.len());
            for clone in &snap.clones {
                if let Some(f) = self.recent.iter().find(|f| f.t_s == clone.t_s) {
                    frames.push(HistoricalFrame {
                        t_s: f.t_s,
                        observations: f
                            .features
                            .iter()
                            .map(|p| HistoricalObservation {
                                id: p.id,
                                xy_norm: p.xy_norm,
                            })
                            .collect(),
                    });
                }
            }
            let descriptors = self
                .pending_keyframe_descriptors
                .remove(&snap.frame_index)
                .unwrap_or_default();
            let mut kf = KeyframeWindow::new(snap.clone(), frames, descriptors);
            // A copy of this window may be held already (read back from disk
            // after a restart, or replayed): what it has more of stays (the
            // keyframe's descriptors may have gone to it, and a restarted
            // sender's first windows lack the frames from before its restart).
            if let Some(held) = self.keyframes.get(&time_key(kf.end_s())) {
                if kf.descriptors.is_empty() {
                    kf.descriptors = held.descriptors.clone();
                }
                if held.frame_times.len() > kf.frame_times.len() {
                    kf.frame_times = held.frame_times.clone();
                    kf.tracks = held.tracks.clone();
                    kf.xy = held.xy.clone();
                }
            }
            self.store(kf, limits);
        }
        if self.latest.as_ref().is_none_or(|l| l.t_s <= snap.t_s) {
            self.latest = Some(snap);
        }
    }

    /// Stores a keyframe window, then drops windows while the history exceeds
    /// its bound.
    fn store(&mut self, kf: KeyframeWindow, limits: &HistoryLimits) {
        self.history_bytes += kf.bytes();
        self.stored_bytes += kf.bytes();
        self.stored_keyframes += 1;
        self.revision += 1;
        if let (Some(a), Some(b)) = (kf.snapshot.clones.first(), kf.snapshot.clones.last()) {
            let (lo, hi) = self.stored_span.unwrap_or((a.t_s, b.t_s));
            self.stored_span = Some((lo.min(a.t_s), hi.max(b.t_s)));
        }
        let key = time_key(kf.end_s());
        // The newest window of a frame index keeps it (a restarted peer counts
        // its frames from zero again).
        let newest = self
            .by_frame_index
            .entry(kf.snapshot.frame_index)
            .or_insert(key);
        if !self.keyframes.contains_key(newest) || *newest < key {
            *newest = key;
        }
        if let Some(old) = self.keyframes.insert(key, kf) {
            // A replaced window: counted once in what was stored.
            self.history_bytes = self.history_bytes.saturating_sub(old.bytes());
            self.stored_bytes = self.stored_bytes.saturating_sub(old.bytes());
            self.stored_keyframes -= 1;
        }
        self.keep_within(limits);
    }

    /// Drops keyframe windows while the history exceeds its bound.
    fn keep_within(&mut self, limits: &HistoryLimits) {
        while self.history_bytes > limits.max_bytes {
            let Some((key, old)) = history_retention::victim(&self.keyframes, limits.retention)
                .and_then(|k| self.keyframes.remove_entry(&k))
            else {
                break;
            };
            let index = old.snapshot.frame_index;
            if self.by_frame_index.get(&index) == Some(&key) {
                self.by_frame_index.remove(&index);
            }
            self.history_bytes = self.history_bytes.saturating_sub(old.bytes());
            self.dropped_keyframes += 1;
        }
    }

    /// Stores a keyframe window sent again on request (history catch-up) when
    /// it is missing, or more complete than the one held; says which.
    pub fn add_replayed(&mut self, kf: KeyframeWindow, limits: &HistoryLimits) -> Replayed {
        let outcome = match self.keyframes.get(&time_key(kf.end_s())) {
            None => Replayed::New,
            Some(held) if kf.completeness() > held.completeness() => Replayed::Completed,
            Some(_) => return Replayed::AlreadyHeld,
        };
        self.store(kf, limits);
        outcome
    }

    /// Adds a replayed part to the window it belongs to, if that window is
    /// held: `Completed` when it added something, `AlreadyHeld` when the copy
    /// held had it all, `None` when the window is not held (a part cannot
    /// make a window: it has no snapshot).
    pub fn add_part(&mut self, part: WindowPart, limits: &HistoryLimits) -> Option<Replayed> {
        let kf = self.keyframes.get_mut(&time_key(part.end_s))?;
        let before = kf.bytes();
        if !kf.merge(part) {
            return Some(Replayed::AlreadyHeld);
        }
        let grown = kf.bytes().saturating_sub(before);
        self.history_bytes += grown;
        self.stored_bytes += grown;
        self.revision += 1;
        // The window grew: the bound may now drop one.
        self.keep_within(limits);
        Some(Replayed::Completed)
    }

    /// The newest stored window's end time, s.
    pub fn newest_window_end_s(&self) -> Option<f64> {
        self.keyframes
            .values()
            .next_back()
            .map(KeyframeWindow::end_s)
    }

    /// Fleet time spanned by every keyframe window stored, s (0 before any).
    pub fn stored_span_s(&self) -> f64 {
        self.stored_span.map_or(0.0, |(a, b)| (b - a).max(0.0))
    }

    /// Approximate bytes held for this peer (history and recent data).
    pub fn bytes(&self) -> usize {
        let recent = self.recent_bytes;
        let latest = self.latest.as_ref().map_or(0, |s| {
            s.covariance.lower.len() * 4
                + s.clones.len() * std::mem::size_of::<common::messages::CameraPose>()
        });
        self.history_bytes + recent + latest + self.recent_descriptors.len() * DESCRIPTOR_BYTES
    }

    /// The keyframe windows whose time span `[oldest clone, newest clone]` overlaps
    /// `[from_s, to_s]`, oldest first.
    pub fn keyframes_between(&self, from_s: f64, to_s: f64) -> Vec<&KeyframeWindow> {
        self.keyframes
            .range(time_key(from_s)..)
            .map(|(_, k)| k)
            .take_while(|k| k.snapshot.clones.first().is_some_and(|c| c.t_s <= to_s))
            .collect()
    }
}

/// Snapshots for the tests of the history and its users.
#[cfg(test)]
pub(crate) mod test_support {
    use common::messages::{
        CameraModelWire, CameraPose, DistortionWire, PackedCovariance, StateSnapshot,
    };
    use nalgebra::DMatrix;

    /// A snapshot at `t_s` (frame index `10 t_s`) of a 752x480 radtan camera,
    /// with `clones`, covariance `cov` and no landmarks.
    pub(crate) fn snapshot(
        t_s: f64,
        keyframe: bool,
        clones: Vec<CameraPose>,
        cov: &DMatrix<f64>,
    ) -> StateSnapshot {
        StateSnapshot {
            frame_index: (t_s * 10.0).round() as u64,
            t_s,
            keyframe,
            frame_epoch: 0,
            camera: CameraModelWire {
                model: DistortionWire::Radtan,
                intrinsics: [450.0, 450.0, 370.0, 240.0, 0.0, 0.0, 0.0, 0.0],
                width: 752,
                height: 480,
            },
            pixel_sigma_px: 1.0,
            covariance: PackedCovariance::from_dmatrix(cov).expect("a square covariance"),
            clones,
            landmarks: Vec::new(),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use common::messages::{CameraPose, PackedCovariance, TrackPoint};
    use nalgebra::{DMatrix, Matrix3, Vector3};

    fn tracks(t: f64, n: usize) -> TrackFrame {
        TrackFrame {
            frame_index: (t * 10.0).round() as u64,
            t_s: t,
            features: (0..n as u64)
                .map(|id| TrackPoint {
                    id,
                    uv_px: [1.0, 2.0],
                    xy_norm: [0.1, 0.2],
                })
                .collect(),
        }
    }

    fn snapshot(t_last: f64, keyframe: bool) -> StateSnapshot {
        let clones: Vec<CameraPose> = (0..11)
            .map(|i| {
                CameraPose::new(
                    t_last - 0.1 * (10 - i) as f64,
                    &Matrix3::identity(),
                    &Vector3::zeros(),
                )
            })
            .collect();
        test_support::snapshot(t_last, keyframe, clones, &DMatrix::identity(66, 66))
    }

    fn limits(max_bytes: usize) -> HistoryLimits {
        HistoryLimits {
            max_bytes,
            recent_s: 2.0,
            retention: Retention::Oldest,
        }
    }

    #[test]
    fn keyframe_windows_keep_their_measurements_and_descriptors() {
        let mut h = PeerHistory::default();
        let l = limits(usize::MAX);
        // Tracks at the clone times of a window ending at t = 2.0 (exact times).
        for i in 0..=20 {
            let t = 2.0 - 0.1 * (20 - i) as f64;
            h.add_tracks(tracks(t, 100), &l);
        }
        let snap = snapshot(2.0, true);
        h.add_descriptors(
            DescriptorBatch {
                frame_index: snap.frame_index,
                t_s: 2.0,
                keyframe: true,
                entries: vec![DescriptorEntry {
                    id: 3,
                    bits: [1; 4],
                }],
            },
            &l,
        );
        h.add_snapshot(snap, &l);
        assert_eq!(h.keyframes.len(), 1);
        let kf = h.keyframes.values().next().unwrap();
        assert_eq!(kf.frames().len(), 11);
        assert_eq!(kf.descriptors.len(), 1);
        assert_eq!(h.keyframes_between(1.5, 1.6).len(), 1);
        assert!(h.keyframes_between(2.5, 3.0).is_empty());
        // Recent frames older than 2 s were dropped.
        assert!(h.recent.front().unwrap().t_s >= 0.0 - 1e-9);
        assert!(h.latest.is_some());
    }

    #[test]
    fn a_window_stretched_by_a_standstill_is_kept_whole() {
        // Frames every 0.1 s up to 3.5 s; the robot stood still from 0.5 to
        // 2.9 s, so those frames got no clone and the window of 11 clones
        // spans 3.5 s, more than the 2 s of recent frames kept otherwise.
        let l = limits(usize::MAX);
        let mut h = PeerHistory::default();
        let mut clone_times: Vec<f64> = Vec::new();
        for i in 0..=35 {
            let t = 0.1 * i as f64;
            h.add_tracks(tracks(t, 10), &l);
            if !(5..30).contains(&i) {
                clone_times.push(t);
            }
            let clones: Vec<CameraPose> = clone_times
                .iter()
                .map(|&t| CameraPose::new(t, &Matrix3::identity(), &Vector3::zeros()))
                .collect();
            let n = 6 * clones.len();
            let keyframe = i == 35;
            if keyframe {
                h.add_descriptors(
                    DescriptorBatch {
                        frame_index: 35,
                        t_s: t,
                        keyframe: true,
                        entries: vec![DescriptorEntry {
                            id: 3,
                            bits: [1; 4],
                        }],
                    },
                    &l,
                );
            }
            h.add_snapshot(
                test_support::snapshot(t, keyframe, clones, &DMatrix::identity(n, n)),
                &l,
            );
        }
        assert_eq!(clone_times.len(), 11);
        let kf = h.keyframes.values().next().unwrap();
        assert_eq!(kf.frames().len(), 11);
        assert!(kf.is_whole());
        // Frames older than the window's oldest clone still go.
        h.add_tracks(tracks(3.6, 10), &l);
        h.add_snapshot(
            test_support::snapshot(
                3.6,
                false,
                clone_times[1..]
                    .iter()
                    .chain([3.6].iter())
                    .map(|&t| CameraPose::new(t, &Matrix3::identity(), &Vector3::zeros()))
                    .collect(),
                &DMatrix::identity(66, 66),
            ),
            &l,
        );
        h.add_tracks(tracks(3.7, 10), &l);
        assert!((h.recent.front().unwrap().t_s - 0.1).abs() < 1e-9);
    }

    #[test]
    fn a_window_already_held_keeps_what_the_live_copy_lacks() {
        // A window read back from disk after a restart, whole.
        let l = limits(usize::MAX);
        let snap = snapshot(2.0, true);
        let descriptors = vec![DescriptorEntry {
            id: 3,
            bits: [1; 4],
        }];
        let mut h = PeerHistory::default();
        let frames: Vec<HistoricalFrame> = snap
            .clones
            .iter()
            .map(|c| HistoricalFrame {
                t_s: c.t_s,
                observations: Vec::new(),
            })
            .collect();
        let whole = KeyframeWindow::new(snap.clone(), frames, descriptors.clone());
        h.add_replayed(whole.clone(), &l);
        // The sender, restarted, sends it again: its keyframe descriptors
        // first (they find the held copy), then a snapshot whose frames
        // before the restart it no longer has.
        h.add_tracks(tracks(2.0, 5), &l);
        h.add_descriptors(
            DescriptorBatch {
                frame_index: snap.frame_index,
                t_s: 2.0,
                keyframe: true,
                entries: descriptors,
            },
            &l,
        );
        h.add_snapshot(snap, &l);
        assert_eq!(h.keyframes.len(), 1);
        let kf = h.keyframes.values().next().unwrap();
        assert_eq!(kf.completeness(), whole.completeness());
    }

    #[test]
    fn a_part_fills_in_what_a_held_window_lacks_and_nothing_else() {
        let l = limits(usize::MAX);
        let snap = snapshot(2.0, true);
        let frame = |t_s: f64| HistoricalFrame {
            t_s,
            observations: vec![HistoricalObservation {
                id: 7,
                xy_norm: [0.1, 0.2],
            }],
        };
        let times: Vec<f64> = snap.clones.iter().map(|c| c.t_s).collect();
        // Held without clones 3 and 8 and without descriptors.
        let short: Vec<HistoricalFrame> = times
            .iter()
            .enumerate()
            .filter(|(i, _)| ![3, 8].contains(i))
            .map(|(_, &t)| frame(t))
            .collect();
        let mut h = PeerHistory::default();
        h.add_replayed(KeyframeWindow::new(snap.clone(), short, Vec::new()), &l);
        let held = h.keyframes.values().next().unwrap().held();
        assert_eq!(held.frames_mask, 0b110_1111_0111);
        assert!(!held.descriptors);
        let whole = KeyframeWindow::new(
            snap.clone(),
            times.iter().map(|&t| frame(t)).collect(),
            vec![DescriptorEntry {
                id: 7,
                bits: [5; 4],
            }],
        );
        let part = whole.part_for([&held]);
        assert_eq!(part.frames.len(), 2);
        assert_eq!(part.descriptors.len(), 1);
        let (bytes, revision) = (h.history_bytes, h.revision);
        // A frame at no clone time is ignored; the rest fills the window.
        let mut stray = part.clone();
        stray.frames.push(frame(2.05));
        assert_eq!(h.add_part(stray, &l), Some(Replayed::Completed));
        let kf = h.keyframes.values().next().unwrap();
        assert_eq!(kf.frames(), whole.frames());
        assert_eq!(kf.descriptors, whole.descriptors);
        assert!(kf.is_whole());
        assert!(h.history_bytes > bytes);
        assert_eq!(h.history_bytes, whole.bytes());
        assert!(h.revision > revision);
        // Again: nothing new. A part of a window not held makes nothing.
        assert_eq!(h.add_part(part.clone(), &l), Some(Replayed::AlreadyHeld));
        let elsewhere = WindowPart { end_s: 9.0, ..part };
        assert_eq!(h.add_part(elsewhere, &l), None);
        assert_eq!(h.keyframes.len(), 1);
        // Nothing is missing for a holder of it all.
        assert!(whole.part_for([&whole.held()]).is_empty());
    }

    #[test]
    fn keyframe_descriptors_after_their_snapshot_count_and_make_a_new_revision() {
        let mut h = PeerHistory::default();
        h.add_snapshot(snapshot(2.0, true), &limits(usize::MAX));
        let (bytes, revision) = (h.history_bytes, h.revision);
        let entries: Vec<DescriptorEntry> = (0..50)
            .map(|id| DescriptorEntry { id, bits: [id; 4] })
            .collect();
        h.add_descriptors(
            DescriptorBatch {
                frame_index: 20,
                t_s: 2.0,
                keyframe: true,
                entries,
            },
            &limits(usize::MAX),
        );
        let kf = h.keyframes.values().next().unwrap();
        assert_eq!(kf.descriptors.len(), 50);
        assert_eq!(h.history_bytes, kf.bytes());
        assert!(h.history_bytes > bytes);
        assert!(h.revision > revision, "the store and the index must see it");
    }

    #[test]
    fn a_tracks_measurements_are_found_in_every_frame_whatever_the_order_sent() {
        let snap = snapshot(2.0, true);
        let obs = |ids: &[u64]| -> Vec<HistoricalObservation> {
            ids.iter()
                .map(|&id| HistoricalObservation {
                    id,
                    xy_norm: [id as f32, 0.0],
                })
                .collect()
        };
        // Ids out of order, and a malformed frame with a repeated id: the
        // first of the repeats is the one found, as a scan would.
        let mut repeated = obs(&[5, 3]);
        repeated.push(HistoricalObservation {
            id: 3,
            xy_norm: [-1.0, 0.0],
        });
        let frames = vec![
            HistoricalFrame {
                t_s: snap.clones[0].t_s,
                observations: obs(&[9, 3, 7, 1]),
            },
            HistoricalFrame {
                t_s: snap.clones[1].t_s,
                observations: obs(&[2, 4]),
            },
            HistoricalFrame {
                t_s: snap.clones[2].t_s,
                observations: repeated,
            },
        ];
        let kf = KeyframeWindow::new(snap.clone(), frames.clone(), Vec::new());
        for id in 0..11 {
            let found: Vec<(f64, f32)> = kf.measurements_of(id).map(|(t, xy)| (t, xy[0])).collect();
            let scanned: Vec<(f64, f32)> = frames
                .iter()
                .filter_map(|f| {
                    let o = f.observations.iter().find(|o| o.id == id)?;
                    Some((f.t_s, o.xy_norm[0]))
                })
                .collect();
            assert_eq!(found, scanned, "track {id}");
        }
        assert_eq!(kf.measurements_of(3).count(), 2);
        // Kept track by track, the frames come back as sent, each by track id,
        // the repeat dropped; and a replay of the window is the window.
        let back = kf.frames();
        assert_eq!(back.len(), frames.len());
        for (b, f) in back.iter().zip(&frames) {
            let mut sent = f.observations.clone();
            sent.sort_by_key(|o| o.id);
            sent.dedup_by_key(|o| o.id);
            assert_eq!((b.t_s, &b.observations), (f.t_s, &sent));
        }
        assert_eq!(KeyframeWindow::from_wire(kf.to_wire()), kf);
        assert_eq!(kf.observations_at(snap.clones[1].t_s), obs(&[2, 4]));
        assert!(kf.observations_at(-1.0).is_empty());
    }

    #[test]
    fn keyframe_descriptors_find_the_newest_window_of_their_frame_index() {
        // A peer that restarted counts its frames from zero again: frame index
        // 20 names a window at 2 s from before the restart and one at 9 s.
        let l = limits(usize::MAX);
        let mut h = PeerHistory::default();
        h.add_snapshot(snapshot(2.0, true), &l);
        let mut again = snapshot(9.0, true);
        again.frame_index = 20;
        h.add_snapshot(again, &l);
        let entries = vec![DescriptorEntry {
            id: 1,
            bits: [7; 4],
        }];
        let batch = |entries| DescriptorBatch {
            frame_index: 20,
            t_s: 9.0,
            keyframe: true,
            entries,
        };
        h.add_descriptors(batch(entries.clone()), &l);
        let newest = h.keyframes.values().next_back().unwrap();
        assert_eq!(newest.descriptors, entries);
        assert!(h.keyframes.values().next().unwrap().descriptors.is_empty());
    }

    #[test]
    fn memory_bound_drops_the_oldest_windows_first() {
        let mut h = PeerHistory::default();
        let one = {
            let mut probe = PeerHistory::default();
            probe.add_snapshot(snapshot(1.0, true), &limits(usize::MAX));
            probe.history_bytes
        };
        let l = limits(one * 5 + one / 2);
        for k in 1..=20 {
            h.add_snapshot(snapshot(1.2 * k as f64, true), &l);
        }
        assert_eq!(h.keyframes.len(), 5);
        assert_eq!(h.dropped_keyframes, 15);
        assert_eq!(h.stored_keyframes, 20);
        assert!(h.history_bytes <= l.max_bytes);
        // The growth counts what was stored, not what is left.
        assert_eq!(h.stored_bytes, 20 * one);
        assert!((h.stored_span_s() - (1.2 * 20.0 - 0.2)).abs() < 1e-9);
        let oldest = h.keyframes.values().next().unwrap().snapshot.t_s;
        assert!((oldest - 1.2 * 16.0).abs() < 1e-9);
    }

    #[test]
    fn informed_retention_keeps_the_most_certain_windows() {
        // Twenty windows, one place each (10 m apart), each less certain than
        // the one before: the bound keeps five, the first five.
        let window = |k: usize| {
            let mut s = snapshot(1.2 * k as f64, true);
            let pose = s.clones[10];
            let pos = Vector3::new(10.0 * k as f64, 0.0, 1.0);
            s.clones = vec![CameraPose::new(pose.t_s, &Matrix3::identity(), &pos)];
            s.covariance =
                PackedCovariance::from_dmatrix(&(DMatrix::identity(6, 6) * (k as f64 * 1e-4)))
                    .unwrap();
            s
        };
        let one = {
            let mut probe = PeerHistory::default();
            probe.add_snapshot(window(1), &limits(usize::MAX));
            probe.history_bytes
        };
        let l = HistoryLimits {
            retention: Retention::Informed,
            ..limits(one * 5 + one / 2)
        };
        let mut h = PeerHistory::default();
        for k in 1..=20 {
            h.add_snapshot(window(k), &l);
        }
        assert_eq!(h.keyframes.len(), 5);
        assert_eq!(h.dropped_keyframes, 15);
        let kept: Vec<f64> = h.keyframes.values().map(|w| w.snapshot.t_s).collect();
        assert_eq!(kept, (1..=5).map(|k| 1.2 * k as f64).collect::<Vec<_>>());
    }

    #[test]
    fn a_flood_of_frames_or_descriptors_stays_within_its_share() {
        let mut h = PeerHistory::default();
        let l = limits(1 << 20);
        // Frames that all claim the same time never age out of the 2 s ring.
        for _ in 0..2000 {
            h.add_tracks(tracks(5.0, 100), &l);
        }
        assert!(h.recent_bytes <= recent_budget(l.max_bytes));
        assert!(!h.recent().is_empty());
        assert_eq!(
            h.recent_bytes,
            h.recent().iter().map(frame_bytes).sum::<usize>()
        );
        // New-track descriptors of ever new ids, no frames to age them out.
        let cap = recent_budget(l.max_bytes) / DESCRIPTOR_BYTES;
        for k in 0..100u64 {
            let batch = DescriptorBatch {
                frame_index: k,
                t_s: k as f64 * 0.01,
                keyframe: false,
                entries: (0..500)
                    .map(|i| DescriptorEntry {
                        id: k * 1000 + i,
                        bits: [i; 4],
                    })
                    .collect(),
            };
            h.add_descriptors(batch, &l);
            assert!(h.recent_descriptors.len() <= cap);
        }
        // The newest stay.
        assert!(h.recent_descriptors.contains_key(&99_499));
        assert!(h.bytes() <= 2 * recent_budget(l.max_bytes) + 4096);
    }

    #[test]
    fn time_keys_sort_like_times() {
        let ts = [-5.0, -0.1, 0.0, 0.1, 3.0, 1e6];
        for w in ts.windows(2) {
            assert!(time_key(w[0]) < time_key(w[1]));
        }
    }
}
