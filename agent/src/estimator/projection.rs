//! The camera measurement function `z = h_d(h_p(h_t(x)))` (thesis Section 2.3.3,
//! App. A) and its Jacobians w.r.t. the clone, the feature and the calibration.
//!
//! `p_FinI = R_ItoGᵀ (p_FinG − p_IinG)`, `p_FinC = R_CtoIᵀ (p_FinI − p_CinI)`,
//! `n = (x/z, y/z)`, `z = distort(n)`. With right perturbations
//! `R_ItoG = R̂ Exp(δθ)` and `R_CtoI = R̂ Exp(δφ)`:
//! `∂p_FinI/∂δθ = [p_FinI]×`, `∂p_FinC/∂δφ = [p_FinC]×`.

use common::calibration::CameraCalibration;
use common::so3::skew;
use nalgebra::{Matrix2x3, Matrix3, SMatrix, Vector2, Vector3};

/// Prediction and Jacobians of one observation of one feature from one clone.
#[derive(Clone, Copy, Debug)]
pub struct Projection {
    /// Predicted raw pixel.
    pub uv: Vector2<f64>,
    /// `∂z/∂[δθ, δp]` of the clone (2x6).
    pub h_clone: SMatrix<f64, 2, 6>,
    /// `∂z/∂p_FinG` (2x3).
    pub h_feature: Matrix2x3<f64>,
    /// `∂z/∂[δφ_CtoI, δp_CinI]` (2x6).
    pub h_extrinsic: SMatrix<f64, 2, 6>,
    /// `∂z/∂[fx, fy, cx, cy, d0..d3]` (2x8).
    pub h_intrinsics: SMatrix<f64, 2, 8>,
}

/// Where a feature is in the camera, or `None` if it is not in front of it.
pub fn point_in_camera(
    rot_i_to_g: &Matrix3<f64>,
    p_i_in_g: &Vector3<f64>,
    p_f_in_g: &Vector3<f64>,
    calib: &CameraCalibration,
) -> Vector3<f64> {
    let p_f_in_i = rot_i_to_g.transpose() * (p_f_in_g - p_i_in_g);
    calib.rot_c_to_i.transpose() * (p_f_in_i - calib.p_c_in_i)
}

/// Predicted pixel of `p_FinG` seen from the clone `(R_ItoG, p_IinG)`; `None` when
/// the point is not in front of the camera, or falls far outside the image
/// (`CameraModel::near_image`: no update linearizes there).
pub fn predict(
    rot_i_to_g: &Matrix3<f64>,
    p_i_in_g: &Vector3<f64>,
    p_f_in_g: &Vector3<f64>,
    calib: &CameraCalibration,
) -> Option<Vector2<f64>> {
    let p_c = point_in_camera(rot_i_to_g, p_i_in_g, p_f_in_g, calib);
    if p_c.z < 1e-3 {
        return None;
    }
    let uv = calib
        .camera
        .distort(&Vector2::new(p_c.x / p_c.z, p_c.y / p_c.z));
    calib.camera.near_image(&uv).then_some(uv)
}

