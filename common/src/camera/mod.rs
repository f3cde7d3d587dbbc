//! Pinhole camera with radial-tangential or equidistant (fisheye) distortion,
//! with the analytic Jacobians the filter needs.
//!
//! The measurement chain (thesis Appendix A, as OpenVINS) is
//! `p_FinC → n = [x/z, y/z] (normalized, undistorted) → n_d (distorted) → uv`,
//! with `u = fx · x_d + cx`, `v = fy · y_d + cy`. The camera frame is `C` of
//! [`crate::conventions`] (z forward, x right, y down); pixel coordinates are
//! continuous with `u` to the right and `v` down, and `(0, 0)` is the top-left
//! corner of the image.
//!
//! * [`Distortion::RadTan`]: `d = [k1, k2, p1, p2]`,
//!   `x_d = x (1 + k1 r² + k2 r⁴) + 2 p1 x y + p2 (r² + 2x²)`,
//!   `y_d = y (1 + k1 r² + k2 r⁴) + p1 (r² + 2y²) + 2 p2 x y`.
//! * [`Distortion::Equidistant`] (Kannala-Brandt as OpenCV fisheye):
//!   `d = [k1, k2, k3, k4]`, `θ = atan(r)`,
//!   `θ_d = θ (1 + k1 θ² + k2 θ⁴ + k3 θ⁶ + k4 θ⁸)`, `n_d = (θ_d / r) n`.
//!
//! Intrinsic Jacobians use the order `[fx, fy, cx, cy, d0, d1, d2, d3]`
//! (additive error, as every vector of [`crate::conventions`]).

mod equidistant;
mod radtan;

use nalgebra::{Matrix2, Matrix2x3, Matrix2x4, SMatrix, Vector2, Vector3, Vector4};
use serde::{Deserialize, Serialize};

/// Points closer than this to the camera plane (`z`, metres) do not project.
pub const MIN_DEPTH_M: f64 = 1e-6;

/// How far outside the image, as a fraction of its size, a predicted point
/// may fall and still be linearized ([`CameraModel::near_image`]): a state's
/// uncertainty moves predictions near the border a little outside it.
pub const PREDICTION_MARGIN: f64 = 0.1;

/// [`CameraModel::undistort`] stops when a Gauss-Newton step is shorter than
/// this (normalized units).
pub const UNDISTORT_TOLERANCE: f64 = 1e-12;

/// Largest number of Gauss-Newton iterations of [`CameraModel::undistort`].
pub const UNDISTORT_MAX_ITERATIONS: usize = 20;

/// The distortion model of a camera; serialized as `"radtan"` or `"equidistant"`.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum Distortion {
    /// Radial-tangential (plumb-bob); distortion vector `[k1, k2, p1, p2]`.
    RadTan,
    /// Equidistant / Kannala-Brandt (OpenCV fisheye); distortion vector
    /// `[k1, k2, k3, k4]`.
    Equidistant,
}

/// Errors of camera validation and undistortion.
#[derive(Clone, Debug, PartialEq, thiserror::Error)]
pub enum CameraError {
    /// The image has no pixels.
    #[error("image size must be nonzero, got {width}x{height} pixels")]
    EmptyImage {
        /// Image width in pixels.
        width: u32,
        /// Image height in pixels.
        height: u32,
    },
    /// A focal length is zero or negative.
    #[error("focal lengths must be positive, got fx = {fx}, fy = {fy} pixels")]
    NonPositiveFocalLength {
        /// Horizontal focal length in pixels.
        fx: f64,
        /// Vertical focal length in pixels.
        fy: f64,
    },
    /// An intrinsic or distortion parameter is NaN or infinite.
    #[error("camera parameter {name} is not finite: {value}")]
    NonFiniteParameter {
        /// Name of the parameter (`fx`, `fy`, `cx`, `cy`, `d0` … `d3`).
        name: &'static str,
        /// Its value.
        value: f64,
    },
    /// The pixel to undistort is NaN or infinite.
    #[error("pixel ({u}, {v}) is not finite")]
    NonFinitePixel {
        /// Horizontal pixel coordinate.
        u: f64,
        /// Vertical pixel coordinate.
        v: f64,
    },
    /// Gauss-Newton undistortion did not converge (the pixel is outside the
    /// invertible region of the distortion model, or the model is degenerate).
    #[error(
        "undistortion of pixel ({u}, {v}) did not converge after {iterations} iterations \
         (residual {residual:e} in normalized units)"
    )]
    UndistortNotConverged {
        /// Horizontal pixel coordinate.
        u: f64,
        /// Vertical pixel coordinate.
        v: f64,
        /// Iterations run.
        iterations: usize,
        /// Norm of the last distorted-normalized residual.
        residual: f64,
    },
}

