//! Keyframe windows kept on disk, so a restarted agent keeps what it learnt.
//!
//! A process that restarts loses its peers' histories and its archive of its
//! own windows. Catch-up gets the peers' windows back from peers that are
//! still there, but not from a robot that has landed and gone, and a peer
//! that joins after the restart could not get our windows from before it.
//! With `history.store_dir` set, each history (one file per robot, ours
//! included) is written there as it grows and read back at start.
//!
//! A file is `FVHS`, a little-endian `u16` format version, the mission (a
//! little-endian `u16` length and UTF-8: the scenario and seed the fleet
//! runs, so a store left from another mission under the same fleet id is not
//! taken for this one's), then records: a
//! little-endian `u32` length and one encoded message (the wire format of a
//! replayed window, [`HistoryReplay`], so a record is decoded with the same
//! bounds and checks as a message from the network).
//!
//! A file is a log: each write appends the windows that are new, or more
//! complete than the copy last written (a part that arrived late), and syncs
//! them. Reading takes a window's most complete record. Rewriting every
//! history at every write grew with the square of the mission (measured: 23.5
//! MB written per agent for the 4 MB it kept over 263 s; appending writes the
//! 4 MB once). A file is replaced whole
//! (written beside it, then renamed, so a crash leaves the old or the new one)
//! only when its superseded records and the windows its history dropped make
//! it more than [`COMPACT_FACTOR`] times what it must hold, when it could not
//! be read to its end, or when it changed behind the store's back. A crash in
//! an append leaves a cut record at the end: reading keeps the records before
//! it, and the next write replaces the file.
//!
//! What cannot be read is reported and set aside (renamed
//! `robot<N>.fvhs.unreadable-<unix time>`, so nothing is lost): a file over
//! its bound, another fleet's or mission's, a bad header; a bad record ends the file's
//! reading with what was read before it kept, and the next write makes a new
//! file of that. A last record cut short is only reported.

use crate::peer_history::{time_key, HistoryLimits, KeyframeWindow, PeerHistory, Replayed};
use common::messages::{decode, encode, Body, Envelope, HistoryReplay, Limits};
use std::collections::BTreeMap;
use std::io::{Read, Seek, Write};
use std::path::{Path, PathBuf};
use thiserror::Error;

/// The first bytes of a history file.
const FILE_MAGIC: [u8; 4] = *b"FVHS";

/// The format version this build writes and reads. Version 2 named the
/// mission after the version (version 1 had none). Version 3: the records are
/// of wire version 6, whose snapshots name their world frame; older files
/// hold records this build cannot decode, so they are set aside whole
/// (renamed, kept) rather than read as empty and overwritten. Version 4: the
/// records are of wire version 7, whose snapshots carry their sender's pixel
/// noise (set aside the same way).
const FILE_VERSION: u16 = 4;

/// The format versions this build reads.
const READABLE_VERSIONS: [u16; 1] = [FILE_VERSION];

/// Bytes of the magic and the version.
const PREFIX_LEN: u64 = FILE_MAGIC.len() as u64 + 2;

/// Longest mission name, bytes.
pub const MAX_MISSION_BYTES: usize = 256;

/// A file is rewritten when it would exceed this many times the bytes of the
/// records its history needs, plus [`COMPACT_SLACK`].
pub const COMPACT_FACTOR: u64 = 2;

/// Bytes a file may hold beyond its factor before it is rewritten.
const COMPACT_SLACK: u64 = 64 << 10;

/// A file read at start may hold this many times its history's memory bound
/// (the log holds superseded records, and a window's encoding and its heap
/// size differ), plus [`FILE_BOUND_SLACK`] bytes.
const FILE_BOUND_FACTOR: usize = 8;

/// Bytes a file may hold beyond its factor of the memory bound.
const FILE_BOUND_SLACK: usize = 4096;

/// What went wrong with the store.
#[derive(Debug, Error)]
pub enum StoreError {
    /// A file or the folder could not be read or written.
    #[error("{path}: {source}")]
    Io {
        /// The file or folder.
        path: PathBuf,
        /// Why.
        source: std::io::Error,
    },
    /// A file was not as long as the store left it (changed behind its
    /// back, or an earlier write failed part-way): nothing was appended, and
    /// the next write replaces it.
    #[error("{path}: not the length last written; it will be written whole")]
    Changed {
        /// The file.
        path: PathBuf,
    },
    /// A window could not be encoded.
    #[error("encoding a window of robot {robot}: {why}")]
    Encode {
        /// Whose window.
        robot: u32,
        /// Why.
        why: String,
    },
}

/// A file that could not be read whole, and why.
#[derive(Clone, Debug, PartialEq)]
pub struct Unreadable {
    /// The file.
    pub path: PathBuf,
    /// Why (windows read before the problem are kept).
    pub why: String,
}

/// What [`HistoryStore::load`] found.
#[derive(Debug, Default)]
pub struct Loaded {
    /// The histories read, by robot id.
    pub histories: BTreeMap<u32, PeerHistory>,
    /// Files (or their tails) that could not be read.
    pub unreadable: Vec<Unreadable>,
}

/// What one [`HistoryStore::save`] did.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Saved {
    /// Nothing new to write.
    Unchanged,
    /// Records appended, bytes.
    Appended(u64),
    /// The file written whole, bytes.
    Rewritten(u64),
}

/// A window's record as the file holds it.
#[derive(Clone, Copy, Debug, PartialEq)]
struct Written {
    /// How complete the copy written is ([`KeyframeWindow::completeness`]).
    completeness: (usize, bool),
    /// Bytes of its record, length prefix included.
    bytes: u64,
    /// Where its record starts in the file.
    offset: u64,
}

/// What the store knows of one robot's file.
#[derive(Debug, Default)]
struct FileState {
    /// Its length as the store left it (`None`: not known to end in a whole
    /// record, so the next write replaces it).
    len: Option<u64>,
    /// The newest record of each window it holds, by time key.
    windows: BTreeMap<u64, Written>,
    /// The history's revision when the file was last brought up to date.
    revision: Option<u64>,
    /// Writes failed in a row.
    failures: u32,
    /// Failures counted since the store opened: a job carries the count of
    /// its planning, so the failures of jobs planned before the last
    /// counted one (queued appends that can only fail after it) are not
    /// counted again.
    failures_total: u64,
    /// Plans still to pass over before the next try (after failures: a disk
    /// that is full or gone is not asked again, and the file encoded again,
    /// every period).
    skip: u32,
}

/// Most plans passed over after failures in a row (5 min at the default
/// 10 s period).
const MAX_SKIP: u32 = 31;

/// One agent's folder of histories.
#[derive(Debug)]
pub struct HistoryStore {
    dir: PathBuf,
    fleet_id: String,
    /// The header of the files written: magic, version and mission.
    header: Vec<u8>,
    mission: String,
    files: BTreeMap<u32, FileState>,
}

impl HistoryStore {
    /// The store in `dir` (made if missing) for the fleet `fleet_id` on
    /// `mission` (cut to [`MAX_MISSION_BYTES`]).
    pub fn open(dir: &Path, fleet_id: &str, mission: &str) -> Result<Self, StoreError> {
        std::fs::create_dir_all(dir).map_err(|source| StoreError::Io {
            path: dir.to_path_buf(),
            source,
        })?;
        let mut end = mission.len().min(MAX_MISSION_BYTES);
        while !mission.is_char_boundary(end) {
            end -= 1;
        }
        let mission = &mission[..end];
        let mut header = FILE_MAGIC.to_vec();
        header.extend_from_slice(&FILE_VERSION.to_le_bytes());
        header.extend_from_slice(&(mission.len() as u16).to_le_bytes());
        header.extend_from_slice(mission.as_bytes());
        Ok(Self {
            dir: dir.to_path_buf(),
            fleet_id: fleet_id.to_owned(),
            header,
            mission: mission.to_owned(),
            files: BTreeMap::new(),
        })
    }

