//! A peer's window as a CI-EKF participant (thesis Section 5.3.3): the camera
//! poses of one of its sliding windows with their joint covariance, from its
//! snapshot message, and the measurement function of a feature seen from one of
//! those cameras.
//!
//! Peers publish camera poses (extrinsics folded in) and undistorted normalized
//! coordinates, so no peer calibration is needed here. Pose error convention (see
//! `common::messages::CameraPose`): `R_CtoG = R̂ Exp(δθ)`, `p_CinG = p̂ + δp`,
//! ordered `[δθ, δp]`. A peer's window is never updated by us (Eq. 5.16 only
//! changes our own state); historical windows are used exactly as stored.

use common::messages::StateSnapshot;
use common::so3::skew;
use nalgebra::{DMatrix, Matrix2x3, Matrix3, SMatrix, Vector2, Vector3};

/// Camera pose of one clone of a peer's window.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct PeerPose {
    /// Camera time of the image, s.
    pub t_s: f64,
    /// `R_CtoG`.
    pub rot: Matrix3<f64>,
    /// `p_CinG`, m.
    pub pos: Vector3<f64>,
}

/// A SLAM landmark of a peer with its marginal covariance.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct PeerLandmark {
    /// The peer's track id of the landmark.
    pub id: u64,
    /// `p_FinG`, m.
    pub pos: Vector3<f64>,
    /// Covariance, m².
    pub cov: Matrix3<f64>,
}

/// One window of one peer: a CI participant.
#[derive(Clone, Debug, PartialEq)]
pub struct PeerWindow {
    /// The peer's robot id.
    pub peer: u32,
    /// Which of the peer's windows (the time key of its newest clone): a
    /// participant is `(peer, key)`.
    pub key: u64,
    /// Camera poses, oldest first.
    pub poses: Vec<PeerPose>,
    /// Their joint covariance, `6n x 6n`, per pose `[δθ, δp]`.
    pub cov: DMatrix<f64>,
    /// The peer's focal length, px (normalized-coordinate noise is pixel noise
    /// divided by it).
    pub focal_px: f64,
    /// SLAM landmarks of the window (keyframe snapshots carry them).
    pub landmarks: Vec<PeerLandmark>,
}

impl PeerWindow {
    /// The window of `snap` sent by `peer`; `None` when the covariance does not
    /// match the poses or has a non-positive diagonal (such a message is unusable;
    /// the decoder already rejects non-finite values).
    pub fn from_snapshot(peer: u32, key: u64, snap: &StateSnapshot) -> Option<Self> {
        let n = snap.clones.len();
        let cov = snap.covariance.to_dmatrix();
        if n == 0
            || cov.nrows() != 6 * n
            || (0..6 * n).any(|i| cov[(i, i)].is_nan() || cov[(i, i)] <= 0.0)
        {
            return None;
        }
        let poses = snap
            .clones
            .iter()
            .map(|c| PeerPose {
                t_s: c.t_s,
                rot: c.rot_c_to_g(),
                pos: c.p_c_in_g(),
            })
            .collect();
        let k = &snap.camera.intrinsics;
        let focal_px = (k[0] * k[1]).abs().sqrt();
        if focal_px.is_nan() || focal_px <= 1.0 {
            return None;
        }
        Some(Self {
            peer,
            key,
            poses,
            cov,
            focal_px,
            landmarks: snap
                .landmarks
                .iter()
                .map(|l| PeerLandmark {
                    id: l.id,
                    pos: l.position(),
                    cov: l.covariance(),
                })
                .collect(),
        })
    }

    /// Index of the pose taken at camera time `t_s` (the same image: times are
    /// copied, not recomputed, so they match exactly; 1 µs of slack).
    pub fn pose_at(&self, t_s: f64) -> Option<usize> {
        self.poses.iter().position(|p| (p.t_s - t_s).abs() < 1e-6)
    }

    /// The landmark the peer tracks as `id`, if it is a SLAM feature in this window.
    pub fn landmark(&self, id: u64) -> Option<&PeerLandmark> {
        self.landmarks.iter().find(|l| l.id == id)
    }

