//! What this agent tells its peers, built from its frames and its estimator
//! (thesis Section 5.3): per frame the active tracks, descriptors of new tracks,
//! a window snapshot every few frames, and keyframe windows with all their
//! descriptors for the peers' histories.

use crate::config::PublishConfig;
use crate::estimator::camera_window::CameraWindow;
use common::calibration::CameraCalibration;
use common::measurement::FeatureFrame;
use common::messages::{
    AgentState, Body, CameraModelWire, CameraPose, DescriptorBatch, DescriptorEntry, Envelope,
    Heartbeat, Landmark, MessageKind, PackedCovariance, StateSnapshot, TrackFrame, TrackPoint,
};
use std::collections::{BTreeMap, HashSet};

/// Builds the envelopes of one agent, numbering them per kind.
#[derive(Debug)]
pub struct Outbox {
    fleet_id: String,
    robot_id: u32,
    cfg: PublishConfig,
    seq: BTreeMap<MessageKind, u64>,
    /// Track ids of the previous frame (a track is new when it was not there).
    prev_ids: HashSet<u64>,
    /// Newest clone time of the last keyframe window.
    last_keyframe_end_s: Option<f64>,
    /// Time of the last keyframe.
    last_keyframe_s: Option<f64>,
    /// Frame index of the last snapshot.
    last_snapshot_frame: Option<u64>,
    /// The world frame our snapshots are in ([`StateSnapshot::frame_epoch`]).
    frame_epoch: u64,
    /// Our pixel noise, pixels ([`StateSnapshot::pixel_sigma_px`]).
    pixel_sigma_px: f64,
}

/// What snapshot a frame sends.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct SnapshotPlan {
    /// A keyframe window (for peers' histories).
    pub keyframe: bool,
    /// With the SLAM features.
    pub landmarks: bool,
}

impl Outbox {
    /// An outbox for robot `robot_id` of fleet `fleet_id`, whose snapshots
    /// are in world frame `frame_epoch` ([`StateSnapshot::frame_epoch`]) and
    /// declare pixel noise `pixel_sigma_px` (the estimator's).
    pub fn new(
        fleet_id: &str,
        robot_id: u32,
        cfg: PublishConfig,
        frame_epoch: u64,
        pixel_sigma_px: f64,
    ) -> Self {
        Self {
            fleet_id: fleet_id.to_string(),
            robot_id,
            cfg,
            seq: BTreeMap::new(),
            prev_ids: HashSet::new(),
            last_keyframe_end_s: None,
            last_keyframe_s: None,
            last_snapshot_frame: None,
            frame_epoch,
            pixel_sigma_px,
        }
    }

    fn envelope(&mut self, stamp_s: f64, body: Body) -> Envelope {
        let seq = self.seq.entry(body.kind()).or_insert(0);
        let env = Envelope {
            fleet_id: self.fleet_id.clone(),
            robot_id: self.robot_id,
            seq: *seq,
            stamp_s,
            sent_wall_ns: 0,
            body,
        };
        *seq += 1;
        env
    }

    /// The tracks of camera frame number `frame_index` (with normalized
    /// coordinates from the current calibration), and the descriptors of the
    /// tracks that start in it.
    pub fn tracks(
        &mut self,
        frame_index: u64,
        frame: &FeatureFrame,
        calib: &CameraCalibration,
    ) -> Vec<Envelope> {
        let t = frame.t;
        let features: Vec<TrackPoint> = frame
            .features
            .iter()
            .filter_map(|f| {
                let xy = calib.camera.undistort(&f.uv).ok()?;
                Some(TrackPoint::new(f.id, &f.uv, &xy))
            })
            .collect();
        let mut out = vec![self.envelope(
            t,
            Body::Tracks(TrackFrame {
                frame_index,
                t_s: t,
                features,
            }),
        )];
        let new: Vec<DescriptorEntry> = frame
            .features
            .iter()
            .filter(|f| !self.prev_ids.contains(&f.id))
            .map(|f| DescriptorEntry::new(f.id, f.descriptor))
            .collect();
        self.prev_ids = frame.features.iter().map(|f| f.id).collect();
        if !new.is_empty() {
            out.push(self.envelope(
                t,
                Body::Descriptors(DescriptorBatch {
                    frame_index,
                    t_s: t,
                    keyframe: false,
                    entries: new,
                }),
            ));
        }
        out
    }