/// A pinhole camera with distortion: size, intrinsics and distortion coefficients.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct CameraModel {
    /// The distortion model, which gives the meaning of [`CameraModel::distortion`].
    pub model: Distortion,
    /// Image width in pixels.
    pub width: u32,
    /// Image height in pixels.
    pub height: u32,
    /// `[fx, fy, cx, cy]`: focal lengths and principal point, in pixels.
    pub intrinsics: Vector4<f64>,
    /// Distortion coefficients (unitless): `[k1, k2, p1, p2]` for
    /// [`Distortion::RadTan`], `[k1, k2, k3, k4]` for [`Distortion::Equidistant`].
    pub distortion: Vector4<f64>,
}

impl Default for CameraModel {
    /// [`CameraModel::euroc_cam0`].
    fn default() -> Self {
        Self::euroc_cam0()
    }
}

impl CameraModel {
    /// The left camera (`cam0`) of the EuRoC MAV dataset: 752x480 pixels, radtan.
    pub fn euroc_cam0() -> Self {
        Self {
            model: Distortion::RadTan,
            width: 752,
            height: 480,
            intrinsics: Vector4::new(458.654, 457.296, 367.215, 248.375),
            distortion: Vector4::new(-0.28340811, 0.07395907, 0.00019359, 1.76187114e-05),
        }
    }

    /// Horizontal focal length in pixels.
    pub fn fx(&self) -> f64 {
        self.intrinsics[0]
    }

    /// Vertical focal length in pixels.
    pub fn fy(&self) -> f64 {
        self.intrinsics[1]
    }

    /// Horizontal principal point in pixels.
    pub fn cx(&self) -> f64 {
        self.intrinsics[2]
    }

    /// Vertical principal point in pixels.
    pub fn cy(&self) -> f64 {
        self.intrinsics[3]
    }

    /// Checks the model is usable: nonzero image size, finite parameters and
    /// positive focal lengths.
    pub fn validate(&self) -> Result<(), CameraError> {
        if self.width == 0 || self.height == 0 {
            return Err(CameraError::EmptyImage {
                width: self.width,
                height: self.height,
            });
        }
        const INTRINSIC_NAMES: [&str; 4] = ["fx", "fy", "cx", "cy"];
        const DISTORTION_NAMES: [&str; 4] = ["d0", "d1", "d2", "d3"];
        let named = INTRINSIC_NAMES
            .iter()
            .zip(self.intrinsics.iter())
            .chain(DISTORTION_NAMES.iter().zip(self.distortion.iter()));
        for (&name, &value) in named {
            if !value.is_finite() {
                return Err(CameraError::NonFiniteParameter { name, value });
            }
        }
        if self.fx() <= 0.0 || self.fy() <= 0.0 {
            return Err(CameraError::NonPositiveFocalLength {
                fx: self.fx(),
                fy: self.fy(),
            });
        }
        Ok(())
    }

    /// The distorted normalized point of the undistorted normalized point `n`.
    fn distort_normalized(&self, n: &Vector2<f64>) -> Vector2<f64> {
        match self.model {
            Distortion::RadTan => radtan::distort(&self.distortion, n),
            Distortion::Equidistant => equidistant::distort(&self.distortion, n),
        }
    }

