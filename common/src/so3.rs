//! SO(3) and SE(3) on nalgebra, small-angle safe.
//!
//! See [`crate::conventions`]: rotations are perturbed on the right,
//! `R = R̂ Exp(δθ)`. [`Se3`] tangent vectors are ordered `[ω; v]` (rotation first).

use nalgebra::{Matrix3, Matrix4, UnitQuaternion, Vector3, Vector6};

/// Below this angle (rad) Taylor expansions replace the closed forms.
const SMALL_ANGLE: f64 = 1e-7;

/// The skew-symmetric matrix `[v]×` with `[v]× w = v × w`.
pub fn skew(v: &Vector3<f64>) -> Matrix3<f64> {
    Matrix3::new(0.0, -v.z, v.y, v.z, 0.0, -v.x, -v.y, v.x, 0.0)
}

/// The vector of a skew-symmetric matrix (inverse of [`skew`]); the
/// antisymmetric part is used, so small asymmetries average out.
pub fn vee(m: &Matrix3<f64>) -> Vector3<f64> {
    Vector3::new(
        0.5 * (m[(2, 1)] - m[(1, 2)]),
        0.5 * (m[(0, 2)] - m[(2, 0)]),
        0.5 * (m[(1, 0)] - m[(0, 1)]),
    )
}

/// SO(3) exponential map (Rodrigues' formula).
pub fn exp_so3(w: &Vector3<f64>) -> Matrix3<f64> {
    let theta2 = w.norm_squared();
    let theta = theta2.sqrt();
    let k = skew(w);
    let (a, b) = if theta < SMALL_ANGLE {
        (1.0 - theta2 / 6.0, 0.5 - theta2 / 24.0)
    } else {
        (theta.sin() / theta, (1.0 - theta.cos()) / theta2)
    };
    Matrix3::identity() + k * a + k * k * b
}

/// SO(3) logarithm: the rotation vector `w` with `exp_so3(w) = r`, `|w| <= π`.
///
/// Uses the quaternion of `r`, which stays accurate near 0 and near π.
pub fn log_so3(r: &Matrix3<f64>) -> Vector3<f64> {
    log_quat(&quat_from_rot(r))
}

/// Unit quaternion of a rotation matrix (Shepperd's method: divides by the
/// largest of the four candidate terms, so it is exact to rounding everywhere).
pub fn quat_from_rot(r: &Matrix3<f64>) -> UnitQuaternion<f64> {
    let tr = r.trace();
    let (w, x, y, z);
    if tr > r[(0, 0)] && tr > r[(1, 1)] && tr > r[(2, 2)] {
        let s = 2.0 * (1.0 + tr).sqrt();
        w = 0.25 * s;
        x = (r[(2, 1)] - r[(1, 2)]) / s;
        y = (r[(0, 2)] - r[(2, 0)]) / s;
        z = (r[(1, 0)] - r[(0, 1)]) / s;
    } else if r[(0, 0)] > r[(1, 1)] && r[(0, 0)] > r[(2, 2)] {
        let s = 2.0 * (1.0 + r[(0, 0)] - r[(1, 1)] - r[(2, 2)]).sqrt();
        w = (r[(2, 1)] - r[(1, 2)]) / s;
        x = 0.25 * s;
        y = (r[(0, 1)] + r[(1, 0)]) / s;
        z = (r[(0, 2)] + r[(2, 0)]) / s;
    } else if r[(1, 1)] > r[(2, 2)] {
        let s = 2.0 * (1.0 + r[(1, 1)] - r[(0, 0)] - r[(2, 2)]).sqrt();
        w = (r[(0, 2)] - r[(2, 0)]) / s;
        x = (r[(0, 1)] + r[(1, 0)]) / s;
        y = 0.25 * s;
        z = (r[(1, 2)] + r[(2, 1)]) / s;
    } else {
        let s = 2.0 * (1.0 + r[(2, 2)] - r[(0, 0)] - r[(1, 1)]).sqrt();
        w = (r[(1, 0)] - r[(0, 1)]) / s;
        x = (r[(0, 2)] + r[(2, 0)]) / s;
        y = (r[(1, 2)] + r[(2, 1)]) / s;
        z = 0.25 * s;
    }
    UnitQuaternion::from_quaternion(nalgebra::Quaternion::new(w, x, y, z))
}

