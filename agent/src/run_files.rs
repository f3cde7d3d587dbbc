//! The run's text outputs (`estimate.txt`, `groundtruth.txt`, `covariance.txt`,
//! `timing.csv`) written as the run goes, so that an agent killed hard (power
//! cut, `SIGKILL`, out of memory) leaves every pose up to its last flush, in
//! the files and formats of a finished run; `tail -f` and `evo` read them live.
//!
//! Rows are gathered in memory and written to the files whole, at most every
//! `flush_period`: a file on disk always ends at the end of a row. At the end
//! of the run the files are byte for byte what [`write_all`] writes.
//! A failed write (disk full, folder gone) costs nothing: streaming stops
//! with a warning and the end of the run writes every file again from memory.

use crate::estimator::FrameRecord;
use crate::runner::{timing_row, RobotRun, TIMING_HEADER};
use common::trajectory::{
    covariance_row, tum_row, StampedCovariance, StampedPose, COVARIANCE_HEADER, TUM_HEADER,
};
use std::fs::File;
use std::io::{BufWriter, Write};
use std::path::{Path, PathBuf};
use std::time::{Duration, Instant};

/// The four files, in the order they are written at a flush (the ground
/// truth first, so that it is never behind the estimate it scores).
const FILES: [(&str, &str); 4] = [
    ("groundtruth.txt", TUM_HEADER),
    ("estimate.txt", TUM_HEADER),
    ("covariance.txt", COVARIANCE_HEADER),
    ("timing.csv", TIMING_HEADER),
];

/// Longest wall time the run's text outputs wait in memory before they are
/// written: what a hard kill can lose of them.
pub const FLUSH_PERIOD: Duration = Duration::from_secs(1);

/// One recorded frame, as the four files see it.
pub struct RunRow<'a> {
    /// The truth at the estimate's time, when known.
    pub truth: Option<&'a StampedPose>,
    /// The estimate.
    pub estimate: &'a StampedPose,
    /// Its orientation and position covariance.
    pub covariance: &'a StampedCovariance,
    /// The frame's counts and costs.
    pub frame: &'a FrameRecord,
}

/// A run's record as [`RunFiles`] reads it: rows that only ever grow.
pub trait RunRecord {
    /// Whether the run knows a truth (`groundtruth.txt` is written).
    fn has_truth(&self) -> bool;
    /// Rows recorded so far.
    fn rows(&self) -> usize;
    /// Row `i < rows()`.
    fn row(&self, i: usize) -> RunRow<'_>;
}

impl RunRecord for RobotRun {
    fn has_truth(&self) -> bool {
        !self.without_truth
    }

    /// Rows complete in all the records (they grow together).
    fn rows(&self) -> usize {
        let rows = (self.estimate.len())
            .min(self.covariance.len())
            .min(self.frames.len());
        match self.without_truth {
            true => rows,
            false => rows.min(self.truth.len()),
        }
    }

    fn row(&self, i: usize) -> RunRow<'_> {
        RunRow {
            truth: self.truth.get(i).filter(|_| !self.without_truth),
            estimate: &self.estimate[i],
            covariance: &self.covariance[i],
            frame: &self.frames[i],
        }
    }
}

/// A row's line in each file (no newline), `None` where a file has none.
fn lines_of(r: RunRow<'_>) -> [Option<String>; 4] {
    [
        r.truth.map(tum_row),
        Some(tum_row(r.estimate)),
        Some(covariance_row(r.covariance)),
        Some(timing_row(r.frame)),
    ]
}

/// Writes `run`'s files at once (`groundtruth.txt` only if it has a truth):
/// what the end of a run writes when it did not stream them.
pub fn write_all(run: &impl RunRecord, dir: &Path) -> std::io::Result<()> {
    std::fs::create_dir_all(dir)?;
    let mut outs = Vec::with_capacity(FILES.len());
    for (k, (name, header)) in FILES.into_iter().enumerate() {
        if k == 0 && !run.has_truth() {
            outs.push(None);
            continue;
        }
        let mut out = BufWriter::new(File::create(dir.join(name))?);
        writeln!(out, "{header}")?;
        outs.push(Some(out));
    }
    for i in 0..run.rows() {
        for (out, line) in outs.iter_mut().zip(lines_of(run.row(i))) {
            if let (Some(out), Some(line)) = (out, line) {
                writeln!(out, "{line}")?;
            }
        }
    }
    outs.iter_mut().flatten().try_for_each(|o| o.flush())
}

