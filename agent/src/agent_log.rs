//! The agent's MCAP log, in JSON with Foxglove's well-known schemas so Foxglove
//! opens it as is: `/estimate` and `/groundtruth` (`foxglove.PoseInFrame`), the
//! estimate's covariance (`fleet.PoseCovariance`), peers' newest camera poses
//! (`/peers/<id>/pose`, `foxglove.PoseInFrame`) and peer events (`/log`,
//! `foxglove.Log`). [`crate::agent_log_views`] adds paths, scenes and images.

use common::so3::xyzw_from_rot;
use nalgebra::{Matrix3, Vector3};
use serde::Serialize;
use serde_json::json;
use std::collections::BTreeMap;
use std::fs::File;
use std::io::BufWriter;
use std::path::Path;
use thiserror::Error;

/// Why the log could not be written.
#[derive(Debug, Error)]
pub enum LogError {
    /// File error.
    #[error("agent log {path}: {source}")]
    Io {
        /// The file.
        path: String,
        /// The cause.
        source: std::io::Error,
    },
    /// MCAP error.
    #[error("agent log: {0}")]
    Mcap(#[from] mcap::McapError),
    /// The writer thread panicked.
    #[error("agent log: the writer thread panicked")]
    WriterPanicked,
    /// The log was closed after an earlier error.
    #[error("agent log: closed after an earlier error")]
    Closed,
    /// More than 65 535 topics or schemas.
    #[error("agent log: too many channels")]
    TooManyChannels,
    /// An image could not be encoded.
    #[error("agent log: {0}")]
    Image(#[from] common::image::ImageError),
}

const POSE_IN_FRAME: &str = r#"{"title":"foxglove.PoseInFrame","type":"object","properties":{"timestamp":{"type":"object","properties":{"sec":{"type":"integer","minimum":0},"nsec":{"type":"integer","minimum":0,"maximum":999999999}}},"frame_id":{"type":"string"},"pose":{"type":"object","properties":{"position":{"type":"object","properties":{"x":{"type":"number"},"y":{"type":"number"},"z":{"type":"number"}}},"orientation":{"type":"object","properties":{"x":{"type":"number"},"y":{"type":"number"},"z":{"type":"number"},"w":{"type":"number"}}}}}}}"#;
const LOG: &str = r#"{"title":"foxglove.Log","type":"object","properties":{"timestamp":{"type":"object","properties":{"sec":{"type":"integer","minimum":0},"nsec":{"type":"integer","minimum":0,"maximum":999999999}}},"level":{"type":"integer","description":"1 debug, 2 info, 3 warning, 4 error, 5 fatal"},"message":{"type":"string"},"name":{"type":"string"},"file":{"type":"string"},"line":{"type":"integer","minimum":0}}}"#;
const POSE_COVARIANCE: &str = r#"{"title":"fleet.PoseCovariance","type":"object","properties":{"t":{"type":"number","description":"IMU time, s"},"cov_ori_rad2":{"type":"array","items":{"type":"number"},"description":"3x3 row-major, local rotation error"},"cov_pos_m2":{"type":"array","items":{"type":"number"},"description":"3x3 row-major"}}}"#;

/// Records queued for the writer thread. Schemas and channels carry the ids
/// this side gave them; the thread maps them to the file's.
enum Record {
    Schema {
        id: u16,
        name: &'static str,
        text: String,
    },
    Channel {
        id: u16,
        schema: u16,
        topic: String,
    },
    Message {
        header: mcap::records::MessageHeader,
        data: Vec<u8>,
    },
}

/// Records handed to the writer thread at once (about ten camera frames' worth):
/// one wake-up of the thread per batch, not per message.
const BATCH_RECORDS: usize = 64;

/// Batches that may wait for the writer thread before `put` waits for it: a
/// few seconds of an agent's messages. The log stays whole; a disk slower than
/// the agent slows the agent rather than losing messages.
const QUEUE_BATCHES: usize = 64;

/// Writer of one agent's MCAP file. Messages are serialized here and queued;
/// a thread of its own compresses them into chunks and writes the file
/// (measured at stop 33: chunk compression took 8-9 % of an in-process fleet's
/// CPU samples, all of it on the agent threads).
pub struct AgentLog {
    queue: Option<std::sync::mpsc::SyncSender<Vec<Record>>>,
    batch: Vec<Record>,
    writer: Option<std::thread::JoinHandle<Result<(), LogError>>>,
    schemas: BTreeMap<&'static str, u16>,
    channels: BTreeMap<String, u16>,
    seq: u32,
    /// Messages written.
    pub messages: u64,
}

/// A log dropped without [`AgentLog::finish`] (an error path) still closes its
/// file whole: the writer thread drains the queue and writes the index.
impl Drop for AgentLog {
    fn drop(&mut self) {
        if self.queue.is_some() {
            let _ = self.flush();
        }
        self.queue = None;
        if let Some(w) = self.writer.take() {
            let _ = w.join();
        }
    }
}

impl std::fmt::Debug for AgentLog {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("AgentLog")
            .field("messages", &self.messages)
            .finish()
    }
}

pub(crate) fn stamp(t: f64) -> serde_json::Value {
    let t = if t.is_finite() { t.max(0.0) } else { 0.0 };
    let sec = t.floor();
    json!({"sec": sec as u64, "nsec": ((t - sec) * 1e9).round().min(999_999_999.0) as u64})
}

fn nanos(t: f64) -> u64 {
    if t.is_finite() {
        (t.max(0.0) * 1e9).round() as u64
    } else {
        0
    }
}

/// The writer thread: writes the queued records until the queue closes, then
/// the file's summary and index. Stops at the first error, which `finish`
/// (or the next `put`) reports.
fn write_records(
    mut w: mcap::Writer<BufWriter<File>>,
    queue: std::sync::mpsc::Receiver<Vec<Record>>,
) -> Result<(), LogError> {
    let mut schemas: BTreeMap<u16, u16> = BTreeMap::new();
    let mut channels: BTreeMap<u16, u16> = BTreeMap::new();
    for record in queue.into_iter().flatten() {
        match record {
            Record::Schema { id, name, text } => {
                let s = w.add_schema(name, "jsonschema", text.as_bytes())?;
                schemas.insert(id, s);
            }
            Record::Channel { id, schema, topic } => {
                let Some(&s) = schemas.get(&schema) else {
                    continue;
                };
                let c = w.add_channel(s, &topic, "json", &BTreeMap::new())?;
                channels.insert(id, c);
            }
            Record::Message { mut header, data } => {
                let Some(&c) = channels.get(&header.channel_id) else {
                    continue;
                };
                header.channel_id = c;
                w.write_to_known_channel(&header, &data)?;
            }
        }
    }
    w.finish()?;
    Ok(())
}

impl AgentLog {
    /// Creates `path` and starts its writer thread.
    pub fn create(path: &Path) -> Result<Self, LogError> {
        let file = File::create(path).map_err(|source| LogError::Io {
            path: path.display().to_string(),
            source,
        })?;
        let w = mcap::WriteOptions::new()
            .profile("")
            .create(BufWriter::new(file))?;
        let (queue, records) = std::sync::mpsc::sync_channel(QUEUE_BATCHES);
        let writer = std::thread::Builder::new()
            .name("mcap-writer".into())
            .spawn(move || write_records(w, records))
            .map_err(|source| LogError::Io {
                path: path.display().to_string(),
                source,
            })?;
        Ok(Self {
            queue: Some(queue),
            batch: Vec::with_capacity(BATCH_RECORDS),
            writer: Some(writer),
            schemas: BTreeMap::new(),
            channels: BTreeMap::new(),
            seq: 0,
            messages: 0,
        })
    }

