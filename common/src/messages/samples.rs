//! Realistic, valid messages of each kind (deterministic, no randomness), for
//! tests, benchmarks and the size budgets below
//! (`cargo run -p common --release --example message_sizes` prints the sizes).
//!
//! Budgets hold for track ids below 2³² and fleet ids up to the 64-byte maximum
//! (the samples use a 17-byte one).
//!
//! They model an EuRoC-like run: a 752x480 radtan camera at 10 Hz, track ids in
//! the thousands, an 11-clone window one frame apart, landmarks a few metres away.

use nalgebra::{DMatrix, Matrix3, Vector2, Vector3};

use super::{
    AgentState, AnsweredWindow, Body, CameraModelWire, CameraPose, DescriptorBatch,
    DescriptorEntry, Envelope, Heartbeat, HeldWindow, HistoryReplay, HistoryRequest, HistoryWindow,
    Landmark, PackedCovariance, RequestRef, StateSnapshot, TimeRange, TrackFrame, TrackPoint,
    WindowFrame, WindowObservation, WindowPart,
};
use crate::camera::CameraModel;
use crate::descriptor::Descriptor;
use crate::so3;

/// Budget of an encoded [`TrackFrame`] of 100 features (track ids below 2³²).
pub const TRACKS_100_BUDGET_BYTES: usize = 2200;

/// Budget of an encoded [`DescriptorBatch`] of 10 entries.
pub const DESCRIPTORS_10_BUDGET_BYTES: usize = 500;

/// Budget of an encoded [`DescriptorBatch`] of 100 entries (a keyframe).
pub const DESCRIPTORS_100_BUDGET_BYTES: usize = 4000;

/// Budget of an encoded 11-clone [`StateSnapshot`] (66x66 covariance) without landmarks.
pub const SNAPSHOT_11_BUDGET_BYTES: usize = 10_000;

/// Budget of an encoded 11-clone [`StateSnapshot`] with 50 landmarks.
pub const SNAPSHOT_11_50_BUDGET_BYTES: usize = 13_000;

/// Budget of an encoded [`Heartbeat`].
pub const HEARTBEAT_BUDGET_BYTES: usize = 128;

/// Budget of an encoded [`HistoryRequest`] of one range.
pub const HISTORY_REQUEST_BUDGET_BYTES: usize = 128;

/// Budget of an encoded [`HistoryReplay`] of an 11-clone keyframe window with
/// 50 landmarks and 100 tracks measured in each frame.
pub const HISTORY_REPLAY_11_100_BUDGET_BYTES: usize = 33_000;

/// Frame rate of the samples, in Hz.
pub const FRAME_RATE_HZ: f64 = 10.0;

/// A deterministic value in `[-1, 1)` for index `i` and stream `s` (a hash).
fn unit(i: u64, s: u64) -> f64 {
    let mut x = i
        .wrapping_mul(0x9e37_79b9_7f4a_7c15)
        .wrapping_add(s.wrapping_mul(0xbf58_476d_1ce4_e5b9));
    x ^= x >> 31;
    x = x.wrapping_mul(0x94d0_49bb_1331_11eb);
    x ^= x >> 29;
    (x >> 11) as f64 / (1u64 << 52) as f64 - 1.0
}

/// First track id of the samples (a run some minutes in).
const FIRST_ID: u64 = 5000;

fn envelope(robot_id: u32, seq: u64, stamp_s: f64, body: Body) -> Envelope {
    Envelope {
        fleet_id: "euroc-vicon-room1".into(),
        robot_id,
        seq,
        stamp_s,
        sent_wall_ns: 0,
        body,
    }
}

fn frame_time(frame_index: u64) -> f64 {
    1_403_715_273.262 + frame_index as f64 / FRAME_RATE_HZ
}

