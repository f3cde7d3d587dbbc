//! Keyframe windows kept on disk, so a restarted agent keeps what it learnt.
//!
//! A process that restarts loses its peers' histories and its archive of its
//! own windows. Catch-up gets the peers' windows back from peers that are
//! still there, but not from a robot that has landed and gone, and a peer
//! that joins after the restart could not get our windows from before it.
//! With `history.store_dir` set, each history (one file per robot, ours
//! included) is written there as it grows and read back at start.
//!
//! A file is `FVHS`, a little-endian `u16` format version, then records: a
//! little-endian `u32` length and one encoded message (the wire format of a
//! replayed window, [`HistoryReplay`], so a record is decoded with the same
//! bounds and checks as a message from the network). A file is replaced
//! whole (written beside it, then renamed), so a crash leaves the old or the
//! new one, never half of one. What cannot be read is reported and skipped:
//! a file over its bound, another fleet's, a bad header; a bad record ends
//! the file's reading with what was read before it kept.

use crate::peer_history::{HistoryLimits, KeyframeWindow, PeerHistory};
use common::messages::{decode, encode, Body, Envelope, HistoryReplay};
use std::collections::BTreeMap;
use std::io::Write;
use std::path::{Path, PathBuf};
use thiserror::Error;

/// The first bytes of a history file.
const FILE_MAGIC: [u8; 4] = *b"FVHS";

/// The format version this build writes and reads.
const FILE_VERSION: u16 = 1;

/// A file read at start may hold this many times its history's memory bound
/// (a window's encoding and its heap size differ a little), plus
/// [`FILE_BOUND_SLACK`] bytes.
const FILE_BOUND_FACTOR: usize = 2;

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

/// One agent's folder of histories.
#[derive(Debug)]
pub struct HistoryStore {
    dir: PathBuf,
    fleet_id: String,
    /// Revision of each history when it was last written.
    written: BTreeMap<u32, u64>,
}