/// Rotation vector of a unit quaternion, `|w| <= π`.
pub fn log_quat(q: &UnitQuaternion<f64>) -> Vector3<f64> {
    let q = q.quaternion();
    // Pick the hemisphere with w >= 0 so the angle is at most π.
    let (w, v) = if q.w < 0.0 {
        (-q.w, -q.imag())
    } else {
        (q.w, q.imag())
    };
    let n = v.norm();
    if n < SMALL_ANGLE {
        // sin(θ/2) ≈ θ/2: w = 2 v / w keeps second-order accuracy.
        return v * (2.0 / w);
    }
    let theta = 2.0 * n.atan2(w);
    v * (theta / n)
}

/// Right Jacobian of SO(3): `Exp(w + δ) ≈ Exp(w) Exp(Jr(w) δ)`.
pub fn jr_so3(w: &Vector3<f64>) -> Matrix3<f64> {
    let theta2 = w.norm_squared();
    let theta = theta2.sqrt();
    let k = skew(w);
    let (a, b) = if theta < 1e-5 {
        (0.5 - theta2 / 24.0, 1.0 / 6.0 - theta2 / 120.0)
    } else {
        (
            (1.0 - theta.cos()) / theta2,
            (theta - theta.sin()) / (theta2 * theta),
        )
    };
    Matrix3::identity() - k * a + k * k * b
}

/// Inverse of the right Jacobian of SO(3): `Log(Exp(w) Exp(δ)) ≈ w + Jr⁻¹(w) δ`.
pub fn jr_inv_so3(w: &Vector3<f64>) -> Matrix3<f64> {
    let theta2 = w.norm_squared();
    let theta = theta2.sqrt();
    let k = skew(w);
    let c = if theta < 1e-5 {
        1.0 / 12.0 + theta2 / 720.0
    } else {
        1.0 / theta2 - (1.0 + theta.cos()) / (2.0 * theta * theta.sin())
    };
    Matrix3::identity() + k * 0.5 + k * k * c
}

/// Left Jacobian of SO(3): `Jl(w) = Jr(-w)`.
pub fn jl_so3(w: &Vector3<f64>) -> Matrix3<f64> {
    jr_so3(&-w)
}

/// Inverse of the left Jacobian of SO(3).
pub fn jl_inv_so3(w: &Vector3<f64>) -> Matrix3<f64> {
    jr_inv_so3(&-w)
}

/// Rotation matrix from a TUM-ordered quaternion `(qx, qy, qz, qw)`, normalized.
pub fn rot_from_xyzw(qx: f64, qy: f64, qz: f64, qw: f64) -> Matrix3<f64> {
    UnitQuaternion::from_quaternion(nalgebra::Quaternion::new(qw, qx, qy, qz))
        .to_rotation_matrix()
        .into_inner()
}

/// TUM-ordered quaternion `[qx, qy, qz, qw]` of a rotation matrix, with `qw >= 0`.
pub fn xyzw_from_rot(r: &Matrix3<f64>) -> [f64; 4] {
    let q = quat_from_rot(r);
    let q = q.quaternion();
    let s = if q.w < 0.0 { -1.0 } else { 1.0 };
    [s * q.i, s * q.j, s * q.k, s * q.w]
}

/// Re-orthonormalize a rotation matrix (after many compositions).
pub fn orthonormalize(r: &Matrix3<f64>) -> Matrix3<f64> {
    quat_from_rot(r).to_rotation_matrix().into_inner()
}

/// A rigid transform `T_AtoB = (R_AtoB, p_AinB)` mapping points of frame `A` into `B`.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Se3 {
    /// Rotation `R_AtoB`.
    pub rot: Matrix3<f64>,
    /// Translation `p_AinB`.
    pub trans: Vector3<f64>,
}

impl Se3 {
    /// The identity transform.
    pub fn identity() -> Self {
        Self {
            rot: Matrix3::identity(),
            trans: Vector3::zeros(),
        }
    }

    /// A transform from its rotation and translation.
    pub fn new(rot: Matrix3<f64>, trans: Vector3<f64>) -> Self {
        Self { rot, trans }
    }

