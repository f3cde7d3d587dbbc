//! History catch-up: getting back the keyframe windows of a peer that a link
//! outage, lost messages or a late start kept from us.
//!
//! Publish/subscribe does not replay what was published while a link was
//! down, and a window we never stored can never give a historical loop closure
//! (thesis Section 5.3.5). Two state machines, free of transport and I/O:
//!
//! * [`CatchUp`] (asking): watches what is delivered from each peer and asks
//!   for the windows it must have missed: everything when a peer is first
//!   heard, everything after the newest window held when a peer comes back
//!   after vanishing, and the windows around a gap in a peer's sequence
//!   numbers. It stores a replayed window only when it asked for it and the
//!   window is missing or more complete than the copy held. A window held
//!   short of some parts is listed in the request with what it holds, and
//!   only the missing parts come back, merged into the copy held.
//! * [`Replayer`] (answering): keeps an archive of this agent's own keyframe
//!   windows, built from what it published exactly as peers build theirs, and
//!   answers requests from it, oldest window first, at a bounded rate of fleet
//!   time so a catch-up never crowds out the live messages: a whole window to
//!   a requester that lacks it, the missing parts to one that holds it short.

use crate::peer_history::{time_key, HistoryLimits, KeyframeWindow, PeerHistory, Replayed};
use common::messages::{
    AnsweredWindow, Body, Envelope, HeldWindow, HistoryReplay, HistoryRequest, MessageKind,
    RequestRef, TimeRange, MAX_ANSWERED_WINDOWS, MAX_HELD_WINDOWS, MAX_REPLAY_ROBOTS,
    MAX_REQUEST_RANGES,
};
use serde::Serialize;
use std::collections::{BTreeMap, BTreeSet};

/// Seconds added before a sequence gap's first lost message: a keyframe
/// window ends a little before its snapshot is sent.
const GAP_SLACK_S: f64 = 1.0;

/// A peer's window span assumed before its first snapshot, s.
const DEFAULT_WINDOW_SPAN_S: f64 = 2.0;

/// Half-width of the range that asks again for one window, s: far below the
/// spacing of keyframes (a camera period at least).
const ONE_WINDOW_S: f64 = 1e-3;

/// Times one window of a peer is asked for again after an answer that
/// should have held it: a window our own memory bound drops must not be
/// fetched forever. At a loss of one message in five, 5 leave 1 window in
/// 15 000 missing.
const MAX_ASKS_PER_WINDOW: u8 = 5;

/// Windows per peer whose asks are counted; beyond, none is asked again.
const MAX_COUNTED_WINDOWS: usize = 1 << 16;

/// Most a range to ask for is put off by merging later ranges into it, s of
/// fleet time: gaps in the three data streams of one outage merge into one
/// request, while on a lossy link, where every second brings a gap that
/// overlaps the last one, the windows are still asked for within a second
/// of existing (merging without a limit put them off as long as the losses
/// went on: tens of seconds).
const MAX_MERGE_DELAY_S: f64 = 1.0;

/// Catch-up counters of one agent.
#[derive(Clone, Debug, Default, PartialEq, Serialize)]
pub struct CatchUpStats {
    /// Requests sent.
    pub requests_sent: u64,
    /// Requests answered in full.
    pub requests_completed: u64,
    /// Requests given up because the peer vanished (asked again if it comes
    /// back).
    pub requests_dropped: u64,
    /// Requests sent again: no reply for the retry period since asking.
    pub requests_retried: u64,
    /// Sequence gaps seen in peers' data messages (each asked about).
    pub gaps_seen: u64,
    /// Times a peer's heartbeat claimed a window we lacked one heartbeat
    /// later, with no gap to explain it (each asked about).
    pub windows_missing: u64,
    /// Replayed windows received that were for us.
    pub windows_received: u64,
    /// Of those, missing windows stored.
    pub windows_stored: u64,
    /// Of those, held windows replaced by a more complete copy.
    pub windows_completed: u64,
    /// Replayed parts received that were for us (the missing frames or
    /// descriptors of a window held short of them).
    pub parts_received: u64,
    /// Of those, parts that completed a window held.
    pub parts_stored: u64,
    /// Windows asked for again: an answer listed them, and their replay was
    /// lost (or left a less complete copy than the answerer's).
    pub windows_reasked: u64,
    /// Requests from peers answered by this agent.
    pub requests_answered: u64,
    /// Windows this agent sent again.
    pub windows_replayed: u64,
    /// Parts of windows this agent sent again (to requesters holding the
    /// rest).
    pub parts_replayed: u64,
    /// Encoded bytes of those replays.
    pub replay_bytes: u64,
}

/// A request waiting for its replays.
#[derive(Clone, Debug)]
struct OpenRequest {
    ranges: Vec<TimeRange>,
}

/// What is known of one peer's stream.
#[derive(Clone, Debug, Default)]
struct PeerStream {
    /// Per data kind: the last delivered sequence number and stamp.
    last: BTreeMap<MessageKind, (u64, f64)>,
    /// Requests sent and not yet answered in full.
    open: BTreeMap<u64, OpenRequest>,
    /// Ranges to ask for.
    wanted: Vec<Wanted>,
    /// Fleet time of the last replay from this peer (or of the oldest open
    /// request when none came since).
    last_progress_s: f64,
    /// Fleet time of our last request to it.
    last_ask_s: f64,
    /// The peer's window span (newest minus oldest clone), s.
    window_span_s: Option<f64>,
    /// The newest window end its last heartbeat claimed, s.
    claimed_end_s: Option<f64>,
    /// Times each window (by [`time_key`] of its end) was asked for again.
    asks: BTreeMap<u64, u8>,
    /// Whether anything of the peer was delivered (a peer known only from
    /// disk is not asked until it is heard).
    heard: bool,
}

/// A range to ask for.
#[derive(Clone, Copy, Debug)]
struct Wanted {
    range: TimeRange,
    /// Fleet time after which to ask (the windows it covers must exist by
    /// then).
    ask_after: f64,
    /// The earliest `ask_after` of the ranges merged into it.
    first_due: f64,
}

impl PeerStream {
    /// Adds a range to ask for after `ask_after`; a range it overlaps is
    /// merged in and asked for at the later of the two times, so one outage
    /// seen as gaps in three streams makes one request, unless that would put
    /// off the earlier by more than [`MAX_MERGE_DELAY_S`].
    /// A range an open request already covers is not asked again.
    fn want(&mut self, range: TimeRange, ask_after: f64) {
        let asked = self
            .open
            .values()
            .flat_map(|r| &r.ranges)
            .any(|r| lo(r) <= lo(&range) && hi(&range) <= hi(r));
        if asked {
            return;
        }
        let mut new = Wanted {
            range,
            ask_after,
            first_due: ask_after,
        };
        self.wanted.retain(|w| {
            let Some(u) = union(&w.range, &new.range) else {
                return true;
            };
            let first_due = w.first_due.min(new.first_due);
            let ask_after = w.ask_after.max(new.ask_after);
            if ask_after > first_due + MAX_MERGE_DELAY_S {
                return true;
            }
            new = Wanted {
                range: u,
                ask_after,
                first_due,
            };
            false
        });
        self.wanted.push(new);
    }
}

