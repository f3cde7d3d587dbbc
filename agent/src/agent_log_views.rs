//! What a user looks at in Foxglove beyond poses: the estimated and true paths
//! (`foxglove.PosesInFrame`), SLAM landmarks and peers as a 3-D scene
//! (`foxglove.SceneUpdate`), and the camera image (`foxglove.CompressedImage`,
//! PNG) with the tracked features drawn on it (`foxglove.ImageAnnotations`).
//!
//! The JSON schemas hold the fields written here, with Foxglove's names; bytes
//! are base64 in JSON, as Foxglove's JSON encoding wants them.

use crate::agent_log::{stamp, AgentLog, LogError};
use crate::estimator::frame_output::StampedTwist;
use common::image::GrayImage;
use common::measurement::FeatureFrame;
use common::so3::xyzw_from_rot;
use common::trajectory::{StampedCovariance, StampedPose};
use nalgebra::{Matrix3, Vector3};
use serde_json::{json, Value};
use simulator::mcap_io::COMPRESSED_IMAGE_SCHEMA;

const TIME: &str = r#"{"type":"object","properties":{"sec":{"type":"integer","minimum":0},"nsec":{"type":"integer","minimum":0,"maximum":999999999}}}"#;
const VEC3: &str = r#"{"type":"object","properties":{"x":{"type":"number"},"y":{"type":"number"},"z":{"type":"number"}}}"#;
const QUAT: &str = r#"{"type":"object","properties":{"x":{"type":"number"},"y":{"type":"number"},"z":{"type":"number"},"w":{"type":"number"}}}"#;
const COLOR: &str = r#"{"type":"object","properties":{"r":{"type":"number"},"g":{"type":"number"},"b":{"type":"number"},"a":{"type":"number"}}}"#;
const POINT2: &str =
    r#"{"type":"object","properties":{"x":{"type":"number"},"y":{"type":"number"}}}"#;

