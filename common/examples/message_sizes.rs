//! Encoded size of each message kind for a realistic case, and the bandwidth
//! one agent sends at 10 Hz.
//!
//! `cargo run -p common --release --example message_sizes`

use common::messages::{encode, samples, EncodeError, Envelope};

fn size(env: &Envelope) -> Result<usize, EncodeError> {
    Ok(encode(env)?.len())
}

fn main() -> Result<(), EncodeError> {
    let frame = 3000;
    let tracks = size(&samples::tracks(frame, 100))?;
    let desc_new = size(&samples::descriptors(frame, 10, false))?;
    let desc_kf = size(&samples::descriptors(frame, 100, true))?;
    let snap_0 = size(&samples::snapshot(frame, 11, 0, false))?;
    let snap_50 = size(&samples::snapshot(frame, 11, 50, false))?;
    let heartbeat = size(&samples::heartbeat(frame))?;

    println!("encoded sizes (header included):");
    let rows = [
        (
            "tracks, 100 features",
            tracks,
            samples::TRACKS_100_BUDGET_BYTES,
        ),
        (
            "descriptors, 10 new tracks",
            desc_new,
            samples::DESCRIPTORS_10_BUDGET_BYTES,
        ),
        (
            "descriptors, keyframe of 100",
            desc_kf,
            samples::DESCRIPTORS_100_BUDGET_BYTES,
        ),
        (
            "snapshot, 11 clones, 0 landmarks",
            snap_0,
            samples::SNAPSHOT_11_BUDGET_BYTES,
        ),
        (
            "snapshot, 11 clones, 50 landmarks",
            snap_50,
            samples::SNAPSHOT_11_50_BUDGET_BYTES,
        ),
        ("heartbeat", heartbeat, samples::HEARTBEAT_BUDGET_BYTES),
    ];
    for (what, bytes, budget) in rows {
        println!("  {what:<36} {bytes:>6} B   (budget < {budget} B)");
    }

    let hz = samples::FRAME_RATE_HZ;
    println!();
    println!(
        "bandwidth per agent at {hz} Hz: tracks every frame, 10 new-track descriptors every \
         frame, a snapshot every 5 frames, plus a keyframe snapshot, keyframe descriptors (100) \
         and a heartbeat at 1 Hz:"
    );
    for (landmarks, snap) in [(0, snap_0), (50, snap_50)] {
        let parts = [
            ("tracks", tracks as f64 * hz),
            ("new-track descriptors", desc_new as f64 * hz),
            ("snapshots", snap as f64 * hz / 5.0),
            ("keyframe snapshots", snap as f64),
            ("keyframe descriptors", desc_kf as f64),
            ("heartbeat", heartbeat as f64),
        ];
        let total: f64 = parts.iter().map(|(_, b)| b).sum();
        println!("  with {landmarks} landmarks per snapshot:");
        for (what, bytes_per_s) in parts {
            println!("    {what:<24} {bytes_per_s:>9.0} B/s");
        }
        println!(
            "    {:<24} {total:>9.0} B/s  ({:.1} kB/s, {:.2} Mbit/s)",
            "total",
            total / 1000.0,
            total * 8.0 / 1e6
        );
    }
    Ok(())
}