    /// The file of robot `robot`'s windows.
    pub fn path_of(&self, robot: u32) -> PathBuf {
        self.dir.join(format!("robot{robot}.fvhs"))
    }

    /// Reads every history file of the folder, each within `limits` (the
    /// memory bound drops windows as it does for received ones).
    pub fn load(&mut self, limits: &HistoryLimits) -> Result<Loaded, StoreError> {
        let entries = std::fs::read_dir(&self.dir).map_err(|source| StoreError::Io {
            path: self.dir.clone(),
            source,
        })?;
        let mut files: Vec<(u32, PathBuf)> = entries
            .filter_map(Result::ok)
            .filter_map(|e| {
                let name = e.file_name();
                let robot = name
                    .to_str()?
                    .strip_prefix("robot")?
                    .strip_suffix(".fvhs")?
                    .parse()
                    .ok()?;
                Some((robot, e.path()))
            })
            .collect();
        files.sort();
        let mut loaded = Loaded::default();
        for (robot, path) in files {
            let mut history = PeerHistory::default();
            let mut file = FileState::default();
            match self.read_file(robot, &path, limits, &mut history, &mut file) {
                Ok(len) => file.len = len,
                Err(stop) => {
                    // A cut last record (a crash in an append) holds nothing
                    // worth keeping; anything else is kept aside.
                    let why = match stop {
                        Stop::CutShort(why) => why,
                        Stop::Unreadable(why) => format!("{why}; {}", set_aside(robot, &path)),
                    };
                    loaded.unreadable.push(Unreadable {
                        path: path.clone(),
                        why,
                    });
                }
            }
            if !history.keyframes.is_empty() {
                // What is on disk is what we hold: no need to write it again.
                file.revision = Some(history.revision);
                loaded.histories.insert(robot, history);
            }
            self.files.insert(robot, file);
        }
        Ok(loaded)
    }

    /// Reads robot `robot`'s file into `history`, noting its records in
    /// `file`; the file's length (`None` for an older format, which the next
    /// write replaces), or why it stopped early (the windows before that are
    /// kept).
    fn read_file(
        &self,
        robot: u32,
        path: &Path,
        limits: &HistoryLimits,
        history: &mut PeerHistory,
        file: &mut FileState,
    ) -> Result<Option<u64>, Stop> {
        let bad = Stop::Unreadable;
        let bound = limits.max_bytes.saturating_mul(FILE_BOUND_FACTOR) + FILE_BOUND_SLACK;
        let f = std::fs::File::open(path).map_err(|e| bad(e.to_string()))?;
        let len = f.metadata().map_err(|e| bad(e.to_string()))?.len();
        if len > bound as u64 {
            return Err(bad(format!(
                "{len} bytes, over the {bound} its history's bound allows"
            )));
        }
        let mut r = std::io::BufReader::new(f);
        let header = parse_header(&mut r)?;
        if let Some(name) = header.mission.as_deref() {
            if name != self.mission {
                return Err(bad(format!("of mission `{name}`, not `{}`", self.mission)));
            }
        }
        let mut records = Records::after(header.len, len, r);
        loop {
            let offset = records.at;
            let Some((index, env, bytes)) = records.next_record()? else {
                break;
            };
            if env.fleet_id != self.fleet_id {
                return Err(bad(format!(
                    "record {index} is of fleet `{}`, not `{}`",
                    env.fleet_id, self.fleet_id
                )));
            }
            if env.robot_id != robot {
                return Err(bad(format!(
                    "record {index} is robot {}'s, in robot {robot}'s file",
                    env.robot_id
                )));
            }
            let Some(kf) = window_of(env) else {
                return Err(bad(format!("record {index} holds no keyframe window")));
            };
            let written = Written {
                completeness: kf.completeness(),
                bytes,
                offset,
            };
            let key = time_key(kf.end_s());
            // A later record of a window is a more complete copy of it.
            if history.add_replayed(kf, limits) != Replayed::AlreadyHeld {
                file.windows.insert(key, written);
            }
        }
        Ok((header.version == FILE_VERSION).then_some(len))
    }

    /// Brings robot `robot`'s file up to date with `history` at once: the
    /// [`HistoryStore::plan`], done on this thread. A file that changed
    /// behind the store's back is written whole.
    pub fn save(&mut self, robot: u32, history: &PeerHistory) -> Result<Saved, StoreError> {
        for _ in 0..2 {
            let Some(job) = self.plan(robot, history)? else {
                return Ok(Saved::Unchanged);
            };
            match job.run() {
                Err(StoreError::Changed { .. }) => {
                    self.failed(robot);
                    self.retry_now();
                }
                Err(e) => {
                    self.failed(robot);
                    return Err(e);
                }
                Ok(saved) => {
                    self.succeeded(robot);
                    return Ok(saved);
                }
            }
        }
        let path = self.path_of(robot);
        Err(StoreError::Changed { path })
    }

    /// The file work that brings robot `robot`'s file up to date with
    /// `history` (`None`: nothing to write): the windows new or more complete
    /// since they were last written, appended, or the whole file when it
    /// would grow past [`COMPACT_FACTOR`] times what the history needs (or is
    /// not known to end in a whole record). New records are encoded here (a
    /// compaction copies the others from the file); the store takes the write
    /// as done, so a job that fails must be reported with
    /// [`HistoryStore::failed`].
    pub fn plan(
        &mut self,
        robot: u32,
        history: &PeerHistory,
    ) -> Result<Option<WriteJob>, StoreError> {
        let path = self.path_of(robot);
        let file = self.files.entry(robot).or_default();
        if file.len.is_some() && file.revision == Some(history.revision) {
            return Ok(None);
        }
        if file.skip > 0 {
            file.skip -= 1;
            return Ok(None);
        }
        // The records the history needs: the ones in the file, and the new.
        let mut needed = 0u64;
        let mut new: Vec<NewRecord> = Vec::new();
        for (&key, kf) in &history.keyframes {
            match file.windows.get(&key) {
                Some(w) if w.completeness == kf.completeness() => needed += w.bytes,
                _ => {
                    let rec = record(&self.fleet_id, robot, key, kf)?;
                    needed += rec.len() as u64;
                    new.push((key, kf.completeness(), rec));
                }
            }
        }
        let grown: u64 = new.iter().map(|(_, _, r)| r.len() as u64).sum();
        file.revision = Some(history.revision);
        match file.len {
            Some(len) if len + grown <= COMPACT_FACTOR * needed + COMPACT_SLACK => {
                if new.is_empty() {
                    return Ok(None);
                }
                let (bytes, end) = lay_out(new, len, &mut file.windows);
                file.len = Some(end);
                Ok(Some(WriteJob {
                    robot,
                    path,
                    planned_after: file.failures_total,
                    kind: JobKind::Append {
                        expected_len: len,
                        bytes,
                    },
                }))
            }
            Some(len) => {
                // Compaction: the records still needed are copied from the
                // file as they are (the writer thread reads them back), only
                // the new ones are encoded here.
                let mut windows = BTreeMap::new();
                let mut copied = Vec::new();
                let mut offset = self.header.len() as u64;
                let new_keys: std::collections::BTreeSet<u64> =
                    new.iter().map(|(k, _, _)| *k).collect();
                for (&key, w) in &file.windows {
                    if history.keyframes.contains_key(&key) && !new_keys.contains(&key) {
                        copied.push((w.offset, w.bytes));
                        windows.insert(key, Written { offset, ..*w });
                        offset += w.bytes;
                    }
                }
                let (bytes, end) = lay_out(new, offset, &mut windows);
                file.windows = windows;
                file.len = Some(end);
                Ok(Some(WriteJob {
                    robot,
                    path,
                    planned_after: file.failures_total,
                    kind: JobKind::Compact {
                        expected_len: len,
                        header: self.header.clone(),
                        copied,
                        bytes,
                    },
                }))
            }
            None => {
                // Whole: every window the history holds, encoded, the file
                // replaced (a new file, or one not known to end well).
                let mut out = Vec::with_capacity(needed as usize + self.header.len());
                out.extend_from_slice(&self.header);
                let mut windows = BTreeMap::new();
                for (&key, kf) in &history.keyframes {
                    let rec = record(&self.fleet_id, robot, key, kf)?;
                    let bytes = rec.len() as u64;
                    let offset = out.len() as u64;
                    out.extend_from_slice(&rec);
                    windows.insert(
                        key,
                        Written {
                            completeness: kf.completeness(),
                            bytes,
                            offset,
                        },
                    );
                }
                file.windows = windows;
                file.len = Some(out.len() as u64);
                Ok(Some(WriteJob {
                    robot,
                    path,
                    planned_after: file.failures_total,
                    kind: JobKind::Replace { bytes: out },
                }))
            }
        }
    }

