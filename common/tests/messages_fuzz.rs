//! Property tests of the wire format: decoding arbitrary or damaged bytes never
//! panics, and valid envelopes round-trip exactly.

use common::messages::{
    decode, encode, AgentState, AnsweredWindow, Body, CameraModelWire, CameraPose, DecodeError,
    DescriptorBatch, DescriptorEntry, DistortionWire, Envelope, Heartbeat, HeldWindow,
    HistoryReplay, HistoryRequest, HistoryWindow, Landmark, Limits, PackedCovariance, RequestRef,
    StateSnapshot, TimeRange, TrackFrame, TrackPoint, WindowFrame, WindowObservation, WindowPart,
    DECODE_CLAIM_LIMIT_BYTES, HEADER_LEN, MAGIC, WIRE_VERSION,
};
use nalgebra::Vector3;
use proptest::collection::vec;
use proptest::prelude::*;

fn finite_f64() -> impl Strategy<Value = f64> {
    prop_oneof![
        any::<f64>().prop_filter("finite", |v| v.is_finite()),
        -1e4..1e4f64,
        Just(0.0),
        Just(-0.0),
    ]
}

fn finite_f32() -> impl Strategy<Value = f32> {
    prop_oneof![
        any::<f32>().prop_filter("finite", |v| v.is_finite()),
        -1e3..1e3f32,
    ]
}

fn variance() -> impl Strategy<Value = f32> {
    prop_oneof![1e-30..1e10f32, Just(f32::MIN_POSITIVE), Just(f32::MAX)]
}

fn fleet_id() -> impl Strategy<Value = String> {
    "[a-zA-Z0-9_.-]{1,64}"
}

fn track_point() -> impl Strategy<Value = TrackPoint> {
    (
        any::<u64>(),
        [finite_f32(), finite_f32()],
        [finite_f32(), finite_f32()],
    )
        .prop_map(|(id, uv_px, xy_norm)| TrackPoint { id, uv_px, xy_norm })
}

fn tracks() -> impl Strategy<Value = Body> {
    (any::<u64>(), finite_f64(), vec(track_point(), 0..40)).prop_map(
        |(frame_index, t_s, features)| {
            Body::Tracks(TrackFrame {
                frame_index,
                t_s,
                features,
            })
        },
    )
}

fn descriptor_entry() -> impl Strategy<Value = DescriptorEntry> {
    (any::<u64>(), any::<[u64; 4]>()).prop_map(|(id, bits)| DescriptorEntry { id, bits })
}

fn descriptors() -> impl Strategy<Value = Body> {
    (
        any::<u64>(),
        finite_f64(),
        any::<bool>(),
        vec(descriptor_entry(), 0..40),
    )
        .prop_map(|(frame_index, t_s, keyframe, entries)| {
            Body::Descriptors(DescriptorBatch {
                frame_index,
                t_s,
                keyframe,
                entries,
            })
        })
}

fn camera() -> impl Strategy<Value = CameraModelWire> {
    (
        prop_oneof![
            Just(DistortionWire::Radtan),
            Just(DistortionWire::Equidistant)
        ],
        1e-3..1e4f64,
        1e-3..1e4f64,
        [
            finite_f64(),
            finite_f64(),
            finite_f64(),
            finite_f64(),
            finite_f64(),
            finite_f64(),
        ],
        1..10_000u32,
        1..10_000u32,
    )
        .prop_map(|(model, fx, fy, rest, width, height)| {
            let [cx, cy, d0, d1, d2, d3] = rest;
            CameraModelWire {
                model,
                intrinsics: [fx, fy, cx, cy, d0, d1, d2, d3],
                width,
                height,
            }
        })
}

fn camera_pose() -> impl Strategy<Value = CameraPose> {
    (
        -1e3..1e3f64,
        [-4.0..4.0f64, -4.0..4.0f64, -4.0..4.0f64],
        [finite_f64(), finite_f64(), finite_f64()],
    )
        .prop_map(|(t_s, w, p)| {
            let rot = common::so3::exp_so3(&Vector3::from(w));
            CameraPose::new(t_s, &rot, &Vector3::from(p))
        })
}