    /// `self ∘ other`: with `self = T_BtoC`, `other = T_AtoB`, gives `T_AtoC`.
    pub fn compose(&self, other: &Se3) -> Se3 {
        Se3 {
            rot: self.rot * other.rot,
            trans: self.rot * other.trans + self.trans,
        }
    }

    /// The inverse transform.
    pub fn inverse(&self) -> Se3 {
        let rt = self.rot.transpose();
        Se3 {
            rot: rt,
            trans: -(rt * self.trans),
        }
    }

    /// Maps a point of frame `A` into frame `B`.
    pub fn transform_point(&self, p: &Vector3<f64>) -> Vector3<f64> {
        self.rot * p + self.trans
    }

    /// The 4x4 homogeneous matrix.
    pub fn matrix(&self) -> Matrix4<f64> {
        let mut m = Matrix4::identity();
        m.fixed_view_mut::<3, 3>(0, 0).copy_from(&self.rot);
        m.fixed_view_mut::<3, 1>(0, 3).copy_from(&self.trans);
        m
    }

    /// SE(3) exponential of `xi = [ω; v]`.
    pub fn exp(xi: &Vector6<f64>) -> Se3 {
        let w = xi.fixed_rows::<3>(0).into_owned();
        let v = xi.fixed_rows::<3>(3).into_owned();
        Se3 {
            rot: exp_so3(&w),
            trans: jl_so3(&w) * v,
        }
    }

