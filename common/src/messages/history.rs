//! History catch-up: what a peer missed while its link was down, or before it
//! started, asked for and sent again.
//!
//! Plain publish/subscribe does not replay what was published during a
//! partition, so an agent that lost a stretch of a peer's keyframe windows
//! would never make a historical loop closure there. It asks the peer with a
//! [`HistoryRequest`] (ranges of window end times); the peer answers from its
//! own archive with one [`HistoryReplay`] per keyframe window, paced, and says
//! when each request is fully answered. A window the requester holds short of
//! some parts (a track frame or the descriptors were lost) is listed in the
//! request with what it holds, and only the missing parts come back
//! ([`WindowPart`]): on a lossy link most windows miss one message of a dozen,
//! and the snapshot, most of a window's bytes, has arrived.
//!
//! A replay is published to the whole fleet (the transports only broadcast);
//! it names the robots that asked for it, and the others ignore it.

use serde::{Deserialize, Serialize};

use super::body::{DescriptorEntry, StateSnapshot};
use super::bounded_vec;

/// An interval of keyframe-window end times (the newest clone's time): `(after_s,
/// up_to_s]`, unbounded on a side that is `None`.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct TimeRange {
    /// Windows ending strictly after this time, s (`None`: from the start).
    pub after_s: Option<f64>,
    /// Windows ending at or before this time, s (`None`: up to the newest).
    pub up_to_s: Option<f64>,
}

impl TimeRange {
    /// Every window.
    pub const ALL: TimeRange = TimeRange {
        after_s: None,
        up_to_s: None,
    };

    /// Whether a window ending at `t_s` is in the range.
    pub fn contains(&self, t_s: f64) -> bool {
        self.after_s.is_none_or(|a| t_s > a) && self.up_to_s.is_none_or(|b| t_s <= b)
    }
}

/// One agent's request of a peer's keyframe windows.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct HistoryRequest {
    /// The peer asked (the others ignore the request).
    pub to_robot: u32,
    /// Increasing per requester; the replay names it when the request is answered.
    pub request_id: u64,
    /// The windows wanted, by end time.
    #[serde(deserialize_with = "bounded_vec::deserialize")]
    pub ranges: Vec<TimeRange>,
    /// Windows in `ranges` the requester holds already, short of some parts:
    /// only those parts are sent. A window not listed is sent whole.
    #[serde(deserialize_with = "bounded_vec::deserialize")]
    pub held: Vec<HeldWindow>,
}

/// A window the requester holds, and which of its parts.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct HeldWindow {
    /// The window's end time, s.
    pub end_s: f64,
    /// Bit `i` set: the frame of measurements at the window's `i`-th clone
    /// (oldest first) is held. Clones past the 64th count as not held.
    pub frames_mask: u64,
    /// Whether the keyframe's descriptors are held.
    pub descriptors: bool,
}

impl HeldWindow {
    /// Whether the frame at clone `index` is held.
    pub fn holds_frame(&self, index: usize) -> bool {
        index < 64 && self.frames_mask & (1 << index) != 0
    }
}

/// The parts of a window its requesters lacked: the frames they miss, and the
/// keyframe's descriptors if one of them misses those.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct WindowPart {
    /// The window's end time, s (it names the window the requesters hold).
    pub end_s: f64,
    /// Frames of measurements, each at one of the window's clone times,
    /// oldest first.
    #[serde(deserialize_with = "bounded_vec::deserialize")]
    pub frames: Vec<WindowFrame>,
    /// The keyframe's descriptors (empty: not sent).
    #[serde(deserialize_with = "bounded_vec::deserialize")]
    pub descriptors: Vec<DescriptorEntry>,
}

impl WindowPart {
    /// Whether it carries nothing.
    pub fn is_empty(&self) -> bool {
        self.frames.is_empty() && self.descriptors.is_empty()
    }
}

/// A request, named by its requester and id.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, PartialOrd, Ord, Serialize, Deserialize)]
pub struct RequestRef {
    /// The requester's robot id.
    pub robot: u32,
    /// Its [`HistoryRequest::request_id`].
    pub request_id: u64,
}

/// One measurement of a track inside a keyframe window.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct WindowObservation {
    /// The sender's track id.
    pub id: u64,
    /// Undistorted normalized image coordinates `[x/z, y/z]`.
    pub xy_norm: [f32; 2],
}