    /// The distorted normalized point with its Jacobians with respect to `n`
    /// and to the distortion vector.
    fn distort_normalized_with_jacobians(
        &self,
        n: &Vector2<f64>,
    ) -> (Vector2<f64>, Matrix2<f64>, Matrix2x4<f64>) {
        match self.model {
            Distortion::RadTan => radtan::distort_with_jacobians(&self.distortion, n),
            Distortion::Equidistant => equidistant::distort_with_jacobians(&self.distortion, n),
        }
    }

    /// Raw pixel (distorted, in pixels) of the normalized undistorted point
    /// `n = [x/z, y/z]`.
    pub fn distort(&self, n: &Vector2<f64>) -> Vector2<f64> {
        let nd = self.distort_normalized(n);
        Vector2::new(self.fx() * nd.x + self.cx(), self.fy() * nd.y + self.cy())
    }

    /// [`CameraModel::distort`] with its Jacobians: returns
    /// `(uv, d_uv/d_n (2x2), d_uv/d_intrinsics (2x8))`, the intrinsics ordered
    /// `[fx, fy, cx, cy, d0, d1, d2, d3]` (`d` = [`CameraModel::distortion`]).
    pub fn distort_with_jacobians(
        &self,
        n: &Vector2<f64>,
    ) -> (Vector2<f64>, Matrix2<f64>, SMatrix<f64, 2, 8>) {
        let (nd, d_nd_d_n, d_nd_d_dist) = self.distort_normalized_with_jacobians(n);
        let (fx, fy) = (self.fx(), self.fy());
        let uv = Vector2::new(fx * nd.x + self.cx(), fy * nd.y + self.cy());
        let focal = Matrix2::new(fx, 0.0, 0.0, fy);
        let d_uv_d_n = focal * d_nd_d_n;
        let mut d_uv_d_intrinsics = SMatrix::<f64, 2, 8>::zeros();
        d_uv_d_intrinsics[(0, 0)] = nd.x;
        d_uv_d_intrinsics[(1, 1)] = nd.y;
        d_uv_d_intrinsics[(0, 2)] = 1.0;
        d_uv_d_intrinsics[(1, 3)] = 1.0;
        d_uv_d_intrinsics
            .fixed_view_mut::<2, 4>(0, 4)
            .copy_from(&(focal * d_nd_d_dist));
        (uv, d_uv_d_n, d_uv_d_intrinsics)
    }

    /// Normalized undistorted point `[x/z, y/z]` of the raw pixel `uv`.
    ///
    /// Inverts [`CameraModel::distort`] by Gauss-Newton iterations (with step
    /// halving when a step does not reduce the residual), starting from the
    /// distorted normalized point; converges when a step is shorter than
    /// [`UNDISTORT_TOLERANCE`], within [`UNDISTORT_MAX_ITERATIONS`].
    pub fn undistort(&self, uv: &Vector2<f64>) -> Result<Vector2<f64>, CameraError> {
        let (u, v) = (uv.x, uv.y);
        if !u.is_finite() || !v.is_finite() {
            return Err(CameraError::NonFinitePixel { u, v });
        }
        let target = Vector2::new((u - self.cx()) / self.fx(), (v - self.cy()) / self.fy());
        let not_converged = |iterations: usize, residual: f64| CameraError::UndistortNotConverged {
            u,
            v,
            iterations,
            residual,
        };
        if !target.x.is_finite() || !target.y.is_finite() {
            return Err(not_converged(0, f64::NAN));
        }

        let residual_and_jacobian = |n: &Vector2<f64>| {
            let (nd, d_nd_d_n, _) = self.distort_normalized_with_jacobians(n);
            (nd - target, d_nd_d_n)
        };
        let mut n = target;
        let (mut residual, mut jacobian) = residual_and_jacobian(&n);
        for iteration in 1..=UNDISTORT_MAX_ITERATIONS {
            let Some(inverse) = jacobian.try_inverse() else {
                return Err(not_converged(iteration, residual.norm()));
            };
            let full_step = inverse * residual;
            if !full_step.x.is_finite() || !full_step.y.is_finite() {
                return Err(not_converged(iteration, residual.norm()));
            }
            // Halve the step until the residual does not grow (at most 10 times).
            let cost = residual.norm();
            let mut scale = 1.0;
            let (mut candidate, mut candidate_eval);
            loop {
                candidate = n - full_step * scale;
                candidate_eval = residual_and_jacobian(&candidate);
                if candidate_eval.0.norm() <= cost || scale < 1e-3 {
                    break;
                }
                scale *= 0.5;
            }
            n = candidate;
            (residual, jacobian) = candidate_eval;
            let step = full_step.norm() * scale;
            if step < UNDISTORT_TOLERANCE && residual.norm() < 1e3 * UNDISTORT_TOLERANCE {
                return Ok(n);
            }
        }
        Err(not_converged(UNDISTORT_MAX_ITERATIONS, residual.norm()))
    }