fn pose_schema() -> String {
    format!(r#"{{"type":"object","properties":{{"position":{VEC3},"orientation":{QUAT}}}}}"#)
}

fn poses_in_frame_schema() -> String {
    format!(
        r#"{{"title":"foxglove.PosesInFrame","type":"object","properties":{{"timestamp":{TIME},"frame_id":{{"type":"string"}},"poses":{{"type":"array","items":{}}}}}}}"#,
        pose_schema()
    )
}

fn scene_update_schema() -> String {
    let sphere = format!(
        r#"{{"type":"object","properties":{{"pose":{},"size":{VEC3},"color":{COLOR}}}}}"#,
        pose_schema()
    );
    let arrow = format!(
        r#"{{"type":"object","properties":{{"pose":{},"shaft_length":{{"type":"number"}},"shaft_diameter":{{"type":"number"}},"head_length":{{"type":"number"}},"head_diameter":{{"type":"number"}},"color":{COLOR}}}}}"#,
        pose_schema()
    );
    let entity = format!(
        r#"{{"type":"object","properties":{{"timestamp":{TIME},"frame_id":{{"type":"string"}},"id":{{"type":"string"}},"lifetime":{TIME},"frame_locked":{{"type":"boolean"}},"spheres":{{"type":"array","items":{sphere}}},"arrows":{{"type":"array","items":{arrow}}}}}}}"#
    );
    let deletion = format!(
        r#"{{"type":"object","properties":{{"timestamp":{TIME},"type":{{"type":"integer","description":"0 matching id, 1 all"}},"id":{{"type":"string"}}}}}}"#
    );
    format!(
        r#"{{"title":"foxglove.SceneUpdate","type":"object","properties":{{"deletions":{{"type":"array","items":{deletion}}},"entities":{{"type":"array","items":{entity}}}}}}}"#
    )
}

fn image_annotations_schema() -> String {
    let points = format!(
        r#"{{"type":"object","properties":{{"timestamp":{TIME},"type":{{"type":"integer","description":"1 points, 2 line loop, 3 line strip, 4 line list"}},"points":{{"type":"array","items":{POINT2}}},"outline_color":{COLOR},"outline_colors":{{"type":"array","items":{COLOR}}},"fill_color":{COLOR},"thickness":{{"type":"number"}}}}}}"#
    );
    format!(
        r#"{{"title":"foxglove.ImageAnnotations","type":"object","properties":{{"circles":{{"type":"array","items":{{"type":"object"}}}},"points":{{"type":"array","items":{points}}},"texts":{{"type":"array","items":{{"type":"object"}}}}}}}}"#
    )
}

fn pose_json(rot: &Matrix3<f64>, pos: &Vector3<f64>) -> Value {
    let [x, y, z, w] = xyzw_from_rot(rot);
    json!({"position": {"x": pos.x, "y": pos.y, "z": pos.z}, "orientation": {"x": x, "y": y, "z": z, "w": w}})
}

/// A `foxglove.Pose`, serialized as it stands: a path of 2 000 of them is
/// logged every second, and building each as a `serde_json::Value` (a map per
/// object, a string per key) cost more of the agent's thread than its
/// estimator did.
#[derive(serde::Serialize)]
struct PoseMsg {
    position: Xyz,
    orientation: Quat,
}

#[derive(serde::Serialize)]
struct Xyz {
    x: f64,
    y: f64,
    z: f64,
}

#[derive(serde::Serialize)]
struct Quat {
    x: f64,
    y: f64,
    z: f64,
    w: f64,
}

#[derive(serde::Serialize)]
struct PosesInFrame {
    timestamp: Value,
    frame_id: &'static str,
    poses: Vec<PoseMsg>,
}

fn pose_msg(p: &StampedPose) -> PoseMsg {
    let [x, y, z, w] = xyzw_from_rot(&p.rot);
    PoseMsg {
        position: Xyz {
            x: p.pos.x,
            y: p.pos.y,
            z: p.pos.z,
        },
        orientation: Quat { x, y, z, w },
    }
}

fn color(r: f64, g: f64, b: f64) -> Value {
    json!({"r": r, "g": g, "b": b, "a": 1.0})
}

/// A peer's newest camera pose, for the scene.
#[derive(Clone, Copy, Debug)]
pub struct PeerPose {
    /// The peer's robot id.
    pub robot: u32,
    /// `R_CtoG`.
    pub rot: Matrix3<f64>,
    /// `p_CinG`, m.
    pub pos: Vector3<f64>,
}

impl AgentLog {
    /// A whole path (e.g. the estimate so far) on `topic`, at most `max_poses`
    /// poses (evenly thinned, the newest always kept).
    pub fn path(
        &mut self,
        topic: &str,
        t: f64,
        poses: &[StampedPose],
        max_poses: usize,
    ) -> Result<(), LogError> {
        let ch = self.channel(topic, "foxglove.PosesInFrame", &poses_in_frame_schema())?;
        let step = poses.len().div_ceil(max_poses.max(1)).max(1);
        let mut picked: Vec<PoseMsg> = poses.iter().step_by(step).map(pose_msg).collect();
        if let Some(last) = poses.last() {
            if (poses.len() - 1) % step != 0 {
                picked.push(pose_msg(last));
            }
        }
        let v = PosesInFrame {
            timestamp: stamp(t),
            frame_id: "world",
            poses: picked,
        };
        self.put(ch, t, &v)
    }

    /// The body's velocity and angular rate (IMU axes) on `topic`, with
    /// their standard deviations when estimated (`sigma` empty for a truth).
    pub fn twist(
        &mut self,
        topic: &str,
        tw: &StampedTwist,
        estimated: bool,
    ) -> Result<(), LogError> {
        let ch = self.channel(topic, "fleet.BodyTwist", &body_twist_schema())?;
        let v = json!({
            "timestamp": stamp(tw.t),
            "frame_id": "imu",
            "linear_mps": {"x": tw.linear.x, "y": tw.linear.y, "z": tw.linear.z},
            "angular_radps": {"x": tw.angular.x, "y": tw.angular.y, "z": tw.angular.z},
            "sigma": if estimated { tw.sigma.to_vec() } else { Vec::new() },
        });
        self.put(ch, tw.t, &v)
    }

    /// A finished run at once (for the standalone commands): the estimate and
    /// truth (`/estimate`, `/groundtruth`), the covariance, the body twists
    /// (`/estimate/twist`, `/groundtruth/twist`), and both paths at the last
    /// pose's time. `truth` and `truth_twists` may be empty.
    pub fn run_poses(
        &mut self,
        estimate: &[StampedPose],
        covariance: &[StampedCovariance],
        twists: &[StampedTwist],
        truth: &[StampedPose],
        truth_twists: &[StampedTwist],
    ) -> Result<(), LogError> {
        for p in estimate {
            self.pose("/estimate", "world", p.t, &p.rot, &p.pos)?;
        }
        for c in covariance {
            self.covariance(c.t, &c.ori, &c.pos)?;
        }
        for tw in twists {
            self.twist("/estimate/twist", tw, true)?;
        }
        for tw in truth_twists {
            self.twist("/groundtruth/twist", tw, false)?;
        }
        for p in truth {
            self.pose("/groundtruth", "world", p.t, &p.rot, &p.pos)?;
        }
        if let Some(last) = estimate.last() {
            self.path("/estimate/path", last.t, estimate, usize::MAX)?;
            if !truth.is_empty() {
                self.path("/groundtruth/path", last.t, truth, usize::MAX)?;
            }
        }
        Ok(())
    }

    /// The 3-D scene on `/scene`: SLAM landmarks (spheres, world frame) and the
    /// peers' newest camera poses (arrows along their optical axes), replacing
    /// the previous scene.
    pub fn scene(
        &mut self,
        t: f64,
        landmarks: &[Vector3<f64>],
        peers: &[PeerPose],
    ) -> Result<(), LogError> {
        let ch = self.channel("/scene", "foxglove.SceneUpdate", &scene_update_schema())?;
        let spheres: Vec<Value> = landmarks
            .iter()
            .map(|p| json!({"pose": pose_json(&Matrix3::identity(), p), "size": {"x": 0.08, "y": 0.08, "z": 0.08}, "color": color(0.95, 0.6, 0.1)}))
            .collect();
        let mut entities = vec![json!({
            "timestamp": stamp(t), "frame_id": "world", "id": "slam_landmarks",
            "lifetime": {"sec": 0, "nsec": 0}, "frame_locked": false, "spheres": spheres, "arrows": []
        })];
        for p in peers {
            // Foxglove arrows point along their pose's +x: turn +x onto the
            // camera's optical axis (+z of C).
            let x_to_z = Matrix3::new(0.0, 0.0, -1.0, 0.0, 1.0, 0.0, 1.0, 0.0, 0.0);
            entities.push(json!({
                "timestamp": stamp(t), "frame_id": "world", "id": format!("peer_{}", p.robot),
                "lifetime": {"sec": 0, "nsec": 0}, "frame_locked": false, "spheres": [],
                "arrows": [{"pose": pose_json(&(p.rot * x_to_z), &p.pos), "shaft_length": 0.4, "shaft_diameter": 0.05,
                            "head_length": 0.15, "head_diameter": 0.12, "color": color(0.2, 0.5, 1.0)}]
            }));
        }
        let v = json!({"deletions": [{"timestamp": stamp(t), "type": 1, "id": ""}], "entities": entities});
        self.put(ch, t, &v)
    }

    /// The camera image on `/camera/image` (PNG).
    pub fn image(&mut self, t: f64, image: &GrayImage) -> Result<(), LogError> {
        let png = image.to_png()?;
        let ch = self.channel(
            "/camera/image",
            "foxglove.CompressedImage",
            COMPRESSED_IMAGE_SCHEMA,
        )?;
        let v = json!({"timestamp": stamp(t), "frame_id": "camera", "data": common::base64::encode(&png), "format": "png"});
        self.put(ch, t, &v)
    }

    /// The tracked features of `frame` on `/camera/tracks`: tracks green, new
    /// ones (`new_ids`) yellow.
    pub fn tracks(&mut self, frame: &FeatureFrame, new_ids: &[u64]) -> Result<(), LogError> {
        let ch = self.channel(
            "/camera/tracks",
            "foxglove.ImageAnnotations",
            &image_annotations_schema(),
        )?;
        let t = frame.t;
        // Foxglove's image origin is the corner of the first pixel; ours is its centre.
        let points: Vec<Value> = frame
            .features
            .iter()
            .map(|f| json!({"x": f.uv.x + 0.5, "y": f.uv.y + 0.5}))
            .collect();
        let colors: Vec<Value> = frame
            .features
            .iter()
            .map(|f| {
                if new_ids.contains(&f.id) {
                    color(1.0, 0.9, 0.0)
                } else {
                    color(0.1, 0.9, 0.2)
                }
            })
            .collect();
        let v = json!({"circles": [], "texts": [], "points": [{
            "timestamp": stamp(t), "type": 1, "points": points, "outline_color": color(0.1, 0.9, 0.2),
            "outline_colors": colors, "fill_color": color(0.1, 0.9, 0.2), "thickness": 4.0
        }]});
        self.put(ch, t, &v)
    }
}

/// `fleet.BodyTwist`: a body's velocity and angular rate in its own axes.
fn body_twist_schema() -> String {
    format!(
        r#"{{"title":"fleet.BodyTwist","type":"object","properties":{{"timestamp":{TIME},"frame_id":{{"type":"string"}},"linear_mps":{VEC3},"angular_radps":{VEC3},"sigma":{{"type":"array","items":{{"type":"number"}},"description":"standard deviations of vx vy vz (m/s) wx wy wz (rad/s); empty for a truth"}}}}}}"#
    )
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_path_pose_serializes_as_the_foxglove_pose_it_was_built_as_before() {
        let rot = nalgebra::Rotation3::from_euler_angles(0.1, -0.2, 0.3).into_inner();
        let p = StampedPose {
            t: 1.5,
            rot,
            pos: Vector3::new(1.0, -2.0, 3.5),
        };
        let typed = serde_json::to_value(pose_msg(&p)).unwrap();
        assert_eq!(typed, pose_json(&p.rot, &p.pos));
        let msg = PosesInFrame {
            timestamp: stamp(1.5),
            frame_id: "world",
            poses: vec![pose_msg(&p)],
        };
        assert_eq!(
            serde_json::to_value(msg).unwrap(),
            json!({"timestamp": stamp(1.5), "frame_id": "world", "poses": [pose_json(&p.rot, &p.pos)]})
        );
    }

    /// A standalone run's log holds the estimated and true twists, one per
    /// pose, the estimate's with six standard deviations.
    #[test]
    fn a_finished_run_logs_its_twists() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("a.mcap");
        let mut log = AgentLog::create(&path).unwrap();
        let poses: Vec<StampedPose> = (0..3)
            .map(|k| StampedPose {
                t: k as f64,
                rot: Matrix3::identity(),
                pos: Vector3::new(k as f64, 0.0, 0.0),
            })
            .collect();
        let twists: Vec<StampedTwist> = poses
            .iter()
            .map(|p| StampedTwist {
                t: p.t,
                linear: Vector3::new(1.0, 0.0, 0.0),
                angular: Vector3::new(0.0, 0.0, 0.1),
                sigma: [0.01, 0.01, 0.01, 0.002, 0.002, 0.002],
            })
            .collect();
        log.run_poses(&poses, &[], &twists, &poses, &twists)
            .unwrap();
        log.finish().unwrap();
        let bytes = std::fs::read(&path).unwrap();
        let mut sigmas = std::collections::BTreeMap::new();
        for m in mcap::MessageStream::new(&bytes).unwrap() {
            let m = m.unwrap();
            if m.channel.schema.as_ref().unwrap().name != "fleet.BodyTwist" {
                continue;
            }
            let v: Value = serde_json::from_slice(&m.data).unwrap();
            assert_eq!(v["linear_mps"]["x"], 1.0);
            assert_eq!(v["angular_radps"]["z"], 0.1);
            sigmas
                .entry(m.channel.topic.clone())
                .or_insert_with(Vec::new)
                .push(v["sigma"].as_array().unwrap().len());
        }
        assert_eq!(sigmas["/estimate/twist"], [6, 6, 6]);
        assert_eq!(sigmas["/groundtruth/twist"], [0, 0, 0]);
    }
}
