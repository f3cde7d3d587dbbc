//! A robot's simulated measurements in an MCAP file (JSON messages with JSON
//! schemas, so Foxglove and `mcap cat` show them), and reading them back.
//!
//! Topics: `/imu` (schema `fleet.ImuSample`), `/features` (`fleet.FeatureFrame`),
//! `/groundtruth` (`fleet.TruthState`) and, for rendered or recorded images,
//! `/camera/image` (`foxglove.CompressedImage`, PNG). Log times are nanoseconds of the
//! fleet clock (IMU time for `/imu` and `/groundtruth`, camera time for `/features`).

use crate::camera_sim::{CameraEvent, TruthState};
use crate::fleet::SimEvent;
use crate::imu::Biases;
use common::descriptor::Descriptor;
use common::image::{GrayImage, ImageError};
use common::measurement::{FeatureFrame, FeatureObservation, ImuSample};
use nalgebra::{Matrix3, Vector2, Vector3};
use serde::{Deserialize, Serialize};
use std::collections::BTreeMap;
use std::io::{BufReader, BufWriter};
use std::path::{Path, PathBuf};
use std::sync::Arc;
use thiserror::Error;

/// Largest message accepted when reading (bytes): a frame of 10 000 features
/// fits, and a base64 PNG of a 2048x2048 image.
const MAX_MESSAGE_BYTES: usize = 16 << 20;

/// Why an MCAP measurement file could not be written or read.
#[derive(Debug, Error)]
pub enum McapIoError {
    /// File system error.
    #[error("{path}: {source}")]
    Io {
        /// The file.
        path: PathBuf,
        /// The cause.
        source: std::io::Error,
    },
    /// MCAP container error.
    #[error("{path}: MCAP error: {source}")]
    Mcap {
        /// The file.
        path: PathBuf,
        /// The cause.
        source: mcap::McapError,
    },
    /// A message does not decode.
    #[error("{path}: message {index} on {topic}: {reason}")]
    BadMessage {
        /// The file.
        path: PathBuf,
        /// Index of the message in the file.
        index: usize,
        /// Its topic.
        topic: String,
        /// What is wrong.
        reason: String,
    },
}

#[derive(Serialize, Deserialize)]
struct ImuRecord {
    t: f64,
    gyro: [f64; 3],
    accel: [f64; 3],
}

#[derive(Serialize, Deserialize)]
struct FeatureRecord {
    id: u64,
    u: f64,
    v: f64,
    descriptor: String,
    landmark: u64,
    outlier: bool,
}

#[derive(Serialize, Deserialize)]
struct FrameRecord {
    t: f64,
    camera: u8,
    features: Vec<FeatureRecord>,
}

#[derive(Serialize, Deserialize)]
struct TruthRecord {
    t: f64,
    /// `R_ItoG` as TUM quaternion `[qx, qy, qz, qw]`.
    q_xyzw: [f64; 4],
    p: [f64; 3],
    v: [f64; 3],
    bias_gyro: [f64; 3],
    bias_accel: [f64; 3],
}

const IMU_SCHEMA: &str = r#"{"type":"object","title":"fleet.ImuSample","properties":{"t":{"type":"number","description":"IMU time, s"},"gyro":{"type":"array","items":{"type":"number"},"description":"rad/s in I"},"accel":{"type":"array","items":{"type":"number"},"description":"m/s^2 in I"}}}"#;
const FRAME_SCHEMA: &str = r#"{"type":"object","title":"fleet.FeatureFrame","properties":{"t":{"type":"number","description":"camera time, s"},"camera":{"type":"integer"},"features":{"type":"array","items":{"type":"object","properties":{"id":{"type":"integer","description":"track id"},"u":{"type":"number","description":"raw pixel x"},"v":{"type":"number","description":"raw pixel y"},"descriptor":{"type":"string","description":"256-bit, hex"},"landmark":{"type":"integer","description":"true landmark id (ground truth)"},"outlier":{"type":"boolean","description":"injected outlier (ground truth)"}}}}}}"#;
const TRUTH_SCHEMA: &str = r#"{"type":"object","title":"fleet.TruthState","properties":{"t":{"type":"number","description":"IMU time, s"},"q_xyzw":{"type":"array","items":{"type":"number"},"description":"R_ItoG quaternion, scalar last"},"p":{"type":"array","items":{"type":"number"},"description":"p_IinG, m"},"v":{"type":"array","items":{"type":"number"},"description":"v_IinG, m/s"},"bias_gyro":{"type":"array","items":{"type":"number"}},"bias_accel":{"type":"array","items":{"type":"number"}}}}"#;

/// JSON schema of Foxglove's `CompressedImage` (bytes are base64 in JSON).
pub const COMPRESSED_IMAGE_SCHEMA: &str = r#"{"title":"foxglove.CompressedImage","type":"object","properties":{"timestamp":{"type":"object","properties":{"sec":{"type":"integer","minimum":0},"nsec":{"type":"integer","minimum":0,"maximum":999999999}}},"frame_id":{"type":"string"},"data":{"type":"string","contentEncoding":"base64"},"format":{"type":"string"}}}"#;