    /// Whether the pixel `uv` lies in the image grown by [`PREDICTION_MARGIN`]
    /// of its size on every side (false for NaN): where a filter may still
    /// linearize a predicted point. Beyond it the distortion polynomial was
    /// never fitted and grows without bound: radtan's fifth-power term gives
    /// a point predicted at a normalized radius of 40 (far off the axis) a
    /// distortion Jacobian near 4·10⁸, and its residual and innovation
    /// covariance grow together, so a chi-square gate passes it and the
    /// update takes it as exact.
    pub fn near_image(&self, uv: &Vector2<f64>) -> bool {
        let (w, h) = (f64::from(self.width), f64::from(self.height));
        let (mu, mv) = (PREDICTION_MARGIN * w, PREDICTION_MARGIN * h);
        uv.x >= -mu && uv.x <= w + mu && uv.y >= -mv && uv.y <= h + mv
    }

    /// Whether the pixel `uv` lies in the image: `0 <= u < width`,
    /// `0 <= v < height` (false for NaN).
    pub fn in_image(&self, uv: &Vector2<f64>) -> bool {
        uv.x >= 0.0 && uv.x < f64::from(self.width) && uv.y >= 0.0 && uv.y < f64::from(self.height)
    }

    /// Raw pixel of the point `p_in_c` (metres, camera frame); `None` when it
    /// is not in front of the camera (`z <= MIN_DEPTH_M`, or NaN). The pixel
    /// may be outside the image: see [`CameraModel::in_image`].
    pub fn project(&self, p_in_c: &Vector3<f64>) -> Option<Vector2<f64>> {
        normalize(p_in_c).map(|n| self.distort(&n))
    }

    /// [`CameraModel::project`] with `d_uv/d_p_in_c` (2x3, pixels per metre):
    /// the distortion Jacobian times `d_n/d_p = [1/z 0 -x/z²; 0 1/z -y/z²]`.
    pub fn project_with_jacobian(
        &self,
        p_in_c: &Vector3<f64>,
    ) -> Option<(Vector2<f64>, Matrix2x3<f64>)> {
        let n = normalize(p_in_c)?;
        let (uv, d_uv_d_n, _) = self.distort_with_jacobians(&n);
        let inv_z = 1.0 / p_in_c.z;
        let d_n_d_p = Matrix2x3::new(inv_z, 0.0, -n.x * inv_z, 0.0, inv_z, -n.y * inv_z);
        Some((uv, d_uv_d_n * d_n_d_p))
    }
}