    /// Whether frame `frame_index` at time `t` sends a snapshot, given the oldest
    /// clone time of the window and whether the window is full: at keyframes
    /// (with landmarks), and otherwise once `snapshot_every_frames` frames have
    /// passed since the last snapshot.
    ///
    /// A keyframe window is always a full one. Peers triangulate our tracks
    /// from it, minutes later maybe: a window of the first frame
    /// alone (one clone) gives no point at all, yet its descriptors win place
    /// recognition there again and again, and as windows never overlap it
    /// held back the next keyframe by a whole window.
    pub fn snapshot_due(
        &self,
        frame_index: u64,
        t: f64,
        oldest_clone_t: Option<f64>,
        window_full: bool,
    ) -> Option<SnapshotPlan> {
        let oldest = oldest_clone_t?;
        let keyframe = window_full
            && match (self.last_keyframe_s, self.last_keyframe_end_s) {
                (Some(last), Some(end)) => t - last >= self.cfg.keyframe_period_s && oldest > end,
                _ => true,
            };
        let every = u64::from(self.cfg.snapshot_every_frames.max(1));
        let periodic = self
            .last_snapshot_frame
            .is_none_or(|last| frame_index >= last + every);
        (keyframe || periodic).then_some(SnapshotPlan {
            keyframe,
            landmarks: keyframe || self.cfg.landmarks_in_snapshots,
        })
    }

    /// The snapshot of `window` as planned; a keyframe's descriptors (every
    /// feature of `frame`) go first.
    pub fn snapshot(
        &mut self,
        frame_index: u64,
        frame: &FeatureFrame,
        plan: SnapshotPlan,
        window: &CameraWindow,
    ) -> Vec<Envelope> {
        let t = frame.t;
        let mut out = Vec::new();
        let Some(mut snapshot) = snapshot_of(
            frame_index,
            t,
            plan.keyframe,
            window,
            self.pixel_sigma_px,
            plan.landmarks,
        ) else {
            return out;
        };
        snapshot.frame_epoch = self.frame_epoch;
        self.last_snapshot_frame = Some(frame_index);
        if plan.keyframe {
            self.last_keyframe_s = Some(t);
            self.last_keyframe_end_s = window.poses.last().map(|p| p.t_cam);
            let entries = frame
                .features
                .iter()
                .map(|f| DescriptorEntry::new(f.id, f.descriptor))
                .collect();
            out.push(self.envelope(
                t,
                Body::Descriptors(DescriptorBatch {
                    frame_index,
                    t_s: t,
                    keyframe: true,
                    entries,
                }),
            ));
        }
        out.push(self.envelope(t, Body::Snapshot(snapshot)));
        out
    }

    /// A heartbeat: the agent's state, the last tick it finished and the end
    /// of its newest keyframe window.
    pub fn heartbeat(
        &mut self,
        stamp_s: f64,
        state: AgentState,
        frames_done: u64,
        last_tick: Option<u64>,
        newest_window_end_s: Option<f64>,
    ) -> Envelope {
        self.envelope(
            stamp_s,
            Body::Heartbeat(Heartbeat {
                state,
                frames_done,
                last_frame_index: last_tick,
                last_t_s: Some(stamp_s),
                newest_window_end_s,
            }),
        )
    }

    /// A history catch-up message (a request, or a replay) stamped `stamp_s`.
    pub fn catch_up(&mut self, stamp_s: f64, body: Body) -> Envelope {
        self.envelope(stamp_s, body)
    }

    /// Messages sent so far, per kind.
    pub fn sent_counts(&self) -> &BTreeMap<MessageKind, u64> {
        &self.seq
    }
}

