//! What a peer needs of this robot's state for a CI-EKF update (thesis Section
//! 5.3): the camera poses of the sliding window with their joint covariance, and
//! the SLAM features' global positions with their marginals.
//!
//! Camera poses rather than IMU clones: `R_CtoG = R_ItoG R_CtoI` and
//! `p_CinG = p_IinG + R_ItoG p_CinI` fold the extrinsic calibration (and its
//! uncertainty) in, so a peer needs no calibration state of ours.
//!
//! Error conventions are the state's (right/local rotation error): with
//! `R_ItoG = R̂ Exp(δθ)`, `R_CtoI = R̂_c Exp(δφ)`, the camera error is
//! `δθ_C = R̂_cᵀ δθ + δφ` and `δp_C = δp − R̂ ⌊p̂_c⌋ δθ + R̂ δp_c`.

use super::frame_alignment::CameraEstimate;
use super::slam_feature::global_position;
use super::state::{ClonePose, State, Var};
use common::calibration::CameraCalibration;
use common::so3::skew;
use nalgebra::{DMatrix, Matrix3, Matrix6, Vector3};

/// One camera pose of the window.
#[derive(Clone, Debug, PartialEq)]
pub struct CameraPoseEstimate {
    /// The clone's key (the estimator's image sequence number).
    pub key: u64,
    /// Camera time of the image, s.
    pub t_cam: f64,
    /// `R_CtoG`.
    pub rot: Matrix3<f64>,
    /// `p_CinG`, m.
    pub pos: Vector3<f64>,
}

/// A SLAM feature's global position and marginal covariance.
#[derive(Clone, Debug, PartialEq)]
pub struct LandmarkEstimate {
    /// Track id.
    pub id: u64,
    /// `p_FinG`, m.
    pub pos: Vector3<f64>,
    /// Its 3x3 covariance, m².
    pub cov: Matrix3<f64>,
}

/// The sliding window as peers see it.
#[derive(Clone, Debug)]
pub struct CameraWindow {
    /// State time (IMU clock), s.
    pub t: f64,
    /// Camera poses, oldest first.
    pub poses: Vec<CameraPoseEstimate>,
    /// Joint covariance of the poses, per pose `[δθ_C, δp_C]` (`6n x 6n`), then,
    /// when the intrinsics are estimated, of `[fx, fy, cx, cy, d0..d3]`
    /// (`6n + 8`).
    pub cov: DMatrix<f64>,
    /// SLAM features.
    pub landmarks: Vec<LandmarkEstimate>,
    /// The current calibration estimate (for raw-pixel users).
    pub calib: CameraCalibration,
}

/// The camera window of `state`, with landmarks when `with_landmarks`.
pub fn camera_window(state: &State, with_landmarks: bool) -> CameraWindow {
    let c = &state.calib;
    let has_ext = state.has(Var::Extrinsic);
    let has_intr = state.has(Var::Intrinsics);
    // Variables involved: every clone, then the extrinsic and the intrinsics
    // (when estimated; the intrinsics pass through, appended after the poses).
    let mut vars: Vec<Var> = state.clones.keys().map(|k| Var::Clone(*k)).collect();
    if has_ext {
        vars.push(Var::Extrinsic);
    }
    if has_intr {
        vars.push(Var::Intrinsics);
    }
    let sub = gather(state, &vars);
    let n = state.clones.len();
    let m = sub.nrows();
    let rows = 6 * n + if has_intr { 8 } else { 0 };
    let mut jac = DMatrix::zeros(rows, m);
    if has_intr {
        jac.view_mut((6 * n, m - 8), (8, 8)).fill_with_identity();
    }
    let mut poses = Vec::with_capacity(n);
    for (i, (key, clone)) in state.clones.iter().enumerate() {
        fill_camera_jacobian(&mut jac, 6 * i, 6 * i, has_ext.then_some(6 * n), c, clone);
        poses.push(CameraPoseEstimate {
            key: *key,
            t_cam: clone.t_cam,
            rot: clone.rot * c.rot_c_to_i,
            pos: clone.pos + clone.rot * c.p_c_in_i,
        });
    }
    let mut cov = &jac * sub * jac.transpose();
    cov = (&cov + cov.transpose()) * 0.5;
    let landmarks = if with_landmarks {
        state
            .features
            .iter()
            .filter_map(|(id, f)| {
                let (pos, jac) = global_position(state, *id, f, false)?;
                Some(LandmarkEstimate {
                    id: *id,
                    pos,
                    cov: marginal(state, &jac),
                })
            })
            .collect()
    } else {
        Vec::new()
    };
    CameraWindow {
        t: state.t,
        poses,
        cov,
        landmarks,
        calib: c.clone(),
    }
}