impl HistoryStore {
    /// The store in `dir` (made if missing) for the fleet `fleet_id`.
    pub fn open(dir: &Path, fleet_id: &str) -> Result<Self, StoreError> {
        std::fs::create_dir_all(dir).map_err(|source| StoreError::Io {
            path: dir.to_path_buf(),
            source,
        })?;
        Ok(Self {
            dir: dir.to_path_buf(),
            fleet_id: fleet_id.to_owned(),
            written: BTreeMap::new(),
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
            if let Err(why) = self.read_file(robot, &path, limits, &mut history) {
                loaded.unreadable.push(Unreadable {
                    path: path.clone(),
                    why,
                });
            }
            if !history.keyframes.is_empty() {
                // What is on disk is what we hold: no need to write it again.
                self.written.insert(robot, history.revision);
                loaded.histories.insert(robot, history);
            }
        }
        Ok(loaded)
    }

    /// Reads robot `robot`'s file into `history`; `Err` says why it stopped
    /// early (the windows before that are kept).
    fn read_file(
        &self,
        robot: u32,
        path: &Path,
        limits: &HistoryLimits,
        history: &mut PeerHistory,
    ) -> Result<(), String> {
        let bound = limits.max_bytes.saturating_mul(FILE_BOUND_FACTOR) + FILE_BOUND_SLACK;
        let len = std::fs::metadata(path).map_err(|e| e.to_string())?.len();
        if len > bound as u64 {
            return Err(format!(
                "{len} bytes, over the {bound} its history's bound allows"
            ));
        }
        let bytes = std::fs::read(path).map_err(|e| e.to_string())?;
        let header = FILE_MAGIC.len() + 2;
        match bytes.get(..header) {
            Some(h) if h[..4] == FILE_MAGIC => {
                let version = u16::from_le_bytes([h[4], h[5]]);
                if version != FILE_VERSION {
                    return Err(format!(
                        "format version {version}; this build reads {FILE_VERSION}"
                    ));
                }
            }
            _ => return Err("not a history file (no FVHS header)".into()),
        }
        let mut at = header;
        let mut index = 0usize;
        while at < bytes.len() {
            let record = bytes
                .get(at..at + 4)
                .map(|b| u32::from_le_bytes([b[0], b[1], b[2], b[3]]) as usize)
                .and_then(|n| bytes.get(at + 4..at + 4 + n));
            let Some(record) = record else {
                return Err(format!("record {index} is cut short at byte {at}"));
            };
            let env = decode(record).map_err(|e| format!("record {index}: {e}"))?;
            if env.fleet_id != self.fleet_id {
                return Err(format!(
                    "record {index} is of fleet `{}`, not `{}`",
                    env.fleet_id, self.fleet_id
                ));
            }
            if env.robot_id != robot {
                return Err(format!(
                    "record {index} is robot {}'s, in robot {robot}'s file",
                    env.robot_id
                ));
            }
            let window = match env.body {
                Body::HistoryReplay(r) => r.window,
                _ => None,
            };
            let Some(window) = window else {
                return Err(format!("record {index} holds no keyframe window"));
            };
            history.add_replayed(KeyframeWindow::from_wire(window), limits);
            at += 4 + record.len();
            index += 1;
        }
        Ok(())
    }

    /// Writes robot `robot`'s history if it changed since it was last
    /// written (`force`: even if not). Returns whether it wrote.
    pub fn save(
        &mut self,
        robot: u32,
        history: &PeerHistory,
        force: bool,
    ) -> Result<bool, StoreError> {
        if !force && self.written.get(&robot) == Some(&history.revision) {
            return Ok(false);
        }
        let mut out = Vec::with_capacity(history.bytes() + 64);
        out.extend_from_slice(&FILE_MAGIC);
        out.extend_from_slice(&FILE_VERSION.to_le_bytes());
        for (seq, kf) in history.keyframes.values().enumerate() {
            let env = Envelope {
                fleet_id: self.fleet_id.clone(),
                robot_id: robot,
                seq: seq as u64,
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
            out.extend_from_slice(&(bytes.len() as u32).to_le_bytes());
            out.extend_from_slice(&bytes);
        }
        let path = self.path_of(robot);
        let tmp = path.with_extension("fvhs.tmp");
        let io = |source| StoreError::Io {
            path: path.clone(),
            source,
        };
        {
            let mut f = std::fs::File::create(&tmp).map_err(io)?;
            f.write_all(&out).map_err(io)?;
            f.sync_data().map_err(io)?;
        }
        std::fs::rename(&tmp, &path).map_err(io)?;
        self.written.insert(robot, history.revision);
        Ok(true)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::history_retention::Retention;
    use common::messages::samples;

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
        for f in 0..=50u64 {
            let Body::Tracks(t) = samples::tracks(f, 20).body else {
                continue;
            };
            h.add_tracks(t, &limits());
            if f >= 10 && f % 10 == 0 {
                if let Body::Snapshot(s) = samples::snapshot(f, 11, 0, true).body {
                    h.add_snapshot(s, &limits());
                }
                if let Body::Descriptors(d) = samples::descriptors(f, 20, true).body {
                    h.add_descriptors(d, &limits());
                }
            }
        }
        h
    }

    #[test]
    fn histories_written_are_read_back_the_same_and_unchanged_ones_are_not_rewritten() {
        let dir = tempfile::tempdir().unwrap();
        let h = history();
        assert_eq!(h.keyframes.len(), 5);
        let mut store = HistoryStore::open(dir.path(), "fleet").unwrap();
        assert!(store.save(3, &h, false).unwrap());
        assert!(!store.save(3, &h, false).unwrap(), "unchanged");
        assert!(store.save(7, &PeerHistory::default(), false).unwrap());
        let mut again = HistoryStore::open(dir.path(), "fleet").unwrap();
        let loaded = again.load(&limits()).unwrap();
        assert!(loaded.unreadable.is_empty(), "{:?}", loaded.unreadable);
        // An empty history leaves no entry.
        assert_eq!(loaded.histories.keys().collect::<Vec<_>>(), [&3]);
        assert_eq!(loaded.histories[&3].keyframes, h.keyframes);
        // What was read is not written again until it changes.
        assert!(!again.save(3, &loaded.histories[&3], false).unwrap());
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
        let mut store = HistoryStore::open(dir.path(), "fleet").unwrap();
        store.save(1, &history(), true).unwrap();
        let good = std::fs::read(store.path_of(1)).unwrap();
        let load = || {
            HistoryStore::open(dir.path(), "fleet")
                .unwrap()
                .load(&limits())
                .unwrap()
        };

        // Cut inside the third record: two windows are kept.
        let record = |i: usize| {
            let mut at = 6;
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
        let mut other = HistoryStore::open(dir.path(), "other").unwrap();
        other.save(1, &history(), true).unwrap();
        let l = load();
        assert!(
            l.unreadable[0].why.contains("fleet `other`"),
            "{:?}",
            l.unreadable
        );
        assert!(!l.histories.contains_key(&1));
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
        let mut huge = good[..6].to_vec();
        huge.extend_from_slice(&u32::MAX.to_le_bytes());
        huge.extend_from_slice(&[0; 64]);
        std::fs::write(store.path_of(2), &huge).unwrap();
        assert!(load().unreadable[0].why.contains("cut short"));
        // A file over its bound is not read at all.
        assert!(good.len() > FILE_BOUND_SLACK + 2);
        let tight = HistoryLimits {
            max_bytes: 1,
            ..limits()
        };
        let l = HistoryStore::open(dir.path(), "fleet")
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
