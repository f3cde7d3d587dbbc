//! The cooperative steps of a frame (thesis Section 5.3), between the estimator's
//! frame flow and the updaters: which CI weights, which of our tracks go to the
//! common updates, what each did and what it cost.

use super::chi2::Chi2Table;
use super::ci_diagnostics;
use super::ci_system::{self, CiRows};
use super::feature_db::FeatureDb;
use super::options::EstimatorOptions;
use super::state::State;
use super::triangulation::TriangulationOptions;
use super::updater_common::{self, CommonOutcome, CommonStats};
use super::updater_common_slam;
use super::window_gate;
use crate::cooperation::loop_closure::FrameFeatures;
use crate::cooperation::{Cooperation, Evidence};
use common::measurement::FeatureFrame;
use std::time::Instant;

/// What the cooperative updates of one frame did, and their cost.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct CoopFrameStats {
    /// Common VIO features (window and historical).
    pub common_vio: CommonStats,
    /// Common SLAM features updated with peers' measurements.
    pub common_slam: CommonStats,
    /// SLAM-to-SLAM constraint updates.
    pub constraints: CommonStats,
    /// Peer windows involved.
    pub participants: usize,
    /// Of which historical keyframe windows.
    pub historical_participants: usize,
    /// Participants of the CI-EKF update (windows' poses and landmark sets).
    pub ci_participants: usize,
    /// Our CI weight `ω_i` in that update (1 without one).
    pub omega_own: f64,
    /// Matching and loop-closure detection, ms.
    pub matching_ms: f64,
    /// Gathering the peers' measurements behind our tracks' links (the
    /// evidence), ms.
    pub evidence_ms: f64,
    /// Common VIO rows (triangulation, projection, gating), ms.
    pub common_vio_ms: f64,
    /// Common SLAM measurement rows, ms.
    pub common_slam_ms: f64,
    /// Constraint rows, ms.
    pub constraint_ms: f64,
    /// Our own rows' EKF update and the one CI-EKF update, ms.
    pub ci_update_ms: f64,
}

impl CoopFrameStats {
    /// Features whose peer information went into an update this frame.
    pub fn updates(&self) -> usize {
        self.common_vio.used + self.common_slam.used + self.constraints.used
    }
}

/// Our frame's features for the matcher: ids, descriptors and the normalized
/// coordinates recorded for clone `key`.
pub fn frame_features(frame: &FeatureFrame, db: &FeatureDb, key: u64) -> FrameFeatures {
    let mut out = FrameFeatures {
        t_s: frame.t,
        ..FrameFeatures::default()
    };
    for f in &frame.features {
        let Some(m) = db.get(f.id).and_then(|t| t.measurement_at(key)) else {
            continue;
        };
        out.ids.push(f.id);
        out.descriptors.push(f.descriptor);
        out.xy.push(m.uvn);
    }
    out
}

/// Which of our tracks the cooperative update used, and which common VIO
/// tracks fall back to the independent MSCKF update.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct CoopUse {
    /// Common VIO tracks used.
    pub vio: Vec<u64>,
    /// Common VIO tracks not used (gated out or failed).
    pub vio_fallback: Vec<u64>,
    /// SLAM features updated with peers' measurements.
    pub slam: Vec<u64>,
    /// SLAM features updated with a constraint.
    pub constraints: Vec<u64>,
}

fn ms(t: Instant) -> f64 {
    t.elapsed().as_secs_f64() * 1e3
}

/// The frame's cooperative update (thesis Section 5.3): the rows of the common
/// VIO tracks, of the peers' measurements of our SLAM features and of the SLAM
/// constraints, all at the current estimate; our own rows of the common tracks
/// by a standard EKF update; everything relating us to peers in one CI-EKF
/// update.
pub fn update(
    state: &mut State,
    db: &FeatureDb,
    ev: &Evidence,
    opts: &EstimatorOptions,
    chi2: &Chi2Table,
    tri: &TriangulationOptions,
    stats: &mut CoopFrameStats,
) -> CoopUse {
    let mut used = CoopUse::default();
    if ev.vio.is_empty() && ev.slam.is_empty() && ev.constraints.is_empty() {
        return used;
    }
    let p = &ev.participants;
    let t = Instant::now();
    let mut vio = updater_common::rows(state, db, &ev.vio, p, opts, chi2, tri);
    stats.common_vio_ms = ms(t);
    let t = Instant::now();
    let (mut slam_rows, mut slam) =
        updater_common_slam::measurement_blocks(state, &ev.slam, p, opts, chi2);
    stats.common_slam_ms = ms(t);
    let t = Instant::now();
    let (constraint_rows, mut constraints) =
        updater_common_slam::constraint_blocks(state, &ev.constraints, p, opts, chi2);
    stats.constraint_ms = ms(t);
    let t = Instant::now();
    let n_slam = slam_rows.len();
    slam_rows.extend(constraint_rows);
    let debug = ci_diagnostics::enabled();
    let before = debug.then(|| state.means.imu.clone());
    let own_applied = updater_common::apply_own_rows(state, &mut vio, &mut slam_rows);
    let after_own = debug.then(|| state.means.imu.clone());
    let mut rows = std::mem::take(&mut vio.ci);
    let n_vio = rows.len();
    rows.extend(slam_rows);
    if debug {
        ci_diagnostics::log_consistency(state, &rows, n_vio, p);
    }
    if opts.cooperation.window_gate {
        let limit = |m: usize| opts.chi2_multiplier * chi2.get(m);
        let out = window_gate::rejected(state, &rows, p, limit);
        if !out.is_empty() {
            let (v, s, c) = (&mut vio.outcome, &mut slam, &mut constraints);
            leave_out(&mut rows, &out, [(n_vio, v), (n_slam, s)], c, own_applied);
        }
    }
    let result = ci_system::update(state, &rows, p, &opts.cooperation);
    let ok = result.is_ok();
    if let Ok(Some(o)) = &result {
        stats.ci_participants = o.omega_peers.len();
        stats.omega_own = o.omega_own;
        if let (Some(b), Some(a)) = (&before, &after_own) {
            ci_diagnostics::log_moves(state, &rows, o, b, a);
        }
    }
    stats.ci_update_ms = ms(t);
    if !ok {
        updater_common::fall_back(&mut vio.outcome, own_applied);
    }
    stats.common_vio = vio.outcome.stats;
    stats.common_slam = slam.stats;
    stats.constraints = constraints.stats;
    used.vio_fallback = vio.outcome.fallback;
    if ok {
        used.vio = vio.outcome.used;
        used.slam = slam.used;
        used.constraints = constraints.used;
    } else {
        stats.common_slam.used = 0;
        stats.constraints.used = 0;
    }
    used
}