/// A track frame of `n` features spread over the EuRoC cam0 image.
pub fn tracks(frame_index: u64, n: usize) -> Envelope {
    let cam = CameraModel::euroc_cam0();
    let features = (0..n as u64)
        .map(|k| {
            let xy = Vector2::new(0.6 * unit(k, 1), 0.4 * unit(k, 2));
            TrackPoint::new(FIRST_ID + 3 * k, &cam.distort(&xy), &xy)
        })
        .collect();
    let t_s = frame_time(frame_index);
    envelope(
        1,
        frame_index,
        t_s + 0.004,
        Body::Tracks(TrackFrame {
            frame_index,
            t_s,
            features,
        }),
    )
}

/// A descriptor batch of `n` entries.
pub fn descriptors(frame_index: u64, n: usize, keyframe: bool) -> Envelope {
    let entries = descriptor_entries(n);
    let t_s = frame_time(frame_index);
    envelope(
        1,
        frame_index,
        t_s + 0.006,
        Body::Descriptors(DescriptorBatch {
            frame_index,
            t_s,
            keyframe,
            entries,
        }),
    )
}

/// Descriptors of the first `n` sample tracks.
fn descriptor_entries(n: usize) -> Vec<DescriptorEntry> {
    (0..n as u64)
        .map(|k| {
            let words = [1, 2, 3, 4].map(|s| unit(k, 10 + s).to_bits());
            DescriptorEntry::new(FIRST_ID + 3 * k, Descriptor(words))
        })
        .collect()
}

/// A snapshot of a window of `clones` camera poses (one frame apart, the newest
/// at `frame_index`) with a dense, positive-definite covariance and `landmarks`
/// SLAM landmarks.
pub fn snapshot(frame_index: u64, clones: usize, landmarks: usize, keyframe: bool) -> Envelope {
    let t_s = frame_time(frame_index);
    let body = snapshot_body(frame_index, clones, landmarks, keyframe);
    envelope(1, frame_index / 5, t_s + 0.02, Body::Snapshot(body))
}

/// The body of [`snapshot`].
fn snapshot_body(
    frame_index: u64,
    clones: usize,
    landmarks: usize,
    keyframe: bool,
) -> StateSnapshot {
    let first = frame_index.saturating_sub(clones.saturating_sub(1) as u64);
    let poses: Vec<CameraPose> = (0..clones as u64)
        .map(|k| {
            let f = first + k;
            let t = f as f64 / FRAME_RATE_HZ;
            let rot = so3::exp_so3(&Vector3::new(0.1 * t.sin(), 0.05 * t.cos(), 0.3 * t));
            let p = Vector3::new(
                2.0 * (0.2 * t).cos(),
                2.0 * (0.2 * t).sin(),
                1.2 + 0.1 * t.sin(),
            );
            CameraPose::new(frame_time(f), &rot, &p)
        })
        .collect();
    let dim = 6 * clones;
    // P = A Aᵀ / dim + diag: dense, correlated, positive definite; orientation
    // variances about (0.5°)², position variances about (5 cm)².
    let a = DMatrix::from_fn(dim, dim, |i, j| unit((i * dim + j) as u64, 7));
    let scale = DMatrix::from_fn(dim, 1, |i, _| if i % 6 < 3 { 0.0087 } else { 0.05 });
    let mut p = &a * a.transpose() / dim as f64;
    for i in 0..dim {
        p[(i, i)] += 0.5;
    }
    let p = DMatrix::from_fn(dim, dim, |i, j| p[(i, j)] * scale[i] * scale[j]);
    let covariance = PackedCovariance::from_dmatrix(&p).unwrap_or_default();
    let lms = (0..landmarks as u64)
        .map(|k| {
            let pos = Vector3::new(4.0 * unit(k, 20), 4.0 * unit(k, 21), 1.5 + unit(k, 22));
            let cov = Matrix3::new(4e-4, 1e-5, 2e-5, 1e-5, 6e-4, -1e-5, 2e-5, -1e-5, 9e-4);
            Landmark::new(FIRST_ID + 7 * k, &pos, &cov)
        })
        .collect();
    StateSnapshot {
        frame_index,
        t_s: frame_time(frame_index),
        keyframe,
        // A live robot in a frame of its own names it by its start's wall
        // clock in ns: the largest varint a snapshot's epoch takes.
        frame_epoch: 1_764_460_800_000_000_000,
        camera: CameraModelWire::from(&CameraModel::euroc_cam0()),
        pixel_sigma_px: 1.0,
        clones: poses,
        covariance,
        landmarks: lms,
    }
}

