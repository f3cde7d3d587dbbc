//! The message bodies and their parts.

use nalgebra::{Matrix3, Vector2, Vector3, Vector4};
use serde::{Deserialize, Serialize};

use super::bounded_vec;
use super::history::{HistoryReplay, HistoryRequest};
use super::packed_cov::PackedCovariance;
use super::MessageKind;
use crate::calibration::CameraCalibration;
use crate::camera::{CameraError, CameraModel, Distortion};
use crate::descriptor::Descriptor;
use crate::measurement::FeatureObservation;
use crate::so3::{self, Se3};

/// What a message carries; the variant decides its [`MessageKind`].
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub enum Body {
    /// The active feature tracks of one camera frame.
    Tracks(TrackFrame),
    /// Descriptors of new tracks, or of all tracks of a keyframe.
    Descriptors(DescriptorBatch),
    /// The sliding window of camera poses with their joint covariance.
    Snapshot(StateSnapshot),
    /// Presence and progress.
    Heartbeat(Heartbeat),
    /// A request for a peer's keyframe windows (history catch-up).
    HistoryRequest(HistoryRequest),
    /// A keyframe window sent again on request (boxed: far larger than the rest).
    HistoryReplay(Box<HistoryReplay>),
}

impl Body {
    /// The kind of this body (the last segment of its key expression).
    pub fn kind(&self) -> MessageKind {
        match self {
            Body::Tracks(_) => MessageKind::Tracks,
            Body::Descriptors(_) => MessageKind::Descriptors,
            Body::Snapshot(_) => MessageKind::Snapshot,
            Body::Heartbeat(_) => MessageKind::Heartbeat,
            Body::HistoryRequest(_) => MessageKind::HistoryRequest,
            Body::HistoryReplay(_) => MessageKind::HistoryReplay,
        }
    }
}

/// The features tracked in one camera frame.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize, Default)]
pub struct TrackFrame {
    /// Index of the camera frame on the sender (0 for its first image).
    pub frame_index: u64,
    /// Camera timestamp of the image, in seconds.
    pub t_s: f64,
    /// The tracked features.
    #[serde(deserialize_with = "bounded_vec::deserialize")]
    pub features: Vec<TrackPoint>,
}

/// One tracked feature in one image.
///
/// Coordinates are `f32`: below 1024 px a pixel coordinate is rounded by at
/// most 3e-5 px, far below any tracker's noise, and a normalized coordinate by
/// 6e-8 of its value.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize, Default)]
pub struct TrackPoint {
    /// Track id, unique within the sender.
    pub id: u64,
    /// Raw (distorted) pixel coordinates `[u, v]`, in pixels.
    pub uv_px: [f32; 2],
    /// Undistorted normalized coordinates `[x/z, y/z]` in the sender's camera,
    /// computed with the sender's current intrinsics.
    pub xy_norm: [f32; 2],
}

impl TrackPoint {
    /// A track point from `f64` pixel and normalized coordinates.
    pub fn new(id: u64, uv_px: &Vector2<f64>, xy_norm: &Vector2<f64>) -> Self {
        Self {
            id,
            uv_px: [uv_px.x as f32, uv_px.y as f32],
            xy_norm: [xy_norm.x as f32, xy_norm.y as f32],
        }
    }

    /// A track point from an observation, undistorting its pixel with `camera`.
    pub fn from_observation(
        obs: &FeatureObservation,
        camera: &CameraModel,
    ) -> Result<Self, CameraError> {
        let xy = camera.undistort(&obs.uv)?;
        Ok(Self::new(obs.id, &obs.uv, &xy))
    }

    /// The raw pixel `[u, v]` in `f64`.
    pub fn uv(&self) -> Vector2<f64> {
        Vector2::new(f64::from(self.uv_px[0]), f64::from(self.uv_px[1]))
    }

    /// The undistorted normalized point `[x/z, y/z]` in `f64`.
    pub fn xy(&self) -> Vector2<f64> {
        Vector2::new(f64::from(self.xy_norm[0]), f64::from(self.xy_norm[1]))
    }
}

