//! Every way a message is refused, each with its own error.

// Helpers outside #[test] functions build fixtures that are known to encode.
#![allow(clippy::unwrap_used)]

use common::messages::{
    decode, decode_with, encode, encode_with, samples, Body, CameraPose, DecodeError, EncodeError,
    Envelope, Limits, PackedCovariance, ValidationError, DECODE_CLAIM_LIMIT_BYTES, HEADER_LEN,
    MAGIC, SUPPORTED_VERSIONS, WIRE_VERSION,
};

/// The wire encoding without validation: what a buggy or hostile peer could send.
fn raw_encode(env: &Envelope) -> Vec<u8> {
    let mut out = MAGIC.to_vec();
    out.extend_from_slice(&WIRE_VERSION.to_le_bytes());
    out.extend(bincode::serde::encode_to_vec(env, bincode::config::standard()).unwrap());
    out
}

/// bincode's varint of `v` as a u64 (marker 253, then 8 little-endian bytes).
fn varint_u64(v: u64) -> Vec<u8> {
    let mut out = vec![253u8];
    out.extend_from_slice(&v.to_le_bytes());
    out
}

fn snapshot_body(env: &mut Envelope) -> &mut common::messages::StateSnapshot {
    match &mut env.body {
        Body::Snapshot(s) => s,
        _ => panic!("not a snapshot"),
    }
}

fn invalid(bytes: &[u8]) -> ValidationError {
    match decode(bytes) {
        Err(DecodeError::Invalid(e)) => e,
        other => panic!("expected a validation error, got {other:?}"),
    }
}

#[test]
fn bad_magic() {
    let mut bytes = encode(&samples::heartbeat(1)).unwrap();
    bytes[0] = b'X';
    let err = decode(&bytes).unwrap_err();
    assert!(matches!(err, DecodeError::BadMagic { found } if &found == b"XVIO"));
    assert!(err.to_string().contains("bad magic"), "{err}");
}

#[test]
fn other_versions_are_refused_naming_both_versions() {
    for other in [WIRE_VERSION - 1, WIRE_VERSION + 1] {
        let mut bytes = encode(&samples::heartbeat(1)).unwrap();
        bytes[4..6].copy_from_slice(&other.to_le_bytes());
        let err = decode(&bytes).unwrap_err();
        assert!(matches!(
            err,
            DecodeError::UnsupportedVersion { found, supported } if found == other && supported == SUPPORTED_VERSIONS
        ));
        let msg = err.to_string();
        assert!(
            msg.contains(&format!("version {other}")) && msg.contains(&format!("[{WIRE_VERSION}]")),
            "{msg}"
        );
    }
}

#[test]
fn a_covariance_may_end_with_the_intrinsics_but_nothing_else() {
    let mut env = samples::snapshot(20, 11, 0, false);
    let with = |dim: usize| {
        PackedCovariance::from_dmatrix(&nalgebra::DMatrix::identity(dim, dim)).unwrap()
    };
    snapshot_body(&mut env).covariance = with(66 + 8);
    assert!(decode(&raw_encode(&env)).is_ok());
    snapshot_body(&mut env).covariance = with(66 + 3);
    assert!(matches!(
        invalid(&raw_encode(&env)),
        ValidationError::CovarianceDim { dim: 69, .. }
    ));
}

#[test]
fn trailing_byte() {
    let mut bytes = encode(&samples::tracks(1, 10)).unwrap();
    bytes.push(0);
    assert!(matches!(
        decode(&bytes),
        Err(DecodeError::TrailingBytes { count: 1 })
    ));
}

#[test]
fn shorter_than_the_header() {
    for len in 0..HEADER_LEN {
        assert!(matches!(
            decode(&MAGIC[..len.min(4)]),
            Err(DecodeError::TooShort { .. })
        ));
    }
    // A bare header has no envelope.
    let bytes = &encode(&samples::heartbeat(1)).unwrap()[..HEADER_LEN];
    assert!(matches!(decode(bytes), Err(DecodeError::Malformed(_))));
}

#[test]
fn oversize_is_refused_before_anything_else() {
    // Not even a valid header: the size check comes first.
    let bytes = vec![0u8; (1 << 20) + 1];
    assert!(matches!(
        decode(&bytes),
        Err(DecodeError::TooLarge { len, max: 1048576 }) if len == (1 << 20) + 1
    ));
    let small = Limits {
        max_message_bytes: 1000,
        ..Limits::default()
    };
    let env = samples::tracks(1, 100);
    let bytes = encode(&env).unwrap();
    assert!(matches!(
        decode_with(&bytes, &small),
        Err(DecodeError::TooLarge { max: 1000, .. })
    ));
    assert!(matches!(
        encode_with(&env, &small),
        Err(EncodeError::TooLarge { max: 1000, .. })
    ));
}

