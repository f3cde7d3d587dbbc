//! Historical loop closures to peers (thesis Section 5.3.5): one bag-of-words
//! database per peer, fed with that peer's keyframe descriptors as its keyframe
//! windows arrive; the current frame queries every peer's database, and each
//! candidate above the score threshold is matched by descriptor (through the
//! direct index) and verified with the fundamental-matrix RANSAC.

use super::matcher::epipolar_inliers;
use crate::estimator::frame_alignment::CameraEstimate;
use crate::peer_history::{KeyframeWindow, PeerHistory};
use common::descriptor::Descriptor;
use nalgebra::Vector2;
use std::collections::{BTreeSet, HashMap};
use std::sync::Arc;
use vocabulary::{
    match_features, BowVector, Database, EntryId, FeatureVector, MatchParams, Vocabulary,
};

/// How many of a peer's newest keyframe windows are checked for indexing each
/// frame (keyframes arrive about once per second; their descriptors may come a
/// tick after the window).
const INDEX_LOOKBACK: usize = 4;

/// Older keyframe windows indexed per frame beyond the newest ones: the windows a
/// peer stored before our first frame (a robot that starts late, or an agent
/// restarted) are indexed over the following frames, a few at a time, so no
/// frame pays for a whole history at once (an hour of a peer, about 3 600
/// windows, takes 450 frames: 45 s).
const INDEX_BACKLOG_PER_FRAME: usize = 8;

/// The keyframe database of one peer.
#[derive(Debug)]
pub struct KeyframeDb {
    vocabulary: Arc<Vocabulary>,
    db: Database,
    /// Keyframe key (see `PeerHistory::keyframes`) of each database entry.
    keys: Vec<u64>,
    /// Descriptors of each entry, in the order the direct index refers to.
    descriptors: Vec<Vec<(u64, Descriptor)>>,
    indexed: BTreeSet<u64>,
    /// Windows passed over for lack of descriptors (also in `indexed`): a
    /// replayed copy with descriptors replaces such a window (history catch-up),
    /// and is indexed then.
    passed_over: BTreeSet<u64>,
    /// The history's count of dropped windows when last looked at.
    seen_dropped: u64,
    /// The history's revision (windows stored or replaced) when the backlog was
    /// last found empty (`None`: not yet): while it is unchanged there is nothing older to
    /// index.
    backlog_clear_at: Option<u64>,
    /// Entries whose window the history may have dropped since the last prune
    /// (an upper bound: not every dropped window was indexed).
    maybe_dead: usize,
}

/// Dropped windows left in a database before it is rebuilt without them: at
/// least this many, and at least a quarter of it.
const MIN_PRUNE: usize = 64;

/// Our current frame as the matcher sees it.
#[derive(Clone, Debug, Default)]
pub struct FrameFeatures {
    /// Our track ids.
    pub ids: Vec<u64>,
    /// Their descriptors.
    pub descriptors: Vec<Descriptor>,
    /// Their undistorted normalized coordinates.
    pub xy: Vec<Vector2<f64>>,
    /// The frame's time, s (fleet clock).
    pub t_s: f64,
    /// Our camera's pose now with its covariance, when the peers' frames are
    /// being aligned (`align_peer_frames`).
    pub camera: Option<CameraEstimate>,
    /// Our pixel noise over our focal length (normalized units).
    pub sigma_normalized: f64,
    /// Our pixel noise, pixels (0 when unset: a peer's is then taken to be
    /// ours).
    pub pixel_sigma_px: f64,
}

/// A verified loop closure: our tracks matched to the peer's tracks of one
/// keyframe window.
#[derive(Clone, Debug, PartialEq)]
pub struct LoopClosure {
    /// The keyframe window's key.
    pub keyframe: u64,
    /// `(our track, peer track)` pairs that passed the epipolar check.
    pub pairs: Vec<(u64, u64)>,
    /// Bag-of-words score of the candidate.
    pub score: f64,
}

impl KeyframeDb {
    /// An empty database; the direct index groups features one level below the
    /// root (coarse groups: few true matches are missed).
    pub fn new(vocabulary: Arc<Vocabulary>) -> Self {
        let levels_up = vocabulary.levels().saturating_sub(1);
        Self {
            db: Database::new(Arc::clone(&vocabulary), levels_up),
            vocabulary,
            keys: Vec::new(),
            descriptors: Vec::new(),
            indexed: BTreeSet::new(),
            passed_over: BTreeSet::new(),
            seen_dropped: 0,
            backlog_clear_at: None,
            maybe_dead: 0,
        }
    }

    /// Keyframe windows in the database.
    pub fn len(&self) -> usize {
        self.keys.len()
    }