fn landmark() -> impl Strategy<Value = Landmark> {
    (
        any::<u64>(),
        [finite_f64(), finite_f64(), finite_f64()],
        (variance(), variance(), variance()),
        [finite_f32(), finite_f32(), finite_f32()],
    )
        .prop_map(|(id, p_m, (xx, yy, zz), [xy, xz, yz])| Landmark {
            id,
            p_m,
            cov_upper: [xx, xy, xz, yy, yz, zz],
        })
}

fn snapshot() -> impl Strategy<Value = Body> {
    state_snapshot().prop_map(Body::Snapshot)
}

fn state_snapshot() -> impl Strategy<Value = StateSnapshot> {
    (0..=8usize)
        .prop_flat_map(|n| {
            let len = PackedCovariance::packed_len(6 * n);
            (
                (any::<u64>(), finite_f64(), any::<bool>(), camera()),
                vec(camera_pose(), n),
                vec(finite_f32(), len),
                vec(variance(), 6 * n),
                vec(landmark(), 0..10),
            )
        })
        .prop_map(|(head, mut clones, mut lower, diag, landmarks)| {
            let (frame_index, t_s, keyframe, camera) = head;
            clones.sort_by(|a, b| a.t_s.total_cmp(&b.t_s));
            let dim = clones.len() * 6;
            for (i, d) in diag.into_iter().enumerate() {
                lower[PackedCovariance::packed_index(i, i)] = d;
            }
            StateSnapshot {
                frame_index,
                t_s,
                keyframe,
                // Any epoch, the full range of the varint.
                frame_epoch: t_s.to_bits(),
                camera,
                // A valid noise, from 0.25 to 2 px.
                pixel_sigma_px: 0.25 * (1 + frame_index % 8) as f64,
                clones,
                covariance: PackedCovariance {
                    dim: dim as u32,
                    lower,
                },
                landmarks,
            }
        })
}

fn window_frame(t_s: f64) -> impl Strategy<Value = WindowFrame> {
    let observation = (any::<u64>(), [finite_f32(), finite_f32()])
        .prop_map(|(id, xy_norm)| WindowObservation { id, xy_norm });
    vec(observation, 0..20).prop_map(move |observations| WindowFrame { t_s, observations })
}

/// Frames at `times` (kept oldest first, one per time).
fn window_frames(mut times: Vec<f64>) -> impl Strategy<Value = Vec<WindowFrame>> {
    times.sort_by(f64::total_cmp);
    times.dedup();
    times.into_iter().map(window_frame).collect::<Vec<_>>()
}

fn time_range() -> impl Strategy<Value = TimeRange> {
    (
        proptest::option::of(-1e3..1e3f64),
        proptest::option::of(0.0..1e3f64),
    )
        .prop_map(|(after_s, length)| TimeRange {
            after_s,
            // Never empty: it ends after it starts.
            up_to_s: length.map(|l| after_s.unwrap_or(0.0) + l + 1e-3),
        })
}

fn history_request() -> impl Strategy<Value = Body> {
    let held = (finite_f64(), any::<u64>(), any::<bool>()).prop_map(
        |(end_s, frames_mask, descriptors)| HeldWindow {
            end_s,
            frames_mask,
            descriptors,
        },
    );
    (
        any::<u32>(),
        any::<u64>(),
        vec(time_range(), 0..8),
        vec(held, 0..20),
    )
        .prop_map(|(to_robot, request_id, ranges, held)| {
            Body::HistoryRequest(HistoryRequest {
                to_robot,
                request_id,
                ranges,
                held,
            })
        })
}

