//! Accuracy and consistency metrics: association, alignment, ATE, RPE and NEES.
//!
//! All functions work on [`PosePair`]s `(estimate, ground truth)` at the same
//! time, made by [`associate`]. Orientations are `R_ItoG`, positions `p_IinG`
//! (see [`crate::conventions`]).
//!
//! * [`align`]: the transform applied to the estimate ([`Alignment`]).
//! * [`ate`]: absolute trajectory error (RMSE) after alignment.
//! * [`rpe`]: relative pose error over path-length segments, as OpenVINS.
//! * [`nees`]: normalized estimation error squared of orientation and position,
//!   with the error state of [`crate::conventions`], without alignment.

use std::fmt;
use std::str::FromStr;

use serde::{Deserialize, Serialize};

use crate::trajectory::{interpolate_pose, StampedPose};

mod align;
mod ate;
mod nees;
mod rpe;

pub use align::{align, apply_alignment};
pub use ate::{ate, ate_with, AteResult};
pub use nees::{
    find_covariance, nees, nees_of, pose_error, NeesResult, CHI2_3DOF_95_HIGH, CHI2_3DOF_95_LOW,
    COVARIANCE_MATCH_TOL_S,
};
pub use rpe::{rpe, RpeResult, DEFAULT_RPE_SEGMENTS_M};

/// The `q` quantile (0..=1) of sorted values by nearest rank: the smallest
/// value with at least a fraction `q` of them at or below it (`q = 0.99` of
/// 100 values is the 99th). `None` when empty. Every percentile the agent and
/// the reports print is this one.
pub fn percentile_sorted(sorted: &[f64], q: f64) -> Option<f64> {
    let n = sorted.len();
    let rank = (q.clamp(0.0, 1.0) * n as f64).ceil() as usize;
    sorted.get(rank.clamp(1, n.max(1)) - 1).copied()
}

/// [`percentile_sorted`] of the finite values among `values`, in any order.
pub fn percentile(values: impl IntoIterator<Item = f64>, q: f64) -> Option<f64> {
    let mut v: Vec<f64> = values.into_iter().filter(|v| v.is_finite()).collect();
    v.sort_unstable_by(f64::total_cmp);
    percentile_sorted(&v, q)
}

/// An estimated pose and the ground truth at the same time: `(est, gt)`.
pub type PosePair = (StampedPose, StampedPose);

/// Default of `max_dt` in [`associate`] (s): ground truth at 20 Hz or faster
/// always has a sample this close to any time inside its span.
pub const DEFAULT_MAX_DT_S: f64 = 0.05;

/// Matches each estimate with the ground truth interpolated at its time
/// ([`interpolate_pose`]). Estimates outside the ground-truth span, or whose
/// nearest ground-truth sample is more than `max_dt` seconds away (a gap in
/// the ground truth), are skipped. Both inputs must be sorted by time.
pub fn associate(est: &[StampedPose], gt: &[StampedPose], max_dt: f64) -> Vec<PosePair> {
    est.iter()
        .filter_map(|e| {
            let j = gt.partition_point(|g| g.t < e.t);
            let after = gt.get(j).map(|g| g.t - e.t);
            let before = j.checked_sub(1).and_then(|i| gt.get(i)).map(|g| e.t - g.t);
            let nearest = [before, after]
                .into_iter()
                .flatten()
                .fold(f64::INFINITY, f64::min);
            let close = nearest.is_finite() && nearest <= max_dt;
            if !close {
                return None;
            }
            interpolate_pose(gt, e.t).map(|g| (*e, g))
        })
        .collect()
}

/// How the estimate is aligned to the ground truth before the ATE.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum Alignment {
    /// No alignment (both already in the same frame).
    #[default]
    None,
    /// Yaw about `z` plus translation (4 DoF, the directions VIO cannot observe).
    PosYaw,
    /// Rotation plus translation (6 DoF), no scale.
    Se3,
}

impl Alignment {
    /// The lowercase name used on the command line and in JSON.
    pub fn as_str(self) -> &'static str {
        match self {
            Alignment::None => "none",
            Alignment::PosYaw => "posyaw",
            Alignment::Se3 => "se3",
        }
    }
}

impl fmt::Display for Alignment {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(self.as_str())
    }
}

/// An alignment name other than `none`, `posyaw` or `se3`.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
#[error("unknown alignment {0:?}: expected none, posyaw or se3")]
pub struct ParseAlignmentError(pub String);

impl FromStr for Alignment {
    type Err = ParseAlignmentError;

    fn from_str(s: &str) -> Result<Self, Self::Err> {
        match s.trim().to_ascii_lowercase().as_str() {
            "none" => Ok(Alignment::None),
            "posyaw" => Ok(Alignment::PosYaw),
            "se3" => Ok(Alignment::Se3),
            _ => Err(ParseAlignmentError(s.to_string())),
        }
    }
}

#[cfg(test)]
pub(crate) mod test_util;

#[cfg(test)]
mod tests {
    #[test]
    fn percentiles_are_nearest_rank_over_finite_values() {
        let v: Vec<f64> = (1..=100).rev().map(f64::from).collect();
        assert_eq!(percentile(v.iter().copied(), 0.99), Some(99.0));
        assert_eq!(percentile(v.iter().copied(), 0.5), Some(50.0));
        assert_eq!(percentile(v.iter().copied(), 1.0), Some(100.0));
        assert_eq!(percentile(v.iter().copied(), 0.0), Some(1.0));
        assert_eq!(percentile([f64::NAN, 3.0, f64::INFINITY], 0.5), Some(3.0));
        assert_eq!(percentile([f64::NAN], 0.5), None);
        assert_eq!(percentile_sorted(&[], 0.5), None);
        assert_eq!(percentile_sorted(&[2.0], 0.99), Some(2.0));
    }

    use super::test_util::pose;
    use super::*;
    use nalgebra::Vector3;

    #[test]
    fn alignment_names_parse_and_print_back() {
        for mode in [Alignment::None, Alignment::PosYaw, Alignment::Se3] {
            assert_eq!(mode.to_string().parse::<Alignment>().unwrap(), mode);
        }
        assert_eq!("PosYaw".parse::<Alignment>().unwrap(), Alignment::PosYaw);
        assert!("sim3".parse::<Alignment>().is_err());
        assert_eq!(serde_json::to_string(&Alignment::Se3).unwrap(), "\"se3\"");
    }

    #[test]
    fn association_interpolates_and_skips_times_outside_or_in_gaps() {
        let gt: Vec<_> = [0.0, 1.0, 2.0, 10.0]
            .iter()
            .map(|&t| pose(t, 0.0, Vector3::new(t, 0.0, 0.0)))
            .collect();
        let est: Vec<_> = [-0.5, 0.0, 0.5, 1.5, 5.0, 10.0, 10.5]
            .iter()
            .map(|&t| pose(t, 0.0, Vector3::zeros()))
            .collect();
        let pairs = associate(&est, &gt, 0.6);
        let times: Vec<f64> = pairs
            .iter()
            .map(|(e, g)| {
                assert_eq!(e.t, g.t);
                g.t
            })
            .collect();
        assert_eq!(times, vec![0.0, 0.5, 1.5, 10.0]);
        assert!((pairs[2].1.pos.x - 1.5).abs() < 1e-15);
    }
}