#[test]
fn nan_in_a_pose_is_refused_with_its_field_name() {
    let mut env = samples::snapshot(20, 11, 0, false);
    snapshot_body(&mut env).clones[4].p_m[1] = f64::NAN;
    let err = invalid(&raw_encode(&env));
    assert!(
        matches!(&err, ValidationError::NonFinite { field, value } if field == "snapshot.clones[4].p_m[1]" && value.is_nan()),
        "{err}"
    );
    assert!(err
        .to_string()
        .contains("snapshot.clones[4].p_m[1] is not finite"));
    // And the sender refuses to send it.
    assert!(matches!(encode(&env), Err(EncodeError::Invalid(_))));

    let mut env = samples::snapshot(20, 11, 0, false);
    snapshot_body(&mut env).clones[0].q_xyzw[3] = f64::INFINITY;
    assert!(matches!(
        invalid(&raw_encode(&env)),
        ValidationError::NonFinite { field, .. } if field == "snapshot.clones[0].q_xyzw[3]"
    ));
}

#[test]
fn nan_elsewhere_is_refused() {
    let mut env = samples::tracks(1, 5);
    if let Body::Tracks(t) = &mut env.body {
        t.features[2].xy_norm[0] = f32::NAN;
    }
    assert!(matches!(
        invalid(&raw_encode(&env)),
        ValidationError::NonFinite { field, .. } if field == "tracks.features[2].xy_norm[0]"
    ));
    let mut env = samples::heartbeat(1);
    env.stamp_s = f64::NEG_INFINITY;
    assert!(matches!(
        invalid(&raw_encode(&env)),
        ValidationError::NonFinite { field, .. } if field == "stamp_s"
    ));
    let mut env = samples::snapshot(20, 2, 3, false);
    snapshot_body(&mut env).covariance.lower[4] = f32::NAN;
    assert!(matches!(
        invalid(&raw_encode(&env)),
        ValidationError::NonFinite { field, .. } if field == "snapshot.covariance[2][1]"
    ));
    for bad in [0.0, -1.0, f64::NAN, f64::INFINITY, 101.0] {
        let mut env = samples::snapshot(20, 2, 3, false);
        snapshot_body(&mut env).pixel_sigma_px = bad;
        let err = invalid(&raw_encode(&env));
        assert!(
            matches!(err, ValidationError::PixelSigma(v) if v.to_bits() == bad.to_bits()),
            "{err}"
        );
        assert!(err.to_string().contains("snapshot.pixel_sigma_px"), "{err}");
    }
    let mut env = samples::snapshot(20, 2, 3, false);
    snapshot_body(&mut env).camera.intrinsics[0] = f64::NAN;
    assert!(matches!(
        invalid(&raw_encode(&env)),
        ValidationError::Camera(_)
    ));
}

#[test]
fn covariance_size_mismatch() {
    // One clone fewer than the covariance covers.
    let mut env = samples::snapshot(20, 11, 0, false);
    snapshot_body(&mut env).clones.pop();
    let err = invalid(&raw_encode(&env));
    assert!(
        matches!(
            err,
            ValidationError::CovarianceDim {
                dim: 66,
                clones: 10,
                expected: 60
            }
        ),
        "{err}"
    );
    // The right dim but a short triangle.
    let mut env = samples::snapshot(20, 11, 0, false);
    snapshot_body(&mut env).covariance.lower.pop();
    assert!(matches!(
        invalid(&raw_encode(&env)),
        ValidationError::CovarianceLength {
            dim: 66,
            expected: 2211,
            len: 2210
        }
    ));
}

#[test]
fn non_positive_variance() {
    let mut env = samples::snapshot(20, 2, 1, false);
    let s = snapshot_body(&mut env);
    s.covariance.lower[common::messages::PackedCovariance::packed_index(7, 7)] = 0.0;
    assert!(matches!(
        invalid(&raw_encode(&env)),
        ValidationError::NonPositiveVariance { field, .. } if field == "snapshot.covariance[7][7]"
    ));
    let mut env = samples::snapshot(20, 2, 1, false);
    snapshot_body(&mut env).landmarks[0].cov_upper[3] = -1.0;
    assert!(matches!(
        invalid(&raw_encode(&env)),
        ValidationError::NonPositiveVariance { field, .. } if field == "snapshot.landmarks[0].cov_upper.yy"
    ));
}

#[test]
fn quaternion_not_unit() {
    let mut env = samples::snapshot(20, 3, 0, false);
    snapshot_body(&mut env).clones[1].q_xyzw = [0.0, 0.0, 0.0, 1.002];
    assert!(matches!(
        invalid(&raw_encode(&env)),
        ValidationError::QuaternionNorm { index: 1, .. }
    ));
    // Within tolerance is fine.
    let mut env = samples::snapshot(20, 3, 0, false);
    snapshot_body(&mut env).clones[1].q_xyzw = [0.0, 0.0, 0.0, 1.0009];
    assert!(decode(&raw_encode(&env)).is_ok());
}

