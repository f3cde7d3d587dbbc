//! Which of one peer's measurements this robot has used: each goes into one
//! update only (a measurement used twice would be counted twice, thesis
//! Section 5.3), whether it was reached through the peer's current window or,
//! later, through a keyframe window of its history.
//!
//! A mark is `(time key, peer track)`: the time of the peer's frame (a
//! constraint marks the window's end time, its track with the top bit set).
//! Marks are kept by time, so a lookup is one search among the peer's frame
//! times and one among the few tracks used at that time. The marks of frames
//! no held window and no recent frame still reaches are forgotten, so they
//! stay within what the history bound keeps however long the mission (kept
//! until the whole history was gone, they grew by about a million an hour per
//! agent, stop 33). A forgotten stretch of time is remembered as a range: a
//! window dropped and then replayed by a catch-up counts as used up there.

use crate::peer_history::{time_key, PeerHistory};
use std::collections::BTreeMap;

/// Windows dropped by the peer's history bound before the marks are swept
/// again (a sweep looks at every marked time once).
const SWEEP_EVERY_DROPPED: u64 = 32;

/// Forgotten ranges kept; beyond, the oldest go (a window dropped that long
/// ago is not asked for again: see `history_catchup`).
const MAX_FORGOTTEN_RANGES: usize = 1 << 16;

/// The used marks of one peer.
#[derive(Clone, Debug, Default)]
pub(super) struct UsedMarks {
    /// Time key -> the tracks used at that time, sorted.
    by_time: BTreeMap<u64, Vec<u64>>,
    /// Time-key ranges `lo -> hi` (inclusive, disjoint) whose marks were
    /// forgotten with the windows that held them.
    forgotten: BTreeMap<u64, u64>,
    /// Marks held.
    marks: usize,
    /// The peer history's dropped-window count at the last sweep.
    swept_at_dropped: u64,
}

impl UsedMarks {
    /// Whether the measurement of `track` at time key `time` was used.
    pub(super) fn contains(&self, time: u64, track: u64) -> bool {
        if let Some((_, hi)) = self.forgotten.range(..=time).next_back() {
            if time <= *hi {
                return true;
            }
        }
        self.by_time
            .get(&time)
            .is_some_and(|tracks| tracks.binary_search(&track).is_ok())
    }

    /// Lookups at times within `lo..=hi` (time keys), made in increasing time
    /// order: one descent into the marks for the range, then a step forward
    /// per lookup (a window's measurements of a track come in time order).
    /// An empty range (`lo > hi`) answers every lookup by [`Self::contains`].
    pub(super) fn cursor(&self, lo: u64, hi: u64) -> MarksCursor<'_> {
        let range = if lo <= hi {
            self.by_time.range(lo..=hi)
        } else {
            self.by_time.range(lo..lo)
        };
        let forgotten = self
            .forgotten
            .range(..=hi)
            .next_back()
            .is_some_and(|(_, end)| *end >= lo);
        MarksCursor {
            marks: self,
            range: range.peekable(),
            lo,
            hi,
            last: None,
            forgotten,
        }
    }

    /// Marks the measurement of `track` at time key `time` used.
    pub(super) fn insert(&mut self, time: u64, track: u64) {
        let tracks = self.by_time.entry(time).or_default();
        if let Err(i) = tracks.binary_search(&track) {
            tracks.insert(i, track);
            self.marks += 1;
        }
    }

    /// Marks held.
    #[cfg(test)]
    pub(super) fn len(&self) -> usize {
        self.marks
    }

    /// Forgets the marks no link can reach any more: before `oldest_s` (the
    /// oldest time the peer's recent frames or held windows reach), and,
    /// once the history bound has dropped windows since the last sweep, at
    /// times no held window spans and older than the recent frames.
    pub(super) fn prune(&mut self, h: &PeerHistory, oldest_s: f64, recent_from_s: Option<f64>) {
        let keep_from = time_key(oldest_s - 1.0);
        let kept = self.by_time.split_off(&keep_from);
        let old = std::mem::replace(&mut self.by_time, kept);
        if let (Some(first), Some(last)) = (old.keys().next(), old.keys().next_back()) {
            self.forget_range(*first, *last);
            self.marks -= old.values().map(Vec::len).sum::<usize>();
        }
        if h.dropped_keyframes < self.swept_at_dropped + SWEEP_EVERY_DROPPED {
            return;
        }
        self.swept_at_dropped = h.dropped_keyframes;
        let recent_from = recent_from_s.map(|t| time_key(t - 1.0));
        // Marked times no held window spans, with the key of the held window
        // before them (0: none): the gap they lie in.
        let mut gone: Vec<(u64, u64)> = Vec::new();
        for &t in self.by_time.keys() {
            if recent_from.is_some_and(|r| t >= r) {
                break;
            }
            // The window ending at or after `t` spans it if it starts at or before it.
            let spanned = h.keyframes.range(t..).next().is_some_and(|(_, w)| {
                w.snapshot
                    .clones
                    .first()
                    .is_some_and(|c| time_key(c.t_s) <= t)
            });
            if !spanned {
                let gap = h.keyframes.range(..t).next_back().map_or(0, |(k, _)| *k);
                gone.push((t, gap));
            }
        }
        for &(t, _) in &gone {
            if let Some(tracks) = self.by_time.remove(&t) {
                self.marks -= tracks.len();
            }
        }
        // One range per gap, from its first forgotten time to its last: it
        // covers the dropped windows' marked times, not a window never held.
        for run in gone.chunk_by(|a, b| a.1 == b.1) {
            if let (Some(first), Some(last)) = (run.first(), run.last()) {
                self.forget_range(first.0, last.0);
            }
        }
    }

    /// Adds `lo..=hi` to the forgotten ranges, merged with those it touches.
    fn forget_range(&mut self, mut lo: u64, mut hi: u64) {
        let touching: Vec<(u64, u64)> = self
            .forgotten
            .range(..=hi.saturating_add(1))
            .rev()
            .take_while(|(_, h)| h.saturating_add(1) >= lo)
            .map(|(l, h)| (*l, *h))
            .collect();
        for (l, h) in touching {
            self.forgotten.remove(&l);
            lo = lo.min(l);
            hi = hi.max(h);
        }
        self.forgotten.insert(lo, hi);
        while self.forgotten.len() > MAX_FORGOTTEN_RANGES {
            self.forgotten.pop_first();
        }
    }
}