/// Binary descriptors of some tracks in one frame: of the tracks that started
/// in it, or of every track when the frame is a keyframe.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize, Default)]
pub struct DescriptorBatch {
    /// Index of the camera frame on the sender.
    pub frame_index: u64,
    /// Camera timestamp of the image, in seconds.
    pub t_s: f64,
    /// Whether the frame is a keyframe (then `entries` covers all its tracks).
    pub keyframe: bool,
    /// The descriptors.
    #[serde(deserialize_with = "bounded_vec::deserialize")]
    pub entries: Vec<DescriptorEntry>,
}

/// The 256-bit descriptor of one track, words as [`Descriptor`].
///
/// On the wire the bits are the 32 bytes of [`Descriptor::to_bytes`] (varint
/// words would take 9 bytes each for random bits).
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, Serialize, Deserialize, Default)]
pub struct DescriptorEntry {
    /// Track id, unique within the sender.
    pub id: u64,
    /// The descriptor's bits (bit `i` is bit `i % 64` of word `i / 64`).
    #[serde(with = "bits_as_bytes")]
    pub bits: [u64; 4],
}

/// Serializes descriptor words as their 32 little-endian bytes.
mod bits_as_bytes {
    use crate::descriptor::Descriptor;
    use serde::{Deserialize, Deserializer, Serialize, Serializer};

    pub(super) fn serialize<S: Serializer>(bits: &[u64; 4], s: S) -> Result<S::Ok, S::Error> {
        Descriptor(*bits).to_bytes().serialize(s)
    }

    pub(super) fn deserialize<'de, D: Deserializer<'de>>(d: D) -> Result<[u64; 4], D::Error> {
        let bytes = <[u8; 32]>::deserialize(d)?;
        Ok(Descriptor::from_bytes(&bytes).0)
    }
}

impl DescriptorEntry {
    /// The entry of track `id` with descriptor `d`.
    pub fn new(id: u64, d: Descriptor) -> Self {
        Self { id, bits: d.0 }
    }

    /// The descriptor.
    pub fn descriptor(&self) -> Descriptor {
        Descriptor(self.bits)
    }
}

impl From<(u64, Descriptor)> for DescriptorEntry {
    fn from((id, d): (u64, Descriptor)) -> Self {
        Self::new(id, d)
    }
}

impl From<DescriptorEntry> for (u64, Descriptor) {
    fn from(e: DescriptorEntry) -> Self {
        (e.id, e.descriptor())
    }
}

impl From<DescriptorEntry> for Descriptor {
    fn from(e: DescriptorEntry) -> Self {
        e.descriptor()
    }
}

impl From<&FeatureObservation> for DescriptorEntry {
    fn from(obs: &FeatureObservation) -> Self {
        Self::new(obs.id, obs.descriptor)
    }
}

/// The sender's sliding window: camera poses of its clones with their joint
/// covariance, its camera model, and its SLAM landmarks.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct StateSnapshot {
    /// Index of the newest camera frame in the window.
    pub frame_index: u64,
    /// Camera timestamp of that frame, in seconds.
    pub t_s: f64,
    /// Whether that frame is a keyframe (receivers keep keyframe windows as history).
    pub keyframe: bool,
    /// Which world frame the poses are in. 0: the fleet's one frame (every
    /// robot was given its start pose in it). Otherwise the frame its start
    /// defined (`align_peer_frames`), named by that start: an agent started
    /// again where the frame cannot be the same (live sensors) sends a new
    /// one, so a receiver aligns it anew and keeps using the windows of
    /// before the restart through the alignment it had.
    pub frame_epoch: u64,
    /// The sender's current camera model, to interpret its pixel tracks.
    pub camera: CameraModelWire,
    /// The sender's pixel noise (standard deviation), pixels: a receiver
    /// weighs the sender's tracks at it, through `camera`, so robots whose
    /// cameras are noisier or cleaner than its own are taken as they are.
    pub pixel_sigma_px: f64,
    /// Camera poses of the clones in the window, oldest first.
    #[serde(deserialize_with = "bounded_vec::deserialize")]
    pub clones: Vec<CameraPose>,
    /// Joint covariance of the clone poses (`6 · clones.len()` square), or of
    /// the poses and then the camera intrinsics `[fx, fy, cx, cy, d0..d3]`
    /// (`6 · clones.len() + 8`) when the sender estimates them: its normalized
    /// track coordinates are only as good as its intrinsics.
    pub covariance: PackedCovariance,
    /// SLAM landmarks in the global frame with their marginal covariances.
    #[serde(deserialize_with = "bounded_vec::deserialize")]
    pub landmarks: Vec<Landmark>,
}