/// The Jacobian of clone `key`'s camera pose error `[δθ_C, δp_C]` w.r.t.
/// the state variables it depends on: the clone, and the extrinsic when
/// estimated (each 6 x 6). `None` without that clone.
pub fn camera_pose_jacobian(state: &State, key: u64) -> Option<Vec<(Var, DMatrix<f64>)>> {
    let clone = state.clones.get(&key)?;
    let has_ext = state.has(Var::Extrinsic);
    let mut jac = DMatrix::zeros(6, if has_ext { 12 } else { 6 });
    fill_camera_jacobian(&mut jac, 0, 0, has_ext.then_some(6), &state.calib, clone);
    let mut out = vec![(Var::Clone(key), jac.columns(0, 6).into_owned())];
    if has_ext {
        out.push((Var::Extrinsic, jac.columns(6, 6).into_owned()));
    }
    Some(out)
}

/// Rows `row..row + 6` of the map from the clone's error (columns `col..col +
/// 6`) and the extrinsic's (at `ext`, when estimated) to the camera pose's.
fn fill_camera_jacobian(
    jac: &mut DMatrix<f64>,
    row: usize,
    col: usize,
    ext: Option<usize>,
    c: &CameraCalibration,
    clone: &ClonePose,
) {
    jac.view_mut((row, col), (3, 3))
        .copy_from(&c.rot_c_to_i.transpose());
    jac.view_mut((row + 3, col), (3, 3))
        .copy_from(&(-clone.rot * skew(&c.p_c_in_i)));
    jac.view_mut((row + 3, col + 3), (3, 3))
        .fill_with_identity();
    if let Some(e) = ext {
        jac.view_mut((row, e), (3, 3)).fill_with_identity();
        jac.view_mut((row + 3, e + 3), (3, 3)).copy_from(&clone.rot);
    }
}

/// The camera pose of clone `key` with the covariance of its `[δθ_C, δp_C]`
/// (the extrinsic's uncertainty folded in), `None` without that clone.
pub fn camera_estimate(state: &State, key: u64) -> Option<CameraEstimate> {
    let clone = state.clones.get(&key)?;
    let c = &state.calib;
    let has_ext = state.has(Var::Extrinsic);
    let mut vars = vec![Var::Clone(key)];
    if has_ext {
        vars.push(Var::Extrinsic);
    }
    let sub = gather(state, &vars);
    let mut jac = DMatrix::zeros(6, sub.nrows());
    fill_camera_jacobian(&mut jac, 0, 0, has_ext.then_some(6), c, clone);
    let cov = &jac * sub * jac.transpose();
    Some(CameraEstimate {
        rot: clone.rot * c.rot_c_to_i,
        pos: clone.pos + clone.rot * c.p_c_in_i,
        cov: Matrix6::from_fn(|r, k| 0.5 * (cov[(r, k)] + cov[(k, r)])),
    })
}

/// The joint covariance of `vars`, in that order.
fn gather(state: &State, vars: &[Var]) -> DMatrix<f64> {
    let sizes: Vec<usize> = vars.iter().map(|v| v.size()).collect();
    let m: usize = sizes.iter().sum();
    let mut out = DMatrix::zeros(m, m);
    let p = state.cov();
    let mut ra = 0;
    for (a, sa) in vars.iter().zip(&sizes) {
        let mut rb = 0;
        for (b, sb) in vars.iter().zip(&sizes) {
            if let (Some(oa), Some(ob)) = (state.offset(*a), state.offset(*b)) {
                out.view_mut((ra, rb), (*sa, *sb))
                    .copy_from(&p.view((oa, ob), (*sa, *sb)));
            }
            rb += sb;
        }
        ra += sa;
    }
    out
}

