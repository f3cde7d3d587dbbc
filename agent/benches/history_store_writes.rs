//! What a history store write costs the agent's thread, and what it leaves to
//! the writer thread: a peer history grown to `MIB` MiB (50 tracks a frame, a
//! keyframe window of 11 clones and 5 landmarks every 10 frames), written
//! whole (a new file), then a window at a time (appended) through three
//! compactions.
//!
//! `cargo bench -p agent --bench history_store_writes [-- MIB [DIR]]` (default
//! 64 MiB, the default `history.max_mib_per_peer`, in a temporary folder; give
//! `DIR` on the disk to measure, e.g. a robot's SD card: a new folder is made
//! in it and removed after). Prints, per write,
//! the time of `plan` (encoding the records: the agent's thread) and of `run`
//! (writing and syncing the file: the writer thread), medians.
use agent::history_retention::Retention;
use agent::history_store::HistoryStore;
use agent::peer_history::{HistoryLimits, PeerHistory};
use common::messages::{samples, Body};
use std::time::Instant;

const FEATURES: usize = 50;
const REPEATS: usize = 5;
const COMPACTIONS: usize = 3;

fn grow(h: &mut PeerHistory, frames: std::ops::Range<u64>, limits: &HistoryLimits) {
    for f in frames {
        if let Body::Tracks(t) = samples::tracks(f, FEATURES).body {
            h.add_tracks(t, limits);
        }
        if f >= 10 && f % 10 == 0 {
            if let Body::Descriptors(d) = samples::descriptors(f, FEATURES, true).body {
                h.add_descriptors(d, limits);
            }
            if let Body::Snapshot(s) = samples::snapshot(f, 11, 5, true).body {
                h.add_snapshot(s, limits);
            }
        }
    }
}

fn median(mut v: Vec<f64>) -> f64 {
    v.sort_by(f64::total_cmp);
    v[v.len() / 2]
}

fn main() -> anyhow::Result<()> {
    let args: Vec<String> = std::env::args()
        .skip(1)
        .filter(|a| !a.starts_with('-'))
        .collect();
    let mib: f64 = args.first().and_then(|a| a.parse().ok()).unwrap_or(64.0);
    // A new folder (inside DIR when given), removed at the end: a store's
    // files already there are never touched.
    let tmp = match args.get(1) {
        Some(d) => tempfile::tempdir_in(d)?,
        None => tempfile::tempdir()?,
    };
    let dir = tmp.path().to_path_buf();
    let limits = HistoryLimits {
        max_bytes: (mib * 1024.0 * 1024.0) as usize,
        recent_s: 2.0,
        retention: Retention::Oldest,
    };
    let mut h = PeerHistory::default();
    let mut frame = 0u64;
    // Until the bound drops the first window: the history is full.
    while h.dropped_keyframes == 0 {
        grow(&mut h, frame..frame + 100, &limits);
        frame += 100;
    }
    println!(
        "history: {} keyframe windows, {:.1} MiB in memory, folder {}",
        h.keyframes.len(),
        h.bytes() as f64 / 1048576.0,
        dir.display()
    );
    println!(
        "{:<26} {:>8} {:>12} {:>12} {:>6}",
        "write", "file MiB", "plan ms", "run ms", "count"
    );
    let mut whole = (vec![], vec![], 0);
    for _ in 0..REPEATS {
        // A fresh store encodes every record: a new file.
        let mut store = HistoryStore::open(&dir, "bench", "bench, seed 1")?;
        let t = Instant::now();
        let job = store
            .plan(1, &h)?
            .ok_or_else(|| anyhow::anyhow!("nothing to write"))?;
        whole.0.push(t.elapsed().as_secs_f64() * 1e3);
        whole.2 = job.len();
        let t = Instant::now();
        job.run()?;
        whole.1.push(t.elapsed().as_secs_f64() * 1e3);
    }
    // Then a window at a time, appended, until the file holds twice what the
    // history needs (the oldest windows dropped meanwhile) and is compacted:
    // the records still needed are copied, not encoded again.
    let mut store = HistoryStore::open(&dir, "bench", "bench, seed 1")?;
    if let Some(job) = store.plan(1, &h)? {
        job.run()?;
    }
    let (mut append, mut compaction) = ((vec![], vec![], 0), (vec![], vec![], 0));
    while compaction.0.len() < COMPACTIONS {
        grow(&mut h, frame..frame + 10, &limits);
        frame += 10;
        let t = Instant::now();
        let Some(job) = store.plan(1, &h)? else {
            continue;
        };
        let plan_ms = t.elapsed().as_secs_f64() * 1e3;
        let row = if job.kind() == "append" {
            &mut append
        } else {
            &mut compaction
        };
        row.0.push(plan_ms);
        row.2 = std::fs::metadata(dir.join("robot1.fvhs"))?.len() as usize;
        let t = Instant::now();
        job.run()?;
        row.1.push(t.elapsed().as_secs_f64() * 1e3);
    }
    for (name, (plan, run, bytes)) in [
        ("whole (new file)", whole),
        ("one window appended", append),
        ("compaction (file before)", compaction),
    ] {
        let n = plan.len();
        println!(
            "{:<26} {:>8.3} {:>12.2} {:>12.2} {:>6}",
            name,
            bytes as f64 / 1048576.0,
            median(plan),
            median(run),
            n
        );
    }
    Ok(())
}