fn lo(r: &TimeRange) -> f64 {
    r.after_s.unwrap_or(f64::NEG_INFINITY)
}

fn hi(r: &TimeRange) -> f64 {
    r.up_to_s.unwrap_or(f64::INFINITY)
}

/// The union of two ranges that overlap or touch.
fn union(a: &TimeRange, b: &TimeRange) -> Option<TimeRange> {
    if lo(a) > hi(b) || lo(b) > hi(a) {
        return None;
    }
    Some(TimeRange {
        after_s: if lo(a) <= lo(b) { a.after_s } else { b.after_s },
        up_to_s: if hi(a) >= hi(b) { a.up_to_s } else { b.up_to_s },
    })
}

/// The asking side of history catch-up (see the module documentation).
#[derive(Debug)]
pub struct CatchUp {
    me: u32,
    next_id: u64,
    /// Fleet seconds without a reply before a request is sent again.
    retry_s: f64,
    peers: BTreeMap<u32, PeerStream>,
    /// Counters (the answering side adds its own in [`Replayer`]).
    pub stats: CatchUpStats,
}

impl CatchUp {
    /// The asking side of robot `me`; a request without a reply for `retry_s`
    /// of fleet time is sent again (a request costs some 50 bytes: a link back
    /// from an outage is used within `retry_s`). Requests are only given up
    /// when their peer vanishes ([`CatchUp::vanished`]).
    pub fn new(me: u32, retry_s: f64) -> Self {
        Self {
            me,
            next_id: 0,
            retry_s,
            peers: BTreeMap::new(),
            stats: CatchUpStats::default(),
        }
    }

    /// Notes a message delivered from `env.robot_id`, whose history we keep in
    /// `history`: a peer heard for the first time is asked for everything, a
    /// gap in a data stream for the windows it may have touched, and windows
    /// a heartbeat says exist, and we still lack a heartbeat later, for
    /// themselves.
    pub fn delivered(&mut self, env: &Envelope, history: &PeerHistory) {
        let kind = env.kind();
        let data = matches!(
            kind,
            MessageKind::Tracks | MessageKind::Descriptors | MessageKind::Snapshot
        );
        let first = !self.peers.contains_key(&env.robot_id);
        let p = self.peers.entry(env.robot_id).or_default();
        p.heard = true;
        if first {
            p.want(TimeRange::ALL, f64::NEG_INFINITY);
        }
        match &env.body {
            Body::Snapshot(s) => {
                if let (Some(a), Some(b)) = (s.clones.first(), s.clones.last()) {
                    p.window_span_s = Some((b.t_s - a.t_s).max(0.0));
                }
            }
            Body::Heartbeat(hb) => {
                // Newest end of any window we stored from it (the bound may
                // have dropped windows since: they are not asked for again).
                let held = history.stored_span.map(|(_, end)| end);
                let claimed = std::mem::replace(&mut p.claimed_end_s, hb.newest_window_end_s);
                // The previous heartbeat's claim, still unmet: its window is
                // lost (not merely on its way: one heartbeat period later).
                if claimed.is_some_and(|c| held.is_none_or(|h| c > h)) {
                    // Everything after what we hold: the peer may have made
                    // more by the time it answers (and may send no further
                    // heartbeat to tell: it may have landed).
                    let range = TimeRange {
                        after_s: held,
                        up_to_s: None,
                    };
                    // One question at a time: while one is out, newer claims
                    // wait for its answer (a peer cut off for a minute would
                    // otherwise be asked at every heartbeat).
                    if p.open.is_empty() && p.wanted.is_empty() {
                        self.stats.windows_missing += 1;
                        p.want(range, f64::NEG_INFINITY);
                    }
                }
            }
            _ => {}
        }
        if !data {
            return;
        }
        let span = p.window_span_s.unwrap_or(DEFAULT_WINDOW_SPAN_S);
        if let Some((seq, stamp)) = p.last.insert(kind, (env.seq, env.stamp_s)) {
            // A restarted peer numbers from 0 again: only forward jumps are losses.
            if env.seq > seq + 1 {
                self.stats.gaps_seen += 1;
                // Messages sent in (stamp, env.stamp_s) were lost: a keyframe
                // window ending there, or holding a lost frame, is incomplete.
                let up_to = env.stamp_s + span;
                let range = TimeRange {
                    after_s: Some(stamp - GAP_SLACK_S),
                    up_to_s: Some(up_to),
                };
                p.want(range, up_to);
            }
        }
    }

    /// Notes that `peer` vanished: its open requests are given up (it is asked
    /// again when it comes back).
    pub fn vanished(&mut self, peer: u32) {
        if let Some(p) = self.peers.get_mut(&peer) {
            self.stats.requests_dropped += p.open.len() as u64;
            p.open.clear();
            p.wanted.clear();
        }
    }

    /// Notes that `history` of `peer` was read back from disk at start: when
    /// the peer is heard, only the windows after the newest one held are
    /// asked for (not everything, as for a peer we know nothing of).
    pub fn restored(&mut self, peer: u32, history: &PeerHistory) {
        let p = self.peers.entry(peer).or_default();
        p.want(
            TimeRange {
                after_s: history.newest_window_end_s(),
                up_to_s: None,
            },
            f64::NEG_INFINITY,
        );
    }

    /// Notes that `peer` came back after vanishing: the windows after the
    /// newest one held are asked for.
    pub fn reappeared(&mut self, peer: u32, history: Option<&PeerHistory>) {
        let p = self.peers.entry(peer).or_default();
        p.heard = true;
        let range = TimeRange {
            after_s: history.and_then(PeerHistory::newest_window_end_s),
            up_to_s: None,
        };
        p.want(range, f64::NEG_INFINITY);
    }

