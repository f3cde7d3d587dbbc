//! Steps 2 of a frame: the peers' unused measurements behind the links of the
//! tracks the estimator is about to use, with the peer windows (CI
//! participants) they belong to, and the peers' SLAM landmarks for constraints.

use super::window_cache::WindowCache;
use super::{Cooperation, FrameUse, Link, LinkSource, Peers, CONSTRAINT_FLAG};
use crate::estimator::peer_window::PeerWindow;
use crate::estimator::updater_common::{CommonTrack, PeerObservation};
use crate::estimator::updater_common_slam::SlamConstraint;
use crate::peer_history::{time_key, KeyframeWindow, PeerHistory};
use common::messages::StateSnapshot;
use nalgebra::Vector2;
use std::collections::{BTreeMap, BTreeSet};

/// The measurements behind one of our tracks in this frame.
#[derive(Clone, Debug, Default)]
pub(super) struct Consumed {
    pub(super) keys: Vec<(u32, u64, u64)>,
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
    pub(super) consumed: BTreeMap<(u8, u64), Consumed>,
    /// Keyframe links found used up: `(our track, link)` (see `chosen_links`).
    pub(super) exhausted: Vec<(u64, Link)>,
}

impl Cooperation {
    /// Step 2: the peers' unused measurements behind the links of our tracks
    /// `vio_ids` (about to leave the window) and of our SLAM features `slam_ids`.
    pub fn evidence(&mut self, vio_ids: &[u64], slam_ids: &[u64], peers: &Peers) -> Evidence {
        let mut ev = Evidence::default();
        let mut index: BTreeMap<(u32, LinkSource), Option<usize>> = BTreeMap::new();
        let mut taken: BTreeSet<(u32, u64, u64)> = BTreeSet::new();
        let classes: [(&[u64], bool); 2] = [(vio_ids, false), (slam_ids, true)];
        let mut exhausted = Vec::new();
        let mut chosen: Vec<(u64, bool, Vec<Link>)> = Vec::new();
        for (ids, slam) in classes {
            for &id in ids {
                let links = self.chosen_links(id, slam, peers, &mut exhausted);
                chosen.push((id, slam, links));
            }
        }
        ev.exhausted = exhausted;
        // The frame's participants first, then our tracks linked to them, the
        // VIO ones up to the bound (in the MSCKF's order, longest first).
        let windows = busiest_windows(&chosen, self.opts.max_ci_participants);
        let mut common = 0;
        for (_, slam, links) in chosen.iter_mut() {
            links.retain(|l| windows.contains(&(l.peer, l.source)));
            if !*slam && !links.is_empty() {
                common += 1;
                if common > self.opts.max_common_per_frame {
                    links.clear();
                }
            }
        }
        for (id, slam, links) in chosen {
            let mut obs = Vec::new();
            let mut consumed = Consumed::default();
            let mut constraint = None;
            for link in &links {
                let Some(h) = peers.get(&link.peer) else {
                    continue;
                };
                let Some(p) = *index.entry((link.peer, link.source)).or_insert_with(|| {
                    let frame = self.frame_of(link.peer, link_snapshot(h, link)?.frame_epoch)?;
                    participant(&mut ev, &mut self.windows, link, h, frame)
                }) else {
                    continue;
                };
                let used = self.peers.get(&link.peer).map(|s| &s.used);
                let is_used = |k: &(u64, u64)| used.is_some_and(|u| u.contains(k.0, k.1));
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
                let measured = measurements(h, link, &ev.participants[p]);
                let span = key_span(measured.iter().map(|m| m.1));
                let mut cursor = used.zip(span).map(|(u, (lo, hi))| u.cursor(lo, hi));
                let newest_only = slam && self.opts.peer_slam_newest_view == Some(true);
                let first = obs.len();
                // Oldest first, as the used marks' cursor reads fastest.
                for (pose, t_s, xy) in measured {
                    let key = (time_key(t_s), link.peer_track);
                    let used = cursor.as_mut().is_some_and(|c| c.contains(key.0, key.1));
                    if used || !taken.insert((link.peer, key.0, key.1)) {
                        continue;
                    }
                    consumed.keys.push((link.peer, key.0, key.1));
                    let o = PeerObservation {
                        participant: p,
                        pose,
                        xy,
                    };
                    if newest_only && obs.len() > first {
                        // A newer view replaces the older one, which is marked
                        // used with the update and never counted.
                        obs[first] = o;
                    } else {
                        obs.push(o);
                    }
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
        ev
    }

    /// The links of our track `id` whose measurements this class may use: every
    /// window link, and per peer the `max_keyframes_per_track` keyframe links
    /// whose windows the peer was most certain of (smallest position variance;
    /// at least two measurements of the peer's track). A landmark the peer kept
    /// in view, or saw on several passes, is in several of its keyframe
    /// windows; each window is one more CI participant, which inflates our
    /// covariance once more, so only the most informative are used.
    /// A link to a whole window with fewer than two unused measurements can
    /// never be chosen again (its measurements only get used up): it goes to
    /// `exhausted`, to be forgotten.
    fn chosen_links(
        &self,
        id: u64,
        slam: bool,
        peers: &Peers,
        exhausted: &mut Vec<(u64, Link)>,
    ) -> Vec<Link> {
        let mut out: Vec<Link> = Vec::new();
        let mut window: Vec<(usize, Link)> = Vec::new();
        let mut historical: Vec<(u32, f64, Link)> = Vec::new();
        for link in self.links_of(id) {
            if !self.allowed(link, slam, peers) {
                continue;
            }
            match link.source {
                LinkSource::Window => {
                    let count = peers
                        .get(&link.peer)
                        .map_or(0, |h| self.fresh_in_window(link, h));
                    if count > 0 {
                        window.push((count, *link));
                    }
                }
                LinkSource::Keyframe(k) => {
                    if let Some(kf) = peers.get(&link.peer).and_then(|h| h.keyframes.get(&k)) {
                        historical.push((link.peer, kf.position_variance_m2, *link));
                    }
                }
            }
        }
        // Most certain window first; ties to the newest keyframe (larger key).
        // A track seen on many passes of a long mission is linked to many
        // keyframe windows of its place: only the first few in this order are
        // looked into for fresh measurements, not all of them.
        historical.sort_by(|a, b| a.0.cmp(&b.0).then(a.1.total_cmp(&b.1)).then(b.2.cmp(&a.2)));
        let mut per_peer: BTreeMap<u32, usize> = BTreeMap::new();
        for (peer, _, link) in historical {
            let n = per_peer.entry(peer).or_default();
            if *n >= self.opts.max_keyframes_per_track {
                continue;
            }
            let kf = peers.get(&peer).and_then(|h| match link.source {
                LinkSource::Keyframe(k) => h.keyframes.get(&k),
                LinkSource::Window => None,
            });
            let Some(kf) = kf else {
                continue;
            };
            if self.fresh_in_keyframe(&link, kf) >= 2 {
                *n += 1;
                out.push(link);
            } else if kf.is_whole() {
                exhausted.push((id, link));
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

    /// Measurements of the linked peer track not used yet, in the peer's
    /// recent frames.
    fn fresh_in_window(&self, link: &Link, h: &PeerHistory) -> usize {
        let times = h.recent().iter().map(|f| f.t_s);
        let mut fresh = self.is_fresh(link, times);
        h.recent()
            .iter()
            .filter(|f| f.features.iter().any(|p| p.id == link.peer_track) && fresh(f.t_s))
            .count()
    }

    /// Measurements of the linked peer track not used yet, in keyframe window
    /// `kf`.
    pub(super) fn fresh_in_keyframe(&self, link: &Link, kf: &KeyframeWindow) -> usize {
        let mut fresh = self.is_fresh(link, kf.frames_times());
        kf.measurements_of(link.peer_track)
            .filter(|(t_s, _)| fresh(*t_s))
            .count()
    }

    /// Whether the linked peer track's measurement at a time (s), one of
    /// `times`, is unused. Looked up in time order, the peer's used marks for
    /// the span of `times` are walked once, not searched per measurement.
    fn is_fresh<'a>(
        &'a self,
        link: &'a Link,
        times: impl Iterator<Item = f64>,
    ) -> impl FnMut(f64) -> bool + 'a {
        let (lo, hi) = key_span(times).unwrap_or((1, 0));
        let mut cursor = self.peers.get(&link.peer).map(|s| s.used.cursor(lo, hi));
        move |t_s| {
            !cursor
                .as_mut()
                .is_some_and(|c| c.contains(time_key(t_s), link.peer_track))
        }
    }

    /// Whether a link may be used for this class under the options (and the
    /// frame of its peer's window is known).
    fn allowed(&self, link: &Link, slam: bool, peers: &Peers) -> bool {
        let epoch = peers
            .get(&link.peer)
            .and_then(|h| link_snapshot(h, link))
            .map(|s| s.frame_epoch);
        if epoch.is_none_or(|e| self.frame_of(link.peer, e).is_none()) {
            return false;
        }
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
}

/// The first and last time keys of `times` (`None` without any).
fn key_span(times: impl Iterator<Item = f64>) -> Option<(u64, u64)> {
    times.map(time_key).fold(None, |span, k| match span {
        None => Some((k, k)),
        Some((lo, hi)) => Some((lo.min(k), hi.max(k))),
    })
}

/// The peer windows behind the most of our tracks' links, at most `cap`
/// (ties to the lower peer id and the older window): the frame's CI
/// participants.
fn busiest_windows(chosen: &[(u64, bool, Vec<Link>)], cap: usize) -> BTreeSet<(u32, LinkSource)> {
    let mut count: BTreeMap<(u32, LinkSource), usize> = BTreeMap::new();
    for (_, _, links) in chosen {
        let distinct: BTreeSet<(u32, LinkSource)> =
            links.iter().map(|l| (l.peer, l.source)).collect();
        for w in distinct {
            *count.entry(w).or_default() += 1;
        }
    }
    let mut ranked: Vec<((u32, LinkSource), usize)> = count.into_iter().collect();
    ranked.sort_by(|a, b| b.1.cmp(&a.1).then(a.0.cmp(&b.0)));
    ranked
        .into_iter()
        .take(cap.max(1))
        .map(|(w, _)| w)
        .collect()
}

/// The participant behind `link`: its index in `ev.participants` (added now if
/// new, from `cache` when a recent frame built it), or `None` when the peer's
/// window is not usable.
fn participant(
    ev: &mut Evidence,
    cache: &mut WindowCache,
    link: &Link,
    h: &PeerHistory,
    frame: FrameUse,
) -> Option<usize> {
    let snap = link_snapshot(h, link)?;
    let historical = matches!(link.source, LinkSource::Keyframe(_));
    let key = time_key(snap.end_s());
    if let Some(i) = ev
        .participants
        .iter()
        .position(|w| w.peer == link.peer && w.key == key)
    {
        return Some(i);
    }
    let w = cache.window(link.peer, key, historical, snap, frame)?;
    ev.participants.push(w);
    ev.historical.push(historical);
    Some(ev.participants.len() - 1)
}

/// The peer window a link points into: the peer's newest, or one of its
/// keyframe windows.
fn link_snapshot<'a>(h: &'a PeerHistory, link: &Link) -> Option<&'a StateSnapshot> {
    match link.source {
        LinkSource::Window => h.latest.as_ref(),
        LinkSource::Keyframe(k) => h.keyframes.get(&k).map(|kf| &kf.snapshot),
    }
}

/// The linked peer track's measurements at the poses of window `w`:
/// `(pose index, camera time, normalized coordinates)`.
fn measurements(h: &PeerHistory, link: &Link, w: &PeerWindow) -> Vec<(usize, f64, Vector2<f64>)> {
    let mut out = Vec::new();
    match link.source {
        LinkSource::Window => {
            for f in h.recent() {
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
            for (t_s, xy) in kf.measurements_of(link.peer_track) {
                if let Some(pose) = w.pose_at(t_s) {
                    out.push((pose, t_s, Vector2::new(f64::from(xy[0]), f64::from(xy[1]))));
                }
            }
        }
    }
    out
}
