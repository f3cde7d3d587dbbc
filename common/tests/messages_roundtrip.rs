//! Round trips of every message kind through the wire format, bit-exact.

// The round-trip helper outside #[test] functions fails the test by unwrapping.
#![allow(clippy::unwrap_used)]

use common::descriptor::Descriptor;
use common::messages::{
    decode, encode, samples, AgentState, Body, CameraModelWire, CameraPose, DescriptorBatch,
    DescriptorEntry, DistortionWire, Envelope, Heartbeat, Landmark, MessageKind, PackedCovariance,
    StateSnapshot, TrackFrame, TrackPoint, MAGIC, WIRE_VERSION,
};
use nalgebra::{DMatrix, Matrix3, Vector3};

/// f64 values whose bits a lossy encoding would change.
const AWKWARD: [f64; 6] = [
    0.1 + 0.2,
    -0.0,
    f64::MIN_POSITIVE / 3.0, // subnormal
    1e300,
    1_403_715_273.262_123_4,
    -std::f64::consts::PI,
];

fn envelope(body: Body) -> Envelope {
    Envelope {
        fleet_id: "fleet-A".into(),
        robot_id: 7,
        seq: u64::MAX - 1,
        stamp_s: AWKWARD[4],
        sent_wall_ns: 1_700_000_000_000_000_000,
        body,
    }
}

fn round_trip(env: &Envelope) -> Envelope {
    let bytes = encode(env).unwrap();
    let back = decode(&bytes).unwrap();
    assert_eq!(&back, env);
    assert_eq!(back.stamp_s.to_bits(), env.stamp_s.to_bits());
    back
}

#[test]
fn header_is_magic_version_then_bincode_standard() {
    let env = samples::heartbeat(12);
    let bytes = encode(&env).unwrap();
    assert_eq!(&bytes[..4], b"FVIO");
    assert_eq!(bytes[..4], MAGIC);
    assert_eq!(u16::from_le_bytes([bytes[4], bytes[5]]), WIRE_VERSION);
    assert_eq!(WIRE_VERSION, 7);
    let payload = bincode::serde::encode_to_vec(&env, bincode::config::standard()).unwrap();
    assert_eq!(&bytes[6..], &payload[..]);
}

#[test]
fn tracks_round_trip() {
    let features = (0..5u64)
        .map(|k| TrackPoint {
            id: k * 1000,
            uv_px: [k as f32 + 0.123, 479.999],
            xy_norm: [-0.0, f32::MIN_POSITIVE],
        })
        .collect();
    for t_s in AWKWARD {
        let env = envelope(Body::Tracks(TrackFrame {
            frame_index: 42,
            t_s,
            features: Vec::clone(&features),
        }));
        assert_eq!(env.kind(), MessageKind::Tracks);
        let back = round_trip(&env);
        let Body::Tracks(t) = back.body else {
            panic!("not tracks")
        };
        assert_eq!(t.t_s.to_bits(), t_s.to_bits());
        for (a, b) in t.features.iter().zip(&features) {
            assert_eq!(a.uv_px.map(f32::to_bits), b.uv_px.map(f32::to_bits));
            assert_eq!(a.xy_norm.map(f32::to_bits), b.xy_norm.map(f32::to_bits));
        }
    }
    round_trip(&samples::tracks(3, 100));
    round_trip(&envelope(Body::Tracks(TrackFrame::default())));
}

#[test]
fn descriptors_round_trip() {
    let entries = vec![
        DescriptorEntry::from((1, Descriptor([0, u64::MAX, 0x0123_4567_89ab_cdef, 1]))),
        DescriptorEntry::new(u64::MAX, Descriptor([u64::MAX; 4])),
    ];
    let env = envelope(Body::Descriptors(DescriptorBatch {
        frame_index: 9,
        t_s: AWKWARD[0],
        keyframe: true,
        entries: entries.clone(),
    }));
    assert_eq!(env.kind(), MessageKind::Descriptors);
    let Body::Descriptors(d) = round_trip(&env).body else {
        panic!("not descriptors")
    };
    assert_eq!(d.entries, entries);
    assert_eq!(d.t_s.to_bits(), AWKWARD[0].to_bits());
    round_trip(&samples::descriptors(3, 100, true));
}