    /// The requests due at fleet time `now_s`, one per peer at most; open
    /// requests without a replay for the timeout are sent again. Windows
    /// `histories` already holds whole are cut out of the ranges asked for.
    pub fn requests(
        &mut self,
        now_s: f64,
        histories: &BTreeMap<u32, PeerHistory>,
    ) -> Vec<HistoryRequest> {
        let mut out = Vec::new();
        for (&peer, p) in self.peers.iter_mut().filter(|(_, p)| p.heard) {
            let fresh = p.open.is_empty();
            if !fresh && now_s - p.last_progress_s.max(p.last_ask_s) > self.retry_s {
                // Nothing came since we asked: the request or its replies
                // were lost (the link may not be back yet). Ask again; the
                // peer merges a request for windows it still has queued.
                self.stats.requests_retried += p.open.len() as u64;
                for r in std::mem::take(&mut p.open).into_values() {
                    for range in r.ranges {
                        p.want(range, f64::NEG_INFINITY);
                    }
                }
            }
            let (due, later): (Vec<_>, Vec<_>) = std::mem::take(&mut p.wanted)
                .into_iter()
                .partition(|w| w.ask_after <= now_s);
            p.wanted = later;
            if due.is_empty() {
                continue;
            }
            // A new request takes over the open ones (their replies would
            // overlap; a lost one would be sent again alongside).
            let mut ranges: Vec<TimeRange> = due.into_iter().map(|w| w.range).collect();
            for r in std::mem::take(&mut p.open).into_values() {
                ranges.extend(r.ranges);
            }
            let mut ranges: Vec<TimeRange> = merge(ranges)
                .into_iter()
                .flat_map(|r| without_whole(r, histories.get(&peer)))
                .collect();
            if ranges.is_empty() {
                // Everything asked for has arrived whole since.
                continue;
            }
            // What does not fit is asked for later (at once, it would take
            // over this request at the next tick, and so on).
            let rest = ranges.split_off(ranges.len().min(MAX_REQUEST_RANGES));
            let later = now_s + self.retry_s;
            p.wanted.extend(rest.into_iter().map(|range| Wanted {
                range,
                ask_after: later,
                first_due: later,
            }));
            // What we hold of the windows asked for: only the missing parts
            // come back. A window not listed comes whole.
            let held: Vec<HeldWindow> = histories
                .get(&peer)
                .into_iter()
                .flat_map(|h| h.keyframes.values())
                .filter(|kf| ranges.iter().any(|r| r.contains(kf.end_s())))
                .map(KeyframeWindow::held)
                .take(MAX_HELD_WINDOWS)
                .collect();
            let request_id = self.next_id;
            self.next_id += 1;
            if fresh {
                p.last_progress_s = now_s;
            }
            p.last_ask_s = now_s;
            p.open.insert(
                request_id,
                OpenRequest {
                    ranges: ranges.clone(),
                },
            );
            self.stats.requests_sent += 1;
            tracing::debug!(peer, request_id, ?ranges, now_s, "history catch-up: asking");
            out.push(HistoryRequest {
                to_robot: peer,
                request_id,
                ranges,
                held,
            });
        }
        out
    }

    /// Takes a replay from `peer` delivered at fleet time `now_s`: stores its
    /// window in `history` if we asked for it and it is missing or more
    /// complete than ours, or merges its part into the window held, and
    /// closes the requests it completes.
    pub fn accept(
        &mut self,
        peer: u32,
        replay: HistoryReplay,
        now_s: f64,
        history: &mut PeerHistory,
        limits: &HistoryLimits,
    ) -> Option<Replayed> {
        let p = self.peers.get_mut(&peer)?;
        let mut outcome = None;
        let for_me = replay.for_robots.contains(&self.me);
        let asked = |p: &PeerStream, end: f64| {
            p.open
                .values()
                .any(|r| r.ranges.iter().any(|range| range.contains(end)))
        };
        if let Some(part) = replay.part.filter(|_| for_me) {
            p.last_progress_s = now_s;
            self.stats.parts_received += 1;
            if asked(p, part.end_s) {
                outcome = history.add_part(part, limits);
                if outcome == Some(Replayed::Completed) {
                    self.stats.parts_stored += 1;
                }
            }
        }
        if let Some(w) = replay.window.filter(|_| for_me) {
            p.last_progress_s = now_s;
            self.stats.windows_received += 1;
            if asked(p, w.end_s()) {
                let r = history.add_replayed(KeyframeWindow::from_wire(w), limits);
                match r {
                    Replayed::New => self.stats.windows_stored += 1,
                    Replayed::Completed => self.stats.windows_completed += 1,
                    Replayed::AlreadyHeld => {}
                }
                outcome = Some(r);
            }
        }
        for c in replay.completes.iter().filter(|c| c.robot == self.me) {
            let Some(request) = p.open.remove(&c.request_id) else {
                continue;
            };
            self.stats.requests_completed += 1;
            // The answer's windows we lack, or hold less of than the peer:
            // their replays were lost. Ask for each again.
            for a in &replay.answered {
                if !request.ranges.iter().any(|r| r.contains(a.end_s)) {
                    continue;
                }
                let key = time_key(a.end_s);
                let short = history.keyframes.get(&key).is_none_or(|held| {
                    let (frames, descriptors) = held.completeness();
                    frames < a.frames as usize || (a.descriptors && !descriptors)
                });
                if !short || (!p.asks.contains_key(&key) && p.asks.len() >= MAX_COUNTED_WINDOWS) {
                    continue;
                }
                let asks = p.asks.entry(key).or_insert(0);
                if *asks >= MAX_ASKS_PER_WINDOW {
                    continue;
                }
                *asks += 1;
                self.stats.windows_reasked += 1;
                let range = TimeRange {
                    after_s: Some(a.end_s - ONE_WINDOW_S),
                    up_to_s: Some(a.end_s),
                };
                p.want(range, f64::NEG_INFINITY);
            }
        }
        outcome
    }

    /// Asks `peer` once more for every window we lack or hold short (the
    /// request leaves out those held whole, and lists those held short):
    /// at the end of a run, the last losses left no later message to show
    /// a gap.
    pub fn sweep(&mut self, peer: u32) {
        if let Some(p) = self.peers.get_mut(&peer).filter(|p| p.heard) {
            p.want(TimeRange::ALL, f64::NEG_INFINITY);
        }
    }

    /// Whether nothing is asked for or waited on from any peer heard.
    pub fn idle(&self) -> bool {
        self.peers
            .values()
            .filter(|p| p.heard)
            .all(|p| p.open.is_empty() && p.wanted.is_empty())
    }

    /// Requests sent to `peer` and not answered in full yet.
    pub fn open_requests(&self, peer: u32) -> usize {
        self.peers.get(&peer).map_or(0, |p| p.open.len())
    }
}

/// `range` with the windows `history` holds whole cut out (a snapshot, a
/// frame of measurements at every clone, and descriptors): what is left to
/// ask for is the windows missing or short of something, so a lost track
/// frame brings back its own window, not every window near the gap.
fn without_whole(range: TimeRange, history: Option<&PeerHistory>) -> Vec<TimeRange> {
    let Some(h) = history else {
        return vec![range];
    };
    let whole = h
        .keyframes
        .values()
        .filter(|kf| range.contains(kf.end_s()) && kf.is_whole())
        .map(KeyframeWindow::end_s);
    let mut out = Vec::new();
    let mut after = range.after_s;
    for end in whole {
        // (after, end - ONE_WINDOW_S]: empty when two whole windows follow
        // each other.
        let piece = TimeRange {
            after_s: after,
            up_to_s: Some(end - ONE_WINDOW_S),
        };
        if after.is_none_or(|a| a < end - ONE_WINDOW_S) {
            out.push(piece);
        }
        after = Some(end);
    }
    if after.is_none_or(|a| range.up_to_s.is_none_or(|b| a < b)) {
        out.push(TimeRange {
            after_s: after,
            up_to_s: range.up_to_s,
        });
    }
    // Many whole windows scattered in a long range: asking for all of it
    // costs bytes, and a request of too many pieces would not fit.
    if out.len() > MAX_REQUEST_RANGES / 4 {
        return vec![range];
    }
    out
}

