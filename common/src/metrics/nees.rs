//! Normalized estimation error squared (filter consistency).

use nalgebra::{SMatrix, SVector, Vector3};
use serde::{Deserialize, Serialize};

use super::PosePair;
use crate::so3::log_so3;
use crate::trajectory::{StampedCovariance, StampedPose};

/// Largest time difference (s) between an estimate and its covariance.
pub const COVARIANCE_MATCH_TOL_S: f64 = 1e-6;

/// Lower two-sided 95 % bound of one run's NEES with 3 DoF (χ²₃ 2.5 % quantile).
pub const CHI2_3DOF_95_LOW: f64 = 0.216;

/// Upper two-sided 95 % bound of one run's NEES with 3 DoF (χ²₃ 97.5 % quantile).
pub const CHI2_3DOF_95_HIGH: f64 = 9.348;

/// NEES of a trajectory: means over the poses, and the per-pose values.
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct NeesResult {
    /// Mean orientation NEES (`None` without any usable pose).
    pub ori_mean: Option<f64>,
    /// Mean position NEES (`None` without any usable pose).
    pub pos_mean: Option<f64>,
    /// `(t, orientation NEES, position NEES)` of each estimate that has a
    /// covariance; a value is `None` where its block is not positive definite.
    pub per_pose: Vec<(f64, Option<f64>, Option<f64>)>,
    /// Orientation blocks skipped as singular / not positive definite.
    pub singular_ori: usize,
    /// Position blocks skipped as singular / not positive definite.
    pub singular_pos: usize,
    /// Estimates without a covariance within [`COVARIANCE_MATCH_TOL_S`].
    pub unmatched: usize,
}

/// The error of an estimate in the convention of [`crate::conventions`]:
/// `δθ = Log(R_estᵀ R_gt)` (so `R_gt = R_est Exp(δθ)`) and `δp = p_gt − p_est`.
pub fn pose_error(est: &StampedPose, gt: &StampedPose) -> (Vector3<f64>, Vector3<f64>) {
    (log_so3(&(est.rot.transpose() * gt.rot)), gt.pos - est.pos)
}

/// `eᵀ P⁻¹ e` for an error of any fixed size (a 3-D orientation or position,
/// a 2-D tilt), or `None` if `P` (symmetrized) is not positive definite.
pub fn nees_of<const D: usize>(e: &SVector<f64, D>, p: &SMatrix<f64, D, D>) -> Option<f64> {
    let sym = (p + p.transpose()) * 0.5;
    let chol = sym.cholesky()?;
    let y = chol.l().solve_lower_triangular(e)?;
    let value = y.norm_squared();
    value.is_finite().then_some(value)
}

/// The covariance stamped within [`COVARIANCE_MATCH_TOL_S`] of `t`, if any.
/// `covs` must be sorted by time, as the reader returns it.
pub fn find_covariance(covs: &[StampedCovariance], t: f64) -> Option<&StampedCovariance> {
    let j = covs.partition_point(|c| c.t < t);
    [j.checked_sub(1), Some(j)]
        .into_iter()
        .flatten()
        .filter_map(|k| covs.get(k))
        .find(|c| (c.t - t).abs() <= COVARIANCE_MATCH_TOL_S)
}

/// NEES of the (unaligned) estimates against the ground truth with the
/// covariances matched by timestamp: errors from [`pose_error`], each 3x3
/// block used on its own (3 DoF each).
pub fn nees(pairs: &[PosePair], covs: &[StampedCovariance]) -> NeesResult {
    let mut out = NeesResult::default();
    let (mut sum_ori, mut n_ori, mut sum_pos, mut n_pos) = (0.0, 0usize, 0.0, 0usize);
    for (est, gt) in pairs {
        let Some(cov) = find_covariance(covs, est.t) else {
            out.unmatched += 1;
            continue;
        };
        let (d_theta, d_p) = pose_error(est, gt);
        let ori = nees_of(&d_theta, &cov.ori);
        let pos = nees_of(&d_p, &cov.pos);
        match ori {
            Some(v) => (sum_ori, n_ori) = (sum_ori + v, n_ori + 1),
            None => out.singular_ori += 1,
        }
        match pos {
            Some(v) => (sum_pos, n_pos) = (sum_pos + v, n_pos + 1),
            None => out.singular_pos += 1,
        }
        out.per_pose.push((est.t, ori, pos));
    }
    out.ori_mean = (n_ori > 0).then(|| sum_ori / n_ori as f64);
    out.pos_mean = (n_pos > 0).then(|| sum_pos / n_pos as f64);
    out
}

