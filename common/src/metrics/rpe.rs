//! Relative pose error over segments of travelled distance (as OpenVINS).

use serde::{Deserialize, Serialize};

use super::PosePair;
use crate::so3::{log_so3, Se3};

/// Segment lengths (m) of the thesis' RPE tables (Table 2.5).
pub const DEFAULT_RPE_SEGMENTS_M: [f64; 6] = [8.0, 16.0, 24.0, 32.0, 40.0, 48.0];

/// Relative pose errors of one segment length. The statistics are `None`
/// when no segment of this length fits in the trajectory (`count == 0`).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct RpeResult {
    /// Segment length along the ground-truth path (m).
    pub segment_m: f64,
    /// Mean rotation error (degrees).
    pub ori_deg_mean: Option<f64>,
    /// Mean translation error (m).
    pub pos_m_mean: Option<f64>,
    /// Median rotation error (degrees).
    pub ori_deg_median: Option<f64>,
    /// Median translation error (m).
    pub pos_m_median: Option<f64>,
    /// Number of segments.
    pub count: usize,
}

/// RPE for each length in `segment_lengths_m` (see [`DEFAULT_RPE_SEGMENTS_M`]).
///
/// For every start pose `i`, the end `j` is the first pose whose distance
/// along the ground-truth path is at least the segment length further. The
/// error is `E = (T_gt_iᵀ T_gt_j)⁻¹ (T_est_i⁻¹ T_est_j)`, reported as the angle
/// of its rotation (degrees) and the norm of its translation (m). Relative
/// motions do not depend on a rigid alignment, so none is applied.
pub fn rpe(pairs: &[PosePair], segment_lengths_m: &[f64]) -> Vec<RpeResult> {
    let mut dist = Vec::with_capacity(pairs.len());
    let mut total = 0.0;
    for (k, (_, g)) in pairs.iter().enumerate() {
        if let Some((_, prev)) = k.checked_sub(1).and_then(|p| pairs.get(p)) {
            total += (g.pos - prev.pos).norm();
        }
        dist.push(total);
    }
    let pose = |p: &crate::trajectory::StampedPose| Se3::new(p.rot, p.pos);
    segment_lengths_m
        .iter()
        .map(|&segment_m| {
            let (mut ori, mut pos) = (Vec::new(), Vec::new());
            let mut j = 0;
            for (i, (est_i, gt_i)) in pairs.iter().enumerate() {
                // The end index only moves forward as the start does.
                j = j.max(i);
                while j < dist.len() && dist[j] - dist[i] < segment_m {
                    j += 1;
                }
                let Some((est_j, gt_j)) = pairs.get(j) else {
                    break;
                };
                let gt_rel = pose(gt_i).inverse().compose(&pose(gt_j));
                let est_rel = pose(est_i).inverse().compose(&pose(est_j));
                let err = gt_rel.inverse().compose(&est_rel);
                ori.push(log_so3(&err.rot).norm().to_degrees());
                pos.push(err.trans.norm());
            }
            RpeResult {
                segment_m,
                ori_deg_mean: mean(&ori),
                pos_m_mean: mean(&pos),
                ori_deg_median: median(&mut ori),
                pos_m_median: median(&mut pos),
                count: ori.len(),
            }
        })
        .collect()
}

/// The mean, or `None` for no values.
fn mean(values: &[f64]) -> Option<f64> {
    (!values.is_empty()).then(|| values.iter().sum::<f64>() / values.len() as f64)
}

/// The median (mean of the two middle values for an even count), or `None`.
fn median(values: &mut [f64]) -> Option<f64> {
    values.sort_by(f64::total_cmp);
    let n = values.len();
    let upper = *values.get(n / 2)?;
    if n % 2 == 1 {
        return Some(upper);
    }
    Some(0.5 * (upper + values.get(n / 2 - 1).copied().unwrap_or(upper)))
}

#[cfg(test)]
mod tests {
    use super::super::test_util::{pose, wiggly};
    use super::*;
    use nalgebra::Vector3;

    #[test]
    fn a_ten_percent_scale_error_on_a_straight_line_gives_ten_percent_of_each_segment() {
        // 1 m steps along x from 0 to 100 m; the estimate travels 1.1 m per step.
        let pairs: Vec<PosePair> = (0..=100)
            .map(|i| {
                let x = i as f64;
                let gt = pose(x, 0.3, Vector3::new(x, 0.0, 0.0));
                let est = pose(x, 0.3, Vector3::new(1.1 * x, 0.0, 0.0));
                (est, gt)
            })
            .collect();
        let results = rpe(&pairs, &DEFAULT_RPE_SEGMENTS_M);
        assert_eq!(results.len(), 6);
        for r in &results {
            assert_eq!(r.count, 101 - r.segment_m as usize);
            let expected = 0.1 * r.segment_m;
            assert!((r.pos_m_mean.unwrap() - expected).abs() < 1e-9, "{r:?}");
            assert!((r.pos_m_median.unwrap() - expected).abs() < 1e-9, "{r:?}");
            assert!(r.ori_deg_mean.unwrap() < 1e-9);
            assert!(r.ori_deg_median.unwrap() < 1e-9);
        }
    }

    #[test]
    fn segments_longer_than_the_path_have_no_statistics() {
        let gt = wiggly(50);
        let pairs: Vec<PosePair> = gt.iter().map(|p| (*p, *p)).collect();
        let results = rpe(&pairs, &[1.0, 1000.0]);
        assert!(results[0].count > 0);
        assert!(results[0].pos_m_mean.unwrap() < 1e-12);
        assert!(results[0].ori_deg_median.unwrap() < 1e-9);
        assert_eq!(results[1].count, 0);
        assert_eq!(results[1].pos_m_mean, None);
        assert_eq!(results[1].ori_deg_median, None);
        assert!(rpe(&[], &[8.0]).iter().all(|r| r.count == 0));
    }

    #[test]
    fn a_constant_yaw_rate_error_shows_up_as_rotation_error_per_segment() {
        // Straight line at 1 m/step; the estimate turns 0.01 rad per step in place.
        let pairs: Vec<PosePair> = (0..=40)
            .map(|i| {
                let x = i as f64;
                let p = Vector3::new(x, 0.0, 0.0);
                (pose(x, 0.01 * x, p), pose(x, 0.0, p))
            })
            .collect();
        let r = &rpe(&pairs, &[10.0])[0];
        assert_eq!(r.count, 31);
        assert!((r.ori_deg_mean.unwrap() - 0.1f64.to_degrees()).abs() < 1e-9);
    }

    #[test]
    fn the_median_of_an_even_count_averages_the_middle_values() {
        assert_eq!(median(&mut [4.0, 1.0, 3.0, 2.0]), Some(2.5));
        assert_eq!(median(&mut [5.0, 1.0, 3.0]), Some(3.0));
        assert_eq!(median(&mut []), None);
    }
}