/// One output file and the rows not yet written to it.
struct Stream {
    file: File,
    pending: String,
}

/// The run's text outputs, appended as frames are recorded.
pub struct RunFiles {
    dir: PathBuf,
    /// One per entry of [`FILES`], `None` for a file the run does not write;
    /// all `None` once a write has failed: the end of the run writes
    /// everything.
    streams: Option<Vec<Option<Stream>>>,
    /// Rows of the run already in `pending` or on disk.
    rows: usize,
    flush_period: Duration,
    last_flush: Instant,
}

impl RunFiles {
    /// Creates the files in `dir` (and `dir`), each with its header line;
    /// `groundtruth.txt` only `with_truth`.
    pub fn create(dir: &Path, with_truth: bool, flush_period: Duration) -> std::io::Result<Self> {
        std::fs::create_dir_all(dir)?;
        let mut streams = Vec::with_capacity(FILES.len());
        for (k, (name, header)) in FILES.into_iter().enumerate() {
            if k == 0 && !with_truth {
                streams.push(None);
                continue;
            }
            let mut file = File::create(dir.join(name))?;
            writeln!(file, "{header}")?;
            streams.push(Some(Stream {
                file,
                pending: String::new(),
            }));
        }
        Ok(RunFiles {
            dir: dir.to_path_buf(),
            streams: Some(streams),
            rows: 0,
            flush_period,
            last_flush: Instant::now(),
        })
    }

    /// Takes the rows `run` recorded since the last call, and writes them out
    /// if the flush period has passed.
    pub fn append(&mut self, run: &impl RunRecord) {
        let Some(streams) = self.streams.as_mut() else {
            return;
        };
        let n = run.rows();
        for i in self.rows..n {
            for (s, row) in streams.iter_mut().zip(lines_of(run.row(i))) {
                if let (Some(s), Some(row)) = (s, row) {
                    s.pending.push_str(&row);
                    s.pending.push('\n');
                }
            }
        }
        self.rows = self.rows.max(n);
        if self.last_flush.elapsed() >= self.flush_period {
            self.flush();
        }
    }

    /// Writes every pending row now.
    pub fn flush(&mut self) {
        self.last_flush = Instant::now();
        let Some(streams) = self.streams.as_mut() else {
            return;
        };
        for s in streams.iter_mut().flatten() {
            if let Err(e) = s.file.write_all(s.pending.as_bytes()) {
                tracing::warn!(
                    "writing {} as the run goes failed ({e}): it is written at the end",
                    self.dir.display()
                );
                self.streams = None;
                return;
            }
            s.pending.clear();
        }
    }

    /// The end of the run: the rows still pending, or, if a write failed on
    /// the way, every file again from `run`.
    pub fn finish(mut self, run: &impl RunRecord) -> std::io::Result<()> {
        self.append(run);
        self.flush();
        match self.streams {
            Some(streams) => streams
                .iter()
                .flatten()
                .try_for_each(|s| s.file.sync_data()),
            None => write_all(run, &self.dir),
        }
    }
}

/// What a run writes as it goes (the MCAP log too): all an unfinished run
/// leaves.
const STREAMED: [&str; 5] = [
    "estimate.txt",
    "groundtruth.txt",
    "covariance.txt",
    "timing.csv",
    "agent.mcap",
];

/// What a run writes at its end; `summary.json` says it finished.
const AT_END: [&str; 3] = ["summary.json", "transport_stats.json", "peer_events.jsonl"];