/// A request for the keyframe windows ending after `after_s`.
pub fn history_request(after_s: f64) -> Envelope {
    envelope(
        1,
        0,
        after_s + 30.0,
        Body::HistoryRequest(HistoryRequest {
            to_robot: 2,
            request_id: 3,
            ranges: vec![TimeRange {
                after_s: Some(after_s),
                up_to_s: None,
            }],
            held: Vec::new(),
        }),
    )
}

/// A replayed keyframe window ending at `frame_index`: the 11-clone keyframe
/// snapshot with 50 landmarks, `n` tracks measured in each of its frames and
/// their descriptors, completing one request.
pub fn history_replay(frame_index: u64, n: usize) -> Envelope {
    let snapshot = snapshot_body(frame_index, 11, 50, true);
    let frames = snapshot
        .clones
        .iter()
        .enumerate()
        .map(|(k, c)| WindowFrame {
            t_s: c.t_s,
            observations: (0..n as u64)
                .map(|i| WindowObservation {
                    id: FIRST_ID + 3 * i + k as u64 / 4,
                    xy_norm: [
                        0.4 * unit(i, 30 + k as u64) as f32,
                        0.3 * unit(i, 50) as f32,
                    ],
                })
                .collect(),
        })
        .collect();
    envelope(
        1,
        0,
        frame_time(frame_index) + 120.0,
        Body::HistoryReplay(Box::new(HistoryReplay {
            for_robots: vec![2],
            window: Some(HistoryWindow {
                snapshot,
                frames,
                descriptors: descriptor_entries(n),
            }),
            part: None,
            completes: vec![RequestRef {
                robot: 2,
                request_id: 3,
            }],
            answered: (0..40)
                .map(|i| AnsweredWindow {
                    end_s: frame_time(frame_index) - 0.5 * f64::from(i),
                    frames: 11,
                    descriptors: true,
                })
                .rev()
                .collect(),
        })),
    )
}

/// The parts of the window of [`history_replay`] a requester lacked: its
/// frames at the clones `missing` (indices, oldest first) and, if
/// `descriptors`, the keyframe's descriptors.
pub fn history_part(frame_index: u64, n: usize, missing: &[usize], descriptors: bool) -> Envelope {
    let mut env = history_replay(frame_index, n);
    if let Body::HistoryReplay(r) = &mut env.body {
        if let Some(w) = r.window.take() {
            r.part = Some(WindowPart {
                end_s: w.end_s(),
                frames: missing
                    .iter()
                    .filter_map(|&i| w.frames.get(i).cloned())
                    .collect(),
                descriptors: if descriptors {
                    w.descriptors
                } else {
                    Vec::new()
                },
            });
        }
    }
    env
}

/// A request for the windows after `after_s`, holding `held` of them short
/// of their newest frame.
pub fn history_request_holding(after_s: f64, held: usize) -> Envelope {
    let mut env = history_request(after_s);
    if let Body::HistoryRequest(r) = &mut env.body {
        r.held = (0..held)
            .map(|i| HeldWindow {
                end_s: after_s + 1.1 * (i + 1) as f64,
                frames_mask: (1 << 10) - 1,
                descriptors: i % 2 == 0,
            })
            .collect();
    }
    env
}

/// A heartbeat of a running agent.
pub fn heartbeat(frame_index: u64) -> Envelope {
    let t_s = frame_time(frame_index);
    envelope(
        1,
        frame_index / 10,
        t_s + 0.001,
        Body::Heartbeat(Heartbeat {
            state: AgentState::Running,
            frames_done: frame_index + 1,
            last_frame_index: Some(frame_index),
            last_t_s: Some(t_s),
            newest_window_end_s: None,
        }),
    )
}

