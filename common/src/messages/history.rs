//! History catch-up: what a peer missed while its link was down, or before it
//! started, asked for and sent again.
//!
//! Plain publish/subscribe does not replay what was published during a
//! partition, so an agent that lost a stretch of a peer's keyframe windows
//! would never make a historical loop closure there. It asks the peer with a
//! [`HistoryRequest`] (ranges of window end times); the peer answers from its
//! own archive with one [`HistoryReplay`] per keyframe window, paced, and says
//! when each request is fully answered.
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
    /// nothing).
    pub window: Option<HistoryWindow>,
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
    use super::super::{decode, encode, samples, Body, Envelope, ValidationError};
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
            samples::history_replay(300, 80),
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
}