/// `[x/z, y/z]`, or `None` when `z <= MIN_DEPTH_M` or NaN.
fn normalize(p: &Vector3<f64>) -> Option<Vector2<f64>> {
    // Written so that a NaN depth is rejected as well.
    if p.z > MIN_DEPTH_M {
        Some(Vector2::new(p.x / p.z, p.y / p.z))
    } else {
        None
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use nalgebra::SVector;
    use rand::{Rng, SeedableRng};
    use rand_chacha::ChaCha8Rng;

    /// A wide-angle fisheye whose image corners are inside its field of view
    /// (about 110° across the diagonal) with non-trivial coefficients.
    fn fisheye() -> CameraModel {
        CameraModel {
            model: Distortion::Equidistant,
            width: 640,
            height: 480,
            intrinsics: Vector4::new(281.3, 279.8, 321.4, 238.9),
            distortion: Vector4::new(0.02, -0.01, 0.004, -0.001),
        }
    }

    fn both_models() -> [CameraModel; 2] {
        [CameraModel::euroc_cam0(), fisheye()]
    }

    /// Central finite differences of `f` at `x`, step `1e-6 · max(1, |x_i|)`.
    fn numeric_jacobian<const R: usize, const C: usize>(
        f: impl Fn(&SVector<f64, C>) -> SVector<f64, R>,
        x: &SVector<f64, C>,
    ) -> SMatrix<f64, R, C> {
        let mut jac = SMatrix::<f64, R, C>::zeros();
        for i in 0..C {
            let h = 1e-6 * x[i].abs().max(1.0);
            let (mut plus, mut minus) = (*x, *x);
            plus[i] += h;
            minus[i] -= h;
            jac.set_column(i, &((f(&plus) - f(&minus)) / (2.0 * h)));
        }
        jac
    }

    fn assert_matrix_close<const R: usize, const C: usize>(
        analytic: &SMatrix<f64, R, C>,
        numeric: &SMatrix<f64, R, C>,
        what: &str,
    ) {
        for (a, n) in analytic.iter().zip(numeric.iter()) {
            assert!(
                (a - n).abs() <= 1e-6 * a.abs().max(1.0),
                "{what}: analytic {analytic} vs numeric {numeric}"
            );
        }
    }

    fn with_intrinsics(camera: &CameraModel, zeta: &SVector<f64, 8>) -> CameraModel {
        CameraModel {
            intrinsics: zeta.fixed_rows::<4>(0).into_owned(),
            distortion: zeta.fixed_rows::<4>(4).into_owned(),
            ..camera.clone()
        }
    }

    /// Random normalized points whose pixels are inside the image, plus points
    /// at and next to the optical axis.
    fn points_in_view(camera: &CameraModel, rng: &mut ChaCha8Rng) -> Vec<Vector2<f64>> {
        let (w, h) = (f64::from(camera.width), f64::from(camera.height));
        let mut points = vec![
            Vector2::zeros(),
            Vector2::new(1e-12, -3e-12),
            Vector2::new(-2e-9, 5e-9),
            Vector2::new(3e-7, 1e-7),
        ];
        for _ in 0..300 {
            let uv = Vector2::new(rng.random_range(0.0..w), rng.random_range(0.0..h));
            points.push(camera.undistort(&uv).unwrap());
        }
        points
    }

    #[test]
    fn distortion_jacobian_wrt_the_normalized_point_matches_finite_differences() {
        let mut rng = ChaCha8Rng::seed_from_u64(1);
        for camera in both_models() {
            for n in points_in_view(&camera, &mut rng) {
                let (uv, d_uv_d_n, _) = camera.distort_with_jacobians(&n);
                assert!((uv - camera.distort(&n)).norm() < 1e-12);
                let numeric = numeric_jacobian(|x: &Vector2<f64>| camera.distort(x), &n);
                assert_matrix_close(
                    &d_uv_d_n,
                    &numeric,
                    &format!("{:?} d_uv/d_n at {n}", camera.model),
                );
            }
        }
    }

    #[test]
    fn distortion_jacobian_wrt_the_intrinsics_matches_finite_differences() {
        let mut rng = ChaCha8Rng::seed_from_u64(1);
        for camera in both_models() {
            let mut zeta = SVector::<f64, 8>::zeros();
            zeta.fixed_rows_mut::<4>(0).copy_from(&camera.intrinsics);
            zeta.fixed_rows_mut::<4>(4).copy_from(&camera.distortion);
            for n in points_in_view(&camera, &mut rng) {
                let (_, _, d_uv_d_zeta) = camera.distort_with_jacobians(&n);
                let numeric = numeric_jacobian(
                    |z: &SVector<f64, 8>| with_intrinsics(&camera, z).distort(&n),
                    &zeta,
                );
                assert_matrix_close(
                    &d_uv_d_zeta,
                    &numeric,
                    &format!("{:?} d_uv/d_zeta at {n}", camera.model),
                );
            }
        }
    }

    #[test]
    fn projection_jacobian_matches_finite_differences() {
        let mut rng = ChaCha8Rng::seed_from_u64(1);
        for camera in both_models() {
            for n in points_in_view(&camera, &mut rng) {
                let depth = rng.random_range(0.5..20.0);
                let p = Vector3::new(n.x, n.y, 1.0) * depth;
                let (uv, d_uv_d_p) = camera.project_with_jacobian(&p).unwrap();
                assert!((uv - camera.project(&p).unwrap()).norm() < 1e-9);
                let numeric = numeric_jacobian(|x: &Vector3<f64>| camera.project(x).unwrap(), &p);
                assert_matrix_close(
                    &d_uv_d_p,
                    &numeric,
                    &format!("{:?} d_uv/d_p at {p}", camera.model),
                );
            }
        }
    }

    #[test]
    fn undistort_inverts_distort_over_the_whole_image_including_the_corners() {
        for camera in both_models() {
            let (w, h) = (f64::from(camera.width), f64::from(camera.height));
            let steps = 24;
            for i in 0..=steps {
                for j in 0..=steps {
                    let uv = Vector2::new(
                        w * f64::from(i) / f64::from(steps),
                        h * f64::from(j) / f64::from(steps),
                    );
                    let n = camera.undistort(&uv).unwrap();
                    let uv_back = camera.distort(&n);
                    assert!(
                        (uv_back - uv).norm() < 1e-9,
                        "{:?}: {uv} -> {n} -> {uv_back}",
                        camera.model
                    );
                    let n_back = camera.undistort(&camera.distort(&n)).unwrap();
                    assert!(
                        (n_back - n).norm() < 1e-9,
                        "{:?}: {n} -> {n_back}",
                        camera.model
                    );
                }
            }
        }
    }

    #[test]
    fn undistort_inverts_distort_on_a_normalized_grid_spanning_the_image() {
        for camera in both_models() {
            let (w, h) = (f64::from(camera.width), f64::from(camera.height));
            let top_left = camera.undistort(&Vector2::new(0.0, 0.0)).unwrap();
            let bottom_right = camera.undistort(&Vector2::new(w, h)).unwrap();
            let steps = 20;
            for i in 0..=steps {
                for j in 0..=steps {
                    let (a, b) = (
                        f64::from(i) / f64::from(steps),
                        f64::from(j) / f64::from(steps),
                    );
                    let n = top_left + (bottom_right - top_left).component_mul(&Vector2::new(a, b));
                    let n_back = camera.undistort(&camera.distort(&n)).unwrap();
                    assert!(
                        (n_back - n).norm() < 1e-9,
                        "{:?}: {n} -> {n_back}",
                        camera.model
                    );
                }
            }
        }
    }

    #[test]
    fn a_point_on_the_optical_axis_projects_to_the_principal_point() {
        for camera in both_models() {
            let uv = camera.project(&Vector3::new(0.0, 0.0, 3.0)).unwrap();
            assert_eq!(uv, Vector2::new(camera.cx(), camera.cy()));
            let n = camera.undistort(&uv).unwrap();
            assert!(n.norm() < 1e-15);
        }
    }

    #[test]
    fn points_behind_or_on_the_camera_plane_do_not_project() {
        let camera = CameraModel::euroc_cam0();
        for p in [
            Vector3::new(0.1, 0.2, 0.0),
            Vector3::new(0.1, 0.2, -1.0),
            Vector3::new(0.0, 0.0, MIN_DEPTH_M),
            Vector3::new(0.0, 0.0, f64::NAN),
        ] {
            assert!(camera.project(&p).is_none(), "{p}");
            assert!(camera.project_with_jacobian(&p).is_none(), "{p}");
        }
    }

    #[test]
    fn near_image_is_the_image_grown_by_a_tenth_and_refuses_nan() {
        let c = CameraModel::euroc_cam0();
        for (u, v, near) in [
            (376.0, 240.0, true),
            (-75.0, 240.0, true),
            (827.0, 528.0, true),
            (-76.0, 240.0, false),
            (376.0, 529.0, false),
            (f64::NAN, 240.0, false),
        ] {
            assert_eq!(c.near_image(&Vector2::new(u, v)), near, "({u}, {v})");
        }
    }

    #[test]
    fn euroc_cam0_validates_and_is_the_default() {
        let camera = CameraModel::euroc_cam0();
        assert_eq!(camera.validate(), Ok(()));
        assert_eq!(CameraModel::default(), camera);
        assert_eq!((camera.width, camera.height), (752, 480));
        assert_eq!(fisheye().validate(), Ok(()));
    }

    #[test]
    fn validation_rejects_empty_images_bad_focal_lengths_and_non_finite_values() {
        let good = CameraModel::euroc_cam0();
        let empty = CameraModel {
            width: 0,
            ..good.clone()
        };
        assert!(matches!(
            empty.validate(),
            Err(CameraError::EmptyImage { .. })
        ));
        let mut flat = good.clone();
        flat.intrinsics[1] = 0.0;
        assert!(matches!(
            flat.validate(),
            Err(CameraError::NonPositiveFocalLength { .. })
        ));
        let mut nan = good.clone();
        nan.intrinsics[2] = f64::NAN;
        assert!(matches!(
            nan.validate(),
            Err(CameraError::NonFiniteParameter { name: "cx", .. })
        ));
        let mut inf = good;
        inf.distortion[3] = f64::INFINITY;
        assert!(matches!(
            inf.validate(),
            Err(CameraError::NonFiniteParameter { name: "d3", .. })
        ));
    }

    #[test]
    fn undistort_reports_non_finite_pixels_and_pixels_outside_the_fisheye_field_of_view() {
        let camera = CameraModel::euroc_cam0();
        let err = camera.undistort(&Vector2::new(f64::NAN, 10.0));
        assert!(matches!(err, Err(CameraError::NonFinitePixel { .. })));
        // θ_d beyond what the equidistant model reaches for θ < 90°.
        let fisheye = fisheye();
        let far = Vector2::new(fisheye.cx() + 10.0 * fisheye.fx(), fisheye.cy());
        assert!(matches!(
            fisheye.undistort(&far),
            Err(CameraError::UndistortNotConverged { .. })
        ));
    }

    #[test]
    fn in_image_accepts_the_image_and_rejects_outside_and_nan() {
        let camera = CameraModel::euroc_cam0();
        assert!(camera.in_image(&Vector2::new(0.0, 0.0)));
        assert!(camera.in_image(&Vector2::new(751.9, 479.9)));
        assert!(!camera.in_image(&Vector2::new(752.0, 10.0)));
        assert!(!camera.in_image(&Vector2::new(10.0, -0.1)));
        assert!(!camera.in_image(&Vector2::new(f64::NAN, 10.0)));
    }

    #[test]
    fn models_serialize_with_lowercase_distortion_names() {
        let camera = CameraModel::euroc_cam0();
        let json = serde_json::to_string(&camera).unwrap();
        assert!(json.contains("\"radtan\""), "{json}");
        assert_eq!(serde_json::from_str::<CameraModel>(&json).unwrap(), camera);
        let json = serde_json::to_string(&fisheye()).unwrap();
        assert!(json.contains("\"equidistant\""), "{json}");
        assert_eq!(
            serde_json::from_str::<CameraModel>(&json).unwrap(),
            fisheye()
        );
    }
}
