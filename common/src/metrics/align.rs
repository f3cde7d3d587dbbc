//! Least-squares alignment of an estimated trajectory to the ground truth.

use nalgebra::{Matrix3, Vector3};

use super::{Alignment, PosePair};
use crate::so3::{exp_so3, Se3};
use crate::trajectory::StampedPose;

/// The transform `T` applied to the estimate (`R' = T.rot R_est`,
/// `p' = T.rot p_est + T.trans`) minimizing `Σ |p_gt − p'|²` over the pairs:
///
/// * [`Alignment::None`] gives the identity.
/// * [`Alignment::PosYaw`] gives a rotation about `z` and a translation, in
///   closed form: with centred positions `e`, `g`,
///   `yaw = atan2(Σ gy ex − gx ey, Σ gx ex + gy ey)`.
/// * [`Alignment::Se3`] gives a rotation and a translation (Umeyama / Horn, no scale).
///
/// With no pairs the identity is returned; with fewer than three non-collinear
/// positions the rotation is not unique and one of the minimizers is returned.
/// A truth that spreads less than [`MIN_YAW_SPREAD_M`] horizontally (a
/// platform standing still) says nothing of yaw: [`Alignment::PosYaw`] then
/// only translates, where the minimizer would turn by whatever the noise says.
pub fn align(pairs: &[PosePair], mode: Alignment) -> Se3 {
    if pairs.is_empty() || mode == Alignment::None {
        return Se3::identity();
    }
    let n = pairs.len() as f64;
    let mu_e = pairs.iter().map(|(e, _)| e.pos).sum::<Vector3<f64>>() / n;
    let mu_g = pairs.iter().map(|(_, g)| g.pos).sum::<Vector3<f64>>() / n;
    let rot = match mode {
        Alignment::None => Matrix3::identity(),
        Alignment::PosYaw if horizontal_spread_m(pairs, &mu_g) < MIN_YAW_SPREAD_M => {
            Matrix3::identity()
        }
        Alignment::PosYaw => {
            let (mut a, mut b) = (0.0, 0.0);
            for (e, g) in pairs {
                let (e, g) = (e.pos - mu_e, g.pos - mu_g);
                a += g.x * e.x + g.y * e.y;
                b += g.y * e.x - g.x * e.y;
            }
            exp_so3(&Vector3::new(0.0, 0.0, b.atan2(a)))
        }
        Alignment::Se3 => {
            // H = Σ g eᵀ; the rotation maximizing tr(Rᵀ H) is U D Vᵀ.
            let h = pairs
                .iter()
                .map(|(e, g)| (g.pos - mu_g) * (e.pos - mu_e).transpose())
                .sum::<Matrix3<f64>>();
            umeyama_rotation(&h)
        }
    };
    Se3::new(rot, mu_g - rot * mu_e)
}

/// RMS horizontal distance of the truth positions from their centroid under
/// which a position-and-yaw alignment keeps the yaw, m.
pub const MIN_YAW_SPREAD_M: f64 = 0.1;

/// RMS horizontal distance of the truth positions from their centroid `mu_g`, m.
fn horizontal_spread_m(pairs: &[PosePair], mu_g: &Vector3<f64>) -> f64 {
    let sum: f64 = pairs
        .iter()
        .map(|(_, g)| (g.pos - mu_g).xy().norm_squared())
        .sum();
    (sum / pairs.len() as f64).sqrt()
}

/// The proper rotation `U D Vᵀ` of the SVD `H = U S Vᵀ`, with `D` flipping the
/// direction of the smallest singular value when `det(U Vᵀ) < 0`.
fn umeyama_rotation(h: &Matrix3<f64>) -> Matrix3<f64> {
    let svd = h.svd(true, true);
    let (Some(u), Some(v_t)) = (svd.u, svd.v_t) else {
        return Matrix3::identity();
    };
    let mut d = Matrix3::identity();
    if (u * v_t).determinant() < 0.0 {
        let smallest = svd.singular_values.imin();
        d[(smallest, smallest)] = -1.0;
    }
    u * d * v_t
}

/// The pose `T ∘ pose` (the estimate after [`align`]).
pub fn apply_alignment(t: &Se3, pose: &StampedPose) -> StampedPose {
    StampedPose {
        t: pose.t,
        rot: t.rot * pose.rot,
        pos: t.transform_point(&pose.pos),
    }
}

#[cfg(test)]
mod tests {
    use super::super::test_util::wiggly;
    use super::*;
    use crate::so3::log_so3;

    fn moved(traj: &[StampedPose], t: &Se3) -> Vec<PosePair> {
        traj.iter().map(|g| (apply_alignment(t, g), *g)).collect()
    }

    #[test]
    fn posyaw_recovers_a_yaw_and_translation_of_the_whole_trajectory() {
        let offset = Se3::new(
            exp_so3(&Vector3::new(0.0, 0.0, 2.5)),
            Vector3::new(4.0, -1.0, 0.3),
        );
        let pairs = moved(&wiggly(200), &offset);
        let t = align(&pairs, Alignment::PosYaw);
        let back = t.compose(&offset);
        assert!(log_so3(&back.rot).norm() < 1e-12);
        assert!(back.trans.norm() < 1e-12);
    }

    /// A platform standing still: millimetres of noise in the truth and the
    /// estimate. The yaw they would give is noise; the alignment only moves.
    #[test]
    fn posyaw_on_a_truth_standing_still_only_translates() {
        let pairs: Vec<PosePair> = (0..50)
            .map(|k| {
                let f = k as f64;
                let g = StampedPose {
                    t: f,
                    rot: Matrix3::identity(),
                    pos: Vector3::new(
                        1.0 + 1e-3 * (0.7 * f).sin(),
                        2.0 + 1e-3 * (1.3 * f).cos(),
                        0.9,
                    ),
                };
                let mut e = g;
                e.pos = Vector3::new(1e-3 * (2.1 * f).cos(), 1e-3 * (0.4 * f).sin(), 0.0);
                (e, g)
            })
            .collect();
        let t = align(&pairs, Alignment::PosYaw);
        assert_eq!(t.rot, Matrix3::identity());
        let after = super::super::ate(&pairs, Alignment::PosYaw);
        assert!(after.ori_deg < 1e-12 && after.pos_m < 0.01, "{after:?}");
    }

    #[test]
    fn se3_recovers_a_general_rigid_transform() {
        let offset = Se3::new(
            exp_so3(&Vector3::new(0.4, -2.0, 1.0)),
            Vector3::new(-3.0, 2.0, 7.0),
        );
        let pairs = moved(&wiggly(200), &offset);
        let t = align(&pairs, Alignment::Se3);
        let back = t.compose(&offset);
        assert!(log_so3(&back.rot).norm() < 1e-10);
        assert!(back.trans.norm() < 1e-10);
    }

    #[test]
    fn posyaw_keeps_roll_and_pitch_offsets_and_none_is_the_identity() {
        let offset = Se3::new(exp_so3(&Vector3::new(0.1, 0.0, 0.0)), Vector3::zeros());
        let pairs = moved(&wiggly(100), &offset);
        let t = align(&pairs, Alignment::PosYaw);
        assert!(log_so3(&t.rot).xy().norm() < 1e-15);
        assert!((t.rot * Vector3::z() - Vector3::z()).norm() < 1e-15);
        let after = super::super::ate(&pairs, Alignment::PosYaw);
        assert!(after.ori_deg >= 0.1f64.to_degrees() - 1e-9, "{after:?}");
        assert_eq!(align(&pairs, Alignment::None), Se3::identity());
        assert_eq!(align(&[], Alignment::Se3), Se3::identity());
    }
}
