//! A small synthetic scene for the cooperative updaters' tests: our window of
//! clones and a peer's window looking at the same landmarks, with exact
//! measurements (the means are the truth).

use super::chi2::Chi2Table;
use super::feature_db::{FeatureDb, FeatureMeasurement};
use super::options::EstimatorOptions;
use super::peer_window::{project_normalized, PeerPose, PeerWindow};
use super::projection::predict;
use super::state::{ClonePose, ImuState, State, Var};
use super::triangulation::TriangulationOptions;
use super::updater_common::{self, CommonOutcome, CommonTrack, PeerObservation};
use common::calibration::CameraCalibration;
use nalgebra::{DMatrix, Matrix3, Vector2, Vector3};

/// Our state and features, the peer's window and the landmarks.
pub struct Scene {
    /// Our state: clones 1..=n at the true poses.
    pub state: State,
    /// Our measurements: track id `l` sees landmark `l` from every clone.
    pub db: FeatureDb,
    /// The landmarks, `p_FinG`.
    pub landmarks: Vec<Vector3<f64>>,
    /// The peer's window (participant 0).
    pub peer: PeerWindow,
}

/// A camera looking along world +y (x right, y down).
fn looking_forward() -> Matrix3<f64> {
    Matrix3::from_columns(&[
        Vector3::new(1.0, 0.0, 0.0),
        Vector3::new(0.0, 0.0, -1.0),
        Vector3::new(0.0, 1.0, 0.0),
    ])
}

/// `n` clones 0.2 m apart along x, landmarks 4-7 m ahead on a grid, a peer
/// window of `n` cameras 1 m to the left and 0.5 m higher. Clone covariance
/// `clone_var` per axis, peer pose covariance `peer_var`.
pub fn scene(n: usize, n_landmarks: usize, clone_var: f64, peer_var: f64) -> Scene {
    let calib = CameraCalibration::euroc_cam0();
    let r_c = looking_forward();
    let r_i = r_c * calib.rot_c_to_i.transpose();
    let cam_pos = |k: usize| Vector3::new(0.2 * k as f64, 0.0, 0.0);
    let imu_pos = |k: usize| cam_pos(k) - r_i * calib.p_c_in_i;
    let imu = ImuState {
        rot: r_i,
        pos: imu_pos(n),
        ..ImuState::default()
    };
    let mut state = State::new(
        0.0,
        imu,
        DMatrix::identity(15, 15) * 1e-3,
        calib.clone(),
        &[(Var::Extrinsic, DMatrix::identity(6, 6) * 1e-6)],
    );
    for k in 1..=n {
        let key = k as u64;
        state
            .augment(Var::Clone(key), &[], &(DMatrix::identity(6, 6) * clone_var))
            .ok();
        let p = imu_pos(k);
        state.clones.insert(
            key,
            ClonePose {
                t: k as f64 * 0.1,
                t_cam: k as f64 * 0.1,
                rot: r_i,
                pos: p,
                rot_fej: r_i,
                pos_fej: p,
            },
        );
    }
    let landmarks: Vec<Vector3<f64>> = (0..n_landmarks)
        .map(|l| {
            let a = l as f64;
            Vector3::new(
                -1.5 + (a * 0.73) % 4.0,
                4.0 + (a * 1.31) % 3.0,
                -1.0 + (a * 0.57) % 2.0,
            )
        })
        .collect();
    let mut db = FeatureDb::new();
    for (l, p_f) in landmarks.iter().enumerate() {
        for k in 1..=n {
            let c = &state.clones[&(k as u64)];
            let Some(uv) = predict(&c.rot, &c.pos, p_f, &calib) else {
                continue;
            };
            let Ok(uvn) = calib.camera.undistort(&uv) else {
                continue;
            };
            let m = FeatureMeasurement {
                clone_key: k as u64,
                t: c.t_cam,
                uv,
                uvn,
            };
            db.insert(l as u64, m).ok();
        }
    }
    let poses: Vec<PeerPose> = (0..n)
        .map(|k| PeerPose {
            t_s: k as f64 * 0.1,
            rot: r_c,
            pos: Vector3::new(-1.0 + 0.15 * k as f64, 0.0, 0.5),
        })
        .collect();
    let peer = PeerWindow {
        peer: 1,
        key: 1,
        cov: std::sync::Arc::new(DMatrix::identity(6 * n, 6 * n) * peer_var),
        poses,
        camera: calib.camera.clone(),
        pixel_sigma_px: 1.0,
        landmarks: Vec::new(),
        frame: None,
    };
    Scene {
        state,
        db,
        landmarks,
        peer,
    }
}

impl Scene {
    /// The common-feature update of `tracks` against the peer's window, with
    /// `opts`, the 95 % gate and the default triangulation.
    pub fn common_update(
        &mut self,
        tracks: &[CommonTrack],
        opts: &EstimatorOptions,
    ) -> CommonOutcome {
        updater_common::update(
            &mut self.state,
            &self.db,
            tracks,
            std::slice::from_ref(&self.peer),
            opts,
            &Chi2Table::new(0.95, 500),
            &TriangulationOptions::default(),
        )
    }

    /// The peer's exact observations of landmark `l` from every pose.
    pub fn peer_obs(&self, l: usize) -> Vec<PeerObservation> {
        self.peer
            .poses
            .iter()
            .enumerate()
            .filter_map(|(j, pose)| {
                let p = project_normalized(pose, &self.landmarks[l])?;
                Some(PeerObservation {
                    participant: 0,
                    pose: j,
                    xy: Vector2::new(p.xy.x, p.xy.y),
                })
            })
            .collect()
    }
}

impl Scene {
    /// Puts landmarks `ids` into our state as global SLAM features at the truth,
    /// uncorrelated, with covariance `var` per axis.
    pub fn add_slam_features(&mut self, ids: &[usize], var: f64) {
        for &l in ids {
            let id = l as u64;
            self.state
                .augment(Var::Feature(id), &[], &(DMatrix::identity(3, 3) * var))
                .ok();
            let p = self.landmarks[l];
            self.state.features.insert(
                id,
                super::state::SlamFeature {
                    pos: p,
                    pos_fej: p,
                    anchor: None,
                    inverse_depth: false,
                },
            );
        }
    }
}