    /// Queues a record; when the writer thread has stopped, its error.
    fn send(&mut self, record: Record) -> Result<(), LogError> {
        if self.queue.is_none() {
            return Err(LogError::Closed);
        }
        self.batch.push(record);
        if self.batch.len() < BATCH_RECORDS {
            return Ok(());
        }
        self.flush()
    }

    /// Hands the batch to the writer thread; when it has stopped, its error.
    fn flush(&mut self) -> Result<(), LogError> {
        let batch = std::mem::replace(&mut self.batch, Vec::with_capacity(BATCH_RECORDS));
        let sent = self.queue.as_ref().is_some_and(|q| q.send(batch).is_ok());
        if sent {
            return Ok(());
        }
        self.queue = None;
        match self.writer.take().map(std::thread::JoinHandle::join) {
            Some(Ok(Err(e))) => Err(e),
            Some(Err(_)) => Err(LogError::WriterPanicked),
            _ => Err(LogError::Closed),
        }
    }

    pub(crate) fn channel(
        &mut self,
        topic: &str,
        schema: &'static str,
        text: &str,
    ) -> Result<u16, LogError> {
        if let Some(id) = self.channels.get(topic) {
            return Ok(*id);
        }
        let sid = match self.schemas.get(schema) {
            Some(s) => *s,
            None => {
                let s =
                    u16::try_from(self.schemas.len() + 1).map_err(|_| LogError::TooManyChannels)?;
                self.send(Record::Schema {
                    id: s,
                    name: schema,
                    text: text.to_string(),
                })?;
                self.schemas.insert(schema, s);
                s
            }
        };
        let id = u16::try_from(self.channels.len()).map_err(|_| LogError::TooManyChannels)?;
        self.send(Record::Channel {
            id,
            schema: sid,
            topic: topic.to_string(),
        })?;
        self.channels.insert(topic.to_string(), id);
        Ok(id)
    }