    /// A job of robot `robot`'s file failed: what the file holds is no
    /// longer known, so the next try writes it whole. After the second
    /// failure in a row, the next try waits: 1, 3, 7, ... up to [`MAX_SKIP`]
    /// plans.
    pub fn failed(&mut self, robot: u32) {
        if let Some(file) = self.files.get_mut(&robot) {
            file.len = None;
            file.revision = None;
            file.failures = file.failures.saturating_add(1);
            file.failures_total += 1;
            file.skip = ((1u32 << (file.failures - 1).min(5)) - 1).min(MAX_SKIP);
        }
    }

    /// A job of robot `robot`'s file failed, planned when `planned_after`
    /// failures of it had been counted ([`WriteJob::planned_after`]). A job
    /// planned before the last counted failure says nothing new (the queued
    /// appends behind a failed write fail with it): the file is written
    /// whole next time, and the back-off does not grow.
    pub fn failed_job(&mut self, robot: u32, planned_after: u64) {
        match self.files.get_mut(&robot) {
            Some(file) if planned_after < file.failures_total => {
                file.len = None;
                file.revision = None;
            }
            _ => self.failed(robot),
        }
    }

    /// A job of robot `robot`'s file was written.
    pub fn succeeded(&mut self, robot: u32) {
        if let Some(file) = self.files.get_mut(&robot) {
            file.failures = 0;
        }
    }

    /// The next plans try every file, whatever failed before (the last write
    /// of a run).
    pub fn retry_now(&mut self) {
        for file in self.files.values_mut() {
            file.skip = 0;
        }
    }
}

/// A new record: its window's key, completeness and bytes.
type NewRecord = (u64, (usize, bool), Vec<u8>);

/// Lays `new` records out one after the other from `offset`, noting each in
/// `windows`: their bytes, and the offset after them.
fn lay_out(
    new: Vec<NewRecord>,
    mut offset: u64,
    windows: &mut BTreeMap<u64, Written>,
) -> (Vec<u8>, u64) {
    let mut bytes = Vec::with_capacity(new.iter().map(|(_, _, r)| r.len()).sum());
    for (key, completeness, rec) in new {
        let n = rec.len() as u64;
        bytes.extend_from_slice(&rec);
        windows.insert(
            key,
            Written {
                completeness,
                bytes: n,
                offset,
            },
        );
        offset += n;
    }
    (bytes, offset)
}

/// The file work of one [`HistoryStore::plan`]: no encoding left, only I/O,
/// so another thread can do it ([`StoreWriter`]).
#[derive(Debug)]
pub struct WriteJob {
    robot: u32,
    path: PathBuf,
    kind: JobKind,
    /// The file's failures counted when the job was planned.
    planned_after: u64,
}

#[derive(Debug)]
enum JobKind {
    /// Records appended to a file that must be `expected_len` bytes long.
    Append { expected_len: u64, bytes: Vec<u8> },
    /// The whole file, written beside it and renamed over it.
    Replace { bytes: Vec<u8> },
    /// A file of `expected_len` bytes rewritten as `header`, its records at
    /// `copied` (offset, bytes) and `bytes`, beside it and renamed over it.
    Compact {
        expected_len: u64,
        header: Vec<u8>,
        copied: Vec<(u64, u64)>,
        bytes: Vec<u8>,
    },
}

impl WriteJob {
    /// Whose file.
    pub fn robot(&self) -> u32 {
        self.robot
    }

    /// The failures of its file counted when it was planned (for
    /// [`HistoryStore::failed_job`]).
    pub fn planned_after(&self) -> u64 {
        self.planned_after
    }

    /// What the job does: `append`, `whole` (every record encoded: a new
    /// file, or one not known to end well) or `compaction` (the records still
    /// needed copied from the file, the new ones after them).
    pub fn kind(&self) -> &'static str {
        match self.kind {
            JobKind::Append { .. } => "append",
            JobKind::Replace { .. } => "whole",
            JobKind::Compact { .. } => "compaction",
        }
    }

    /// Bytes held in memory until the job is done.
    pub fn len(&self) -> usize {
        match &self.kind {
            JobKind::Append { bytes, .. } | JobKind::Replace { bytes } => bytes.len(),
            JobKind::Compact { header, bytes, .. } => header.len() + bytes.len(),
        }
    }

    /// Whether there is nothing to write (never for a planned job).
    pub fn is_empty(&self) -> bool {
        self.len() == 0
    }

    /// Writes and syncs. An append to a file whose length is not the one
    /// planned (it changed behind the store's back, or an earlier job failed
    /// part-way) writes nothing: [`StoreError::Changed`].
    pub fn run(&self) -> Result<Saved, StoreError> {
        let io = |source| StoreError::Io {
            path: self.path.clone(),
            source,
        };
        match &self.kind {
            JobKind::Append {
                expected_len,
                bytes,
            } => {
                let on_disk = std::fs::metadata(&self.path).map(|m| m.len()).ok();
                if on_disk != Some(*expected_len) {
                    return Err(StoreError::Changed {
                        path: self.path.clone(),
                    });
                }
                let mut f = std::fs::OpenOptions::new()
                    .append(true)
                    .open(&self.path)
                    .map_err(io)?;
                f.write_all(bytes).map_err(io)?;
                f.sync_data().map_err(io)?;
                Ok(Saved::Appended(bytes.len() as u64))
            }
            JobKind::Replace { bytes } => {
                let tmp = self.path.with_extension("fvhs.tmp");
                {
                    let mut f = std::fs::File::create(&tmp).map_err(io)?;
                    f.write_all(bytes).map_err(io)?;
                    f.sync_data().map_err(io)?;
                }
                std::fs::rename(&tmp, &self.path).map_err(io)?;
                Ok(Saved::Rewritten(bytes.len() as u64))
            }
            JobKind::Compact {
                expected_len,
                header,
                copied,
                bytes,
            } => {
                let mut old = std::fs::File::open(&self.path).map_err(io)?;
                if old.metadata().map_err(io)?.len() != *expected_len {
                    return Err(StoreError::Changed {
                        path: self.path.clone(),
                    });
                }
                let tmp = self.path.with_extension("fvhs.tmp");
                let mut written = 0u64;
                {
                    let mut f = std::io::BufWriter::new(std::fs::File::create(&tmp).map_err(io)?);
                    f.write_all(header).map_err(io)?;
                    written += header.len() as u64;
                    for &(offset, n) in copied {
                        old.seek(std::io::SeekFrom::Start(offset)).map_err(io)?;
                        let copied = std::io::copy(&mut (&mut old).take(n), &mut f).map_err(io)?;
                        if copied != n {
                            return Err(StoreError::Changed {
                                path: self.path.clone(),
                            });
                        }
                        written += n;
                    }
                    f.write_all(bytes).map_err(io)?;
                    written += bytes.len() as u64;
                    let f = f.into_inner().map_err(|e| io(e.into_error()))?;
                    f.sync_data().map_err(io)?;
                }
                std::fs::rename(&tmp, &self.path).map_err(io)?;
                Ok(Saved::Rewritten(written))
            }
        }
    }
}