#[derive(Serialize, Deserialize)]
struct Stamp {
    sec: u64,
    nsec: u32,
}

#[derive(Serialize, Deserialize)]
struct ImageRecord {
    timestamp: Stamp,
    frame_id: String,
    data: String,
    format: String,
}

/// A Foxglove `CompressedImage` JSON message of a gray image at time `t` (PNG).
pub fn image_message(t: f64, image: &GrayImage) -> Result<Vec<u8>, ImageError> {
    let t = if t.is_finite() { t.max(0.0) } else { 0.0 };
    let record = ImageRecord {
        timestamp: Stamp {
            sec: t.floor() as u64,
            nsec: ((t - t.floor()) * 1e9).round().min(999_999_999.0) as u32,
        },
        frame_id: "camera".into(),
        data: common::base64::encode(&image.to_png()?),
        format: "png".into(),
    };
    Ok(encode(&record))
}

fn decode_image(data: &[u8]) -> Result<GrayImage, String> {
    let r: ImageRecord = serde_json::from_slice(data).map_err(|e| e.to_string())?;
    if r.format != "png" {
        return Err(format!("image format `{}` is not png", r.format));
    }
    let png = common::base64::decode(&r.data).ok_or("image data is not base64")?;
    GrayImage::from_png(&png).map_err(|e| e.to_string())
}

fn nanos(t: f64) -> u64 {
    (t.max(0.0) * 1e9).round() as u64
}

/// Writes a robot's measurement stream to `path`; returns the number of messages.
pub fn write_stream<I: IntoIterator<Item = SimEvent>>(
    path: &Path,
    events: I,
) -> Result<u64, McapIoError> {
    let io_err = |source| McapIoError::Io {
        path: path.to_path_buf(),
        source,
    };
    let mc_err = |source| McapIoError::Mcap {
        path: path.to_path_buf(),
        source,
    };
    let file = std::fs::File::create(path).map_err(io_err)?;
    let mut w = mcap::WriteOptions::new()
        .profile("")
        .create(BufWriter::new(file))
        .map_err(mc_err)?;
    let meta = BTreeMap::new();
    let mut channel = |name: &str, topic: &str, schema: &str| -> Result<u16, McapIoError> {
        let sid = w
            .add_schema(name, "jsonschema", schema.as_bytes())
            .map_err(mc_err)?;
        w.add_channel(sid, topic, "json", &meta).map_err(mc_err)
    };
    let imu_ch = channel("fleet.ImuSample", "/imu", IMU_SCHEMA)?;
    let frame_ch = channel("fleet.FeatureFrame", "/features", FRAME_SCHEMA)?;
    let truth_ch = channel("fleet.TruthState", "/groundtruth", TRUTH_SCHEMA)?;
    let image_ch = channel(
        "foxglove.CompressedImage",
        "/camera/image",
        COMPRESSED_IMAGE_SCHEMA,
    )?;
    let mut count = 0u64;
    for ev in events {
        let (ch, t, data) = match ev {
            SimEvent::Imu(s) => (imu_ch, s.t, encode(&imu_record(&s))),
            SimEvent::Camera(c) => {
                put(
                    &mut w,
                    truth_ch,
                    count,
                    c.truth.t,
                    &encode(&truth_record(&c.truth)),
                )
                .map_err(mc_err)?;
                count += 1;
                if let Some(img) = &c.image {
                    let data =
                        image_message(c.frame.t, img).map_err(|e| McapIoError::BadMessage {
                            path: path.to_path_buf(),
                            index: count as usize,
                            topic: "/camera/image".into(),
                            reason: e.to_string(),
                        })?;
                    put(&mut w, image_ch, count, c.frame.t, &data).map_err(mc_err)?;
                    count += 1;
                }
                (frame_ch, c.frame.t, encode(&frame_record(&c)))
            }
        };
        put(&mut w, ch, count, t, &data).map_err(mc_err)?;
        count += 1;
    }
    w.finish().map_err(mc_err)?;
    Ok(count)
}

fn put<W: std::io::Write + std::io::Seek>(
    w: &mut mcap::Writer<W>,
    channel_id: u16,
    seq: u64,
    t: f64,
    data: &[u8],
) -> Result<(), mcap::McapError> {
    let header = mcap::records::MessageHeader {
        channel_id,
        sequence: seq as u32,
        log_time: nanos(t),
        publish_time: nanos(t),
    };
    w.write_to_known_channel(&header, data)
}

fn encode<T: Serialize>(v: &T) -> Vec<u8> {
    // Serializing plain structs of numbers and strings cannot fail.
    serde_json::to_vec(v).unwrap_or_default()
}

fn imu_record(s: &ImuSample) -> ImuRecord {
    ImuRecord {
        t: s.t,
        gyro: s.gyro.into(),
        accel: s.accel.into(),
    }
}

