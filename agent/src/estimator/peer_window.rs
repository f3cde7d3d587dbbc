//! A peer's window as a CI-EKF participant (thesis Section 5.3.3): the camera
//! poses of one of its sliding windows with their joint covariance, from its
//! snapshot message, and the measurement function of a feature seen from one of
//! those cameras.
//!
//! Peers publish camera poses (extrinsics folded in) and undistorted normalized
//! coordinates, so a peer's calibration enters only through the error of its
//! intrinsics (when it estimates them). Pose error convention (see
//! `common::messages::CameraPose`): `R_CtoG = R̂ Exp(δθ)`, `p_CinG = p̂ + δp`,
//! ordered `[δθ, δp]`. A peer's window is never updated by us (Eq. 5.16 only
//! changes our own state); historical windows are used exactly as stored.

use super::state::{PeerFrameMean, Var};
use common::camera::CameraModel;
use common::messages::{cover_f32_rounding, StateSnapshot, INTRINSICS_DIM};
use common::so3::skew;
use nalgebra::{DMatrix, Matrix2x3, Matrix3, SMatrix, Vector2, Vector3};
use std::sync::Arc;

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
    /// Their joint covariance, per pose `[δθ, δp]`, then (when the peer
    /// estimates them) its intrinsics `[fx, fy, cx, cy, d0..d3]`. Shared: a
    /// window is a participant in many frames' updates and is never changed.
    pub cov: Arc<DMatrix<f64>>,
    /// The peer's camera model as it estimated it (its normalized coordinates
    /// were undistorted with it).
    pub camera: CameraModel,
    /// The peer's pixel noise, pixels: its measurements are weighed at it.
    pub pixel_sigma_px: f64,
    /// SLAM landmarks of the window (keyframe snapshots carry them).
    pub landmarks: Vec<PeerLandmark>,
    /// The peer frame in our state this window was taken into our frame
    /// through (`cooperation.peer_frame_state_s`), with the Jacobians of the
    /// window w.r.t. it; `None` for a window in our frame as it is or with
    /// the alignment's covariance folded into `cov`.
    pub frame: Option<Arc<FrameLink>>,
}

/// How a window taken into our frame through a peer frame held in our state
/// depends on that frame's error `[δψ, δt]`.
#[derive(Clone, Debug, PartialEq)]
pub struct FrameLink {
    /// The state variable (`Var::PeerFrame`).
    pub var: Var,
    /// The frame's mean the window was taken into our frame at.
    pub at: PeerFrameMean,
    /// `∂(window error)/∂[δψ, δt]`, rows as the window's covariance (the
    /// intrinsics' rows zero).
    pub poses: DMatrix<f64>,
    /// `∂p_FinG/∂[δψ, δt]` of each landmark.
    pub landmarks: Vec<SMatrix<f64, 3, 4>>,
}

impl PeerWindow {
    /// The window of `snap` sent by `peer`; `None` when the covariance does not
    /// match the poses, has a non-positive diagonal or is not positive definite
    /// once its `f32` rounding is covered (such a message is unusable; the
    /// decoder already rejects non-finite values).
    ///
    /// The covariances are taken at least as large as the peer's own before it
    /// rounded them to `f32` (`to_dmatrix_at_least_sent`): CI is consistent only
    /// with participants no smaller than the truth, and rounding moves a
    /// window's smallest eigenvalues by more than their size.
    pub fn from_snapshot(peer: u32, key: u64, snap: &StateSnapshot) -> Option<Self> {
        let n = snap.clones.len();
        let cov = snap.covariance.to_dmatrix_at_least_sent();
        let dim = cov.nrows();
        // The variances as sent: the cover would lift a zero one above zero.
        if n == 0
            || (dim != 6 * n && dim != 6 * n + INTRINSICS_DIM)
            || snap.covariance.diagonal().any(|v| v.is_nan() || v <= 0.0)
            || cov.clone().cholesky().is_none()
        {
            return None;
        }
        let camera = snap.camera.to_camera_model().ok()?;
        let poses = snap
            .clones
            .iter()
            .map(|c| PeerPose {
                t_s: c.t_s,
                rot: c.rot_c_to_g(),
                pos: c.p_c_in_g(),
            })
            .collect();
        Some(Self {
            peer,
            key,
            poses,
            cov: Arc::new(cov),
            camera,
            pixel_sigma_px: snap.pixel_sigma_px,
            landmarks: snap
                .landmarks
                .iter()
                .filter_map(|l| {
                    let mut cov = l.covariance();
                    cover_f32_rounding(&mut cov);
                    cov.cholesky().is_some().then(|| PeerLandmark {
                        id: l.id,
                        pos: l.position(),
                        cov,
                    })
                })
                .collect(),
            frame: None,
        })
    }