/// A finished [`WriteJob`].
#[derive(Debug)]
pub struct Done {
    /// Whose file.
    pub robot: u32,
    /// Its file's failures counted when the job was planned.
    pub planned_after: u64,
    /// What was written, or why not.
    pub result: Result<Saved, StoreError>,
    /// Wall time of the write, s (on the writer's thread).
    pub wall_s: f64,
}

/// Bytes of write jobs queued for [`StoreWriter`] from which no new job is
/// planned (so at most this plus one job's bytes wait in memory).
pub const MAX_QUEUED_BYTES: usize = 64 << 20;

/// A thread that does the store's file work, so an agent's frames never wait
/// for a disk (writing a 64 MiB file at an SD card's 10-20 MB/s takes 3-6 s).
/// Jobs are done in order, one at a time.
#[derive(Debug)]
pub struct StoreWriter {
    jobs: Option<std::sync::mpsc::Sender<WriteJob>>,
    done: std::sync::mpsc::Receiver<Done>,
    queued: std::sync::Arc<std::sync::atomic::AtomicUsize>,
    thread: Option<std::thread::JoinHandle<()>>,
}

impl StoreWriter {
    /// Starts the writer thread.
    pub fn spawn() -> std::io::Result<Self> {
        use std::sync::atomic::Ordering;
        let (jobs, rx) = std::sync::mpsc::channel::<WriteJob>();
        let (tx, done) = std::sync::mpsc::channel();
        let queued = std::sync::Arc::new(std::sync::atomic::AtomicUsize::new(0));
        let counter = std::sync::Arc::clone(&queued);
        let thread = std::thread::Builder::new()
            .name("history-store".into())
            .spawn(move || {
                for job in rx {
                    let started = std::time::Instant::now();
                    let result = job.run();
                    counter.fetch_sub(job.len(), Ordering::AcqRel);
                    let done = Done {
                        robot: job.robot,
                        planned_after: job.planned_after,
                        result,
                        wall_s: started.elapsed().as_secs_f64(),
                    };
                    if tx.send(done).is_err() {
                        return;
                    }
                }
            })?;
        Ok(Self {
            jobs: Some(jobs),
            done,
            queued,
            thread: Some(thread),
        })
    }

    /// Queues `job`; it is handed back if the thread is gone. The caller
    /// keeps the queue bounded: no plan while [`StoreWriter::busy`].
    pub fn submit(&self, job: WriteJob) -> Result<(), WriteJob> {
        use std::sync::atomic::Ordering;
        let Some(jobs) = self.jobs.as_ref() else {
            return Err(job);
        };
        self.queued.fetch_add(job.len(), Ordering::AcqRel);
        jobs.send(job).map_err(|e| {
            self.queued.fetch_sub(e.0.len(), Ordering::AcqRel);
            e.0
        })
    }

    /// Whether [`MAX_QUEUED_BYTES`] wait for the disk: a plan now would hold
    /// its records in memory behind them (the disk is slower than the
    /// histories grow), so it waits for a later period.
    pub fn busy(&self) -> bool {
        self.queued_bytes() >= MAX_QUEUED_BYTES
    }

    /// Bytes queued and not written yet.
    pub fn queued_bytes(&self) -> usize {
        self.queued.load(std::sync::atomic::Ordering::Acquire)
    }

    /// The jobs finished since the last call.
    pub fn finished(&self) -> Vec<Done> {
        self.done.try_iter().collect()
    }

    /// Waits for every queued job, and stops the thread: the jobs finished
    /// since [`StoreWriter::finished`] was last called.
    pub fn finish(mut self) -> Vec<Done> {
        self.jobs = None;
        if let Some(t) = self.thread.take() {
            if t.join().is_err() {
                tracing::warn!("history store: the writer thread panicked");
            }
        }
        self.done.try_iter().collect()
    }
}

impl Drop for StoreWriter {
    fn drop(&mut self) {
        self.jobs = None;
        if let Some(t) = self.thread.take() {
            let _ = t.join();
        }
    }
}

/// Why reading a file stopped before its end.
#[derive(Debug)]
enum Stop {
    /// Its last record is cut short: a crash in an append. What was read is
    /// all there is; the next write replaces the file.
    CutShort(String),
    /// Anything else: another fleet's, damaged, not a history file.
    Unreadable(String),
}

/// What a history file holds, as `agent store` shows it: read with the
/// same bounds as at start, but whatever its fleet and mission.
#[derive(Clone, Debug, Default, PartialEq, serde::Serialize)]
pub struct FileSummary {
    /// The file.
    pub path: PathBuf,
    /// Its bytes.
    pub bytes: u64,
    /// Its format version (`None`: not a history file).
    pub format: Option<u16>,
    /// The mission its header names (format 2 on).
    pub mission: Option<String>,
    /// The fleet id and robot of its first record.
    pub fleet_id: Option<String>,
    /// The robot whose windows it holds.
    pub robot: Option<u32>,
    /// Records read.
    pub records: usize,
    /// Distinct windows among them, and of those the ones held whole.
    pub windows: usize,
    /// Windows held whole (most complete record of each).
    pub whole: usize,
    /// End times of the first and last window, s.
    pub span_s: Option<(f64, f64)>,
    /// Why reading stopped before the end, if it did.
    pub problem: Option<String>,
}