fn frame_record(c: &CameraEvent) -> FrameRecord {
    FrameRecord {
        t: c.frame.t,
        camera: c.frame.camera,
        features: c
            .frame
            .features
            .iter()
            .enumerate()
            .map(|(i, f)| FeatureRecord {
                id: f.id,
                u: f.uv.x,
                v: f.uv.y,
                descriptor: f.descriptor.to_hex(),
                landmark: c.landmark_ids.get(i).copied().unwrap_or(u64::MAX),
                outlier: c.outlier.get(i).copied().unwrap_or(false),
            })
            .collect(),
    }
}

fn truth_record(t: &TruthState) -> TruthRecord {
    TruthRecord {
        t: t.t,
        q_xyzw: common::so3::xyzw_from_rot(&t.rot),
        p: t.pos.into(),
        v: t.vel.into(),
        bias_gyro: t.biases.gyro.into(),
        bias_accel: t.biases.accel.into(),
    }
}

fn finite(values: &[f64]) -> bool {
    values.iter().all(|v| v.is_finite())
}

/// Reads a file written by [`write_stream`] back into the same events. A camera
/// frame is paired with the ground truth written just before it.
pub fn read_stream(path: &Path) -> Result<Vec<SimEvent>, McapIoError> {
    let file = std::fs::File::open(path).map_err(|source| McapIoError::Io {
        path: path.to_path_buf(),
        source,
    })?;
    let mut events = Vec::new();
    let mut pending_truth: Option<TruthState> = None;
    let mut pending_image: Option<Arc<GrayImage>> = None;
    for (index, msg) in mcap::io::MessageReader::new(BufReader::new(file)).enumerate() {
        let msg = msg.map_err(|source| McapIoError::Mcap {
            path: path.to_path_buf(),
            source,
        })?;
        let topic = msg.channel.topic.clone();
        let bad = |reason: String| McapIoError::BadMessage {
            path: path.to_path_buf(),
            index,
            topic: topic.clone(),
            reason,
        };
        if msg.data.len() > MAX_MESSAGE_BYTES {
            return Err(bad(format!("{} bytes exceeds the limit", msg.data.len())));
        }
        match topic.as_str() {
            "/camera/image" => {
                pending_image = Some(Arc::new(decode_image(&msg.data).map_err(bad)?));
            }
            "/imu" => {
                let r: ImuRecord =
                    serde_json::from_slice(&msg.data).map_err(|e| bad(e.to_string()))?;
                if !finite(&[r.t]) || !finite(&r.gyro) || !finite(&r.accel) {
                    return Err(bad("non-finite value".into()));
                }
                events.push(SimEvent::Imu(ImuSample {
                    t: r.t,
                    gyro: Vector3::from(r.gyro),
                    accel: Vector3::from(r.accel),
                }));
            }
            "/groundtruth" => {
                let r: TruthRecord =
                    serde_json::from_slice(&msg.data).map_err(|e| bad(e.to_string()))?;
                let [x, y, z, w] = r.q_xyzw;
                if !finite(&r.q_xyzw) || (x * x + y * y + z * z + w * w) < 1e-12 {
                    return Err(bad("invalid quaternion".into()));
                }
                pending_truth = Some(TruthState {
                    t: r.t,
                    rot: common::so3::rot_from_xyzw(x, y, z, w),
                    pos: Vector3::from(r.p),
                    vel: Vector3::from(r.v),
                    biases: Biases {
                        gyro: Vector3::from(r.bias_gyro),
                        accel: Vector3::from(r.bias_accel),
                    },
                });
            }
            "/features" => {
                let r: FrameRecord =
                    serde_json::from_slice(&msg.data).map_err(|e| bad(e.to_string()))?;
                let mut features = Vec::with_capacity(r.features.len());
                let mut landmark_ids = Vec::with_capacity(r.features.len());
                let mut outlier = Vec::with_capacity(r.features.len());
                for f in &r.features {
                    let descriptor = Descriptor::from_hex(&f.descriptor)
                        .ok_or_else(|| bad(format!("feature {}: bad descriptor", f.id)))?;
                    if !finite(&[f.u, f.v]) {
                        return Err(bad(format!("feature {}: non-finite pixel", f.id)));
                    }
                    features.push(FeatureObservation {
                        id: f.id,
                        uv: Vector2::new(f.u, f.v),
                        descriptor,
                    });
                    landmark_ids.push(f.landmark);
                    outlier.push(f.outlier);
                }
                let truth = pending_truth.take().unwrap_or(TruthState {
                    t: f64::NAN,
                    rot: Matrix3::identity(),
                    pos: Vector3::zeros(),
                    vel: Vector3::zeros(),
                    biases: Biases::default(),
                });
                events.push(SimEvent::Camera(Box::new(CameraEvent {
                    frame: FeatureFrame {
                        t: r.t,
                        camera: r.camera,
                        features,
                    },
                    truth,
                    landmark_ids,
                    outlier,
                    image: pending_image.take(),
                })));
            }
            _ => {}
        }
    }
    Ok(events)
}