#[test]
fn clones_out_of_order() {
    let mut env = samples::snapshot(20, 3, 0, false);
    let s = snapshot_body(&mut env);
    s.clones.swap(0, 2);
    assert!(matches!(
        invalid(&raw_encode(&env)),
        ValidationError::ClonesOutOfOrder { index: 1, .. }
    ));
    // Equal times are allowed (non-decreasing).
    let mut env = samples::snapshot(20, 3, 0, false);
    let s = snapshot_body(&mut env);
    s.clones[1] = CameraPose {
        t_s: s.clones[0].t_s,
        ..s.clones[1]
    };
    assert!(decode(&raw_encode(&env)).is_ok());
}

#[test]
fn fleet_id_rules() {
    for (fleet_id, check) in [
        ("", "empty"),
        ("a/b", "'/'"),
        ("fleet*", "'*'"),
        ("tab\there", "'\\t'"),
    ] {
        let mut env = samples::heartbeat(1);
        env.fleet_id = fleet_id.into();
        let err = invalid(&raw_encode(&env));
        assert!(err.to_string().contains(check), "{fleet_id:?}: {err}");
    }
    let mut env = samples::heartbeat(1);
    env.fleet_id = "é".repeat(33); // 66 bytes
    assert!(matches!(
        invalid(&raw_encode(&env)),
        ValidationError::FleetIdTooLong { len: 66, max: 64 }
    ));
    env.fleet_id = "é".repeat(32);
    assert!(decode(&raw_encode(&env)).is_ok());
}

#[test]
fn counts_over_limits() {
    let limits = Limits::default();
    let env = samples::tracks(1, limits.max_features + 1);
    assert!(matches!(
        invalid(&raw_encode(&env)),
        ValidationError::TooMany {
            field: "tracks.features",
            count: 4097,
            max: 4096
        }
    ));
    let env = samples::descriptors(1, limits.max_descriptor_entries + 1, true);
    assert!(matches!(
        invalid(&raw_encode(&env)),
        ValidationError::TooMany {
            field: "descriptors.entries",
            ..
        }
    ));
    let env = samples::snapshot(100, limits.max_clones + 1, 0, false);
    assert!(matches!(
        invalid(&raw_encode(&env)),
        ValidationError::TooMany {
            field: "snapshot.clones",
            ..
        }
    ));
    let env = samples::snapshot(100, 1, limits.max_landmarks + 1, false);
    assert!(matches!(
        invalid(&raw_encode(&env)),
        ValidationError::TooMany {
            field: "snapshot.landmarks",
            ..
        }
    ));
    // At the limits, everything is accepted.
    for env in [
        samples::tracks(1, limits.max_features),
        samples::descriptors(1, limits.max_descriptor_entries, true),
        samples::snapshot(100, limits.max_clones, limits.max_landmarks, true),
    ] {
        assert_eq!(decode(&encode(&env).unwrap()).unwrap(), env);
    }
}

#[test]
fn huge_string_length_is_refused_before_allocating() {
    // Header, then the fleet id's length prefix claiming u64::MAX bytes.
    let mut bytes = MAGIC.to_vec();
    bytes.extend_from_slice(&WIRE_VERSION.to_le_bytes());
    bytes.extend(varint_u64(u64::MAX));
    bytes.extend_from_slice(b"fleet");
    assert!(matches!(
        decode(&bytes),
        Err(DecodeError::LimitExceeded { limit }) if limit == DECODE_CLAIM_LIMIT_BYTES
    ));
    // Just above the decode limit is refused the same way.
    bytes.truncate(HEADER_LEN);
    bytes.extend(varint_u64(DECODE_CLAIM_LIMIT_BYTES as u64 + 1));
    assert!(matches!(
        decode(&bytes),
        Err(DecodeError::LimitExceeded { .. })
    ));
}

#[test]
fn huge_vec_length_is_refused_before_allocating() {
    // An empty track frame: its features' length prefix (0) is the last byte.
    let mut env = samples::tracks(1, 0);
    env.fleet_id = "x".into();
    let mut bytes = encode(&env).unwrap();
    assert_eq!(bytes.pop(), Some(0));
    for huge in [
        u64::MAX,
        u64::MAX / 24,
        1 << 40,
        DECODE_CLAIM_LIMIT_BYTES as u64,
    ] {
        let mut b = bytes.clone();
        b.extend(varint_u64(huge));
        let err = decode(&b).unwrap_err();
        // Refused at the length prefix, not after reading elements.
        assert!(
            matches!(&err, DecodeError::Malformed(_)) && err.to_string().contains("invalid length"),
            "{huge}: {err}"
        );
    }
    // A plausible length with missing data runs out of input instead.
    let mut b = bytes.clone();
    b.extend(varint_u64(1000));
    assert!(matches!(decode(&b), Err(DecodeError::Malformed(_))));
}

#[test]
fn error_messages_are_clear() {
    let err = decode(b"FVIO\x01").unwrap_err();
    assert_eq!(
        err.to_string(),
        "message of 5 bytes is shorter than the 6-byte header"
    );
    let err = decode(&[0u8; 2_000_000]).unwrap_err();
    assert_eq!(
        err.to_string(),
        "message of 2000000 bytes exceeds the limit of 1048576 bytes"
    );
}