/// Removes blocks `out` (ascending) of `rows`, which hold the common VIO
/// blocks, then the SLAM measurement blocks, then the constraint blocks, in
/// the orders of their outcomes' `used` lists (the first two kinds with their
/// counts): each left-out block is counted as gated out. A common VIO track
/// whose own rows were applied does not fall back to the MSCKF (its
/// measurements are spent).
fn leave_out(
    rows: &mut Vec<CiRows>,
    out: &[usize],
    counted: [(usize, &mut CommonOutcome); 2],
    constraints: &mut CommonOutcome,
    own_applied: bool,
) {
    let [(n_vio, vio), (n_slam, slam)] = counted;
    // From the last, so that the indices before stay valid.
    for &i in out.iter().rev() {
        let (outcome, j, falls_back) = if i < n_vio {
            (&mut *vio, i, !own_applied)
        } else if i < n_vio + n_slam {
            (&mut *slam, i - n_vio, true)
        } else {
            (&mut *constraints, i - n_vio - n_slam, true)
        };
        let block = rows.remove(i);
        if j < outcome.used.len() {
            let id = outcome.used.remove(j);
            if falls_back {
                outcome.fallback.push(id);
            }
            outcome.stats.used = outcome.stats.used.saturating_sub(1);
            outcome.stats.rejected_chi2 += 1;
            outcome.stats.ci_rows = outcome.stats.ci_rows.saturating_sub(block.res.len());
        }
    }
}

/// Records which participants were involved, and marks the used measurements.
pub fn finish(coop: &mut Cooperation, ev: &Evidence, used: &CoopUse, stats: &mut CoopFrameStats) {
    stats.participants = ev.participants.len();
    stats.historical_participants = ev.historical.iter().filter(|h| **h).count();
    coop.mark_used(ev, &used.vio, &used.slam, &used.constraints);
}

#[cfg(test)]
mod tests {
    use super::*;
    use nalgebra::{DMatrix, DVector};

    fn block(m: usize) -> CiRows {
        CiRows {
            vars: Vec::new(),
            h: DMatrix::zeros(m, 0),
            res: DVector::zeros(m),
            peers: Vec::new(),
        }
    }

    fn outcome(ids: &[u64], rows: usize) -> CommonOutcome {
        let mut o = CommonOutcome {
            used: ids.to_vec(),
            ..CommonOutcome::default()
        };
        o.stats.used = ids.len();
        o.stats.ci_rows = rows;
        o
    }

    /// Blocks left out by the window gate leave their outcome's used list and
    /// count as gated out; a common VIO track whose own rows were applied
    /// does not fall back to the MSCKF, the rest do.
    #[test]
    fn blocks_left_out_are_counted_as_gated_out_of_their_kind() {
        // Common VIO 10, 11 (3 rows each), SLAM 20, 21, 22 (2), constraint 30 (3).
        let sizes = [3, 3, 2, 2, 2, 3];
        for own_applied in [true, false] {
            let mut rows: Vec<CiRows> = sizes.iter().map(|&m| block(m)).collect();
            let mut vio = outcome(&[10, 11], 6);
            let mut slam = outcome(&[20, 21, 22], 6);
            let mut constraints = outcome(&[30], 3);
            leave_out(
                &mut rows,
                &[1, 3, 5],
                [(2, &mut vio), (3, &mut slam)],
                &mut constraints,
                own_applied,
            );
            assert_eq!(rows.len(), 3);
            assert_eq!((vio.used.clone(), vio.stats.used), (vec![10], 1));
            assert_eq!((slam.used.clone(), slam.stats.used), (vec![20, 22], 2));
            assert!(constraints.used.is_empty() && constraints.stats.used == 0);
            assert_eq!(vio.fallback.is_empty(), own_applied);
            assert_eq!(
                (slam.fallback.clone(), constraints.fallback.clone()),
                (vec![21], vec![30])
            );
            for (o, rows_left) in [(&vio, 3), (&slam, 4), (&constraints, 0)] {
                assert_eq!(o.stats.rejected_chi2, 1);
                assert_eq!(o.stats.ci_rows, rows_left);
            }
        }
    }
}