#[test]
fn snapshot_round_trip_is_bit_exact() {
    let clones: Vec<CameraPose> = (0..3)
        .map(|k| {
            let rot = common::so3::exp_so3(&Vector3::new(0.1 * k as f64, -0.7, 2.9));
            let p = Vector3::new(AWKWARD[0] * k as f64, AWKWARD[2], AWKWARD[5]);
            CameraPose::new(AWKWARD[4] + 0.1 * k as f64, &rot, &p)
        })
        .collect();
    let dim = 18;
    let p = DMatrix::from_fn(dim, dim, |i, j| {
        if i == j {
            1e-4 * (1 + i) as f64
        } else {
            1e-7 / (1 + i + j) as f64
        }
    });
    let covariance = PackedCovariance::from_dmatrix(&p).unwrap();
    let cov3 = Matrix3::new(1e-3, 2e-5, 0.0, 2e-5, 2e-3, -1e-5, 0.0, -1e-5, 4e-3);
    let landmarks = vec![Landmark::new(
        77,
        &Vector3::new(AWKWARD[3], -0.0, 1.0),
        &cov3,
    )];
    let camera = CameraModelWire {
        model: DistortionWire::Equidistant,
        intrinsics: [
            190.97, 190.97, 254.93, 256.89, 0.0034, 0.0007, -0.0020, 0.0002,
        ],
        width: 512,
        height: 512,
    };
    let snapshot = StateSnapshot {
        frame_index: 1234,
        t_s: AWKWARD[4],
        keyframe: false,
        frame_epoch: u64::MAX,
        camera,
        pixel_sigma_px: AWKWARD[0],
        clones: clones.clone(),
        covariance: covariance.clone(),
        landmarks: landmarks.clone(),
    };
    let env = envelope(Body::Snapshot(snapshot));
    assert_eq!(env.kind(), MessageKind::Snapshot);
    let Body::Snapshot(s) = round_trip(&env).body else {
        panic!("not a snapshot")
    };
    assert_eq!(s.pixel_sigma_px.to_bits(), AWKWARD[0].to_bits());
    for (a, b) in s.clones.iter().zip(&clones) {
        assert_eq!(a.t_s.to_bits(), b.t_s.to_bits());
        assert_eq!(a.q_xyzw.map(f64::to_bits), b.q_xyzw.map(f64::to_bits));
        assert_eq!(a.p_m.map(f64::to_bits), b.p_m.map(f64::to_bits));
    }
    assert_eq!(
        s.landmarks[0].p_m.map(f64::to_bits),
        landmarks[0].p_m.map(f64::to_bits)
    );
    assert_eq!(
        s.camera.intrinsics.map(f64::to_bits),
        camera.intrinsics.map(f64::to_bits)
    );
    assert_eq!(s.covariance, covariance);
    // The unpacked covariance is the symmetric input to f32 precision.
    let back = s.covariance.to_dmatrix();
    assert_eq!(back, back.transpose());
    assert!(((back - &p).abs().max()) < 1e-7 * p.abs().max());
    round_trip(&samples::snapshot(100, 11, 50, true));
}

#[test]
fn heartbeat_round_trip() {
    for (state, last_frame_index, last_t_s) in [
        (AgentState::Starting, None, None),
        (AgentState::Running, Some(41), Some(AWKWARD[0])),
        (AgentState::Finished, Some(u64::MAX), Some(AWKWARD[2])),
    ] {
        let env = envelope(Body::Heartbeat(Heartbeat {
            state,
            frames_done: last_frame_index.map_or(0, |f: u64| f.saturating_add(1)),
            last_frame_index,
            last_t_s,
            newest_window_end_s: last_t_s.map(|t| t - 0.5),
        }));
        assert_eq!(env.kind(), MessageKind::Heartbeat);
        let Body::Heartbeat(h) = round_trip(&env).body else {
            panic!("not a heartbeat")
        };
        assert_eq!(h.last_t_s.map(f64::to_bits), last_t_s.map(f64::to_bits));
    }
}

#[test]
fn kinds_match_key_segments() {
    let kinds: Vec<MessageKind> = [
        samples::tracks(0, 1),
        samples::descriptors(0, 1, false),
        samples::snapshot(0, 1, 0, false),
        samples::heartbeat(0),
        samples::history_request(0.0),
        samples::history_replay(20, 1),
    ]
    .iter()
    .map(Envelope::kind)
    .collect();
    assert_eq!(kinds, MessageKind::ALL);
    for k in MessageKind::ALL {
        assert_eq!(MessageKind::from_segment(k.as_str()), Some(k));
    }
}