/// Sorts ranges and merges those that overlap or touch.
fn merge(mut ranges: Vec<TimeRange>) -> Vec<TimeRange> {
    ranges.sort_by(|a, b| lo(a).total_cmp(&lo(b)));
    let mut out: Vec<TimeRange> = Vec::with_capacity(ranges.len());
    for r in ranges {
        match out
            .last_mut()
            .and_then(|last| union(last, &r).map(|u| (last, u)))
        {
            Some((last, u)) => *last = u,
            None => out.push(r),
        }
    }
    out
}

/// A window queued for replay.
#[derive(Clone, Debug, Default)]
struct Queued {
    /// Robots that lack the window: it goes whole.
    for_robots: BTreeSet<u32>,
    /// Robots that hold it short of some parts, with what they hold: if none
    /// lacks it, only the parts some of them miss go.
    parts: BTreeMap<u32, HeldWindow>,
    /// Requests whose last window this is.
    completes: Vec<RequestRef>,
}

/// The answering side of history catch-up (see the module documentation).
#[derive(Debug)]
pub struct Replayer {
    me: u32,
    /// Our own keyframe windows, built as a peer builds them.
    archive: PeerHistory,
    limits: HistoryLimits,
    /// Windows to send, by key (oldest first).
    queue: BTreeMap<u64, Queued>,
    /// Requests that found nothing, to complete with the next message.
    found_nothing: Vec<RequestRef>,
    /// The windows (archive keys) each queued request is answered with, for
    /// the list of its completing message.
    answers: BTreeMap<RequestRef, Vec<u64>>,
    /// Replay bytes per second of fleet time.
    bytes_per_s: f64,
    /// Bytes that may still be sent now (a token bucket of one second).
    budget: f64,
    last_refill_s: Option<f64>,
    /// Counters of the answering side.
    pub stats: CatchUpStats,
}

impl Replayer {
    /// The answering side of robot `me`, keeping its own windows within
    /// `limits` (the bound its peers keep of it) and replaying at most
    /// `bytes_per_s` per second of fleet time.
    pub fn new(me: u32, limits: HistoryLimits, bytes_per_s: f64) -> Self {
        Self {
            me,
            archive: PeerHistory::default(),
            limits,
            queue: BTreeMap::new(),
            found_nothing: Vec::new(),
            answers: BTreeMap::new(),
            bytes_per_s,
            budget: bytes_per_s,
            last_refill_s: None,
            stats: CatchUpStats::default(),
        }
    }

    /// Archives what this agent published (its tracks, descriptors and
    /// snapshots), so its keyframe windows can be sent again.
    pub fn published(&mut self, body: &Body) {
        match body {
            Body::Tracks(t) => self.archive.add_tracks(t.clone(), &self.limits),
            Body::Descriptors(d) => self.archive.add_descriptors(d.clone(), &self.limits),
            Body::Snapshot(s) => self.archive.add_snapshot(s.clone(), &self.limits),
            Body::Heartbeat(_) | Body::HistoryRequest(_) | Body::HistoryReplay(_) => {}
        }
    }

    /// Takes `archive`, read back from disk at start, as the archive of our
    /// own windows (those made from now on join it).
    pub fn restore(&mut self, archive: PeerHistory) {
        self.archive = archive;
    }

    /// The archive of our own windows.
    pub fn archive(&self) -> &PeerHistory {
        &self.archive
    }

    /// Queues the windows `from` asked for, if it asked us.
    pub fn request(&mut self, from: u32, req: &HistoryRequest) {
        if req.to_robot != self.me || from == self.me {
            return;
        }
        self.stats.requests_answered += 1;
        let id = RequestRef {
            robot: from,
            request_id: req.request_id,
        };
        let held: BTreeMap<u64, &HeldWindow> =
            req.held.iter().map(|h| (time_key(h.end_s), h)).collect();
        let mut keys = Vec::new();
        let mut last = None;
        for (&k, kf) in &self.archive.keyframes {
            if !req.ranges.iter().any(|r| r.contains(kf.end_s())) {
                continue;
            }
            keys.push(k);
            // This request takes over the requester's older ones: what it
            // holds now decides between whole, part and nothing.
            if let Some(q) = self.queue.get_mut(&k) {
                q.for_robots.remove(&from);
                q.parts.remove(&from);
            }
            let held = held.get(&k).copied();
            // A requester holding every part we have gets nothing.
            if held.is_some_and(|h| kf.part_for([h]).is_empty()) {
                continue;
            }
            last = Some(k);
            let q = self.queue.entry(k).or_default();
            if q.for_robots.len() + q.parts.len() >= MAX_REPLAY_ROBOTS {
                continue;
            }
            match held {
                Some(h) => {
                    q.parts.insert(from, *h);
                }
                None => {
                    q.for_robots.insert(from);
                }
            }
        }
        tracing::debug!(
            from,
            request_id = req.request_id,
            windows = keys.len(),
            to_send = self.queue.len(),
            "history catch-up: answering"
        );
        match last {
            Some(last) => self.queue.entry(last).or_default().completes.push(id),
            None => self.found_nothing.push(id),
        }
        // A requester's new request takes over its older ones (it asks
        // again for what they did not bring), so only its newest answer's
        // list is kept: the lists stay bounded by the peers times the archive.
        self.answers.retain(|r, _| r.robot != from);
        self.answers.insert(id, keys);
    }

    /// The windows of the answers to `completes`, as the archive holds them
    /// now, oldest first (the answers' lists are dropped).
    fn answered(&mut self, completes: &[RequestRef]) -> Vec<AnsweredWindow> {
        let keys: BTreeSet<u64> = completes
            .iter()
            .filter_map(|c| self.answers.remove(c))
            .flatten()
            .collect();
        keys.into_iter()
            .filter_map(|k| self.archive.keyframes.get(&k))
            .take(MAX_ANSWERED_WINDOWS)
            .map(|kf| {
                let (frames, descriptors) = kf.completeness();
                AnsweredWindow {
                    end_s: kf.end_s(),
                    frames: frames as u32,
                    descriptors,
                }
            })
            .collect()
    }

    /// Adds the budget of the fleet time elapsed up to `now_s` (at most one
    /// second's worth held).
    pub fn refill(&mut self, now_s: f64) {
        let dt = self.last_refill_s.map_or(0.0, |t| (now_s - t).max(0.0));
        self.last_refill_s = Some(now_s);
        self.budget = (self.budget + dt * self.bytes_per_s).min(self.bytes_per_s);
    }

    /// The next replay to send, if there is one and budget left for it.
    pub fn next_replay(&mut self) -> Option<HistoryReplay> {
        if self.budget <= 0.0 {
            return None;
        }
        while let Some((key, q)) = self.queue.pop_first() {
            let mut completes = std::mem::take(&mut self.found_nothing);
            completes.extend(q.completes);
            let Some(kf) = self.archive.keyframes.get(&key) else {
                // Dropped from the archive since it was asked for: what it
                // completes goes with the next message.
                self.found_nothing = completes;
                continue;
            };
            // Whole if anyone lacks it (those holding it short take the
            // whole copy too: one message instead of two), else the union
            // of the parts its holders miss.
            let (window, part) = if q.for_robots.is_empty() {
                (None, Some(kf.part_for(q.parts.values())))
            } else {
                (Some(kf.to_wire()), None)
            };
            if part.as_ref().is_some_and(|p| p.is_empty()) {
                // Nobody asked for it (only completes travel with it).
                self.found_nothing = completes;
                continue;
            }
            let for_robots = q.for_robots.into_iter().chain(q.parts.into_keys());
            let answered = self.answered(&completes);
            return Some(HistoryReplay {
                for_robots: for_robots.collect::<BTreeSet<_>>().into_iter().collect(),
                window,
                part,
                completes,
                answered,
            });
        }
        if self.found_nothing.is_empty() {
            return None;
        }
        let completes = std::mem::take(&mut self.found_nothing);
        let answered = self.answered(&completes);
        Some(HistoryReplay {
            for_robots: Vec::new(),
            window: None,
            part: None,
            completes,
            answered,
        })
    }