    /// Approximate heap bytes held: the database and the descriptors kept for
    /// matching.
    pub fn bytes(&self) -> usize {
        let descriptors: usize = self
            .descriptors
            .iter()
            .map(|d| d.len() * std::mem::size_of::<(u64, Descriptor)>())
            .sum();
        self.db.bytes() + descriptors + self.keys.len() * 8 + self.indexed.len() * 8
    }

    /// What one keyframe window adds to [`KeyframeDb::bytes`] on average (0
    /// when empty).
    pub fn bytes_per_keyframe(&self) -> f64 {
        if self.keys.is_empty() {
            return 0.0;
        }
        (self.bytes() - self.db.fixed_bytes()) as f64 / self.keys.len() as f64
    }

    /// Whether the database is empty.
    pub fn is_empty(&self) -> bool {
        self.keys.is_empty()
    }

    /// Adds the peer's newest keyframe windows that have descriptors and are not
    /// indexed yet, and up to [`INDEX_BACKLOG_PER_FRAME`] older ones (newest
    /// first) that are not either: a window stored before we looked is found
    /// later, not never. An older window without descriptors will not get them
    /// (they come within a tick of it) and is passed over for good.
    /// First drops the windows the history's memory bound dropped, so the
    /// database stays within that bound too.
    pub fn index_new(&mut self, history: &PeerHistory) {
        self.prune(history);
        for (key, kf) in history.keyframes.iter().rev().take(INDEX_LOOKBACK) {
            if !kf.descriptors.is_empty() && self.wants(key) {
                self.add(*key, kf);
            }
        }
        if self.backlog_clear_at == Some(history.revision) {
            return;
        }
        // Every new window changes the revision, so this walk runs about once a
        // second per peer over a history of thousands: the indexed keys are
        // walked alongside (both newest first) instead of looked up per window.
        let (mut add, mut pass_over, mut more) = (Vec::new(), Vec::new(), false);
        let mut indexed = self.indexed.iter().rev().peekable();
        for (key, kf) in history.keyframes.iter().rev().skip(INDEX_LOOKBACK) {
            while indexed.next_if(|k| *k > key).is_some() {}
            let passed_over = self.passed_over.contains(key);
            let wants = indexed.peek() != Some(&key) || passed_over;
            if !wants || (kf.descriptors.is_empty() && passed_over) {
                continue;
            }
            if add.len() == INDEX_BACKLOG_PER_FRAME {
                more = true;
                break;
            }
            if kf.descriptors.is_empty() {
                pass_over.push(*key);
            } else {
                add.push((*key, kf));
            }
        }
        for key in pass_over {
            self.indexed.insert(key);
            self.passed_over.insert(key);
        }
        for (key, kf) in add {
            self.add(key, kf);
        }
        if !more {
            self.backlog_clear_at = Some(history.revision);
        }
    }

    /// Whether window `key` is still to be indexed: never looked at, or passed
    /// over for lack of descriptors (they may have come with a replayed copy).
    fn wants(&self, key: &u64) -> bool {
        !self.indexed.contains(key) || self.passed_over.contains(key)
    }

    /// Indexes keyframe window `key`.
    fn add(&mut self, key: u64, kf: &KeyframeWindow) {
        self.passed_over.remove(&key);
        let list: Vec<(u64, Descriptor)> = kf
            .descriptors
            .iter()
            .map(|e| (e.id, e.descriptor()))
            .collect();
        let desc: Vec<Descriptor> = list.iter().map(|(_, d)| *d).collect();
        self.db.add(&desc);
        self.keys.push(key);
        self.descriptors.push(list);
        self.indexed.insert(key);
    }