/// The measurements of one frame of a keyframe window.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct WindowFrame {
    /// Camera time, s: the time of one of the window's clones.
    pub t_s: f64,
    /// The measurements.
    #[serde(deserialize_with = "bounded_vec::deserialize")]
    pub observations: Vec<WindowObservation>,
}

/// A keyframe window as peers store it: the snapshot, the track measurements
/// at its clone times and the keyframe's descriptors.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct HistoryWindow {
    /// The keyframe snapshot (`keyframe` is set).
    pub snapshot: StateSnapshot,
    /// Measurements, one frame per clone at most, oldest first.
    #[serde(deserialize_with = "bounded_vec::deserialize")]
    pub frames: Vec<WindowFrame>,
    /// The keyframe's descriptors.
    #[serde(deserialize_with = "bounded_vec::deserialize")]
    pub descriptors: Vec<DescriptorEntry>,
}

impl HistoryWindow {
    /// The window's end time: its newest clone's time (the snapshot's time
    /// without clones).
    pub fn end_s(&self) -> f64 {
        self.snapshot.end_s()
    }
}

/// A keyframe window sent again, and the requests it completes.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct HistoryReplay {
    /// The robots that asked for `window`.
    #[serde(deserialize_with = "bounded_vec::deserialize")]
    pub for_robots: Vec<u32>,
    /// The window (`None` when the message only completes requests that found
    /// nothing, or carries a part).
    pub window: Option<HistoryWindow>,
    /// The missing parts of a window the requesters hold (never with `window`).
    pub part: Option<WindowPart>,
    /// Requests fully answered once this message is in.
    #[serde(deserialize_with = "bounded_vec::deserialize")]
    pub completes: Vec<RequestRef>,
    /// Every window the requests in `completes` were answered with, as the
    /// answerer holds it, oldest first: a requester that lacks one of them,
    /// or holds a less complete copy, lost its replay and asks for it again.
    #[serde(deserialize_with = "bounded_vec::deserialize")]
    pub answered: Vec<AnsweredWindow>,
}

/// A window of an answer, named by its end time, with how complete the
/// answerer's copy is.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct AnsweredWindow {
    /// The window's end time, s.
    pub end_s: f64,
    /// Frames with measurements in it.
    pub frames: u32,
    /// Whether it carries the keyframe's descriptors.
    pub descriptors: bool,
}

#[cfg(test)]
mod tests {
    use super::super::{
        decode, encode, samples, Body, Envelope, ValidationError, MAX_HELD_WINDOWS,
    };
    use super::*;

    fn replay(env: &mut Envelope) -> &mut HistoryReplay {
        match &mut env.body {
            Body::HistoryReplay(r) => r,
            _ => panic!("not a replay"),
        }
    }

    #[test]
    fn requests_and_replays_round_trip() {
        for env in [
            samples::history_request(12.5),
            samples::history_request_holding(12.5, 30),
            samples::history_replay(300, 80),
            samples::history_part(300, 80, &[2, 7], true),
        ] {
            assert_eq!(decode(&encode(&env).unwrap()).unwrap(), env);
        }
    }

    #[test]
    fn ranges_are_half_open_and_may_be_unbounded() {
        let r = TimeRange {
            after_s: Some(1.0),
            up_to_s: Some(2.0),
        };
        assert!(!r.contains(1.0) && r.contains(1.5) && r.contains(2.0) && !r.contains(2.5));
        assert!(TimeRange::ALL.contains(-1e9) && TimeRange::ALL.contains(1e9));
    }

    #[test]
    fn an_empty_or_nan_range_is_refused() {
        let mut env = samples::history_request(5.0);
        if let Body::HistoryRequest(r) = &mut env.body {
            r.ranges[0].up_to_s = Some(5.0);
        }
        assert!(matches!(
            env.validate(&Default::default()),
            Err(ValidationError::EmptyRange { index: 0, .. })
        ));
        if let Body::HistoryRequest(r) = &mut env.body {
            r.ranges[0].after_s = Some(f64::NAN);
        }
        assert!(encode(&env).is_err());
    }