/// The wire form of a window (covariance in f32), or `None` when it cannot be
/// represented (a non-finite value: never sent).
pub fn snapshot_of(
    frame_index: u64,
    t_s: f64,
    keyframe: bool,
    window: &CameraWindow,
    pixel_sigma_px: f64,
    with_landmarks: bool,
) -> Option<StateSnapshot> {
    let covariance = PackedCovariance::from_dmatrix(&window.cov).ok()?;
    Some(StateSnapshot {
        frame_index,
        t_s,
        keyframe,
        frame_epoch: 0,
        camera: CameraModelWire::from(&window.calib.camera),
        pixel_sigma_px,
        clones: window
            .poses
            .iter()
            .map(|p| CameraPose::new(p.t_cam, &p.rot, &p.pos))
            .collect(),
        covariance,
        landmarks: if with_landmarks {
            window
                .landmarks
                .iter()
                .map(|l| Landmark::new(l.id, &l.pos, &l.cov))
                .collect()
        } else {
            Vec::new()
        },
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::estimator::camera_window::CameraPoseEstimate;
    use common::descriptor::Descriptor;
    use common::measurement::FeatureObservation;
    use nalgebra::{DMatrix, Matrix3, Vector2, Vector3};

    fn frame(t: f64, ids: std::ops::Range<u64>) -> FeatureFrame {
        FeatureFrame {
            t,
            camera: 0,
            features: ids
                .map(|id| FeatureObservation {
                    id,
                    uv: Vector2::new(300.0 + id as f64, 200.0),
                    descriptor: Descriptor([id; 4]),
                })
                .collect(),
        }
    }

    /// A window of `n` clones 0.1 s apart ending at `t_last`.
    fn window(t_last: f64, n: u64) -> CameraWindow {
        let poses: Vec<CameraPoseEstimate> = (0..n)
            .map(|i| CameraPoseEstimate {
                key: i,
                t_cam: t_last - 0.1 * (n - 1 - i) as f64,
                rot: Matrix3::identity(),
                pos: Vector3::zeros(),
            })
            .collect();
        CameraWindow {
            t: t_last,
            poses,
            cov: DMatrix::identity(6 * n as usize, 6 * n as usize) * 1e-4,
            landmarks: Vec::new(),
            calib: CameraCalibration::euroc_cam0(),
        }
    }

    /// Every snapshot declares the estimator's pixel noise, so peers weigh
    /// our tracks at it.
    #[test]
    fn snapshots_carry_our_pixel_noise() {
        let mut ob = Outbox::new("f", 2, PublishConfig::default(), 0, 2.5);
        let (f, w) = (frame(1.0, 0..20), window(1.0, 11));
        let plan = SnapshotPlan {
            keyframe: true,
            landmarks: false,
        };
        let sent: Vec<f64> = ob
            .snapshot(0, &f, plan, &w)
            .iter()
            .filter_map(|e| match &e.body {
                Body::Snapshot(s) => Some(s.pixel_sigma_px),
                _ => None,
            })
            .collect();
        assert_eq!(sent, vec![2.5]);
    }

    #[test]
    fn new_tracks_get_descriptors_once_and_keyframes_do_not_overlap() {
        let cfg = PublishConfig::default();
        let mut ob = Outbox::new("f", 2, cfg, 0, 1.0);
        let calib = CameraCalibration::euroc_cam0();
        let mut keyframes = Vec::new();
        let mut snapshots = 0;
        for k in 0..40u64 {
            let t = 1.0 + 0.1 * k as f64;
            // Tracks 0..50 persist; one new track per frame.
            let f = frame(t, k..(k + 50));
            // The window fills over the first 11 frames.
            let w = window(t, (k + 1).min(11));
            let mut envelopes = ob.tracks(k, &f, &calib);
            let full = w.poses.len() == 11;
            let plan = ob.snapshot_due(k, t, w.poses.first().map(|p| p.t_cam), full);
            if let Some(plan) = plan {
                envelopes.extend(ob.snapshot(k, &f, plan, &w));
            }
            let kinds: Vec<MessageKind> = envelopes.iter().map(|e| e.kind()).collect();
            assert_eq!(kinds[0], MessageKind::Tracks);
            let new_desc = envelopes.iter().find_map(|e| match &e.body {
                Body::Descriptors(d) if !d.keyframe => Some(d.entries.len()),
                _ => None,
            });
            assert_eq!(new_desc, Some(if k == 0 { 50 } else { 1 }));
            if plan.is_some_and(|p| p.keyframe) {
                keyframes.push(t);
            }
            snapshots += kinds
                .iter()
                .filter(|k| **k == MessageKind::Snapshot)
                .count();
        }
        // Keyframes at t = 2.0 (the first full window), 3.1, 4.2 (period 1 s,
        // but windows of 1.0 s must not overlap), and one snapshot between
        // keyframes (6 frames after each; the first at the first frame).
        assert_eq!(keyframes.len(), 3, "{keyframes:?}");
        assert!((keyframes[0] - 2.0).abs() < 1e-9, "{keyframes:?}");
        for w in keyframes.windows(2) {
            assert!(w[1] - w[0] > 1.0 + 1e-9);
        }
        assert_eq!(snapshots, 8);
        assert_eq!(ob.sent_counts()[&MessageKind::Tracks], 40);
    }
}
