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
    /// An image could not be encoded.
    #[error("agent log: {0}")]
    Image(#[from] common::image::ImageError),
}

const POSE_IN_FRAME: &str = r#"{"title":"foxglove.PoseInFrame","type":"object","properties":{"timestamp":{"type":"object","properties":{"sec":{"type":"integer","minimum":0},"nsec":{"type":"integer","minimum":0,"maximum":999999999}}},"frame_id":{"type":"string"},"pose":{"type":"object","properties":{"position":{"type":"object","properties":{"x":{"type":"number"},"y":{"type":"number"},"z":{"type":"number"}}},"orientation":{"type":"object","properties":{"x":{"type":"number"},"y":{"type":"number"},"z":{"type":"number"},"w":{"type":"number"}}}}}}}"#;
const LOG: &str = r#"{"title":"foxglove.Log","type":"object","properties":{"timestamp":{"type":"object","properties":{"sec":{"type":"integer","minimum":0},"nsec":{"type":"integer","minimum":0,"maximum":999999999}}},"level":{"type":"integer","description":"1 debug, 2 info, 3 warning, 4 error, 5 fatal"},"message":{"type":"string"},"name":{"type":"string"},"file":{"type":"string"},"line":{"type":"integer","minimum":0}}}"#;
const POSE_COVARIANCE: &str = r#"{"title":"fleet.PoseCovariance","type":"object","properties":{"t":{"type":"number","description":"IMU time, s"},"cov_ori_rad2":{"type":"array","items":{"type":"number"},"description":"3x3 row-major, local rotation error"},"cov_pos_m2":{"type":"array","items":{"type":"number"},"description":"3x3 row-major"}}}"#;

/// Writer of one agent's MCAP file.
pub struct AgentLog {
    w: mcap::Writer<BufWriter<File>>,
    schemas: BTreeMap<&'static str, u16>,
    channels: BTreeMap<String, u16>,
    seq: u32,
    /// Messages written.
    pub messages: u64,
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

impl AgentLog {
    /// Creates `path`.
    pub fn create(path: &Path) -> Result<Self, LogError> {
        let file = File::create(path).map_err(|source| LogError::Io {
            path: path.display().to_string(),
            source,
        })?;
        let w = mcap::WriteOptions::new()
            .profile("")
            .create(BufWriter::new(file))?;
        Ok(Self {
            w,
            schemas: BTreeMap::new(),
            channels: BTreeMap::new(),
            seq: 0,
            messages: 0,
        })
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
                let s = self.w.add_schema(schema, "jsonschema", text.as_bytes())?;
                self.schemas.insert(schema, s);
                s
            }
        };
        let id = self.w.add_channel(sid, topic, "json", &BTreeMap::new())?;
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
        self.messages += 1;
        self.w.write_to_known_channel(&header, &data)?;
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

    /// Closes the file (writes the summary and index).
    pub fn finish(mut self) -> Result<u64, LogError> {
        self.w.finish()?;
        Ok(self.messages)
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
}