/// A keyframe window: frames at some of its clones' times.
fn history_window() -> impl Strategy<Value = HistoryWindow> {
    (
        state_snapshot(),
        any::<u64>(),
        vec(descriptor_entry(), 0..20),
    )
        .prop_flat_map(|(mut snapshot, mask, descriptors)| {
            snapshot.keyframe = true;
            let times: Vec<f64> = snapshot
                .clones
                .iter()
                .enumerate()
                .filter(|(i, _)| mask & (1 << i) != 0)
                .map(|(_, c)| c.t_s)
                .collect();
            (Just(snapshot), window_frames(times), Just(descriptors))
        })
        .prop_map(|(snapshot, frames, descriptors)| HistoryWindow {
            snapshot,
            frames,
            descriptors,
        })
}

fn window_part() -> impl Strategy<Value = WindowPart> {
    (
        finite_f64(),
        vec(-1e3..1e3f64, 0..8),
        vec(descriptor_entry(), 0..20),
    )
        .prop_flat_map(|(end_s, times, descriptors)| {
            (Just(end_s), window_frames(times), Just(descriptors))
        })
        .prop_map(|(end_s, frames, descriptors)| WindowPart {
            end_s,
            frames,
            descriptors,
        })
}

fn history_replay() -> impl Strategy<Value = Body> {
    let request = (any::<u32>(), any::<u64>())
        .prop_map(|(robot, request_id)| RequestRef { robot, request_id });
    let answered =
        (finite_f64(), any::<u32>(), any::<bool>()).prop_map(|(end_s, frames, descriptors)| {
            AnsweredWindow {
                end_s,
                frames,
                descriptors,
            }
        });
    // A whole window, a part, or neither (a message that only completes).
    let carried = prop_oneof![
        history_window().prop_map(|w| (Some(w), None)),
        window_part().prop_map(|p| (None, Some(p))),
        Just((None, None)),
    ];
    (
        vec(any::<u32>(), 0..8),
        carried,
        vec(request, 0..8),
        vec(answered, 0..20),
    )
        .prop_map(|(for_robots, (window, part), completes, answered)| {
            Body::HistoryReplay(Box::new(HistoryReplay {
                for_robots,
                window,
                part,
                completes,
                answered,
            }))
        })
}

fn heartbeat() -> impl Strategy<Value = Body> {
    (
        prop_oneof![
            Just(AgentState::Starting),
            Just(AgentState::Running),
            Just(AgentState::Finished),
            Just(AgentState::Settled)
        ],
        any::<u64>(),
        proptest::option::of(any::<u64>()),
        proptest::option::of(finite_f64()),
        proptest::option::of(finite_f64()),
    )
        .prop_map(
            |(state, frames_done, last_frame_index, last_t_s, newest_window_end_s)| {
                Body::Heartbeat(Heartbeat {
                    state,
                    frames_done,
                    last_frame_index,
                    last_t_s,
                    newest_window_end_s,
                })
            },
        )
}

fn envelope() -> BoxedStrategy<Envelope> {
    (
        fleet_id(),
        any::<u32>(),
        any::<u64>(),
        finite_f64(),
        prop_oneof![
            tracks().boxed(),
            descriptors().boxed(),
            snapshot().boxed(),
            heartbeat().boxed(),
            history_request().boxed(),
            history_replay().boxed()
        ],
    )
        .prop_map(|(fleet_id, robot_id, seq, stamp_s, body)| Envelope {
            fleet_id,
            robot_id,
            seq,
            stamp_s,
            sent_wall_ns: seq.wrapping_mul(7),
            body,
        })
        // Boxed, and each kind of body too: unboxed, an envelope's value tree
        // is built on the stack, and a debug build overflowed the test
        // thread's 2 MiB (either box alone was not enough).
        .boxed()
}

/// Decoding either fails or returns an envelope that is valid and re-encodes to
/// the same bytes (so nothing was lost or invented).
fn check_decode(bytes: &[u8]) -> Result<(), TestCaseError> {
    if let Ok(env) = decode(bytes) {
        prop_assert!(env.validate(&Limits::default()).is_ok());
        let again = encode(&env).map_err(|e| TestCaseError::fail(e.to_string()))?;
        prop_assert_eq!(decode(&again).ok(), Some(env));
    }
    Ok(())
}