/// [`UsedMarks::contains`] for lookups in time order within a range
/// ([`UsedMarks::cursor`]); any other lookup is answered by `contains`.
pub(super) struct MarksCursor<'a> {
    marks: &'a UsedMarks,
    range: std::iter::Peekable<std::collections::btree_map::Range<'a, u64, Vec<u64>>>,
    lo: u64,
    hi: u64,
    /// The time of the last lookup.
    last: Option<u64>,
    /// A forgotten range overlaps the cursor's: every lookup goes to `contains`.
    forgotten: bool,
}

impl MarksCursor<'_> {
    /// Whether the measurement of `track` at time key `time` was used.
    pub(super) fn contains(&mut self, time: u64, track: u64) -> bool {
        let in_order = time >= self.lo && time <= self.hi && self.last.is_none_or(|l| time >= l);
        if !in_order || self.forgotten {
            return self.marks.contains(time, track);
        }
        self.last = Some(time);
        while self.range.next_if(|(t, _)| **t < time).is_some() {}
        self.range
            .peek()
            .is_some_and(|(t, tracks)| **t == time && tracks.binary_search(&track).is_ok())
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::history_retention::Retention;
    use crate::peer_history::test_support::snapshot;
    use crate::peer_history::{HistoryLimits, KeyframeWindow};
    use common::messages::CameraPose;
    use nalgebra::{DMatrix, Matrix3, Vector3};

    /// A keyframe window with clones at `first..=last` (0.1 s apart).
    fn window(first: f64, last: f64) -> KeyframeWindow {
        let n = ((last - first) / 0.1).round() as usize + 1;
        let clones: Vec<CameraPose> = (0..n)
            .map(|i| {
                CameraPose::new(
                    first + 0.1 * i as f64,
                    &Matrix3::identity(),
                    &Vector3::zeros(),
                )
            })
            .collect();
        let snap = snapshot(last, true, clones, &DMatrix::identity(12, 12));
        KeyframeWindow::new(snap, Vec::new(), Vec::new())
    }

    fn limits() -> HistoryLimits {
        HistoryLimits {
            max_bytes: usize::MAX,
            recent_s: 2.0,
            retention: Retention::Oldest,
        }
    }

    #[test]
    fn marks_are_found_by_time_and_track() {
        let mut m = UsedMarks::default();
        m.insert(time_key(1.0), 7);
        m.insert(time_key(1.0), 3);
        m.insert(time_key(1.0), 7);
        m.insert(time_key(2.0), 7 | 1 << 63);
        assert_eq!(m.len(), 3);
        assert!(m.contains(time_key(1.0), 3) && m.contains(time_key(1.0), 7));
        assert!(!m.contains(time_key(1.0), 5));
        assert!(!m.contains(time_key(2.0), 7));
        assert!(m.contains(time_key(2.0), 7 | 1 << 63));
    }

    #[test]
    fn marks_of_dropped_windows_are_forgotten_and_their_times_stay_used() {
        // Windows over [0, 1], [1.1, 2], [2.1, 3], one mark in each.
        let mut h = PeerHistory::default();
        for k in 0..3 {
            let first = if k == 0 {
                0.0
            } else {
                1.1 * k as f64 - 0.1 * (k - 1) as f64
            };
            h.add_replayed(window(first, k as f64 + 1.0), &limits());
        }
        let mut m = UsedMarks::default();
        for t in [0.5, 1.5, 2.5] {
            m.insert(time_key(t), 1);
        }
        // The middle window goes (as `informed` retention drops one).
        h.keyframes.remove(&time_key(2.0));
        h.dropped_keyframes = SWEEP_EVERY_DROPPED;
        m.prune(&h, 0.0, None);
        assert_eq!(m.len(), 2);
        assert!(m.by_time.contains_key(&time_key(0.5)) && m.by_time.contains_key(&time_key(2.5)));
        // The dropped window's marked time counts as used, any track: were
        // it replayed, its measurement must not be used again. Its unmarked
        // times were never used: they stay usable.
        assert!(m.contains(time_key(1.5), 9));
        assert!(!m.contains(time_key(1.1), 9) && !m.contains(time_key(1.9), 9));
        // Times in held windows are not.
        assert!(!m.contains(time_key(0.5), 9) && !m.contains(time_key(2.5), 9));
        assert!(!m.contains(time_key(1.0), 9) && !m.contains(time_key(2.1), 9));
    }

    #[test]
    fn marks_before_the_oldest_reachable_time_go_and_recent_ones_stay() {
        let mut h = PeerHistory::default();
        h.add_replayed(window(10.0, 11.0), &limits());
        let mut m = UsedMarks::default();
        for t in [1.0, 2.0, 10.5, 20.0] {
            m.insert(time_key(t), 4);
        }
        h.dropped_keyframes = SWEEP_EVERY_DROPPED;
        // Recent frames from 19.5 s: the mark at 20 s is theirs.
        m.prune(&h, 10.0, Some(19.5));
        assert_eq!(m.len(), 2);
        assert!(m.contains(time_key(10.5), 4) && m.contains(time_key(20.0), 4));
        assert!(
            m.contains(time_key(1.5), 4),
            "forgotten before the oldest time"
        );
        assert!(!m.contains(time_key(10.6), 4));
    }

    #[test]
    fn forgotten_ranges_merge() {
        let mut m = UsedMarks::default();
        m.forget_range(10, 20);
        m.forget_range(30, 40);
        m.forget_range(21, 29);
        assert_eq!(m.forgotten.len(), 1);
        assert_eq!(m.forgotten.get(&10), Some(&40));
        m.forget_range(5, 12);
        assert_eq!(m.forgotten.into_iter().collect::<Vec<_>>(), vec![(5, 40)]);
    }

    /// The cursor answers as `contains` does, lookups in order or not, with
    /// forgotten ranges inside its range or not.
    #[test]
    fn a_cursor_answers_as_single_lookups_do() {
        let mut m = UsedMarks::default();
        for t in (0..200u64).step_by(3) {
            for track in [t % 7, t % 11 + 20] {
                m.insert(t, track);
            }
        }
        let check = |m: &UsedMarks, lo: u64, hi: u64, times: &[u64]| {
            for track in 0..32 {
                let mut c = m.cursor(lo, hi);
                for &t in times {
                    assert_eq!(c.contains(t, track), m.contains(t, track), "{t} {track}");
                }
            }
        };
        let in_order: Vec<u64> = (40..80).collect();
        check(&m, 40, 79, &in_order);
        // Out of order, outside the range, repeated.
        check(&m, 40, 79, &[50, 45, 45, 90, 10, 60, 79, 80, 39]);
        m.forget_range(60, 65);
        check(&m, 40, 79, &in_order);
        check(&m, 70, 99, &(70..100).collect::<Vec<_>>());
        check(&m, 1, 0, &[0, 3, 61]);
    }
}