    /// The covariance of the poses `idx` (in that order), `6k x 6k`.
    pub fn sub_covariance(&self, idx: &[usize]) -> DMatrix<f64> {
        let k = idx.len();
        let mut out = DMatrix::zeros(6 * k, 6 * k);
        for (a, &i) in idx.iter().enumerate() {
            for (b, &j) in idx.iter().enumerate() {
                out.view_mut((6 * a, 6 * b), (6, 6))
                    .copy_from(&self.cov.view((6 * i, 6 * j), (6, 6)));
            }
        }
        out
    }
}

/// A feature seen from a peer camera, in normalized coordinates, and its
/// Jacobians.
#[derive(Clone, Copy, Debug)]
pub struct NormalizedProjection {
    /// `[x/z, y/z]` of the point in the camera.
    pub xy: Vector2<f64>,
    /// `∂xy/∂[δθ, δp]` of the camera pose (2x6).
    pub h_pose: SMatrix<f64, 2, 6>,
    /// `∂xy/∂p_FinG` (2x3).
    pub h_feature: Matrix2x3<f64>,
}

/// Projects `p_FinG` into the camera `pose`: `p_C = R_CtoGᵀ (p_F − p_C)`,
/// `xy = (x/z, y/z)`. With `R = R̂ Exp(δθ)`: `∂p_C/∂δθ = ⌊p_C⌋×`,
/// `∂p_C/∂δp = −R̂ᵀ`, `∂p_C/∂p_F = R̂ᵀ`. `None` when the point is not in front.
pub fn project_normalized(pose: &PeerPose, p_f: &Vector3<f64>) -> Option<NormalizedProjection> {
    let r_t = pose.rot.transpose();
    let p_c = r_t * (p_f - pose.pos);
    if p_c.z < 1e-3 {
        return None;
    }
    let iz = 1.0 / p_c.z;
    let dn = Matrix2x3::new(iz, 0.0, -p_c.x * iz * iz, 0.0, iz, -p_c.y * iz * iz);
    let mut h_pose = SMatrix::<f64, 2, 6>::zeros();
    h_pose
        .fixed_view_mut::<2, 3>(0, 0)
        .copy_from(&(dn * skew(&p_c)));
    h_pose.fixed_view_mut::<2, 3>(0, 3).copy_from(&(-dn * r_t));
    Some(NormalizedProjection {
        xy: Vector2::new(p_c.x * iz, p_c.y * iz),
        h_pose,
        h_feature: dn * r_t,
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use common::so3::exp_so3;

    #[test]
    fn normalized_projection_jacobians_match_numerical_differentiation() {
        let pose = PeerPose {
            t_s: 0.0,
            rot: exp_so3(&Vector3::new(0.3, -0.4, 1.1)),
            pos: Vector3::new(1.0, -0.5, 2.0),
        };
        let p_f = pose.pos + pose.rot * Vector3::new(0.7, -0.3, 4.0);
        let p = project_normalized(&pose, &p_f).unwrap();
        let h = 1e-6;
        for i in 0..3 {
            let mut e = Vector3::zeros();
            e[i] = h;
            let f = |rot: Matrix3<f64>, pos: Vector3<f64>, pf: Vector3<f64>| {
                project_normalized(&PeerPose { t_s: 0.0, rot, pos }, &pf)
                    .unwrap()
                    .xy
            };
            let num = (f(pose.rot * exp_so3(&e), pose.pos, p_f)
                - f(pose.rot * exp_so3(&-e), pose.pos, p_f))
                / (2.0 * h);
            assert!((p.h_pose.column(i) - num).norm() < 1e-6, "dθ {i}");
            let num = (f(pose.rot, pose.pos + e, p_f) - f(pose.rot, pose.pos - e, p_f)) / (2.0 * h);
            assert!((p.h_pose.column(3 + i) - num).norm() < 1e-6, "dp {i}");
            let num = (f(pose.rot, pose.pos, p_f + e) - f(pose.rot, pose.pos, p_f - e)) / (2.0 * h);
            assert!((p.h_feature.column(i) - num).norm() < 1e-6, "dpf {i}");
        }
    }

    #[test]
    fn a_point_behind_the_peer_camera_has_no_projection() {
        let pose = PeerPose {
            t_s: 0.0,
            rot: Matrix3::identity(),
            pos: Vector3::zeros(),
        };
        assert!(project_normalized(&pose, &Vector3::new(0.0, 0.0, -1.0)).is_none());
    }
}