fn header() -> Vec<u8> {
    let mut h = MAGIC.to_vec();
    h.extend_from_slice(&WIRE_VERSION.to_le_bytes());
    h
}

proptest! {
    #![proptest_config(ProptestConfig { cases: 2048, ..ProptestConfig::default() })]

    /// (1) Arbitrary bytes never make decode panic.
    #[test]
    fn arbitrary_bytes_never_panic(bytes in vec(any::<u8>(), 0..4096)) {
        check_decode(&bytes)?;
    }

    /// (1b) The same behind a valid header, so the payload decoder is exercised.
    #[test]
    fn arbitrary_payload_never_panics(payload in vec(any::<u8>(), 0..4096)) {
        let mut bytes = header();
        bytes.extend(payload);
        check_decode(&bytes)?;
    }

    /// (2) Valid envelopes round-trip exactly (bit-exact floats included).
    #[test]
    fn valid_envelopes_round_trip(env in envelope()) {
        let bytes = encode(&env).map_err(|e| TestCaseError::fail(e.to_string()))?;
        let back = decode(&bytes).map_err(|e| TestCaseError::fail(e.to_string()))?;
        // Bit-exact: re-encoding gives the same bytes (PartialEq alone would
        // equate 0.0 and -0.0).
        prop_assert_eq!(encode(&back).ok(), Some(bytes));
        prop_assert_eq!(back, env);
    }

    /// (3) A mutated, truncated or extended valid encoding decodes to a valid
    /// envelope or fails; it never panics.
    #[test]
    fn damaged_encodings_never_panic(
        env in envelope(),
        mutations in vec((any::<prop::sample::Index>(), any::<u8>()), 8),
        cuts in vec(any::<prop::sample::Index>(), 8),
        byte in any::<u8>(),
    ) {
        let bytes = encode(&env).map_err(|e| TestCaseError::fail(e.to_string()))?;

        for (at, b) in mutations {
            let mut mutated = bytes.clone();
            let i = at.index(mutated.len());
            mutated[i] = b;
            check_decode(&mutated)?;
        }

        for cut in cuts {
            let truncated = &bytes[..cut.index(bytes.len())];
            prop_assert!(decode(truncated).is_err());
        }

        let mut extended = bytes.clone();
        extended.push(byte);
        prop_assert!(
            matches!(decode(&extended), Err(DecodeError::TrailingBytes { count: 1 })),
            "appended byte accepted"
        );
    }

    /// (4) A length prefix beyond the decode limit, for the fleet id (a string)
    /// or for a vector, is refused without reading further.
    #[test]
    fn huge_length_prefixes_are_refused(
        huge in (DECODE_CLAIM_LIMIT_BYTES as u64 + 1)..=u64::MAX,
        in_vec in any::<bool>(),
        tail in vec(any::<u8>(), 0..64),
    ) {
        let mut bytes = if in_vec {
            // An empty track frame ends with its features' length prefix (0).
            let env = Envelope {
                fleet_id: "f".into(),
                robot_id: 1,
                seq: 0,
                stamp_s: 0.0,
                sent_wall_ns: 0,
                body: Body::Tracks(TrackFrame::default()),
            };
            let mut b = encode(&env).map_err(|e| TestCaseError::fail(e.to_string()))?;
            prop_assert_eq!(b.pop(), Some(0));
            b
        } else {
            header()
        };
        bytes.push(253);
        bytes.extend_from_slice(&huge.to_le_bytes());
        bytes.extend(tail);
        let result = decode(&bytes);
        let refused_at_length = match &result {
            Err(DecodeError::LimitExceeded { .. }) => true,
            Err(e @ DecodeError::Malformed(_)) => e.to_string().contains("invalid length"),
            _ => false,
        };
        prop_assert!(refused_at_length, "{:?}", result);
    }
}

#[test]
fn header_length_is_six() {
    assert_eq!(HEADER_LEN, header().len());
}