    pub(crate) fn put(
        &mut self,
        channel_id: u16,
        t: f64,
        value: &impl Serialize,
    ) -> Result<(), LogError> {
        let data = serde_json::to_vec(value).unwrap_or_default();
        let header = mcap::records::MessageHeader {
            channel_id,
            sequence: self.seq,
            log_time: nanos(t),
            publish_time: nanos(t),
        };
        self.seq = self.seq.wrapping_add(1);
        self.send(Record::Message { header, data })?;
        self.messages += 1;
        Ok(())
    }

    /// A pose (`R_ItoG` or `R_CtoG`, position) on `topic` in frame `frame_id`.
    pub fn pose(
        &mut self,
        topic: &str,
        frame_id: &str,
        t: f64,
        rot: &Matrix3<f64>,
        pos: &Vector3<f64>,
    ) -> Result<(), LogError> {
        let ch = self.channel(topic, "foxglove.PoseInFrame", POSE_IN_FRAME)?;
        let [x, y, z, w] = xyzw_from_rot(rot);
        let v = json!({
            "timestamp": stamp(t),
            "frame_id": frame_id,
            "pose": {
                "position": {"x": pos.x, "y": pos.y, "z": pos.z},
                "orientation": {"x": x, "y": y, "z": z, "w": w},
            }
        });
        self.put(ch, t, &v)
    }

    /// The estimate's orientation and position covariances.
    pub fn covariance(
        &mut self,
        t: f64,
        ori: &Matrix3<f64>,
        pos: &Matrix3<f64>,
    ) -> Result<(), LogError> {
        let ch = self.channel(
            "/estimate/covariance",
            "fleet.PoseCovariance",
            POSE_COVARIANCE,
        )?;
        let row_major = |m: &Matrix3<f64>| -> Vec<f64> { m.transpose().iter().copied().collect() };
        let v = json!({"t": t, "cov_ori_rad2": row_major(ori), "cov_pos_m2": row_major(pos)});
        self.put(ch, t, &v)
    }

    /// A log line (`level` 1 debug ... 5 fatal).
    pub fn log(&mut self, t: f64, level: u8, name: &str, message: &str) -> Result<(), LogError> {
        let ch = self.channel("/log", "foxglove.Log", LOG)?;
        let v = json!({
            "timestamp": stamp(t),
            "level": level,
            "message": message,
            "name": name,
            "file": "",
            "line": 0,
        });
        self.put(ch, t, &v)
    }

    /// Closes the file (writes the summary and index) once the writer thread
    /// has written everything queued.
    pub fn finish(mut self) -> Result<u64, LogError> {
        self.flush()?;
        self.queue = None;
        match self.writer.take().map(std::thread::JoinHandle::join) {
            Some(Ok(Ok(()))) => Ok(self.messages),
            Some(Ok(Err(e))) => Err(e),
            Some(Err(_)) => Err(LogError::WriterPanicked),
            None => Err(LogError::Closed),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn writes_a_readable_file_with_foxglove_schemas() {
        let dir = tempfile::tempdir().unwrap();
        let p = dir.path().join("a.mcap");
        let mut log = AgentLog::create(&p).unwrap();
        for k in 0..3 {
            let t = 1.0 + k as f64;
            log.pose(
                "/estimate",
                "world",
                t,
                &Matrix3::identity(),
                &Vector3::zeros(),
            )
            .unwrap();
            log.covariance(t, &Matrix3::identity(), &Matrix3::identity())
                .unwrap();
        }
        log.log(2.0, 2, "peers", "robot 1 appeared").unwrap();
        assert_eq!(log.finish().unwrap(), 7);
        let bytes = std::fs::read(&p).unwrap();
        let mut schemas = BTreeMap::new();
        for m in mcap::MessageStream::new(&bytes).unwrap() {
            let m = m.unwrap();
            let name = m.channel.schema.as_ref().unwrap().name.clone();
            *schemas.entry(name).or_insert(0) += 1;
            let _: serde_json::Value = serde_json::from_slice(&m.data).unwrap();
        }
        assert_eq!(schemas["foxglove.PoseInFrame"], 3);
        assert_eq!(schemas["foxglove.Log"], 1);
        assert_eq!(schemas["fleet.PoseCovariance"], 3);
    }

    #[test]
    fn a_log_dropped_without_finish_is_still_whole() {
        let dir = tempfile::tempdir().unwrap();
        let p = dir.path().join("a.mcap");
        {
            let mut log = AgentLog::create(&p).unwrap();
            for k in 0..5000 {
                log.log(f64::from(k) * 0.01, 2, "test", "line").unwrap();
            }
        }
        let bytes = std::fs::read(&p).unwrap();
        let summary = mcap::Summary::read(&bytes).unwrap().expect("a summary");
        assert_eq!(summary.stats.unwrap().message_count, 5000);
    }
}