/// Reads `path` as a history file and sums up what it holds.
pub fn inspect(path: &Path) -> FileSummary {
    let mut out = FileSummary {
        path: path.to_path_buf(),
        ..FileSummary::default()
    };
    let opened = std::fs::File::open(path).and_then(|f| Ok((f.metadata()?.len(), f)));
    let (len, f) = match opened {
        Ok(x) => x,
        Err(e) => {
            out.problem = Some(e.to_string());
            return out;
        }
    };
    out.bytes = len;
    let mut r = std::io::BufReader::new(f);
    let stop = |e: Stop| match e {
        Stop::CutShort(why) | Stop::Unreadable(why) => why,
    };
    let header = match parse_header(&mut r) {
        Ok(h) => h,
        Err(e) => {
            out.problem = Some(stop(e));
            return out;
        }
    };
    out.format = Some(header.version);
    out.mission = header.mission;
    let mut windows: BTreeMap<u64, KeyframeWindow> = BTreeMap::new();
    let mut records = Records::after(header.len, len, r);
    loop {
        match records.next_record() {
            Ok(Some((_, env, _))) => {
                out.records += 1;
                out.fleet_id.get_or_insert_with(|| env.fleet_id.clone());
                out.robot.get_or_insert(env.robot_id);
                if let Some(kf) = window_of(env) {
                    let key = time_key(kf.end_s());
                    let better = windows
                        .get(&key)
                        .is_none_or(|held| kf.completeness() > held.completeness());
                    if better {
                        windows.insert(key, kf);
                    }
                }
            }
            Ok(None) => break,
            Err(e) => {
                out.problem = Some(stop(e));
                break;
            }
        }
    }
    out.windows = windows.len();
    out.whole = windows.values().filter(|kf| kf.is_whole()).count();
    out.span_s = windows
        .values()
        .next()
        .zip(windows.values().next_back())
        .map(|(a, b)| (a.end_s(), b.end_s()));
    out
}

/// A file's header.
struct Header {
    /// Its bytes.
    len: u64,
    /// The format version.
    version: u16,
    /// The mission it names.
    mission: Option<String>,
}

/// Reads a file's header, or says why it is not a history file this build
/// reads.
fn parse_header(r: &mut impl Read) -> Result<Header, Stop> {
    let bad = Stop::Unreadable;
    let mut prefix = [0u8; PREFIX_LEN as usize];
    if r.read_exact(&mut prefix).is_err() || prefix[..4] != FILE_MAGIC {
        return Err(bad("not a history file (no FVHS header)".into()));
    }
    let version = u16::from_le_bytes([prefix[4], prefix[5]]);
    if !READABLE_VERSIONS.contains(&version) {
        return Err(bad(format!(
            "format version {version}; this build reads {READABLE_VERSIONS:?}"
        )));
    }
    let cut = || bad("the header is cut short".into());
    let mut n = [0u8; 2];
    r.read_exact(&mut n).map_err(|_| cut())?;
    let n = usize::from(u16::from_le_bytes(n));
    if n > MAX_MISSION_BYTES {
        return Err(bad(format!("a mission name of {n} bytes")));
    }
    let mut name = vec![0u8; n];
    r.read_exact(&mut name).map_err(|_| cut())?;
    Ok(Header {
        len: PREFIX_LEN + 2 + n as u64,
        version,
        mission: Some(String::from_utf8_lossy(&name).into_owned()),
    })
}

/// A file's records, read one at a time, each decoded with the bounds and
/// checks of a network message.
struct Records<R> {
    r: R,
    /// Offset of the next record.
    at: u64,
    /// The file's length.
    len: u64,
    /// Index of the next record.
    index: usize,
}

impl<R: Read> Records<R> {
    /// The records of a file of `len` bytes, `r` standing after its header of
    /// `header_len` bytes.
    fn after(header_len: u64, len: u64, r: R) -> Self {
        Self {
            r,
            at: header_len,
            len,
            index: 0,
        }
    }

    /// The next record: its index, its message and its bytes (length prefix
    /// included); `None` at the end of the file.
    fn next_record(&mut self) -> Result<Option<(usize, Envelope, u64)>, Stop> {
        if self.at >= self.len {
            return Ok(None);
        }
        let (index, at) = (self.index, self.at);
        let cut = || Stop::CutShort(format!("record {index} is cut short at byte {at}"));
        let mut prefix = [0u8; 4];
        self.r.read_exact(&mut prefix).map_err(|_| cut())?;
        let n = u64::from(u32::from_le_bytes(prefix));
        // A record is one message: a damaged length makes it allocate one
        // message at most.
        if n > Limits::default().max_message_bytes as u64 {
            return Err(Stop::Unreadable(format!(
                "record {index} at byte {at} claims {n} bytes, more than a message may hold"
            )));
        }
        if at + 4 + n > self.len {
            return Err(cut());
        }
        let mut record = vec![0u8; n as usize];
        self.r.read_exact(&mut record).map_err(|_| cut())?;
        let env = decode(&record).map_err(|e| Stop::Unreadable(format!("record {index}: {e}")))?;
        self.at += 4 + n;
        self.index += 1;
        Ok(Some((index, env, 4 + n)))
    }
}

/// The keyframe window a record carries.
fn window_of(env: Envelope) -> Option<KeyframeWindow> {
    match env.body {
        Body::HistoryReplay(r) => r.window.map(KeyframeWindow::from_wire),
        _ => None,
    }
}

/// Moves a file that could not be read to its end out of the way, so the
/// next write (which keeps what was read before the problem) loses nothing
/// of it: another fleet's file, or records past a damaged one. Says where
/// it went.
fn set_aside(robot: u32, path: &Path) -> String {
    let stamp = std::time::SystemTime::now()
        .duration_since(std::time::UNIX_EPOCH)
        .map_or(0, |d| d.as_secs());
    let aside = path.with_file_name(format!("robot{robot}.fvhs.unreadable-{stamp}"));
    match std::fs::rename(path, &aside) {
        Ok(()) => format!("kept as {}", aside.display()),
        Err(e) => format!("could not be set aside ({e}): the next write replaces it"),
    }
}

