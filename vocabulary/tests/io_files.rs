//! Vocabulary files: round trip, and rejection (never a panic) of truncated,
//! corrupted, wrong-version and trailing-byte files.
#![allow(clippy::unwrap_used)] // helpers outside #[test] functions

mod support;

use proptest::prelude::*;
use rand::Rng;
use std::sync::Arc;
use support::{places, random_descriptor, rng};
use vocabulary::io::{FORMAT_VERSION, MAGIC};
use vocabulary::{Database, Descriptor, FormatError, TrainParams, VocabIoError, Vocabulary};

fn small_vocab() -> Vocabulary {
    let mut r = rng(1);
    let images = places(10, 30, &mut r);
    let params = TrainParams {
        k: 4,
        levels: 2,
        ..TrainParams::default()
    };
    Vocabulary::train(&images, &params).unwrap()
}

/// Decoding must not panic; whatever decodes must be usable.
fn check_no_panic(bytes: &[u8], probes: &[Descriptor]) -> bool {
    match Vocabulary::from_bytes(bytes) {
        Ok(v) => {
            v.validate().unwrap();
            let _ = v.transform_with_features(probes, 1);
            true
        }
        Err(_) => false,
    }
}

#[test]
fn round_trip_gives_identical_results() {
    let mut r = rng(2);
    let images = places(100, 50, &mut r);
    let vocab = Vocabulary::train(&images, &TrainParams::default()).unwrap();
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("v.voc");
    vocab.save(&path).unwrap();
    let loaded = Vocabulary::load(&path).unwrap();
    assert_eq!(loaded, vocab);
    let mut a = Database::new(Arc::new(vocab.clone()), 2);
    let mut b = Database::new(Arc::new(loaded.clone()), 2);
    for img in &images {
        assert_eq!(vocab.transform(img), loaded.transform(img));
        assert_eq!(
            vocab.transform_with_features(img, 2),
            loaded.transform_with_features(img, 2)
        );
        a.add(img);
        b.add(img);
    }
    for img in images.iter().take(20) {
        assert_eq!(a.query(img, 10), b.query(img, 10));
    }
}

#[test]
fn header_errors() {
    let bytes = small_vocab().to_bytes().unwrap();
    assert!(Vocabulary::from_bytes(&bytes).is_ok());

    let mut wrong_version = bytes.clone();
    wrong_version[MAGIC.len()..MAGIC.len() + 4]
        .copy_from_slice(&(FORMAT_VERSION + 1).to_le_bytes());
    assert!(matches!(
        Vocabulary::from_bytes(&wrong_version),
        Err(FormatError::UnsupportedVersion { found, .. }) if found == FORMAT_VERSION + 1
    ));

    let mut trailing = bytes.clone();
    trailing.push(0);
    assert!(matches!(
        Vocabulary::from_bytes(&trailing),
        Err(FormatError::TrailingBytes(1))
    ));

    let mut magic = bytes.clone();
    magic[0] ^= 1;
    assert!(matches!(
        Vocabulary::from_bytes(&magic),
        Err(FormatError::BadMagic)
    ));

    assert!(matches!(
        Vocabulary::from_bytes(&bytes[..5]),
        Err(FormatError::Truncated(5))
    ));

    // A payload claiming 2^60 nodes fails quickly instead of allocating.
    let mut huge = bytes[..MAGIC.len() + 4].to_vec();
    huge.extend_from_slice(&[10, 4, 0xFD, 0, 0, 0, 0, 0, 0, 0, 0x10]);
    assert!(Vocabulary::from_bytes(&huge).is_err());
}

#[test]
fn errors_name_the_file() {
    let dir = tempfile::tempdir().unwrap();
    let missing = dir.path().join("missing.voc");
    let err = Vocabulary::load(&missing).unwrap_err();
    assert!(matches!(err, VocabIoError::Read { .. }));
    assert!(err.to_string().contains("missing.voc"), "{err}");

    let bad = dir.path().join("bad.voc");
    let mut bytes = small_vocab().to_bytes().unwrap();
    bytes.truncate(bytes.len() - 3);
    std::fs::write(&bad, &bytes).unwrap();
    let err = Vocabulary::load(&bad).unwrap_err();
    assert!(matches!(err, VocabIoError::Format { .. }));
    assert!(err.to_string().contains("bad.voc"), "{err}");
}

#[test]
fn every_truncation_and_byte_corruption_is_handled() {
    let vocab = small_vocab();
    let bytes = vocab.to_bytes().unwrap();
    let mut r = rng(3);
    let probes: Vec<Descriptor> = (0..50).map(|_| random_descriptor(&mut r)).collect();
    for len in 0..bytes.len() {
        assert!(
            !check_no_panic(&bytes[..len], &probes),
            "prefix of {len} bytes accepted"
        );
    }
    let mut accepted = 0;
    for pos in 0..bytes.len() {
        for mask in [0x01u8, 0x80, 0xFF] {
            let mut m = bytes.clone();
            m[pos] ^= mask;
            accepted += usize::from(check_no_panic(&m, &probes));
        }
    }
    // Random multi-byte corruption.
    for _ in 0..2000 {
        let mut m = bytes.clone();
        for _ in 0..r.random_range(1..8) {
            let pos = r.random_range(0..m.len());
            m[pos] = r.random();
        }
        accepted += usize::from(check_no_panic(&m, &probes));
    }
    println!(
        "io: {} bytes; {} corruptions decoded into a valid vocabulary (center bits and \
         weights), the rest rejected",
        bytes.len(),
        accepted
    );
}

proptest! {
    #![proptest_config(ProptestConfig::with_cases(512))]
    #[test]
    fn arbitrary_payloads_never_panic(payload in proptest::collection::vec(any::<u8>(), 0..600)) {
        let mut bytes = MAGIC.to_vec();
        bytes.extend_from_slice(&FORMAT_VERSION.to_le_bytes());
        bytes.extend_from_slice(&payload);
        let _ = check_no_panic(&bytes, &[Descriptor([1, 2, 3, 4])]);
    }
}