/// Readies `dir` for a new run. An earlier run that never finished (its
/// files written as it went, no `summary.json`: a robot that lost power) is
/// moved whole into `dir/unfinished-<k>/` (the first free `k`), so that the
/// robot restarted keeps the trajectory of before. A finished one is
/// overwritten as always; its end-of-run files go now, so that a run killed
/// in turn does not leave them beside its own. Returns where an unfinished
/// run went.
pub fn set_aside_unfinished(dir: &Path) -> std::io::Result<Option<PathBuf>> {
    let finished = dir.join("summary.json").exists();
    let left: Vec<&str> = STREAMED
        .into_iter()
        .filter(|name| dir.join(name).exists())
        .collect();
    if finished || left.is_empty() {
        for name in AT_END {
            match std::fs::remove_file(dir.join(name)) {
                Err(e) if e.kind() != std::io::ErrorKind::NotFound => return Err(e),
                _ => {}
            }
        }
        return Ok(None);
    }
    let Some(aside) = (1..10_000)
        .map(|k| dir.join(format!("unfinished-{k}")))
        .find(|p| !p.exists())
    else {
        return Err(std::io::Error::other(
            "10 000 unfinished runs set aside already",
        ));
    };
    std::fs::create_dir_all(&aside)?;
    for name in left.into_iter().chain(AT_END) {
        if dir.join(name).exists() {
            std::fs::rename(dir.join(name), aside.join(name))?;
        }
    }
    Ok(Some(aside))
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::estimator::FrameRecord;
    use common::trajectory::{StampedCovariance, StampedPose};
    use nalgebra::{Matrix3, Rotation3, Vector3};

    fn run_of(frames: usize) -> RobotRun {
        let mut run = RobotRun::default();
        for k in 0..frames {
            let t = 0.1 * k as f64 + 1.0 / 3.0;
            let rot = Rotation3::from_euler_angles(0.1 * t, -0.2, 0.7 * t).into_inner();
            let pos = Vector3::new(t.cos(), t.sin() / 3.0, 0.1 * t);
            run.estimate.push(StampedPose { t, rot, pos });
            run.truth.push(StampedPose {
                t,
                rot,
                pos: pos * 1.01,
            });
            run.covariance.push(StampedCovariance {
                t,
                ori: Matrix3::identity() * 1e-5 * t,
                pos: Matrix3::from_fn(|r, c| if r == c { 1e-3 } else { 1e-4 / 7.0 }),
            });
            let mut f = FrameRecord {
                t,
                ..FrameRecord::default()
            };
            f.timing.total_ms = 1.0 + t;
            run.frames.push(f);
        }
        run
    }

    fn read_all(dir: &Path) -> Vec<Vec<u8>> {
        FILES
            .iter()
            .map(|(name, _)| std::fs::read(dir.join(name)).unwrap())
            .collect()
    }

    /// Appended frame by frame, flushed at odd times, the files end as those
    /// written at once at the end.
    #[test]
    fn files_streamed_frame_by_frame_are_those_written_at_the_end() {
        let whole = run_of(57);
        let at_end = tempfile::tempdir().unwrap();
        write_all(&whole, at_end.path()).unwrap();
        let streamed = tempfile::tempdir().unwrap();
        let mut files = RunFiles::create(streamed.path(), true, Duration::from_secs(3600)).unwrap();
        let mut run = RobotRun::default();
        for k in 0..whole.estimate.len() {
            run.estimate.push(whole.estimate[k]);
            run.truth.push(whole.truth[k]);
            run.covariance.push(whole.covariance[k]);
            run.frames.push(whole.frames[k]);
            files.append(&run);
            if k % 13 == 5 {
                files.flush();
            }
        }
        files.finish(&run).unwrap();
        assert_eq!(read_all(streamed.path()), read_all(at_end.path()));
    }

    /// What a hard kill leaves: every row flushed, each file ending with a
    /// whole row, readable as a trajectory.
    #[test]
    fn a_run_cut_short_leaves_every_flushed_row_readable() {
        let run = run_of(20);
        let dir = tempfile::tempdir().unwrap();
        let mut files = RunFiles::create(dir.path(), true, Duration::ZERO).unwrap();
        let mut partial = RobotRun::default();
        for k in 0..12 {
            partial.estimate.push(run.estimate[k]);
            partial.truth.push(run.truth[k]);
            partial.covariance.push(run.covariance[k]);
            partial.frames.push(run.frames[k]);
            files.append(&partial);
        }
        // Dropped without `finish`, as a killed process would leave it.
        drop(files);
        let est = common::trajectory::read_tum(dir.path().join("estimate.txt")).unwrap();
        assert_eq!(est.len(), 12);
        for (read, made) in est.iter().zip(&run.estimate) {
            // Times have 9 decimals in the file; positions read back exactly.
            assert!((read.t - made.t).abs() < 1e-9);
            assert_eq!(read.pos, made.pos);
        }
        let covs = common::trajectory::read_covariances(dir.path().join("covariance.txt")).unwrap();
        assert_eq!(covs.len(), 12);
        let timing = std::fs::read_to_string(dir.path().join("timing.csv")).unwrap();
        assert_eq!(timing.lines().count(), 13);
        assert!(timing.ends_with('\n'));
    }

    /// A folder that vanishes mid-run: streaming stops, and the end of the run
    /// writes every file from memory, nothing lost.
    #[test]
    fn a_failed_write_is_made_good_at_the_end() {
        let run = run_of(30);
        let root = tempfile::tempdir().unwrap();
        let dir = root.path().join("robot0");
        let mut files = RunFiles::create(&dir, true, Duration::ZERO).unwrap();
        files.append(&run);
        // The folder goes, and the next write fails: the first file is
        // swapped for a handle on a directory, which takes no writes.
        std::fs::remove_dir_all(&dir).unwrap();
        let first = files.streams.as_mut().unwrap()[0].as_mut().unwrap();
        first.file = File::open(root.path()).unwrap();
        first.pending.push_str("x\n");
        files.flush();
        assert!(files.streams.is_none());
        files.finish(&run).unwrap();
        let at_end = tempfile::tempdir().unwrap();
        write_all(&run, at_end.path()).unwrap();
        assert_eq!(read_all(&dir), read_all(at_end.path()));
    }

    /// A run that never finished is set aside whole before the next one; a
    /// finished one is overwritten, its end-of-run files removed first.
    #[test]
    fn an_unfinished_run_is_set_aside_and_a_finished_one_overwritten() {
        let dir = tempfile::tempdir().unwrap();
        let d = dir.path();
        assert_eq!(set_aside_unfinished(d).unwrap(), None);
        // Killed hard: the streamed files, no summary.
        let mut files = RunFiles::create(d, true, Duration::ZERO).unwrap();
        files.append(&run_of(7));
        drop(files);
        std::fs::write(d.join("agent.mcap"), b"partial").unwrap();
        std::fs::write(d.join("config.yaml"), b"robot_id: 0").unwrap();
        let aside = set_aside_unfinished(d).unwrap().unwrap();
        assert_eq!(aside, d.join("unfinished-1"));
        assert_eq!(
            common::trajectory::read_tum(aside.join("estimate.txt"))
                .unwrap()
                .len(),
            7
        );
        assert!(aside.join("agent.mcap").is_file() && !d.join("estimate.txt").exists());
        assert!(d.join("config.yaml").is_file(), "the configuration stays");
        // Killed again: the next goes beside it.
        RunFiles::create(d, true, Duration::ZERO).unwrap();
        assert_eq!(
            set_aside_unfinished(d).unwrap(),
            Some(d.join("unfinished-2"))
        );
        // A finished run stays where it is, its end-of-run files gone.
        write_all(&run_of(3), d).unwrap();
        std::fs::write(d.join("summary.json"), b"{}").unwrap();
        std::fs::write(d.join("peer_events.jsonl"), b"").unwrap();
        assert_eq!(set_aside_unfinished(d).unwrap(), None);
        assert!(!d.join("summary.json").exists() && !d.join("peer_events.jsonl").exists());
        assert!(d.join("estimate.txt").is_file());
        assert!(!d.join("unfinished-3").exists());
    }
}
