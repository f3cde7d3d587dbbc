//! The `vocab` binary: train, info and query on a small descriptor file.

mod support;

use std::process::Command;
use support::{noisy_view, places, rng};
use vocabulary::text::write_images;

fn vocab() -> Command {
    Command::new(env!("CARGO_BIN_EXE_vocab"))
}

#[test]
fn train_info_query() {
    let dir = tempfile::tempdir().unwrap();
    let mut r = rng(9);
    let places = places(15, 60, &mut r);
    // Images 2i and 2i+1 are two views of place i.
    let images: Vec<_> = places
        .iter()
        .flat_map(|p| {
            [
                noisy_view(p, 0.03, 0.1, &mut r).0,
                noisy_view(p, 0.03, 0.1, &mut r).0,
            ]
        })
        .collect();
    let desc = dir.path().join("images.txt");
    write_images(&desc, &images).unwrap();
    let out = dir.path().join("v.voc");

    let st = vocab()
        .args(["train", "--k", "6", "--levels", "3", "--descriptors"])
        .arg(&desc)
        .arg("--out")
        .arg(&out)
        .output()
        .unwrap();
    assert!(
        st.status.success(),
        "{}",
        String::from_utf8_lossy(&st.stderr)
    );

    let info = vocab().arg("info").arg(&out).output().unwrap();
    let text = String::from_utf8(info.stdout).unwrap();
    assert!(text.contains("k: 6") && text.contains("L: 3"), "{text}");
    assert!(text.contains("training images: 30"), "{text}");

    let q = vocab()
        .args(["query", "--vocab"])
        .arg(&out)
        .arg("--descriptors")
        .arg(&desc)
        .output()
        .unwrap();
    assert!(q.status.success());
    let text = String::from_utf8(q.stdout).unwrap();
    let mut right = 0;
    for line in text.lines().skip(1) {
        let f: Vec<&str> = line.split_whitespace().collect();
        let (i, j): (usize, usize) = (f[0].parse().unwrap(), f[1].parse().unwrap());
        right += usize::from(i / 2 == j / 2 && i != j);
    }
    assert!(right >= 27, "{right}/30 paired views found\n{text}");

    // A corrupt vocabulary is an error naming the file, not a panic.
    std::fs::write(&out, b"FVBOWVOC\x01\x00\x00\x00garbage").unwrap();
    let bad = vocab().arg("info").arg(&out).output().unwrap();
    assert!(!bad.status.success());
    let err = String::from_utf8_lossy(&bad.stderr);
    assert!(err.contains("v.voc") && !err.contains("panicked"), "{err}");
}