/// `J P Jᵀ` for a 3-row Jacobian given by blocks.
fn marginal(state: &State, jac: &[(Var, DMatrix<f64>)]) -> Matrix3<f64> {
    let p = state.cov();
    let mut out = Matrix3::zeros();
    for (a, ja) in jac {
        let Some(oa) = state.offset(*a) else { continue };
        for (b, jb) in jac {
            let Some(ob) = state.offset(*b) else { continue };
            let block = p.view((oa, ob), (a.size(), b.size()));
            let prod = ja * block * jb.transpose();
            for r in 0..3 {
                for c in 0..3 {
                    out[(r, c)] += prod[(r, c)];
                }
            }
        }
    }
    (out + out.transpose()) * 0.5
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::estimator::state::{ClonePose, ImuState, SlamFeature};
    use common::so3::{exp_so3, log_so3};
    use nalgebra::DVector;
    use rand::{Rng, SeedableRng};
    use rand_chacha::ChaCha8Rng;

    /// A state with three clones, extrinsics and one anchored feature, with a
    /// random dense covariance.
    fn state() -> State {
        let mut rng = ChaCha8Rng::seed_from_u64(3);
        let calib = CameraCalibration::euroc_cam0();
        let ext = DMatrix::identity(6, 6) * 1e-4;
        let mut s = State::new(
            0.0,
            ImuState::default(),
            DMatrix::identity(15, 15) * 1e-3,
            calib,
            &[
                (Var::Extrinsic, ext),
                (Var::Intrinsics, DMatrix::identity(8, 8) * 1e-2),
            ],
        );
        for k in 0..3u64 {
            let rot = exp_so3(&Vector3::new(0.1 * k as f64, -0.2, 0.3));
            let pos = Vector3::new(k as f64, 0.5, -0.2);
            s.augment(Var::Clone(k), &[], &(DMatrix::identity(6, 6) * 1e-2))
                .ok();
            s.clones.insert(
                k,
                ClonePose {
                    t: k as f64,
                    t_cam: k as f64,
                    rot,
                    pos,
                    rot_fej: rot,
                    pos_fej: pos,
                },
            );
        }
        s.augment(Var::Feature(7), &[], &(DMatrix::identity(3, 3) * 1e-2))
            .ok();
        let p = Vector3::new(0.3, -0.1, 4.0);
        s.features.insert(
            7,
            SlamFeature {
                pos: p,
                pos_fej: p,
                anchor: Some(1),
                inverse_depth: false,
            },
        );
        let n = s.dim();
        let a = DMatrix::from_fn(n, n, |_, _| rng.random_range(-0.05..0.05));
        s.set_cov(&a * a.transpose() + DMatrix::identity(n, n) * 1e-3)
            .ok();
        s
    }

    /// Camera-pose errors of a perturbed state relative to the nominal one.
    fn camera_errors(nominal: &CameraWindow, s: &State) -> DVector<f64> {
        let w = camera_window(s, false);
        let n = w.poses.len();
        let mut e = DVector::zeros(w.cov.nrows());
        for (i, (a, b)) in nominal.poses.iter().zip(&w.poses).enumerate() {
            let dth = log_so3(&(a.rot.transpose() * b.rot));
            e.fixed_rows_mut::<3>(6 * i).copy_from(&dth);
            e.fixed_rows_mut::<3>(6 * i + 3).copy_from(&(b.pos - a.pos));
        }
        if e.len() == 6 * n + 8 {
            let (a, b) = (&nominal.calib.camera, &w.calib.camera);
            for k in 0..4 {
                e[6 * n + k] = b.intrinsics[k] - a.intrinsics[k];
                e[6 * n + 4 + k] = b.distortion[k] - a.distortion[k];
            }
        }
        e
    }

    #[test]
    fn covariance_is_the_first_order_propagation_of_the_state_covariance() {
        // Numerical Jacobian of the camera poses w.r.t. every state variable, then
        // J P Jᵀ compared with what `camera_window` reports.
        let s = state();
        let nominal = camera_window(&s, false);
        let n = s.dim();
        let eps = 1e-6;
        let mut jac = DMatrix::zeros(nominal.cov.nrows(), n);
        for col in 0..n {
            let mut dx = DVector::zeros(n);
            dx[col] = eps;
            let mut p = s.clone();
            p.apply_correction(&dx);
            let e = camera_errors(&nominal, &p);
            jac.column_mut(col).copy_from(&(e / eps));
        }
        let expected = &jac * s.cov() * jac.transpose();
        let err = (&expected - &nominal.cov).abs().max();
        assert!(err < 1e-6 * expected.abs().max(), "max error {err}");
    }

    #[test]
    fn one_camera_estimate_is_its_block_of_the_window() {
        let s = state();
        let w = camera_window(&s, false);
        for (i, pose) in w.poses.iter().enumerate() {
            let one = camera_estimate(&s, pose.key).expect("a clone");
            assert_eq!(one.rot, pose.rot);
            assert_eq!(one.pos, pose.pos);
            let block = w.cov.view((6 * i, 6 * i), (6, 6));
            assert!((one.cov - block).abs().max() < 1e-12 * block.abs().max());
        }
        assert!(camera_estimate(&s, 999).is_none());
    }

    #[test]
    fn landmark_marginal_matches_numerical_propagation() {
        let s = state();
        let w = camera_window(&s, true);
        let lm = &w.landmarks[0];
        let n = s.dim();
        let eps = 1e-6;
        let mut jac = DMatrix::zeros(3, n);
        for col in 0..n {
            let mut dx = DVector::zeros(n);
            dx[col] = eps;
            let mut p = s.clone();
            p.apply_correction(&dx);
            let q = camera_window(&p, true).landmarks[0].pos;
            jac.column_mut(col).copy_from(&((q - lm.pos) / eps));
        }
        let expected = &jac * s.cov() * jac.transpose();
        let scale = expected.abs().max();
        for r in 0..3 {
            for c in 0..3 {
                let err = (expected[(r, c)] - lm.cov[(r, c)]).abs();
                assert!(err < 1e-5 * scale, "({r},{c}): error {err}, scale {scale}");
            }
        }
    }
}