impl StateSnapshot {
    /// The window's end time: its newest clone's time (the snapshot's time
    /// without clones), s. Peers key keyframe windows by it.
    pub fn end_s(&self) -> f64 {
        self.clones.last().map_or(self.t_s, |c| c.t_s)
    }
}

/// The pose of the camera in the global frame `G` when one image was taken:
/// `(R_CtoG, p_CinG)`.
///
/// Its error (in [`PackedCovariance`]) follows [`crate::conventions`]:
/// `R_CtoG = R̂_CtoG · Exp(δθ)` (right, local error) and `p_CinG = p̂_CinG + δp`,
/// ordered `[δθ, δp]`.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct CameraPose {
    /// Camera timestamp of the image, in seconds.
    pub t_s: f64,
    /// `R_CtoG` as a Hamilton unit quaternion, scalar last `[qx, qy, qz, qw]`.
    pub q_xyzw: [f64; 4],
    /// `p_CinG`, the camera position in the global frame, in metres.
    pub p_m: [f64; 3],
}

impl Default for CameraPose {
    /// At time 0, at the origin, axes aligned with `G`.
    fn default() -> Self {
        Self {
            t_s: 0.0,
            q_xyzw: [0.0, 0.0, 0.0, 1.0],
            p_m: [0.0; 3],
        }
    }
}

impl CameraPose {
    /// The pose of rotation `rot_c_to_g` and position `p_c_in_g` at `t_s`
    /// (the quaternion has `qw >= 0`).
    pub fn new(t_s: f64, rot_c_to_g: &Matrix3<f64>, p_c_in_g: &Vector3<f64>) -> Self {
        Self {
            t_s,
            q_xyzw: so3::xyzw_from_rot(rot_c_to_g),
            p_m: [p_c_in_g.x, p_c_in_g.y, p_c_in_g.z],
        }
    }

    /// The camera pose of the IMU pose `(R_ItoG, p_IinG)` through the
    /// calibration's extrinsics: `R_CtoG = R_ItoG R_CtoI`,
    /// `p_CinG = p_IinG + R_ItoG p_CinI`.
    pub fn from_imu_pose(
        t_s: f64,
        rot_i_to_g: &Matrix3<f64>,
        p_i_in_g: &Vector3<f64>,
        calibration: &CameraCalibration,
    ) -> Self {
        let rot_c_to_g = rot_i_to_g * calibration.rot_c_to_i;
        let p_c_in_g = p_i_in_g + rot_i_to_g * calibration.p_c_in_i;
        Self::new(t_s, &rot_c_to_g, &p_c_in_g)
    }

    /// `R_CtoG` (the quaternion is normalized first).
    pub fn rot_c_to_g(&self) -> Matrix3<f64> {
        let [x, y, z, w] = self.q_xyzw;
        so3::rot_from_xyzw(x, y, z, w)
    }

    /// `p_CinG` in metres.
    pub fn p_c_in_g(&self) -> Vector3<f64> {
        Vector3::from(self.p_m)
    }

    /// The transform `T_CtoG`.
    pub fn t_c_to_g(&self) -> Se3 {
        Se3::new(self.rot_c_to_g(), self.p_c_in_g())
    }
}

/// A SLAM landmark: its position in `G` and the 3x3 marginal covariance of it.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct Landmark {
    /// Landmark id, unique within the sender (the id of the track it came from).
    pub id: u64,
    /// Position `p_FinG` in metres.
    pub p_m: [f64; 3],
    /// Upper triangle of the position covariance in m²: `[xx, xy, xz, yy, yz, zz]`.
    pub cov_upper: [f32; 6],
}