    /// The item of the peer's intrinsics (after the poses), when its covariance
    /// has them.
    pub fn intrinsics_item(&self) -> Option<usize> {
        (self.cov.nrows() == 6 * self.poses.len() + INTRINSICS_DIM).then_some(self.poses.len())
    }

    /// Size of item `i`: a pose (6) or the intrinsics (8).
    pub fn item_size(&self, i: usize) -> usize {
        if i < self.poses.len() {
            6
        } else {
            INTRINSICS_DIM
        }
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

    /// The covariance of the items `idx` (poses, or the intrinsics item), in
    /// that order.
    pub fn sub_covariance(&self, idx: &[usize]) -> DMatrix<f64> {
        let sizes: Vec<usize> = idx.iter().map(|i| self.item_size(*i)).collect();
        let total = sizes.iter().sum();
        let mut out = DMatrix::zeros(total, total);
        let (mut ra, mut rb);
        ra = 0;
        for (&i, &si) in idx.iter().zip(&sizes) {
            rb = 0;
            for (&j, &sj) in idx.iter().zip(&sizes) {
                out.view_mut((ra, rb), (si, sj))
                    .copy_from(&self.cov.view((6 * i, 6 * j), (si, sj)));
                rb += sj;
            }
            ra += si;
        }
        out
    }
}

/// One measurement of a feature by a peer, whitened (unit noise): the residual
/// and Jacobians of `W (xy − π(p_F))`, `W = (∂uv/∂xy) / σ_px` at the predicted
/// point, which turns normalized coordinates back into pixels of the peer's
/// camera.
#[derive(Clone, Copy, Debug)]
pub struct PeerMeasurement {
    /// Whitened residual.
    pub res: Vector2<f64>,
    /// Jacobian w.r.t. the camera pose `[δθ, δp]` (2x6).
    pub h_pose: SMatrix<f64, 2, 6>,
    /// Jacobian w.r.t. `p_FinG` (2x3).
    pub h_feature: Matrix2x3<f64>,
    /// Jacobian w.r.t. the peer's intrinsics (2x8).
    pub h_intrinsics: SMatrix<f64, 2, 8>,
}

/// The peer's normalized measurement `xy` of a feature from pose `pose` of
/// window `w`, linearized at `p_lin` (Jacobians) and `p_cur` (residual).
///
/// The peer undistorted its pixel with its intrinsics estimate `θ̂`: with
/// `distort(θ, n(θ)) = uv`, `∂n/∂θ = −(∂uv/∂n)⁻¹ ∂uv/∂θ`, so an error `δθ` of the
/// peer's intrinsics moves its reported coordinates by `(∂uv/∂n)⁻¹ (∂uv/∂θ) δθ`:
/// whitened, `H_θ = (∂uv/∂θ) / σ`.
///
/// Both `∂uv/∂n` and `∂uv/∂θ` are taken at the predicted point `π(p_lin)`, never
/// at the measured `xy`: there they would carry the measurement's own noise.
/// `∂uv/∂θ` grows with the distance from the principal point (the focal
/// columns are `[x_d, y_d]`), so a point the noise pushed outward would get a
/// larger modelled noise, through the peer's intrinsics, than one pushed
/// inward, and the update would weigh inward errors more: in expectation it
/// pulls the features toward the peer's image centre, and the focal lengths
/// that fit them grow. Measured that way, two robots on a 3 m circle that
/// fused the peers' intrinsics in their common SLAM updates ran their focal
/// lengths away, +54 px in 60 s in each of seeds 1-4, and not at all with
/// noise-free pixels.
pub fn peer_measurement(
    w: &PeerWindow,
    pose: usize,
    xy: &Vector2<f64>,
    p_lin: &Vector3<f64>,
    p_cur: &Vector3<f64>,
    pixel_sigma: f64,
) -> Option<PeerMeasurement> {
    let pose = w.poses.get(pose)?;
    let lin = project_normalized(pose, p_lin)?;
    let cur = project_normalized(pose, p_cur)?;
    let (uv, dz_dn, dz_dintr) = w.camera.distort_with_jacobians(&lin.xy);
    // A wrong link can put our landmark nearly in the peer camera's plane
    // (a whitened residual of 1.3e10 passed its gate at d = 1.3 over 2 rows).
    if !w.camera.near_image(&uv) || !w.camera.near_image(&w.camera.distort(&cur.xy)) {
        return None;
    }
    let white = dz_dn / pixel_sigma;
    Some(PeerMeasurement {
        res: white * (xy - cur.xy),
        h_pose: white * lin.h_pose,
        h_feature: white * lin.h_feature,
        h_intrinsics: dz_dintr / pixel_sigma,
    })
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

    /// A window of one pose at the origin, looking along +z, with `camera`
    /// and its intrinsics in the covariance (6 + 8 columns).
    fn one_pose_window(camera: CameraModel) -> PeerWindow {
        PeerWindow {
            peer: 1,
            key: 0,
            poses: vec![PeerPose {
                t_s: 0.0,
                rot: Matrix3::identity(),
                pos: Vector3::zeros(),
            }],
            cov: Arc::new(DMatrix::identity(14, 14)),
            camera,
            pixel_sigma_px: 1.0,
            landmarks: Vec::new(),
            frame: None,
        }
    }

    /// A peer whose intrinsics estimate is off by `δθ` reports coordinates that
    /// the measurement's intrinsics Jacobian predicts: `res ≈ H_θ δθ`.
    #[test]
    fn the_intrinsics_jacobian_predicts_the_coordinates_a_miscalibrated_peer_reports() {
        let truth = CameraModel::euroc_cam0();
        let p_f = Vector3::new(1.2, -0.7, 3.0);
        let n_true = Vector2::new(p_f.x / p_f.z, p_f.y / p_f.z);
        let uv = truth.distort(&n_true);
        let delta = [0.8, -0.6, 0.5, 0.9, 0.004, -0.003, 0.0005, -0.0004];
        let mut estimate = truth.clone();
        for k in 0..4 {
            estimate.intrinsics[k] -= delta[k] * 1e-3;
            estimate.distortion[k] -= delta[4 + k] * 1e-3;
        }
        let xy = estimate.undistort(&uv).unwrap();
        let w = one_pose_window(estimate);
        assert_eq!(w.intrinsics_item(), Some(1));
        let m = peer_measurement(&w, 0, &xy, &p_f, &p_f, 1.0).unwrap();
        let d = nalgebra::SVector::<f64, 8>::from_column_slice(&delta) * 1e-3;
        let predicted = m.h_intrinsics * d;
        assert!(
            (m.res - predicted).norm() < 1e-3 * predicted.norm(),
            "residual {:?}, predicted {:?}",
            m.res,
            predicted
        );
    }

    /// The Jacobians are functions of the estimates only: a measurement that
    /// noise moved gets the same ones (at the measured point they would weigh
    /// inward and outward errors differently, and bias the update).
    #[test]
    fn the_jacobians_do_not_depend_on_the_measured_point() {
        let camera = CameraModel::euroc_cam0();
        assert!(camera.distortion.norm() > 0.1);
        let w = one_pose_window(camera);
        let p_f = Vector3::new(1.2, -0.7, 3.0);
        let xy = Vector2::new(p_f.x / p_f.z, p_f.y / p_f.z);
        let at = |xy: Vector2<f64>| peer_measurement(&w, 0, &xy, &p_f, &p_f, 1.0).unwrap();
        let (exact, moved) = (at(xy), at(xy + Vector2::new(0.004, -0.003)));
        assert_eq!(exact.h_pose, moved.h_pose);
        assert_eq!(exact.h_feature, moved.h_feature);
        assert_eq!(exact.h_intrinsics, moved.h_intrinsics);
        assert!(exact.res.norm() < 1e-12 && moved.res.norm() > 1.0);
    }

    /// A point predicted far outside the peer's image is not measured: the
    /// distortion there is outside its fit, and its Jacobian unbounded.
    #[test]
    fn a_point_predicted_far_outside_the_image_is_not_measured() {
        let w = one_pose_window(CameraModel::euroc_cam0());
        let xy = Vector2::new(0.1, -0.05);
        let at = |p: Vector3<f64>| peer_measurement(&w, 0, &xy, &p, &p, 1.0);
        // In view, and just outside the image's right edge (x/z = 1.2 is
        // 25 px beyond it): measured.
        assert!(at(Vector3::new(0.3, -0.15, 3.0)).is_some());
        assert!(at(Vector3::new(3.6, 0.0, 3.0)).is_some());
        // Nearly in the camera's plane: predicted at x/z = 300.
        assert!(at(Vector3::new(3.0, 0.0, 0.01)).is_none());
        // Far beyond the right edge (x/z = 2, 580 px beyond it).
        assert!(at(Vector3::new(6.0, 0.0, 3.0)).is_none());
    }

    fn sample_snapshot() -> StateSnapshot {
        match common::messages::samples::snapshot(40, 11, 3, true).body {
            common::messages::Body::Snapshot(s) => s,
            other => panic!("not a snapshot: {other:?}"),
        }
    }

    /// A window is a CI participant only if its covariance is one: positive
    /// variances are not enough (two poses claiming to be perfectly
    /// anti-correlated beyond what their variances allow).
    #[test]
    fn a_window_whose_covariance_is_not_positive_definite_is_refused() {
        let snap = sample_snapshot();
        let w = PeerWindow::from_snapshot(2, 7, &snap).expect("a valid window");
        assert_eq!(w.poses.len(), 11);
        assert_eq!(w.landmarks.len(), 3);
        // The sender's pixel noise comes with its window.
        let mut noisy = snap.clone();
        noisy.pixel_sigma_px = 2.5;
        let n = PeerWindow::from_snapshot(2, 7, &noisy).expect("a valid window");
        assert_eq!((w.pixel_sigma_px, n.pixel_sigma_px), (1.0, 2.5));
        // At least what was sent: each variance is raised, none lowered.
        let sent = snap.covariance.to_dmatrix();
        assert!((0..sent.nrows()).all(|i| w.cov[(i, i)] > sent[(i, i)]));

        let mut bad = snap.clone();
        let mut p = bad.covariance.to_dmatrix();
        let (a, b) = (3, 9); // the first two positions' x
        p[(a, b)] = -2.0 * (p[(a, a)] * p[(b, b)]).sqrt();
        p[(b, a)] = p[(a, b)];
        bad.covariance = common::messages::PackedCovariance::from_dmatrix(&p).unwrap();
        assert!(PeerWindow::from_snapshot(2, 7, &bad).is_none());

        let mut zero_variance = snap.clone();
        let k = common::messages::PackedCovariance::packed_index(4, 4);
        zero_variance.covariance.lower[k] = 0.0;
        assert!(PeerWindow::from_snapshot(2, 7, &zero_variance).is_none());

        let mut bad_landmark = snap;
        bad_landmark.landmarks[1].cov_upper[1] = 1.0; // xy covariance ≫ √(xx yy)
        let w = PeerWindow::from_snapshot(2, 7, &bad_landmark).expect("the window stays");
        assert_eq!(w.landmarks.len(), 2, "only the broken landmark is dropped");
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