/// One record: the length prefix and the encoded window of robot `robot`
/// (its time key as the sequence number).
fn record(
    fleet_id: &str,
    robot: u32,
    key: u64,
    kf: &KeyframeWindow,
) -> Result<Vec<u8>, StoreError> {
    let env = Envelope {
        fleet_id: fleet_id.to_owned(),
        robot_id: robot,
        seq: key,
        stamp_s: kf.end_s(),
        sent_wall_ns: 0,
        body: Body::HistoryReplay(Box::new(HistoryReplay {
            for_robots: Vec::new(),
            window: Some(kf.to_wire()),
            part: None,
            completes: Vec::new(),
            answered: Vec::new(),
        })),
    };
    let bytes = encode(&env).map_err(|e| StoreError::Encode {
        robot,
        why: e.to_string(),
    })?;
    let mut rec = Vec::with_capacity(4 + bytes.len());
    rec.extend_from_slice(&(bytes.len() as u32).to_le_bytes());
    rec.extend_from_slice(&bytes);
    Ok(rec)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::history_retention::Retention;
    use common::messages::samples;

    const MISSION: &str = "loop, seed 1";

    fn limits() -> HistoryLimits {
        HistoryLimits {
            max_bytes: 64 << 20,
            recent_s: 2.0,
            retention: Retention::Oldest,
        }
    }

    /// A history of 5 keyframe windows with their tracks and descriptors.
    fn history() -> PeerHistory {
        let mut h = PeerHistory::default();
        grow(&mut h, 0..=50, &limits(), true);
        h
    }

    /// Adds the frames `frames` to `h`, a keyframe window every 10th from
    /// the 10th on (with its descriptors if `descriptors`).
    fn grow(
        h: &mut PeerHistory,
        frames: std::ops::RangeInclusive<u64>,
        limits: &HistoryLimits,
        descriptors: bool,
    ) {
        for f in frames {
            let Body::Tracks(t) = samples::tracks(f, 20).body else {
                continue;
            };
            h.add_tracks(t, limits);
            if f >= 10 && f % 10 == 0 {
                if let Body::Snapshot(s) = samples::snapshot(f, 11, 0, true).body {
                    h.add_snapshot(s, limits);
                }
                if descriptors {
                    add_descriptors(h, f, limits);
                }
            }
        }
    }

    fn add_descriptors(h: &mut PeerHistory, frame: u64, limits: &HistoryLimits) {
        if let Body::Descriptors(d) = samples::descriptors(frame, 20, true).body {
            h.add_descriptors(d, limits);
        }
    }

    fn load(dir: &Path) -> (HistoryStore, Loaded) {
        let mut store = HistoryStore::open(dir, "fleet", MISSION).unwrap();
        let loaded = store.load(&limits()).unwrap();
        (store, loaded)
    }

    #[test]
    fn a_write_appends_only_the_windows_new_or_more_complete() {
        let dir = tempfile::tempdir().unwrap();
        let mut h = history();
        let mut store = HistoryStore::open(dir.path(), "fleet", MISSION).unwrap();
        let Saved::Rewritten(first) = store.save(3, &h).unwrap() else {
            panic!("a new file is written whole");
        };
        let size = || {
            std::fs::metadata(dir.path().join("robot3.fvhs"))
                .unwrap()
                .len()
        };
        assert_eq!(size(), first);

        // One window more, its descriptors late: one record appended.
        grow(&mut h, 51..=60, &limits(), false);
        assert_eq!(h.keyframes.len(), 6);
        assert!(!h.keyframes.values().last().unwrap().is_whole());
        let Saved::Appended(one) = store.save(3, &h).unwrap() else {
            panic!("appended");
        };
        assert!(one < first / 4, "{one} of {first}");
        assert_eq!(size(), first + one);
        assert_eq!(store.save(3, &h).unwrap(), Saved::Unchanged);

        // The descriptors arrive: that window's record again, whole now.
        add_descriptors(&mut h, 60, &limits());
        assert!(h.keyframes.values().last().unwrap().is_whole());
        let Saved::Appended(again) = store.save(3, &h).unwrap() else {
            panic!("appended");
        };
        assert!(again > one, "with the descriptors: {again} > {one}");
        assert_eq!(size(), first + one + again);

        // Read back: the most complete copy of each window, and nothing to
        // write until something changes.
        let (mut back, loaded) = load(dir.path());
        assert!(loaded.unreadable.is_empty(), "{:?}", loaded.unreadable);
        assert_eq!(loaded.histories[&3].keyframes, h.keyframes);
        assert_eq!(
            back.save(3, &loaded.histories[&3]).unwrap(),
            Saved::Unchanged
        );
    }

    #[test]
    fn the_writer_thread_writes_what_was_planned_and_the_files_read_back() {
        let dir = tempfile::tempdir().unwrap();
        let mut store = HistoryStore::open(dir.path(), "fleet", MISSION).unwrap();
        let writer = StoreWriter::spawn().unwrap();
        let mut h = history();
        let mut done = Vec::new();
        // The first plan is the whole file, then one appended window a period.
        for k in 0..4u64 {
            let job = store.plan(2, &h).unwrap().unwrap();
            assert!(writer.submit(job).is_ok());
            done.extend(writer.finished());
            grow(&mut h, 51 + k * 10..=60 + k * 10, &limits(), true);
        }
        assert!(store.plan(2, &h).unwrap().is_some());
        // Planned, not handed to the writer: the store must write it whole.
        store.failed(2);
        let job = store.plan(2, &h).unwrap().unwrap();
        assert!(writer.submit(job).is_ok());
        done.extend(writer.finish());
        assert_eq!(done.len(), 5, "{done:?}");
        assert!(done.iter().all(|d| d.result.is_ok()), "{done:?}");
        let kinds: Vec<bool> = done
            .iter()
            .map(|d| matches!(d.result, Ok(Saved::Rewritten(_))))
            .collect();
        assert_eq!(kinds, [true, false, false, false, true]);
        let (_, loaded) = load(dir.path());
        assert!(loaded.unreadable.is_empty(), "{:?}", loaded.unreadable);
        assert_eq!(loaded.histories[&2].keyframes, h.keyframes);
    }

    #[test]
    fn a_file_that_cannot_be_written_is_tried_less_and_less_often_then_written_whole() {
        let dir = tempfile::tempdir().unwrap();
        let mut store = HistoryStore::open(dir.path(), "fleet", MISSION).unwrap();
        let h = history();
        // A folder where the new file is made: every whole write fails (as on
        // a full or vanished disk; the tests run as root, so permissions
        // would not stop it).
        let blocker = store.path_of(7).with_extension("fvhs.tmp");
        std::fs::create_dir(&blocker).unwrap();
        let mut tries = Vec::new();
        for period in 0..20 {
            if let Some(job) = store.plan(7, &h).unwrap() {
                assert!(job.run().is_err());
                store.failed(7);
                tries.push(period);
            }
        }
        assert_eq!(tries, [0, 1, 3, 7, 15]);
        // The disk is back; the last write of a run tries at once.
        std::fs::remove_dir(&blocker).unwrap();
        store.retry_now();
        let job = store.plan(7, &h).unwrap().unwrap();
        assert_eq!(job.kind(), "whole");
        assert!(matches!(job.run(), Ok(Saved::Rewritten(_))));
        store.succeeded(7);
        let (_, loaded) = load(dir.path());
        assert_eq!(loaded.histories[&7].keyframes, h.keyframes);
        // Once written, a failure is tried again at the next period.
        store.failed(7);
        assert!(store.plan(7, &h).unwrap().is_some());
    }

    #[test]
    fn the_appends_queued_behind_a_failed_write_do_not_lengthen_the_back_off() {
        let dir = tempfile::tempdir().unwrap();
        let mut store = HistoryStore::open(dir.path(), "fleet", MISSION).unwrap();
        let mut h = history();
        assert!(matches!(store.save(4, &h), Ok(Saved::Rewritten(_))));
        // Three periods' appends queued for the writer thread, then the file
        // is cut before the first runs: all three fail, for one cause.
        let mut jobs = Vec::new();
        for k in 0..3u64 {
            grow(&mut h, 51 + k * 10..=60 + k * 10, &limits(), true);
            jobs.push(store.plan(4, &h).unwrap().unwrap());
        }
        let path = store.path_of(4);
        let len = std::fs::metadata(&path).unwrap().len();
        let f = std::fs::OpenOptions::new().write(true).open(&path).unwrap();
        f.set_len(len - 3).unwrap();
        for job in &jobs {
            assert!(job.run().is_err());
            store.failed_job(4, job.planned_after());
        }
        // One failure in a row: the next period tries again, whole.
        let job = store.plan(4, &h).unwrap().unwrap();
        assert_eq!(job.kind(), "whole");
        // Planned after the counted failure, its failure counts: the second
        // in a row, so one period is passed over.
        store.failed_job(4, job.planned_after());
        assert!(store.plan(4, &h).unwrap().is_none());
        assert!(store.plan(4, &h).unwrap().is_some());
    }

    #[test]
    fn an_append_to_a_file_changed_behind_the_stores_back_writes_nothing() {
        let dir = tempfile::tempdir().unwrap();
        let mut store = HistoryStore::open(dir.path(), "fleet", MISSION).unwrap();
        let mut h = history();
        assert!(matches!(store.save(5, &h), Ok(Saved::Rewritten(_))));
        // Someone cuts the file; the next planned append must not land after
        // a torn record.
        let path = store.path_of(5);
        let len = std::fs::metadata(&path).unwrap().len();
        let f = std::fs::OpenOptions::new().write(true).open(&path).unwrap();
        f.set_len(len - 3).unwrap();
        grow(&mut h, 51..=60, &limits(), true);
        let job = store.plan(5, &h).unwrap().unwrap();
        assert!(matches!(job.run(), Err(StoreError::Changed { .. })));
        assert_eq!(std::fs::metadata(&path).unwrap().len(), len - 3);
        // Reported, the file is written whole at the next write.
        store.failed(5);
        assert!(matches!(store.save(5, &h), Ok(Saved::Rewritten(_))));
        let (_, loaded) = load(dir.path());
        assert_eq!(loaded.histories[&5].keyframes, h.keyframes);
        // `save` does both at once.
        let f = std::fs::OpenOptions::new().write(true).open(&path).unwrap();
        let len = f.metadata().unwrap().len();
        f.set_len(len - 3).unwrap();
        grow(&mut h, 61..=70, &limits(), true);
        assert!(matches!(store.save(5, &h), Ok(Saved::Rewritten(_))));
    }

    #[test]
    fn a_file_grown_past_its_factor_is_written_whole_again() {
        let dir = tempfile::tempdir().unwrap();
        // Room for about 20 windows: the oldest leave as new ones come, and
        // the log keeps their records until it is rewritten.
        let bounded = HistoryLimits {
            max_bytes: history().bytes() * 4,
            ..limits()
        };
        let mut h = PeerHistory::default();
        let mut store = HistoryStore::open(dir.path(), "fleet", MISSION).unwrap();
        let (mut rewrites, mut written, mut whole) = (0, 0, 0);
        for k in 0..300u64 {
            grow(&mut h, k * 10 + 1..=k * 10 + 10, &bounded, true);
            match store.save(1, &h).unwrap() {
                Saved::Rewritten(n) => {
                    rewrites += 1;
                    written += n;
                }
                Saved::Appended(n) => written += n,
                Saved::Unchanged => {}
            }
            let len = std::fs::metadata(store.path_of(1)).unwrap().len();
            let needed: u64 = store.files[&1]
                .windows
                .iter()
                .filter(|(k, _)| h.keyframes.contains_key(k))
                .map(|(_, w)| w.bytes)
                .sum();
            assert!(
                len <= COMPACT_FACTOR * needed + COMPACT_SLACK,
                "{len} for {needed}"
            );
            // What writing the whole file every time would have cost.
            whole += needed + store.header.len() as u64;
        }
        assert!(h.dropped_keyframes > 250, "{}", h.dropped_keyframes);
        assert!(h.keyframes.len() > 15, "{}", h.keyframes.len());
        assert!(
            rewrites > 1,
            "compacted at least once after the first write"
        );
        // Appending costs about a record per window (and the compactions
        // about as much again), not the whole file per write.
        let record = store.files[&1]
            .windows
            .values()
            .map(|w| w.bytes)
            .max()
            .unwrap();
        assert!(
            written <= 3 * 300 * record,
            "{written} bytes, {record} per record"
        );
        assert!(
            written * 5 < whole,
            "{written} bytes against {whole} written whole"
        );
        let mut back = HistoryStore::open(dir.path(), "fleet", MISSION).unwrap();
        let loaded = back.load(&bounded).unwrap();
        let keys = |h: &PeerHistory| h.keyframes.keys().copied().collect::<Vec<_>>();
        assert_eq!(keys(&loaded.histories[&1]), keys(&h));
        assert_eq!(loaded.histories[&1].keyframes, h.keyframes);
        // The records are where the store planned them (compactions copy
        // records by offset): read back, the file says the same.
        assert_eq!(back.files[&1].len, store.files[&1].len);
        let live = |st: &HistoryStore| -> Vec<(u64, Written)> {
            st.files[&1]
                .windows
                .iter()
                .filter(|(k, _)| h.keyframes.contains_key(k))
                .map(|(k, w)| (*k, *w))
                .collect()
        };
        assert_eq!(live(&back), live(&store));
    }

    #[test]
    fn another_missions_file_and_an_older_formats_are_set_aside() {
        let dir = tempfile::tempdir().unwrap();
        let h = history();
        let mut before = HistoryStore::open(dir.path(), "fleet", "loop, seed 2").unwrap();
        before.save(4, &h).unwrap();
        let (_, loaded) = load(dir.path());
        let why = &loaded.unreadable[0].why;
        assert!(
            why.contains("of mission `loop, seed 2`, not `loop, seed 1`"),
            "{why}"
        );
        assert!(why.contains("kept as"), "{why}");
        assert!(loaded.histories.is_empty());

        // Format 2 (records of an older wire version): kept aside whole, not
        // read as nothing and overwritten.
        let dir = tempfile::tempdir().unwrap();
        let mut store = HistoryStore::open(dir.path(), "fleet", MISSION).unwrap();
        store.save(4, &h).unwrap();
        let mut old = std::fs::read(store.path_of(4)).unwrap();
        old[4..6].copy_from_slice(&2u16.to_le_bytes());
        std::fs::write(store.path_of(4), &old).unwrap();
        let (_, loaded) = load(dir.path());
        let why = &loaded.unreadable[0].why;
        assert!(why.contains("format version 2"), "{why}");
        assert!(why.contains("kept as"), "{why}");
        assert!(loaded.histories.is_empty());
        let kept: Vec<Vec<u8>> = std::fs::read_dir(dir.path())
            .unwrap()
            .filter_map(|e| {
                let p = e.ok()?.path();
                let name = p.file_name()?.to_string_lossy().into_owned();
                name.contains("unreadable")
                    .then(|| std::fs::read(&p).unwrap())
            })
            .collect();
        assert_eq!(kept, vec![old]);
    }

    #[test]
    fn inspecting_a_file_shows_its_mission_fleet_windows_and_damage() {
        let dir = tempfile::tempdir().unwrap();
        let mut h = history();
        let mut store = HistoryStore::open(dir.path(), "fleet", MISSION).unwrap();
        store.save(5, &h).unwrap();
        grow(&mut h, 51..=60, &limits(), false);
        store.save(5, &h).unwrap();
        add_descriptors(&mut h, 60, &limits());
        store.save(5, &h).unwrap();
        let path = store.path_of(5);
        let s = inspect(&path);
        assert_eq!(s.format, Some(FILE_VERSION));
        assert_eq!(s.mission.as_deref(), Some(MISSION));
        assert_eq!(s.fleet_id.as_deref(), Some("fleet"));
        assert_eq!(s.robot, Some(5));
        assert_eq!((s.records, s.windows, s.whole), (7, 6, 6));
        let (first, last) = s.span_s.unwrap();
        assert!(last > first);
        assert_eq!(s.problem, None);
        assert_eq!(s.bytes, std::fs::metadata(&path).unwrap().len());

        let mut cut = std::fs::read(&path).unwrap();
        cut.truncate(cut.len() - 10);
        std::fs::write(&path, &cut).unwrap();
        let s = inspect(&path);
        assert_eq!((s.records, s.windows, s.whole), (6, 6, 5));
        assert!(s.problem.unwrap().contains("record 6 is cut short"));
        std::fs::write(&path, b"hello").unwrap();
        assert!(inspect(&path).problem.unwrap().contains("FVHS"));
        assert!(inspect(&dir.path().join("none")).problem.is_some());
    }

    #[test]
    fn a_record_cut_by_a_crash_is_dropped_and_the_next_write_replaces_the_file() {
        let dir = tempfile::tempdir().unwrap();
        let h = history();
        let mut store = HistoryStore::open(dir.path(), "fleet", MISSION).unwrap();
        store.save(2, &h).unwrap();
        let path = store.path_of(2);
        let good = std::fs::read(&path).unwrap();
        // Half of an appended record: its length says more than follows.
        let mut cut = good.clone();
        cut.extend_from_slice(&1000u32.to_le_bytes());
        cut.extend_from_slice(&[7; 100]);
        std::fs::write(&path, &cut).unwrap();

        let (mut store, loaded) = load(dir.path());
        // Nothing to keep of a cut last record: the file is not set aside.
        assert!(!loaded.unreadable[0].why.contains("kept as"));
        assert!(
            loaded.unreadable[0].why.contains("cut short"),
            "{:?}",
            loaded.unreadable
        );
        assert_eq!(loaded.histories[&2].keyframes, h.keyframes);
        let mut more = loaded.histories[&2].clone();
        grow(&mut more, 51..=60, &limits(), true);
        assert!(matches!(store.save(2, &more).unwrap(), Saved::Rewritten(_)));
        let (_, again) = load(dir.path());
        assert!(again.unreadable.is_empty(), "{:?}", again.unreadable);
        assert_eq!(again.histories[&2].keyframes, more.keyframes);

        // A file changed behind the store's back is written whole too.
        std::fs::write(&path, &good).unwrap();
        let mut most = more.clone();
        grow(&mut most, 61..=70, &limits(), true);
        assert!(matches!(store.save(2, &most).unwrap(), Saved::Rewritten(_)));
        let (_, last) = load(dir.path());
        assert_eq!(last.histories[&2].keyframes, most.keyframes);
    }

    #[test]
    fn histories_written_are_read_back_the_same_and_unchanged_ones_are_not_rewritten() {
        let dir = tempfile::tempdir().unwrap();
        let h = history();
        assert_eq!(h.keyframes.len(), 5);
        let mut store = HistoryStore::open(dir.path(), "fleet", MISSION).unwrap();
        assert!(matches!(store.save(3, &h).unwrap(), Saved::Rewritten(_)));
        assert_eq!(store.save(3, &h).unwrap(), Saved::Unchanged);
        assert!(matches!(
            store.save(7, &PeerHistory::default()).unwrap(),
            Saved::Rewritten(_)
        ));
        let mut again = HistoryStore::open(dir.path(), "fleet", MISSION).unwrap();
        let loaded = again.load(&limits()).unwrap();
        assert!(loaded.unreadable.is_empty(), "{:?}", loaded.unreadable);
        // An empty history leaves no entry.
        assert_eq!(loaded.histories.keys().collect::<Vec<_>>(), [&3]);
        assert_eq!(loaded.histories[&3].keyframes, h.keyframes);
        // What was read is not written again until it changes.
        assert_eq!(
            again.save(3, &loaded.histories[&3]).unwrap(),
            Saved::Unchanged
        );
        // No temporary file is left behind.
        let names: Vec<String> = std::fs::read_dir(dir.path())
            .unwrap()
            .map(|e| e.unwrap().file_name().to_string_lossy().into_owned())
            .collect();
        assert!(names.iter().all(|n| !n.ends_with(".tmp")), "{names:?}");
    }

    #[test]
    fn bad_files_are_reported_and_what_was_read_before_the_damage_is_kept() {
        let dir = tempfile::tempdir().unwrap();
        let mut store = HistoryStore::open(dir.path(), "fleet", MISSION).unwrap();
        store.save(1, &history()).unwrap();
        let good = std::fs::read(store.path_of(1)).unwrap();
        let load = || {
            HistoryStore::open(dir.path(), "fleet", MISSION)
                .unwrap()
                .load(&limits())
                .unwrap()
        };

        // Cut inside the third record: two windows are kept.
        let head = store.header.len();
        let record = |i: usize| {
            let mut at = head;
            for _ in 0..i {
                let n = u32::from_le_bytes(good[at..at + 4].try_into().unwrap()) as usize;
                at += 4 + n;
            }
            at
        };
        std::fs::write(store.path_of(1), &good[..record(2) + 100]).unwrap();
        let l = load();
        assert_eq!(l.histories[&1].keyframes.len(), 2);
        assert!(
            l.unreadable[0].why.contains("cut short"),
            "{:?}",
            l.unreadable
        );

        // The fourth record's message damaged (its magic): three kept.
        let mut bad = good.clone();
        bad[record(3) + 4] ^= 0xff;
        std::fs::write(store.path_of(1), &bad).unwrap();
        let l = load();
        assert_eq!(l.histories[&1].keyframes.len(), 3);
        assert!(
            l.unreadable[0].why.contains("record 3"),
            "{:?}",
            l.unreadable
        );

        // A file of another fleet, a file under another robot's name, a
        // foreign file, a huge length: reported, nothing invented.
        let mut other = HistoryStore::open(dir.path(), "other", MISSION).unwrap();
        other.save(1, &history()).unwrap();
        let theirs = std::fs::read(store.path_of(1)).unwrap();
        let l = load();
        assert!(
            l.unreadable[0].why.contains("fleet `other`"),
            "{:?}",
            l.unreadable
        );
        assert!(!l.histories.contains_key(&1));
        // Set aside, whole, where our next write cannot replace it.
        assert!(
            l.unreadable[0].why.contains("kept as"),
            "{:?}",
            l.unreadable
        );
        assert!(!store.path_of(1).exists());
        let aside: Vec<Vec<u8>> = std::fs::read_dir(dir.path())
            .unwrap()
            .map(|e| e.unwrap())
            .filter(|e| {
                e.file_name()
                    .to_string_lossy()
                    .starts_with("robot1.fvhs.unreadable-")
            })
            .map(|e| std::fs::read(e.path()).unwrap())
            .collect();
        assert!(aside.contains(&theirs));
        let again = load();
        assert!(
            again.unreadable.is_empty(),
            "an aside file is not read: {:?}",
            again.unreadable
        );
        std::fs::write(store.path_of(1), &good).unwrap();
        std::fs::copy(store.path_of(1), store.path_of(2)).unwrap();
        let l = load();
        assert_eq!(l.histories[&1].keyframes.len(), 5);
        assert!(
            l.unreadable[0].why.contains("robot 1's, in robot 2's"),
            "{:?}",
            l.unreadable
        );
        std::fs::write(store.path_of(2), b"not a history").unwrap();
        assert!(load().unreadable[0].why.contains("FVHS"));
        let mut huge = good[..head].to_vec();
        huge.extend_from_slice(&u32::MAX.to_le_bytes());
        huge.extend_from_slice(&[0; 64]);
        std::fs::write(store.path_of(2), &huge).unwrap();
        assert!(load().unreadable[0]
            .why
            .contains("more than a message may hold"));
        // A file over its bound is not read at all.
        assert!(good.len() > FILE_BOUND_SLACK + FILE_BOUND_FACTOR);
        let tight = HistoryLimits {
            max_bytes: 1,
            ..limits()
        };
        let l = HistoryStore::open(dir.path(), "fleet", MISSION)
            .unwrap()
            .load(&tight)
            .unwrap();
        assert!(
            l.unreadable.iter().any(|u| u.why.contains("over the")),
            "{:?}",
            l.unreadable
        );
    }
}