    /// Rebuilds the database without the windows the history no longer holds,
    /// once they are many enough to be worth it ([`MIN_PRUNE`]).
    fn prune(&mut self, history: &PeerHistory) {
        let newly = history.dropped_keyframes.saturating_sub(self.seen_dropped);
        self.seen_dropped = history.dropped_keyframes;
        self.maybe_dead += usize::try_from(newly).unwrap_or(usize::MAX);
        let enough = MIN_PRUNE.max(self.keys.len() / 4);
        if self.maybe_dead < enough {
            return;
        }
        let live: Vec<bool> = self
            .keys
            .iter()
            .map(|k| history.keyframes.contains_key(k))
            .collect();
        let dead = live.iter().filter(|l| !**l).count();
        self.maybe_dead = dead;
        if dead < enough {
            return;
        }
        self.maybe_dead = 0;
        let mut db = Database::new(
            Arc::clone(&self.vocabulary),
            self.db.direct_index_levels_up(),
        );
        let mut keys = Vec::with_capacity(self.keys.len() - dead);
        let mut descriptors = Vec::with_capacity(self.keys.len() - dead);
        let old = std::mem::take(&mut self.descriptors);
        for (i, (d, keep)) in old.into_iter().zip(live).enumerate() {
            let key = self.keys.get(i).copied();
            match (keep, key, self.db.entry(EntryId(i as u32))) {
                (true, Some(key), Some(e)) => {
                    db.add_transformed(e.bow.clone(), e.features.clone());
                    keys.push(key);
                    descriptors.push(d);
                }
                (_, Some(key), _) => {
                    self.indexed.remove(&key);
                }
                _ => {}
            }
        }
        self.db = db;
        self.keys = keys;
        self.descriptors = descriptors;
        // Windows passed over for lack of descriptors are forgotten with the rest.
        self.indexed.retain(|k| history.keyframes.contains_key(k));
        self.passed_over
            .retain(|k| history.keyframes.contains_key(k));
    }

    /// The best `n` keyframes for `bow` scoring at least `min_score`:
    /// `(database entry, keyframe key, score)`.
    fn candidates(&self, bow: &BowVector, n: usize, min_score: f64) -> Vec<(usize, u64, f64)> {
        self.db
            .query_bow(bow, n)
            .into_iter()
            .filter(|(_, s)| *s >= min_score)
            .filter_map(|(e, s)| Some((e.0 as usize, *self.keys.get(e.0 as usize)?, s)))
            .collect()
    }
}

/// The BoW vector and direct index of our frame, for [`detect`].
pub fn describe(vocabulary: &Vocabulary, frame: &FrameFeatures) -> (BowVector, FeatureVector) {
    let levels_up = vocabulary.levels().saturating_sub(1);
    vocabulary.transform_with_features(&frame.descriptors, levels_up)
}

/// Settings of loop-closure detection.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct LoopParams {
    /// Candidates checked.
    pub candidates: usize,
    /// Smallest BoW score.
    pub min_score: f64,
    /// Descriptor match rules.
    pub matching: MatchParams,
    /// Epipolar threshold, normalized units.
    pub threshold: f64,
    /// Fewest inliers.
    pub min_inliers: usize,
    /// RANSAC seed.
    pub seed: u64,
}

/// The keyframe frame's normalized coordinates by the peer's track id.
fn keyframe_points(kf: &KeyframeWindow) -> HashMap<u64, Vector2<f64>> {
    kf.observations_at(kf.snapshot.t_s)
        .into_iter()
        .map(|o| {
            (
                o.id,
                Vector2::new(f64::from(o.xy_norm[0]), f64::from(o.xy_norm[1])),
            )
        })
        .collect()
}

/// Queries `db` with our frame and verifies the candidates against `history`:
/// every loop closure that passes.
pub fn detect(
    db: &KeyframeDb,
    history: &PeerHistory,
    frame: &FrameFeatures,
    bow: &BowVector,
    index: &FeatureVector,
    params: &LoopParams,
) -> Vec<LoopClosure> {
    let mut out = Vec::new();
    for (entry, key, score) in db.candidates(bow, params.candidates, params.min_score) {
        let (Some(kf), Some(kf_index), Some(list)) = (
            history.keyframes.get(&key),
            db.db.features(vocabulary::EntryId(entry as u32)),
            db.descriptors.get(entry),
        ) else {
            continue;
        };
        let kf_desc: Vec<Descriptor> = list.iter().map(|(_, d)| *d).collect();
        let pairs = match_features(
            &frame.descriptors,
            index,
            &kf_desc,
            kf_index,
            &params.matching,
        );
        let points = keyframe_points(kf);
        let (mut ours, mut theirs, mut x1, mut x2) = (vec![], vec![], vec![], vec![]);
        for (a, b) in pairs {
            let (id_b, _) = list[b];
            if let Some(p) = points.get(&id_b) {
                ours.push(frame.ids[a]);
                theirs.push(id_b);
                x1.push(frame.xy[a]);
                x2.push(*p);
            }
        }
        let Some(inl) = epipolar_inliers(
            &x1,
            &x2,
            params.threshold,
            params.min_inliers,
            params.seed ^ key,
        ) else {
            continue;
        };
        let pairs: Vec<(u64, u64)> = ours
            .into_iter()
            .zip(theirs)
            .zip(inl)
            .filter(|(_, keep)| *keep)
            .map(|(p, _)| p)
            .collect();
        out.push(LoopClosure {
            keyframe: key,
            pairs,
            score,
        });
    }
    out
}