#[cfg(test)]
mod tests {
    use super::super::test_util::wiggly;
    use super::*;
    use crate::so3::exp_so3;
    use nalgebra::Matrix3;
    use rand::{Rng, SeedableRng};
    use rand_chacha::ChaCha8Rng;

    /// A standard normal sample (Box–Muller).
    fn normal(rng: &mut ChaCha8Rng) -> f64 {
        let u1: f64 = 1.0 - rng.random::<f64>();
        let u2: f64 = rng.random::<f64>();
        (-2.0 * u1.ln()).sqrt() * (std::f64::consts::TAU * u2).cos()
    }

    fn sample(rng: &mut ChaCha8Rng, p: &Matrix3<f64>) -> Vector3<f64> {
        let l = p.cholesky().unwrap().l();
        l * Vector3::new(normal(rng), normal(rng), normal(rng))
    }

    #[test]
    fn errors_drawn_from_the_covariance_give_a_mean_nees_near_three() {
        let mut rng = ChaCha8Rng::seed_from_u64(7);
        let a = Matrix3::new(1.0, 0.2, 0.0, -0.3, 0.5, 0.1, 0.4, 0.0, 2.0);
        let p_ori = a * a.transpose() * 1e-4;
        let p_pos = a.transpose() * a * 0.01;
        let est = wiggly(4000);
        let mut pairs = Vec::new();
        let mut covs = Vec::new();
        for e in &est {
            let gt = StampedPose {
                t: e.t,
                rot: e.rot * exp_so3(&sample(&mut rng, &p_ori)),
                pos: e.pos + sample(&mut rng, &p_pos),
            };
            pairs.push((*e, gt));
            covs.push(StampedCovariance {
                t: e.t,
                ori: p_ori,
                pos: p_pos,
            });
        }
        let r = nees(&pairs, &covs);
        assert_eq!(r.per_pose.len(), 4000);
        assert_eq!((r.unmatched, r.singular_ori, r.singular_pos), (0, 0, 0));
        // The mean of 4000 χ²₃ values has standard deviation √(6/4000) ≈ 0.04.
        let (ori, pos) = (r.ori_mean.unwrap(), r.pos_mean.unwrap());
        assert!((ori - 3.0).abs() < 0.15, "{ori}");
        assert!((pos - 3.0).abs() < 0.15, "{pos}");
    }

    #[test]
    fn a_known_error_gives_its_known_nees_and_follows_the_right_error_convention() {
        let est = wiggly(1)[0];
        let d_theta = Vector3::new(0.01, -0.02, 0.0);
        let gt = StampedPose {
            t: est.t,
            rot: est.rot * exp_so3(&d_theta),
            pos: est.pos + Vector3::new(0.0, 0.3, 0.0),
        };
        let (dt, dp) = pose_error(&est, &gt);
        assert!((dt - d_theta).norm() < 1e-14);
        let cov = StampedCovariance {
            t: est.t + 5e-7,
            ori: Matrix3::from_diagonal(&Vector3::new(1e-4, 4e-4, 1.0)),
            pos: Matrix3::from_diagonal(&Vector3::new(1.0, 0.09, 1.0)),
        };
        assert!((nees_of(&dp, &cov.pos).unwrap() - 1.0).abs() < 1e-12);
        let r = nees(&[(est, gt)], &[cov]);
        assert!((r.ori_mean.unwrap() - 2.0).abs() < 1e-9, "{r:?}");
        assert!((r.pos_mean.unwrap() - 1.0).abs() < 1e-12);
    }

    #[test]
    fn singular_blocks_and_unmatched_times_are_skipped_and_counted() {
        let traj = wiggly(3);
        let pairs: Vec<PosePair> = traj.iter().map(|p| (*p, *p)).collect();
        let covs = [
            StampedCovariance {
                t: traj[0].t,
                ori: Matrix3::zeros(),
                pos: Matrix3::identity(),
            },
            StampedCovariance {
                t: traj[2].t + 1e-3,
                ori: Matrix3::identity(),
                pos: Matrix3::identity(),
            },
        ];
        let r = nees(&pairs, &covs);
        assert_eq!((r.unmatched, r.singular_ori, r.singular_pos), (2, 1, 0));
        assert_eq!(r.ori_mean, None);
        assert_eq!(r.pos_mean, Some(0.0));
        assert_eq!(r.per_pose, vec![(traj[0].t, None, Some(0.0))]);
    }
}