#[cfg(test)]
mod tests {
    use super::super::{decode, encode};
    use super::*;

    fn size(env: &Envelope) -> usize {
        let bytes = encode(env).unwrap();
        assert_eq!(&decode(&bytes).unwrap(), env);
        bytes.len()
    }

    #[test]
    fn sizes_stay_within_budgets() {
        let f = 3000;
        assert!(size(&tracks(f, 100)) < TRACKS_100_BUDGET_BYTES);
        assert!(size(&descriptors(f, 10, false)) < DESCRIPTORS_10_BUDGET_BYTES);
        assert!(size(&descriptors(f, 100, true)) < DESCRIPTORS_100_BUDGET_BYTES);
        assert!(size(&snapshot(f, 11, 0, false)) < SNAPSHOT_11_BUDGET_BYTES);
        assert!(size(&snapshot(f, 11, 50, true)) < SNAPSHOT_11_50_BUDGET_BYTES);
        assert!(size(&heartbeat(f)) < HEARTBEAT_BUDGET_BYTES);
        assert!(size(&history_request(100.0)) < HISTORY_REQUEST_BUDGET_BYTES);
        assert!(size(&history_replay(f, 100)) < HISTORY_REPLAY_11_100_BUDGET_BYTES);
    }

    /// The same message with a 64-byte fleet id and ids just below 2³².
    fn worst_case(mut env: Envelope) -> Envelope {
        env.fleet_id = "f".repeat(super::super::MAX_FLEET_ID_BYTES);
        let big = |id: &mut u64| *id += u64::from(u32::MAX) - 100_000;
        match &mut env.body {
            Body::Tracks(t) => t.features.iter_mut().for_each(|f| big(&mut f.id)),
            Body::Descriptors(d) => d.entries.iter_mut().for_each(|e| big(&mut e.id)),
            Body::Snapshot(s) => s.landmarks.iter_mut().for_each(|l| big(&mut l.id)),
            Body::Heartbeat(_) | Body::HistoryRequest(_) => {}
            Body::HistoryReplay(r) => {
                if let Some(w) = r.window.as_mut() {
                    w.snapshot.landmarks.iter_mut().for_each(|l| big(&mut l.id));
                    w.descriptors.iter_mut().for_each(|e| big(&mut e.id));
                    for f in &mut w.frames {
                        f.observations.iter_mut().for_each(|o| big(&mut o.id));
                    }
                }
            }
        }
        env
    }

    #[test]
    fn budgets_hold_for_32_bit_ids_and_longest_fleet_id() {
        let f = 3000;
        assert!(size(&worst_case(tracks(f, 100))) < TRACKS_100_BUDGET_BYTES);
        assert!(size(&worst_case(descriptors(f, 10, false))) < DESCRIPTORS_10_BUDGET_BYTES);
        assert!(size(&worst_case(descriptors(f, 100, true))) < DESCRIPTORS_100_BUDGET_BYTES);
        assert!(size(&worst_case(snapshot(f, 11, 0, false))) < SNAPSHOT_11_BUDGET_BYTES);
        assert!(size(&worst_case(snapshot(f, 11, 50, true))) < SNAPSHOT_11_50_BUDGET_BYTES);
        assert!(size(&worst_case(heartbeat(f))) < HEARTBEAT_BUDGET_BYTES);
        assert!(size(&worst_case(history_request(1e4))) < HISTORY_REQUEST_BUDGET_BYTES);
        assert!(size(&worst_case(history_replay(f, 100))) < HISTORY_REPLAY_11_100_BUDGET_BYTES);
    }

    #[test]
    fn largest_valid_snapshot_decodes_under_default_limits() {
        let limits = super::super::Limits::default();
        let env = snapshot(100, limits.max_clones, limits.max_landmarks, true);
        let bytes = encode(&env).unwrap();
        assert!(bytes.len() < limits.max_message_bytes);
        assert_eq!(decode(&bytes).unwrap(), env);
    }
}