impl Landmark {
    /// A landmark from its position and covariance (symmetrized as `(P + Pᵀ) / 2`).
    pub fn new(id: u64, p_in_g: &Vector3<f64>, cov: &Matrix3<f64>) -> Self {
        let s = |i: usize, j: usize| (0.5 * (cov[(i, j)] + cov[(j, i)])) as f32;
        Self {
            id,
            p_m: [p_in_g.x, p_in_g.y, p_in_g.z],
            cov_upper: [s(0, 0), s(0, 1), s(0, 2), s(1, 1), s(1, 2), s(2, 2)],
        }
    }

    /// Position `p_FinG` in metres.
    pub fn position(&self) -> Vector3<f64> {
        Vector3::from(self.p_m)
    }

    /// The full symmetric 3x3 covariance in m².
    pub fn covariance(&self) -> Matrix3<f64> {
        let [xx, xy, xz, yy, yz, zz] = self.cov_upper.map(f64::from);
        Matrix3::new(xx, xy, xz, xy, yy, yz, xz, yz, zz)
    }
}

/// Distortion model on the wire (mirrors [`Distortion`]).
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, Serialize, Deserialize)]
pub enum DistortionWire {
    /// Radial-tangential, `d = [k1, k2, p1, p2]`.
    Radtan,
    /// Equidistant (Kannala-Brandt), `d = [k1, k2, k3, k4]`.
    Equidistant,
}

impl From<Distortion> for DistortionWire {
    fn from(d: Distortion) -> Self {
        match d {
            Distortion::RadTan => DistortionWire::Radtan,
            Distortion::Equidistant => DistortionWire::Equidistant,
        }
    }
}

impl From<DistortionWire> for Distortion {
    fn from(d: DistortionWire) -> Self {
        match d {
            DistortionWire::Radtan => Distortion::RadTan,
            DistortionWire::Equidistant => Distortion::Equidistant,
        }
    }
}

/// A camera model on the wire (as [`CameraModel`], flattened).
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct CameraModelWire {
    /// Distortion model, which gives the meaning of `intrinsics[4..8]`.
    pub model: DistortionWire,
    /// `[fx, fy, cx, cy, d0, d1, d2, d3]`: pixels, then unitless distortion.
    pub intrinsics: [f64; 8],
    /// Image width in pixels.
    pub width: u32,
    /// Image height in pixels.
    pub height: u32,
}

impl Default for CameraModelWire {
    /// [`CameraModel::euroc_cam0`].
    fn default() -> Self {
        Self::from(&CameraModel::euroc_cam0())
    }
}

impl From<&CameraModel> for CameraModelWire {
    fn from(c: &CameraModel) -> Self {
        let (k, d) = (&c.intrinsics, &c.distortion);
        Self {
            model: c.model.into(),
            intrinsics: [k[0], k[1], k[2], k[3], d[0], d[1], d[2], d[3]],
            width: c.width,
            height: c.height,
        }
    }
}

impl From<&CameraModelWire> for CameraModel {
    /// The model as is; check it with [`CameraModel::validate`] (which
    /// [`super::Envelope::validate`] does for snapshots).
    fn from(w: &CameraModelWire) -> Self {
        let k = &w.intrinsics;
        CameraModel {
            model: w.model.into(),
            width: w.width,
            height: w.height,
            intrinsics: Vector4::new(k[0], k[1], k[2], k[3]),
            distortion: Vector4::new(k[4], k[5], k[6], k[7]),
        }
    }
}

impl CameraModelWire {
    /// The camera model, validated.
    pub fn to_camera_model(&self) -> Result<CameraModel, CameraError> {
        let model = CameraModel::from(self);
        model.validate()?;
        Ok(model)
    }
}

/// Where an agent is in its run.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, Serialize, Deserialize)]
pub enum AgentState {
    /// Started, not yet processing frames (initializing, waiting for peers).
    Starting,
    /// Processing frames.
    Running,
    /// Done: no more frames will come.
    Finished,
    /// Done, and done asking its peers for the keyframe windows it lacks or
    /// holds short: it leaves once every peer has settled too.
    Settled,
}