/// Prediction and Jacobians, evaluated at the given linearization point (the
/// caller passes first estimates for FEJ). `None` when the point is behind, or
/// falls far outside the image (`CameraModel::near_image`).
pub fn project(
    rot_i_to_g: &Matrix3<f64>,
    p_i_in_g: &Vector3<f64>,
    p_f_in_g: &Vector3<f64>,
    calib: &CameraCalibration,
) -> Option<Projection> {
    let p_f_in_i = rot_i_to_g.transpose() * (p_f_in_g - p_i_in_g);
    let r_c_to_i_t = calib.rot_c_to_i.transpose();
    let p_c = r_c_to_i_t * (p_f_in_i - calib.p_c_in_i);
    if p_c.z < 1e-3 {
        return None;
    }
    let n = Vector2::new(p_c.x / p_c.z, p_c.y / p_c.z);
    let (uv, dz_dn, dz_dintr) = calib.camera.distort_with_jacobians(&n);
    if !calib.camera.near_image(&uv) {
        return None;
    }
    let iz = 1.0 / p_c.z;
    let dn_dpc = Matrix2x3::new(iz, 0.0, -p_c.x * iz * iz, 0.0, iz, -p_c.y * iz * iz);
    let dz_dpc = dz_dn * dn_dpc;
    // p_FinC w.r.t. p_FinI, clone and feature.
    let dpc_dpi = r_c_to_i_t;
    let dpi_dtheta = skew(&p_f_in_i);
    let dpi_dpos = -rot_i_to_g.transpose();
    let mut h_clone = SMatrix::<f64, 2, 6>::zeros();
    h_clone
        .fixed_view_mut::<2, 3>(0, 0)
        .copy_from(&(dz_dpc * dpc_dpi * dpi_dtheta));
    h_clone
        .fixed_view_mut::<2, 3>(0, 3)
        .copy_from(&(dz_dpc * dpc_dpi * dpi_dpos));
    let h_feature = dz_dpc * dpc_dpi * rot_i_to_g.transpose();
    let mut h_extrinsic = SMatrix::<f64, 2, 6>::zeros();
    h_extrinsic
        .fixed_view_mut::<2, 3>(0, 0)
        .copy_from(&(dz_dpc * skew(&p_c)));
    h_extrinsic
        .fixed_view_mut::<2, 3>(0, 3)
        .copy_from(&(-dz_dpc * r_c_to_i_t));
    Some(Projection {
        uv,
        h_clone,
        h_feature,
        h_extrinsic,
        h_intrinsics: dz_dintr,
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use common::so3::exp_so3;

    fn setup() -> (Matrix3<f64>, Vector3<f64>, Vector3<f64>, CameraCalibration) {
        let rot = exp_so3(&Vector3::new(0.2, -0.1, 0.4));
        let pos = Vector3::new(1.0, -2.0, 0.5);
        let mut calib = CameraCalibration::euroc_cam0();
        calib.rot_c_to_i = exp_so3(&Vector3::new(0.01, 0.02, -0.03)) * calib.rot_c_to_i;
        // A point 4 m in front of the camera, off-axis.
        let p_c = Vector3::new(0.8, -0.5, 4.0);
        let p_i = calib.rot_c_to_i * p_c + calib.p_c_in_i;
        let p_f = rot * p_i + pos;
        (rot, pos, p_f, calib)
    }

    /// No prediction or linearization far outside the image, where the
    /// distortion polynomial was never fitted.
    #[test]
    fn a_point_far_outside_the_image_is_not_predicted() {
        let (rot, pos, _, calib) = setup();
        let at = |p_c: Vector3<f64>| {
            let p_f = rot * (calib.rot_c_to_i * p_c + calib.p_c_in_i) + pos;
            (
                predict(&rot, &pos, &p_f, &calib).is_some(),
                project(&rot, &pos, &p_f, &calib).is_some(),
            )
        };
        assert_eq!(at(Vector3::new(0.8, -0.5, 4.0)), (true, true));
        // Nearly in the camera's plane: x/z = 300.
        assert_eq!(at(Vector3::new(3.0, 0.0, 0.01)), (false, false));
    }

    #[test]
    fn jacobians_match_numerical_differentiation() {
        let (rot, pos, p_f, calib) = setup();
        let proj = project(&rot, &pos, &p_f, &calib).unwrap();
        let f = |r: &Matrix3<f64>, p: &Vector3<f64>, pf: &Vector3<f64>, c: &CameraCalibration| {
            predict(r, p, pf, c).unwrap()
        };
        assert!((proj.uv - f(&rot, &pos, &p_f, &calib)).norm() < 1e-12);
        let h = 1e-6;
        for i in 0..3 {
            let mut e = Vector3::zeros();
            e[i] = h;
            let num = (f(&(rot * exp_so3(&e)), &pos, &p_f, &calib)
                - f(&(rot * exp_so3(&-e)), &pos, &p_f, &calib))
                / (2.0 * h);
            assert!((proj.h_clone.column(i) - num).norm() < 1e-4, "dθ {i}");
            let num =
                (f(&rot, &(pos + e), &p_f, &calib) - f(&rot, &(pos - e), &p_f, &calib)) / (2.0 * h);
            assert!((proj.h_clone.column(3 + i) - num).norm() < 1e-4, "dp {i}");
            let num =
                (f(&rot, &pos, &(p_f + e), &calib) - f(&rot, &pos, &(p_f - e), &calib)) / (2.0 * h);
            assert!((proj.h_feature.column(i) - num).norm() < 1e-4, "dpf {i}");
            let (mut cp, mut cm) = (calib.clone(), calib.clone());
            cp.rot_c_to_i *= exp_so3(&e);
            cm.rot_c_to_i *= exp_so3(&-e);
            let num = (f(&rot, &pos, &p_f, &cp) - f(&rot, &pos, &p_f, &cm)) / (2.0 * h);
            assert!((proj.h_extrinsic.column(i) - num).norm() < 1e-4, "dφ {i}");
            let (mut cp, mut cm) = (calib.clone(), calib.clone());
            cp.p_c_in_i += e;
            cm.p_c_in_i -= e;
            let num = (f(&rot, &pos, &p_f, &cp) - f(&rot, &pos, &p_f, &cm)) / (2.0 * h);
            assert!(
                (proj.h_extrinsic.column(3 + i) - num).norm() < 1e-4,
                "dpc {i}"
            );
        }
        for i in 0..8 {
            let (mut cp, mut cm) = (calib.clone(), calib.clone());
            if i < 4 {
                cp.camera.intrinsics[i] += h;
                cm.camera.intrinsics[i] -= h;
            } else {
                cp.camera.distortion[i - 4] += h;
                cm.camera.distortion[i - 4] -= h;
            }
            let num = (f(&rot, &pos, &p_f, &cp) - f(&rot, &pos, &p_f, &cm)) / (2.0 * h);
            assert!(
                (proj.h_intrinsics.column(i) - num).norm() < 1e-4,
                "intrinsic {i}"
            );
        }
    }

    #[test]
    fn a_point_behind_the_camera_has_no_projection() {
        let (rot, pos, _, calib) = setup();
        let behind = rot * (calib.rot_c_to_i * Vector3::new(0.0, 0.0, -2.0) + calib.p_c_in_i) + pos;
        assert!(project(&rot, &pos, &behind, &calib).is_none());
    }
}