    /// SE(3) logarithm `[ω; v]`, inverse of [`Se3::exp`].
    pub fn log(&self) -> Vector6<f64> {
        let w = log_so3(&self.rot);
        let v = jl_inv_so3(&w) * self.trans;
        let mut xi = Vector6::zeros();
        xi.fixed_rows_mut::<3>(0).copy_from(&w);
        xi.fixed_rows_mut::<3>(3).copy_from(&v);
        xi
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use rand::{Rng, SeedableRng};
    use rand_chacha::ChaCha8Rng;

    fn random_vec(rng: &mut ChaCha8Rng, scale: f64) -> Vector3<f64> {
        Vector3::new(
            rng.random_range(-1.0..1.0),
            rng.random_range(-1.0..1.0),
            rng.random_range(-1.0..1.0),
        ) * scale
    }

    #[test]
    fn exp_log_round_trip_from_tiny_to_near_pi() {
        let mut rng = ChaCha8Rng::seed_from_u64(1);
        for scale in [1e-12, 1e-8, 1e-4, 0.1, 1.0, 1.8] {
            for _ in 0..50 {
                let w = random_vec(&mut rng, scale);
                let back = log_so3(&exp_so3(&w));
                assert!(
                    (back - w).norm() < 1e-10 * (1.0 + w.norm()),
                    "{w} -> {back}"
                );
            }
        }
        let near_pi = Vector3::new(0.0, 0.0, std::f64::consts::PI - 1e-9);
        assert!((log_so3(&exp_so3(&near_pi)) - near_pi).norm() < 1e-7);
    }

    #[test]
    fn exp_is_a_rotation_and_a_homomorphism_on_one_axis() {
        let mut rng = ChaCha8Rng::seed_from_u64(2);
        for _ in 0..50 {
            let w = random_vec(&mut rng, 2.0);
            let r = exp_so3(&w);
            assert!((r.transpose() * r - Matrix3::identity()).norm() < 1e-12);
            assert!((r.determinant() - 1.0).abs() < 1e-12);
            // Exp(a w) Exp(b w) = Exp((a+b) w)
            let lhs = exp_so3(&(w * 0.3)) * exp_so3(&(w * 0.5));
            assert!((lhs - exp_so3(&(w * 0.8))).norm() < 1e-12);
            // Exp(-w) = Exp(w)ᵀ
            assert!((exp_so3(&-w) - r.transpose()).norm() < 1e-12);
            // Adjoint: R Exp(w) Rᵀ = Exp(R w)
            let q = exp_so3(&random_vec(&mut rng, 2.0));
            assert!((q * r * q.transpose() - exp_so3(&(q * w))).norm() < 1e-12);
        }
    }

    #[test]
    fn skew_and_vee_are_inverse_and_skew_is_the_cross_product() {
        let a = Vector3::new(0.3, -1.2, 2.0);
        let b = Vector3::new(-0.7, 0.1, 0.4);
        assert!((skew(&a) * b - a.cross(&b)).norm() < 1e-15);
        assert_eq!(vee(&skew(&a)), a);
    }

    /// Numerical right Jacobian: columns of Log(Exp(w)ᵀ Exp(w + h e_i)) / h.
    fn numeric_jr(w: &Vector3<f64>) -> Matrix3<f64> {
        let h = 1e-6;
        let mut j = Matrix3::zeros();
        for i in 0..3 {
            let mut dp = *w;
            dp[i] += h;
            let mut dm = *w;
            dm[i] -= h;
            let col = (log_so3(&(exp_so3(w).transpose() * exp_so3(&dp)))
                - log_so3(&(exp_so3(w).transpose() * exp_so3(&dm))))
                / (2.0 * h);
            j.set_column(i, &col);
        }
        j
    }

    #[test]
    fn right_jacobian_matches_numerical_differentiation() {
        let mut rng = ChaCha8Rng::seed_from_u64(3);
        for scale in [1e-9, 1e-6, 1e-3, 0.5, 2.5] {
            for _ in 0..20 {
                let w = random_vec(&mut rng, scale);
                let err = (jr_so3(&w) - numeric_jr(&w)).norm();
                assert!(err < 1e-7, "w={w} err={err}");
                let inv_err = (jr_inv_so3(&w) * jr_so3(&w) - Matrix3::identity()).norm();
                assert!(inv_err < 1e-9, "w={w} inv_err={inv_err}");
                let l_err = (jl_inv_so3(&w) * jl_so3(&w) - Matrix3::identity()).norm();
                assert!(l_err < 1e-9);
            }
        }
    }

    #[test]
    fn log_of_composition_follows_the_inverse_right_jacobian() {
        let mut rng = ChaCha8Rng::seed_from_u64(4);
        for _ in 0..20 {
            let w = random_vec(&mut rng, 1.5);
            let d = random_vec(&mut rng, 1e-6);
            let lhs = log_so3(&(exp_so3(&w) * exp_so3(&d)));
            let rhs = w + jr_inv_so3(&w) * d;
            assert!((lhs - rhs).norm() < 1e-11);
        }
    }

    #[test]
    fn quaternion_file_order_round_trips_and_picks_positive_scalar() {
        let r = exp_so3(&Vector3::new(0.1, -2.9, 0.4));
        let [x, y, z, w] = xyzw_from_rot(&r);
        assert!(w >= 0.0);
        assert!((rot_from_xyzw(x, y, z, w) - r).norm() < 1e-12);
        // 90 degrees about z: qz = qw = sqrt(1/2)
        let rz = rot_from_xyzw(0.0, 0.0, 0.5f64.sqrt(), 0.5f64.sqrt());
        assert!((rz * Vector3::x() - Vector3::y()).norm() < 1e-12);
    }

    #[test]
    fn se3_group_laws_and_exp_log_round_trip() {
        let mut rng = ChaCha8Rng::seed_from_u64(5);
        for scale in [1e-10f64, 1e-3, 1.0, 1.7] {
            for _ in 0..20 {
                let mut xi = Vector6::zeros();
                xi.fixed_rows_mut::<3>(0)
                    .copy_from(&random_vec(&mut rng, scale));
                xi.fixed_rows_mut::<3>(3)
                    .copy_from(&random_vec(&mut rng, 5.0));
                let t = Se3::exp(&xi);
                assert!((t.log() - xi).norm() < 1e-9 * (1.0 + xi.norm()));
                let id = t.compose(&t.inverse());
                assert!((id.matrix() - Matrix4::identity()).norm() < 1e-12);
                let p = random_vec(&mut rng, 3.0);
                let hp = t.matrix() * p.push(1.0);
                assert!((t.transform_point(&p) - hp.xyz()).norm() < 1e-12);
            }
        }
    }

    #[test]
    fn se3_exp_of_pure_translation_is_a_translation() {
        let xi = Vector6::new(0.0, 0.0, 0.0, 1.0, -2.0, 3.0);
        let t = Se3::exp(&xi);
        assert_eq!(t.rot, Matrix3::identity());
        assert!((t.trans - Vector3::new(1.0, -2.0, 3.0)).norm() < 1e-15);
    }
}