/// Presence and progress of an agent (the fleet clock in lockstep runs).
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct Heartbeat {
    /// Where the agent is in its run.
    pub state: AgentState,
    /// Number of camera frames processed so far.
    pub frames_done: u64,
    /// Index of the last processed frame, if any.
    pub last_frame_index: Option<u64>,
    /// Camera timestamp of the last processed frame in seconds, if any.
    pub last_t_s: Option<f64>,
    /// End time (newest clone) of the newest keyframe window the agent has
    /// published, s: a peer that holds nothing that recent has lost windows,
    /// even when no later message shows a gap (history catch-up).
    pub newest_window_end_s: Option<f64>,
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn camera_model_round_trips_through_wire() {
        let cam = CameraModel::euroc_cam0();
        let wire = CameraModelWire::from(&cam);
        assert_eq!(wire.intrinsics[0], 458.654);
        assert_eq!(wire.model, DistortionWire::Radtan);
        assert_eq!(wire.to_camera_model().unwrap(), cam);
        let mut bad = wire;
        bad.intrinsics[5] = f64::NAN;
        assert!(matches!(
            bad.to_camera_model(),
            Err(CameraError::NonFiniteParameter { name: "d1", .. })
        ));
    }

    #[test]
    fn camera_pose_round_trips_rotation_and_position() {
        let rot = so3::exp_so3(&Vector3::new(0.3, -1.2, 2.5));
        let p = Vector3::new(1.0, -2.0, 3.5);
        let pose = CameraPose::new(4.25, &rot, &p);
        assert!(pose.q_xyzw[3] >= 0.0);
        assert!((pose.rot_c_to_g() - rot).norm() < 1e-14);
        assert_eq!(pose.p_c_in_g(), p);
        assert_eq!(pose.t_c_to_g().rot, pose.rot_c_to_g());
    }

    #[test]
    fn camera_pose_from_imu_pose_applies_extrinsics() {
        let calib = CameraCalibration::euroc_cam0();
        let rot_i_to_g = so3::exp_so3(&Vector3::new(0.1, 0.2, -0.4));
        let p_i_in_g = Vector3::new(3.0, 1.0, 1.5);
        let pose = CameraPose::from_imu_pose(1.0, &rot_i_to_g, &p_i_in_g, &calib);
        let expected = Se3::new(rot_i_to_g, p_i_in_g).compose(&calib.t_c_to_i());
        assert!((pose.rot_c_to_g() - expected.rot).norm() < 1e-12);
        assert!((pose.p_c_in_g() - expected.trans).norm() < 1e-14);
    }

    #[test]
    fn landmark_covariance_round_trips() {
        let cov = Matrix3::new(0.04, 0.001, -0.002, 0.001, 0.09, 0.003, -0.002, 0.003, 0.25);
        let lm = Landmark::new(7, &Vector3::new(1.0, 2.0, 3.0), &cov);
        assert_eq!(lm.position(), Vector3::new(1.0, 2.0, 3.0));
        assert!((lm.covariance() - cov).norm() < 1e-8);
        assert_eq!(lm.covariance(), lm.covariance().transpose());
    }

    #[test]
    fn descriptor_entry_conversions() {
        let d = Descriptor([1, 2, 3, u64::MAX]);
        let e = DescriptorEntry::from((9, d));
        assert_eq!(e.bits, d.0);
        assert_eq!(Descriptor::from(e), d);
        assert_eq!(<(u64, Descriptor)>::from(e), (9, d));
    }

    #[test]
    fn track_point_from_observation_undistorts() {
        let cam = CameraModel::euroc_cam0();
        let xy = Vector2::new(0.1, -0.05);
        let uv = cam.distort(&xy);
        let obs = FeatureObservation {
            id: 3,
            uv,
            descriptor: Descriptor::default(),
        };
        let tp = TrackPoint::from_observation(&obs, &cam).unwrap();
        assert_eq!(tp.id, 3);
        assert!((tp.xy() - xy).norm() < 1e-6);
        assert!((tp.uv() - uv).norm() < 1e-3);
    }
}