    /// Counts a replay sent as `bytes` encoded bytes against the budget;
    /// `(window, part)`: whether it carried a window, a part.
    pub fn sent(&mut self, (window, part): (bool, bool), bytes: usize) {
        self.budget -= bytes as f64;
        self.stats.replay_bytes += bytes as u64;
        if window {
            self.stats.windows_replayed += 1;
        }
        if part {
            self.stats.parts_replayed += 1;
        }
    }

    /// Whether nothing waits to be sent.
    pub fn idle(&self) -> bool {
        self.queue.is_empty() && self.found_nothing.is_empty()
    }

    /// Windows waiting to be sent.
    pub fn queued(&self) -> usize {
        self.queue.len()
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::history_retention::Retention;
    use common::messages::{samples, HistoryWindow};

    const PEER: u32 = 1;
    const ME: u32 = 2;

    fn limits() -> HistoryLimits {
        HistoryLimits {
            max_bytes: 64 << 20,
            recent_s: 2.0,
            retention: Retention::Oldest,
        }
    }

    /// What peer 1 publishes at frame `f`: its tracks, and every 10th frame
    /// (from frame 10) a keyframe window with its descriptors. Sequence
    /// numbers count per kind, as an outbox does.
    fn published(f: u64) -> Vec<Envelope> {
        let mut out = vec![samples::tracks(f, 20)];
        if f >= 10 && f % 10 == 0 {
            let mut s = samples::snapshot(f, 11, 0, true);
            let mut d = samples::descriptors(f, 20, true);
            s.seq = f / 10 - 1;
            d.seq = f / 10 - 1;
            out.extend([s, d]);
        }
        out
    }

    /// A live peer history fed with `envs`, as an agent's node does.
    fn feed(h: &mut PeerHistory, envs: &[Envelope]) {
        for e in envs {
            match e.body.clone() {
                Body::Tracks(t) => h.add_tracks(t, &limits()),
                Body::Descriptors(d) => h.add_descriptors(d, &limits()),
                Body::Snapshot(s) => h.add_snapshot(s, &limits()),
                _ => {}
            }
        }
    }

    /// Our asking side and our history of the peer after hearing its frames
    /// `0..=last`.
    fn heard(last: u64) -> (CatchUp, PeerHistory) {
        let mut c = CatchUp::new(ME, 5.0);
        let mut h = PeerHistory::default();
        let envs: Vec<Envelope> = (0..=last).flat_map(published).collect();
        feed(&mut h, &envs);
        for e in &envs {
            c.delivered(e, &h);
        }
        (c, h)
    }

    /// The peer's answer that `req` found nothing more.
    fn done(req: &HistoryRequest) -> HistoryReplay {
        HistoryReplay {
            for_robots: Vec::new(),
            window: None,
            part: None,
            completes: vec![RequestRef {
                robot: ME,
                request_id: req.request_id,
            }],
            answered: Vec::new(),
        }
    }

    fn t(f: u64) -> f64 {
        let Body::Tracks(tr) = samples::tracks(f, 1).body else {
            return f64::NAN;
        };
        tr.t_s
    }

    #[test]
    fn a_peer_heard_first_is_asked_for_everything_once() {
        let mut c = CatchUp::new(ME, 5.0);
        for f in 0..3 {
            for e in published(f) {
                c.delivered(&e, &PeerHistory::default());
            }
        }
        let reqs = c.requests(t(3), &BTreeMap::new());
        assert_eq!(reqs.len(), 1);
        assert_eq!(reqs[0].to_robot, PEER);
        assert_eq!(reqs[0].ranges, [TimeRange::ALL]);
        assert!(c.requests(t(4), &BTreeMap::new()).is_empty());
        assert_eq!(c.open_requests(PEER), 1);
    }

    #[test]
    fn a_gap_in_three_streams_is_one_request_made_once_its_windows_exist() {
        let mut c = CatchUp::new(ME, 5.0);
        let mut all: Vec<Envelope> = (0..=120).flat_map(published).collect();
        // Frames 35 to 84 are lost: tracks, snapshots and descriptors.
        all.retain(|e| {
            let f = match &e.body {
                Body::Tracks(x) => x.frame_index,
                Body::Snapshot(x) => x.frame_index,
                Body::Descriptors(x) => x.frame_index,
                _ => 0,
            };
            !(35..85).contains(&f)
        });
        // The first request (everything) goes at once, and is answered.
        c.delivered(&all[0], &PeerHistory::default());
        let first = c.requests(t(0), &BTreeMap::new());
        assert_eq!(first.len(), 1);
        assert_eq!(first[0].ranges, [TimeRange::ALL]);
        c.accept(
            PEER,
            done(&first[0]),
            t(0),
            &mut PeerHistory::default(),
            &limits(),
        );
        for e in &all[1..] {
            c.delivered(e, &PeerHistory::default());
        }
        assert_eq!(c.stats.gaps_seen, 3);
        // The gap's waits until the windows that may hold a lost frame are
        // made: one window span (1 s) after the first snapshot past the gap
        // (frame 90).
        assert!(c.requests(t(99), &BTreeMap::new()).is_empty());
        let gap = c.requests(t(101), &BTreeMap::new());
        assert_eq!(gap.len(), 1, "{gap:?}");
        let [range] = gap[0].ranges[..] else {
            panic!("{gap:?}")
        };
        // Every window that ends in the gap or holds a frame of it.
        for f in [40, 50, 80, 90] {
            assert!(range.contains(t(f)), "window of frame {f}: {range:?}");
        }
        assert!(
            !range.contains(t(20)) && !range.contains(t(110)),
            "{range:?}"
        );
    }

    /// Peer 1's replayer after publishing frames `0..=last`.
    fn replayer(last: u64, bytes_per_s: f64) -> Replayer {
        let mut r = Replayer::new(PEER, limits(), bytes_per_s);
        for e in (0..=last).flat_map(published) {
            r.published(&e.body);
        }
        r
    }

    fn request(id: u64, ranges: Vec<TimeRange>) -> HistoryRequest {
        HistoryRequest {
            to_robot: PEER,
            request_id: id,
            ranges,
            held: Vec::new(),
        }
    }

    fn window_end(r: &HistoryReplay) -> Option<f64> {
        r.window.as_ref().map(HistoryWindow::end_s)
    }

    #[test]
    fn a_replayer_answers_from_its_archive_oldest_first_within_its_budget() {
        let mut r = replayer(100, 1e9);
        assert_eq!(r.archive().keyframes.len(), 10);
        // Another robot's request, and one for robots 2 and 3 overlapping.
        r.request(ME, &request(9, vec![TimeRange::ALL]));
        r.request(
            3,
            &HistoryRequest {
                to_robot: 7,
                ..request(1, vec![TimeRange::ALL])
            },
        );
        r.request(
            3,
            &request(
                4,
                vec![TimeRange {
                    after_s: Some(t(75)),
                    up_to_s: None,
                }],
            ),
        );
        assert_eq!(r.queued(), 10);
        let mut ends = Vec::new();
        let mut completes = Vec::new();
        while let Some(x) = r.next_replay() {
            assert!(x.for_robots.contains(&ME));
            assert_eq!(x.for_robots.contains(&3), window_end(&x) > Some(t(75)));
            ends.extend(window_end(&x));
            completes.extend(x.completes.iter().map(|c| (c.robot, c.request_id)));
            r.sent((x.window.is_some(), false), 10);
        }
        let expected: Vec<f64> = (1..=10).map(|k| t(10 * k)).collect();
        assert_eq!(ends, expected);
        assert_eq!(completes, [(ME, 9), (3, 4)]);

        // A budget of 30 kB per second, windows of 20 kB, ticks of 0.5 s: a
        // window goes while the budget is above zero, so the first tick sends
        // the one-second burst and one more; then 7 windows (140 kB) in 4 s
        // against the 150 kB of the burst and 3.5 s.
        let mut r = replayer(100, 30e3);
        r.request(ME, &request(0, vec![TimeRange::ALL]));
        let mut per_tick = Vec::new();
        for tick in 0..8 {
            r.refill(f64::from(tick) * 0.5);
            let mut n = 0;
            while let Some(x) = r.next_replay() {
                r.sent((x.window.is_some(), false), 20_000);
                n += 1;
            }
            per_tick.push(n);
        }
        assert_eq!(per_tick, [2, 1, 0, 1, 1, 1, 0, 1]);
    }

    #[test]
    fn a_request_that_finds_nothing_is_completed_at_once() {
        let mut r = replayer(5, 1e9);
        r.request(ME, &request(3, vec![TimeRange::ALL]));
        let x = r.next_replay().expect("a completion");
        assert!(x.window.is_none());
        assert_eq!(
            x.completes,
            [RequestRef {
                robot: ME,
                request_id: 3
            }]
        );
        assert!(r.next_replay().is_none());
    }

    #[test]
    fn replayed_windows_are_what_a_live_peer_stores_and_are_kept_only_when_asked() {
        let live_all: Vec<Envelope> = (0..=100).flat_map(published).collect();
        let mut live = PeerHistory::default();
        feed(&mut live, &live_all);

        // We lost frames 35-84: our history lacks windows 40-80 and holds
        // window 90 without the frames 80-84.
        let mut ours = PeerHistory::default();
        let mut c = CatchUp::new(ME, 5.0);
        let kept: Vec<Envelope> = live_all
            .iter()
            .filter(|e| match &e.body {
                Body::Tracks(x) => !(35..85).contains(&x.frame_index),
                Body::Snapshot(x) => !(35..85).contains(&x.frame_index),
                Body::Descriptors(x) => !(35..85).contains(&x.frame_index),
                _ => true,
            })
            .cloned()
            .collect();
        for e in &kept {
            c.delivered(e, &PeerHistory::default());
        }
        feed(&mut ours, &kept);
        assert_eq!(ours.keyframes.len(), 5);

        // A replay we did not ask for is ignored.
        let mut r = replayer(100, 1e9);
        r.request(ME, &request(77, vec![TimeRange::ALL]));
        let unasked = r.next_replay().expect("a window");
        assert_eq!(c.accept(PEER, unasked, 0.0, &mut ours, &limits()), None);

        let mut r = replayer(100, 1e9);
        for req in c.requests(t(102), &BTreeMap::new()) {
            r.request(ME, &req);
        }
        let mut outcomes = Vec::new();
        while let Some(x) = r.next_replay() {
            outcomes.extend(c.accept(PEER, x, t(100), &mut ours, &limits()));
        }
        assert_eq!(c.open_requests(PEER), 0);
        assert_eq!(ours.keyframes.len(), 10);
        assert_eq!(ours.keyframes, live.keyframes);
        assert_eq!(c.stats.windows_stored, 5);
        assert_eq!(c.stats.windows_completed, 1);
        assert!(outcomes.contains(&Replayed::AlreadyHeld));

        // A window for another robot is not ours to store.
        let mut r = replayer(100, 1e9);
        let mut other = CatchUp::new(ME, 5.0);
        for e in &kept {
            other.delivered(e, &PeerHistory::default());
        }
        let reqs = other.requests(t(102), &BTreeMap::new());
        r.request(3, &reqs[0]);
        let mut fresh = PeerHistory::default();
        while let Some(x) = r.next_replay() {
            assert_eq!(other.accept(PEER, x, 0.0, &mut fresh, &limits()), None);
        }
        assert!(fresh.keyframes.is_empty());
    }

    #[test]
    fn windows_whose_replays_were_lost_are_asked_for_again_from_the_answers_list() {
        let live: Vec<Envelope> = (0..=100).flat_map(published).collect();
        let mut whole = PeerHistory::default();
        feed(&mut whole, &live);
        // We heard the peer's first frames only (no window yet): everything
        // is asked for.
        let (mut c, mut ours) = heard(2);
        let mut r = replayer(100, 1e9);
        for req in c.requests(t(3), &BTreeMap::new()) {
            r.request(ME, &req);
        }
        // Replays 1, 4 and 7 are lost on the way; the last one, which
        // completes the request and lists the answer, arrives.
        let mut lost = Vec::new();
        let mut i = 0;
        while let Some(x) = r.next_replay() {
            i += 1;
            if i % 3 == 1 && x.completes.is_empty() {
                lost.extend(window_end(&x));
                continue;
            }
            if !x.completes.is_empty() {
                assert_eq!(x.answered.len(), 10);
                assert!(x.answered.iter().all(|a| a.frames > 0 && a.descriptors));
            }
            c.accept(PEER, x, t(100), &mut ours, &limits());
        }
        assert_eq!(lost.len(), 3);
        assert_eq!(ours.keyframes.len(), 7);
        assert_eq!(c.stats.windows_reasked, 3);
        assert_eq!(c.open_requests(PEER), 0);
        // One request asks for exactly the lost windows, one range each.
        let reqs = c.requests(t(101), &BTreeMap::new());
        assert_eq!(reqs.len(), 1, "{reqs:?}");
        assert_eq!(reqs[0].ranges.len(), 3);
        for (range, end) in reqs[0].ranges.iter().zip(&lost) {
            assert!(range.contains(*end), "{range:?} {end}");
            assert_eq!(
                whole
                    .keyframes
                    .values()
                    .filter(|k| range.contains(k.end_s()))
                    .count(),
                1
            );
        }
        for req in &reqs {
            r.request(ME, req);
        }
        while let Some(x) = r.next_replay() {
            c.accept(PEER, x, t(102), &mut ours, &limits());
        }
        assert_eq!(ours.keyframes, whole.keyframes);
        // Nothing is missing now: the second answer asks for nothing more.
        assert_eq!(c.stats.windows_reasked, 3);
        assert!(c.requests(t(103), &BTreeMap::new()).is_empty());

        // A window our own bound keeps dropping is asked for a few times,
        // not forever.
        let (mut c, mut tiny) = heard(2);
        let small = HistoryLimits {
            max_bytes: 1,
            ..limits()
        };
        for round in 0..10 {
            for req in c.requests(t(103 + round), &BTreeMap::new()) {
                r.request(ME, &req);
            }
            while let Some(x) = r.next_replay() {
                c.accept(PEER, x, t(103 + round), &mut tiny, &small);
            }
        }
        assert!(c.stats.windows_reasked <= 10 * u64::from(MAX_ASKS_PER_WINDOW));
        assert!(c.requests(t(200), &BTreeMap::new()).is_empty());
    }

    #[test]
    fn unanswered_requests_are_sent_again_until_the_peer_vanishes() {
        let (mut c, h) = heard(40);
        let first = c.requests(100.0, &BTreeMap::new());
        assert_eq!(first.len(), 1);
        // No reply: asked again every 5 s, with the same ranges.
        let mut asked_at = Vec::new();
        for k in 1..=20 {
            let now = 100.0 + f64::from(k);
            for r in c.requests(now, &BTreeMap::new()) {
                assert_eq!(r.ranges, first[0].ranges);
                asked_at.push(now);
            }
        }
        assert_eq!(asked_at, [106.0, 112.0, 118.0]);
        assert_eq!(c.stats.requests_retried, 3);
        assert_eq!(c.open_requests(PEER), 1);

        // Gone: given up. Back: asked for what came after the newest held.
        c.vanished(PEER);
        assert_eq!(c.open_requests(PEER), 0);
        assert_eq!(c.stats.requests_dropped, 1);
        assert!(c.requests(240.0, &BTreeMap::new()).is_empty());
        c.reappeared(PEER, Some(&h));
        let back = c.requests(250.0, &BTreeMap::new());
        assert_eq!(
            back[0].ranges,
            [TimeRange {
                after_s: Some(t(40)),
                up_to_s: None
            }]
        );
    }

    fn heartbeat(seq: u64, newest_window_end_s: Option<f64>) -> Envelope {
        let mut hb = samples::heartbeat(seq * 10);
        hb.seq = seq;
        if let Body::Heartbeat(h) = &mut hb.body {
            h.newest_window_end_s = newest_window_end_s;
        }
        hb
    }

    /// The peer's last windows were lost and it sends no data after them (it
    /// landed): no gap shows, but its heartbeats say what it made.
    #[test]
    fn windows_a_heartbeat_claims_and_we_still_lack_a_heartbeat_later_are_asked_for() {
        let (mut c, mut h) = heard(15);
        // Everything, at first sight: answered with what the peer had then.
        let first = c.requests(t(16), &BTreeMap::new());
        c.accept(PEER, done(&first[0]), t(16), &mut h, &limits());
        assert_eq!(c.open_requests(PEER), 0);
        // Claims we meet ask for nothing, nor does a claim on its way.
        c.delivered(&heartbeat(1, Some(t(10))), &h);
        c.delivered(&heartbeat(2, Some(t(40))), &h);
        assert!(c.requests(t(41), &BTreeMap::new()).is_empty());
        c.delivered(&heartbeat(3, Some(t(40))), &h);
        let reqs = c.requests(t(42), &BTreeMap::new());
        assert_eq!(
            reqs[0].ranges,
            [TimeRange {
                after_s: Some(t(10)),
                up_to_s: None
            }]
        );
        assert_eq!(c.stats.windows_missing, 1);
        // Asked once, not at every heartbeat while the replay is on its way.
        c.delivered(&heartbeat(4, Some(t(40))), &h);
        assert!(c.requests(t(43), &BTreeMap::new()).is_empty());
    }

    #[test]
    fn a_lost_track_frame_brings_back_that_frame_only() {
        let live: Vec<Envelope> = (0..=100).flat_map(published).collect();
        let mut whole = PeerHistory::default();
        feed(&mut whole, &live);
        // Track frame 55 is lost: window 60 (clones of frames 50-60) is short
        // of it; the gap's range also spans the whole windows 50 and 70.
        let kept: Vec<Envelope> = live
            .iter()
            .filter(|e| !matches!(&e.body, Body::Tracks(x) if x.frame_index == 55))
            .cloned()
            .collect();
        let mut ours = PeerHistory::default();
        feed(&mut ours, &kept);
        let mut c = CatchUp::new(ME, 5.0);
        for e in &kept {
            c.delivered(e, &ours);
        }
        let mut histories = BTreeMap::new();
        histories.insert(PEER, ours);
        let mut r = replayer(100, 1e9);
        // The first request (everything, the peer being new) is answered.
        for req in c.requests(t(40), &BTreeMap::new()) {
            r.request(ME, &req);
        }
        while r.next_replay().is_some() {}
        // The gap's request, once its windows exist, asks for window 60
        // only, and says it holds it short of its sixth frame.
        let reqs = c.requests(t(101), &histories);
        assert_eq!(reqs.len(), 1, "{reqs:?}");
        let [held] = reqs[0].held[..] else {
            panic!("{reqs:?}")
        };
        assert_eq!(held.end_s, t(60));
        assert_eq!(held.frames_mask, 0b111_1101_1111);
        assert!(held.descriptors);
        r.request(ME, &reqs[0]);
        let ours = histories.get_mut(&PEER).unwrap();
        let mut parts = Vec::new();
        while let Some(x) = r.next_replay() {
            assert!(x.window.is_none());
            parts.extend(x.part.clone());
            c.accept(PEER, x, t(101), ours, &limits());
        }
        // Back comes frame 55 alone: no snapshot, no other frame, no
        // descriptors.
        let [part] = &parts[..] else {
            panic!("{parts:?}")
        };
        assert_eq!(part.end_s, t(60));
        assert_eq!(part.frames.len(), 1);
        assert_eq!(part.frames[0].t_s, t(55));
        assert!(part.descriptors.is_empty());
        assert_eq!(ours.keyframes, whole.keyframes);
        assert_eq!(ours.history_bytes, whole.history_bytes);
        assert_eq!((c.stats.parts_received, c.stats.parts_stored), (1, 1));
        assert_eq!(r.stats.parts_replayed, 0, "counted when sent");
        // Whole now: nothing more is asked.
        assert!(c.requests(t(120), &histories).is_empty());
    }

    /// Losses every second make overlapping gaps one after another: each
    /// window is still asked for about a second after it exists, not when
    /// the losses stop.
    #[test]
    fn on_a_steadily_lossy_link_windows_are_asked_for_as_they_come() {
        let mut c = CatchUp::new(ME, 5.0);
        let mut ours = PeerHistory::default();
        let mut histories = BTreeMap::new();
        let mut first_asked: BTreeMap<u64, f64> = BTreeMap::new();
        for f in 0..=300u64 {
            // One track frame in seven is lost.
            let envs: Vec<Envelope> = published(f)
                .into_iter()
                .filter(|e| !(matches!(e.body, Body::Tracks(_)) && f % 7 == 3))
                .collect();
            feed(&mut ours, &envs);
            for e in &envs {
                c.delivered(e, &ours);
            }
            histories.insert(PEER, ours.clone());
            for req in c.requests(t(f), &histories) {
                if req.ranges == [TimeRange::ALL] {
                    // The first request, before any window: nothing found.
                    c.accept(PEER, done(&req), t(f), &mut ours, &limits());
                    continue;
                }
                for w in (1..=30).map(|k| 10 * k) {
                    if req.ranges.iter().any(|r| r.contains(t(w))) {
                        first_asked.entry(w).or_insert(t(f));
                    }
                }
            }
        }
        // Every window short of a frame (all but none: a window spans 11
        // frames) is asked for within two seconds of its end.
        for w in (2..=29).map(|k| 10 * k) {
            let asked = first_asked.get(&w).copied();
            assert!(
                asked.is_some_and(|a| a - t(w) <= 2.0),
                "window {w} (end {}) first asked at {asked:?}",
                t(w)
            );
        }
    }

    /// The peer's last track frame is lost and nothing follows it (it
    /// landed): no gap shows. The sweep at the end asks once more, and only
    /// that frame comes back.
    #[test]
    fn the_sweep_at_the_end_brings_back_what_no_gap_showed() {
        let live: Vec<Envelope> = (0..=100).flat_map(published).collect();
        let mut whole = PeerHistory::default();
        feed(&mut whole, &live);
        let kept: Vec<Envelope> = live
            .iter()
            .filter(|e| !matches!(&e.body, Body::Tracks(x) if x.frame_index == 100))
            .cloned()
            .collect();
        let (before, after): (Vec<Envelope>, Vec<Envelope>) =
            kept.into_iter().partition(|e| e.stamp_s <= t(90) + 1e-3);
        // The first request (everything, at first sight) is answered at
        // frame 90, before the loss.
        let (mut c, mut ours) = heard(90);
        let mut r = replayer(90, 1e9);
        for req in c.requests(t(90), &BTreeMap::new()) {
            r.request(ME, &req);
        }
        while let Some(x) = r.next_replay() {
            c.accept(PEER, x, t(90), &mut ours, &limits());
        }
        for e in (91..=100).flat_map(published) {
            r.published(&e.body);
        }
        feed(&mut ours, &after);
        for e in &after {
            c.delivered(e, &ours);
        }
        assert!(before.len() > after.len());
        assert!(c.idle() && r.idle());
        let mut histories = BTreeMap::new();
        histories.insert(PEER, ours);
        assert!(c.requests(t(120), &histories).is_empty(), "no gap showed");
        assert_ne!(histories[&PEER].keyframes, whole.keyframes);

        c.sweep(PEER);
        assert!(!c.idle());
        let reqs = c.requests(t(121), &histories);
        let [req] = &reqs[..] else { panic!("{reqs:?}") };
        r.request(ME, req);
        assert!(!r.idle());
        let ours = histories.get_mut(&PEER).unwrap();
        let mut parts = 0;
        while let Some(x) = r.next_replay() {
            assert!(x.window.is_none());
            parts += usize::from(x.part.is_some());
            c.accept(PEER, x, t(121), ours, &limits());
        }
        assert_eq!(parts, 1);
        assert_eq!(ours.keyframes, whole.keyframes);
        assert!(c.idle() && r.idle());
        // A peer never heard (known from disk only) is not swept.
        c.sweep(9);
        assert!(c.idle());
    }

    #[test]
    fn a_window_goes_whole_to_whoever_lacks_it_and_in_parts_to_its_holders() {
        let mut r = replayer(100, 1e9);
        let end = t(60);
        let range = TimeRange {
            after_s: Some(end - ONE_WINDOW_S),
            up_to_s: Some(end),
        };
        let holding = |robot_mask: u64, descriptors: bool| HeldWindow {
            end_s: end,
            frames_mask: robot_mask,
            descriptors,
        };
        // Robot 2 lacks frame 0, robot 3 frame 4 and the descriptors.
        let all = (1u64 << 11) - 1;
        r.request(
            ME,
            &HistoryRequest {
                held: vec![holding(all & !1, true)],
                ..request(0, vec![range])
            },
        );
        r.request(
            3,
            &HistoryRequest {
                held: vec![holding(all & !(1 << 4), false)],
                ..request(0, vec![range])
            },
        );
        let x = r.next_replay().expect("a part");
        assert!(r.next_replay().is_none());
        assert_eq!(x.for_robots, [ME, 3]);
        let part = x.part.expect("a part");
        let times: Vec<f64> = part.frames.iter().map(|f| f.t_s).collect();
        assert_eq!(times, [t(50), t(54)]);
        assert!(!part.descriptors.is_empty());
        assert_eq!(x.completes.len(), 2);

        // Robot 4 lacks the window: it goes whole, to all three.
        r.request(
            ME,
            &HistoryRequest {
                held: vec![holding(all & !1, true)],
                ..request(1, vec![range])
            },
        );
        r.request(4, &request(0, vec![range]));
        let x = r.next_replay().expect("a window");
        assert_eq!(x.for_robots, [ME, 4]);
        assert!(x.window.is_some() && x.part.is_none());

        // A newer request that holds it all takes back the part queued
        // for an older one.
        r.request(
            ME,
            &HistoryRequest {
                held: vec![holding(all & !1, true)],
                ..request(4, vec![range])
            },
        );
        r.request(
            ME,
            &HistoryRequest {
                held: vec![holding(all, true)],
                ..request(5, vec![range])
            },
        );
        let x = r.next_replay().expect("a completion");
        assert!(x.window.is_none() && x.part.is_none(), "{x:?}");
        assert!(r.next_replay().is_none());

        // A holder of every part there is gets nothing, and its request
        // completes at once.
        r.request(
            ME,
            &HistoryRequest {
                held: vec![holding(all, true)],
                ..request(2, vec![range])
            },
        );
        let x = r.next_replay().expect("a completion");
        assert!(x.window.is_none() && x.part.is_none());
        assert_eq!(
            x.completes,
            [RequestRef {
                robot: ME,
                request_id: 2
            }]
        );
        assert_eq!(x.answered.len(), 1);
    }

    #[test]
    fn ranges_merge_when_they_overlap_or_touch() {
        let r = |a: f64, b: f64| TimeRange {
            after_s: Some(a),
            up_to_s: Some(b),
        };
        assert_eq!(
            merge(vec![r(5.0, 6.0), r(1.0, 2.0), r(2.0, 3.0), r(2.5, 2.7)]),
            [r(1.0, 3.0), r(5.0, 6.0)]
        );
        let open = TimeRange {
            after_s: Some(4.0),
            up_to_s: None,
        };
        assert_eq!(merge(vec![r(5.0, 6.0), open]), [open]);
    }
}
