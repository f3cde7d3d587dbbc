//! Absolute trajectory error.

use serde::{Deserialize, Serialize};

use super::{align, apply_alignment, Alignment, PosePair};
use crate::so3::{log_so3, Se3};

/// Root-mean-square absolute errors of an aligned estimate.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct AteResult {
    /// RMSE of the rotation angle `|Log(R_gtᵀ R_est')|`, degrees (NaN when `n == 0`).
    pub ori_deg: f64,
    /// RMSE of `|p_est' − p_gt|`, metres (NaN when `n == 0`).
    pub pos_m: f64,
    /// Number of pose pairs.
    pub n: usize,
}

/// ATE after aligning the estimate with `mode` (see [`align`]).
pub fn ate(pairs: &[PosePair], mode: Alignment) -> AteResult {
    ate_with(pairs, &align(pairs, mode))
}

/// ATE after applying the given alignment `t` to the estimate.
pub fn ate_with(pairs: &[PosePair], t: &Se3) -> AteResult {
    let (mut sum_ori, mut sum_pos) = (0.0, 0.0);
    for (e, g) in pairs {
        let e = apply_alignment(t, e);
        sum_ori += log_so3(&(g.rot.transpose() * e.rot)).norm_squared();
        sum_pos += (e.pos - g.pos).norm_squared();
    }
    let n = pairs.len();
    AteResult {
        ori_deg: (sum_ori / n as f64).sqrt().to_degrees(),
        pos_m: (sum_pos / n as f64).sqrt(),
        n,
    }
}

#[cfg(test)]
mod tests {
    use super::super::test_util::{pose, wiggly};
    use super::*;
    use crate::so3::exp_so3;
    use crate::trajectory::StampedPose;
    use nalgebra::Vector3;

    fn pairs_of(est: &[StampedPose], gt: &[StampedPose]) -> Vec<PosePair> {
        est.iter().copied().zip(gt.iter().copied()).collect()
    }

    #[test]
    fn identical_trajectories_have_zero_ate_under_every_alignment() {
        let gt = wiggly(100);
        let pairs = pairs_of(&gt, &gt);
        for mode in [Alignment::None, Alignment::PosYaw, Alignment::Se3] {
            let r = ate(&pairs, mode);
            assert_eq!(r.n, 100);
            assert!(r.ori_deg < 1e-9 && r.pos_m < 1e-12, "{mode}: {r:?}");
        }
    }

    #[test]
    fn a_constant_ten_centimetre_offset_is_removed_by_alignment_only() {
        let gt = wiggly(100);
        let est: Vec<_> = gt
            .iter()
            .map(|p| StampedPose {
                pos: p.pos + Vector3::new(0.06, 0.0, 0.08),
                ..*p
            })
            .collect();
        let pairs = pairs_of(&est, &gt);
        let none = ate(&pairs, Alignment::None);
        assert!((none.pos_m - 0.1).abs() < 1e-12, "{none:?}");
        assert!(none.ori_deg < 1e-12);
        for mode in [Alignment::PosYaw, Alignment::Se3] {
            let r = ate(&pairs, mode);
            assert!(r.pos_m < 1e-10 && r.ori_deg < 1e-8, "{mode}: {r:?}");
        }
    }

    #[test]
    fn a_constant_one_degree_roll_error_gives_one_degree_ate() {
        let gt = wiggly(100);
        let roll = exp_so3(&Vector3::new(1f64.to_radians(), 0.0, 0.0));
        let est: Vec<_> = gt
            .iter()
            .map(|p| StampedPose {
                rot: p.rot * roll,
                ..*p
            })
            .collect();
        let r = ate(&pairs_of(&est, &gt), Alignment::None);
        assert!((r.ori_deg - 1.0).abs() < 1e-12, "{r:?}");
        assert!(r.pos_m < 1e-15);
    }

    #[test]
    fn a_yawed_copy_of_the_trajectory_is_recovered_by_posyaw_but_not_by_none() {
        let gt = wiggly(150);
        let yaw = Se3::new(
            exp_so3(&Vector3::new(0.0, 0.0, -1.2)),
            Vector3::new(1.0, 2.0, 0.0),
        );
        let est: Vec<_> = gt.iter().map(|p| apply_alignment(&yaw, p)).collect();
        let pairs = pairs_of(&est, &gt);
        let r = ate(&pairs, Alignment::PosYaw);
        assert!(r.pos_m < 1e-10 && r.ori_deg < 1e-8, "{r:?}");
        let none = ate(&pairs, Alignment::None);
        assert!((none.ori_deg - 1.2f64.to_degrees()).abs() < 1e-9);
    }

    #[test]
    fn no_pairs_give_nan_and_zero_count() {
        let r = ate(&[], Alignment::Se3);
        assert_eq!(r.n, 0);
        assert!(r.ori_deg.is_nan() && r.pos_m.is_nan());
        let one = pose(0.0, 0.0, Vector3::zeros());
        assert_eq!(ate(&[(one, one)], Alignment::Se3).pos_m, 0.0);
    }
}