    #[test]
    fn a_replayed_window_must_be_a_keyframe_with_frames_at_its_clone_times() {
        let limits = Default::default();
        let mut env = samples::history_replay(300, 10);
        let w = replay(&mut env).window.as_mut().unwrap();
        w.frames[3].t_s += 0.01;
        assert!(matches!(
            env.validate(&limits),
            Err(ValidationError::ReplayFrameTime { index: 3, .. })
        ));

        let mut env = samples::history_replay(300, 10);
        let w = replay(&mut env).window.as_mut().unwrap();
        w.frames.swap(0, 1);
        assert!(matches!(
            env.validate(&limits),
            Err(ValidationError::ReplayFrameTime { index: 1, .. })
        ));

        let mut env = samples::history_replay(300, 10);
        replay(&mut env).answered[5].end_s = f64::NAN;
        assert!(matches!(
            env.validate(&limits),
            Err(ValidationError::NonFinite { field, .. }) if field == "history.answered[5].end_s"
        ));

        let mut env = samples::history_replay(300, 10);
        replay(&mut env).window.as_mut().unwrap().snapshot.keyframe = false;
        assert_eq!(
            env.validate(&limits),
            Err(ValidationError::ReplayNotKeyframe)
        );

        let mut env = samples::history_replay(300, 10);
        let w = replay(&mut env).window.as_mut().unwrap();
        w.frames[2].observations[4].xy_norm[1] = f32::INFINITY;
        assert!(matches!(
            env.validate(&limits),
            Err(ValidationError::NonFinite { .. })
        ));

        let mut env = samples::history_replay(300, 10);
        let w = replay(&mut env).window.as_mut().unwrap();
        let extra = w.frames[0].clone();
        w.frames.extend(std::iter::repeat_n(extra, 11));
        assert!(matches!(
            env.validate(&limits),
            Err(ValidationError::TooMany { .. })
        ));
    }

    #[test]
    fn a_replay_may_only_complete_requests() {
        let mut env = samples::history_replay(300, 10);
        replay(&mut env).window = None;
        assert_eq!(decode(&encode(&env).unwrap()).unwrap(), env);
    }

    #[test]
    fn a_part_is_small_and_checked() {
        let limits = Default::default();
        let whole = encode(&samples::history_replay(300, 100)).unwrap().len();
        let part = encode(&samples::history_part(300, 100, &[4], false))
            .unwrap()
            .len();
        // One frame of eleven, no snapshot: a tenth of the window or less.
        assert!(part * 10 < whole, "part {part} B, whole {whole} B");

        let mut env = samples::history_part(300, 10, &[2, 7], true);
        let w = samples::history_replay(300, 10);
        replay(&mut env).window = match w.body {
            Body::HistoryReplay(r) => r.window,
            _ => None,
        };
        assert_eq!(
            env.validate(&limits),
            Err(ValidationError::ReplayWindowAndPart)
        );

        let env = samples::history_part(300, 10, &[7, 2], true);
        assert!(matches!(
            env.validate(&limits),
            Err(ValidationError::PartFramesOutOfOrder { index: 1, .. })
        ));

        let mut env = samples::history_part(300, 10, &[2], true);
        replay(&mut env).part.as_mut().unwrap().frames[0].observations[1].xy_norm[0] = f32::NAN;
        assert!(matches!(
            env.validate(&limits),
            Err(ValidationError::NonFinite { field, .. })
                if field == "history.part.frames[0].observations[1].xy_norm[0]"
        ));

        let mut env = samples::history_part(300, 10, &[2], true);
        replay(&mut env).part.as_mut().unwrap().end_s = f64::INFINITY;
        assert!(env.validate(&limits).is_err());
    }

    #[test]
    fn a_request_lists_at_most_so_many_held_windows_with_finite_ends() {
        let limits = Default::default();
        let env = samples::history_request_holding(3.0, MAX_HELD_WINDOWS);
        assert_eq!(env.validate(&limits), Ok(()));
        let env = samples::history_request_holding(3.0, MAX_HELD_WINDOWS + 1);
        assert!(matches!(
            env.validate(&limits),
            Err(ValidationError::TooMany {
                field: "history_request.held",
                ..
            })
        ));
        let mut env = samples::history_request_holding(3.0, 4);
        if let Body::HistoryRequest(r) = &mut env.body {
            r.held[2].end_s = f64::NAN;
        }
        assert!(env.validate(&limits).is_err());
        let held = HeldWindow {
            end_s: 1.0,
            frames_mask: 0b101,
            descriptors: false,
        };
        assert!(held.holds_frame(0) && !held.holds_frame(1) && held.holds_frame(2));
        assert!(!held.holds_frame(64) && !held.holds_frame(200));
    }
}
