//! The cooperative steps of a frame (thesis Section 5.3), between the estimator's
//! frame flow and the updaters: which CI weights, which of our tracks go to the
//! common updates, what each did and what it cost.

use super::chi2::Chi2Table;
use super::feature_db::FeatureDb;
use super::options::EstimatorOptions;
use super::state::State;
use super::triangulation::TriangulationOptions;
use super::updater_ci::CiWeights;
use super::updater_common::{self, CommonStats};
use super::updater_common_slam;
use crate::cooperation::loop_closure::FrameFeatures;
use crate::cooperation::{Cooperation, Evidence};
use common::estimator_options::{CiWeighting, CooperationOptions};
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
    /// Matching and loop-closure detection, ms.
    pub matching_ms: f64,
    /// Common VIO update, ms.
    pub common_vio_ms: f64,
    /// Common SLAM measurement update, ms.
    pub common_slam_ms: f64,
    /// Constraint update, ms.
    pub constraint_ms: f64,
}

impl CoopFrameStats {
    /// Features whose peer information went into an update this frame.
    pub fn updates(&self) -> usize {
        self.common_vio.used + self.common_slam.used + self.constraints.used
    }
}

/// The CI weights of the options; `constraint` picks the constraint update's.
pub fn weights(opts: &CooperationOptions, constraint: bool) -> CiWeights {
    match opts.ci_weighting {
        CiWeighting::FixedPeer if constraint => CiWeights::FixedPeer(opts.constraint_peer_weight),
        CiWeighting::FixedPeer => CiWeights::FixedPeer(opts.ci_peer_weight),
        CiWeighting::FixedOwn => CiWeights::FixedOwn(opts.ci_own_weight),
        CiWeighting::MinTrace => CiWeights::MinTrace,
        CiWeighting::MinDeterminant => CiWeights::MinDeterminant,
    }
}

/// Our frame's features for the matcher: ids, descriptors and the normalized
/// coordinates recorded for clone `key`.
pub fn frame_features(frame: &FeatureFrame, db: &FeatureDb, key: u64) -> FrameFeatures {
    let mut out = FrameFeatures::default();
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

/// Common VIO features: returns our tracks whose measurements were used (the
/// rest of `ev.vio` falls back to the independent MSCKF update).
#[allow(clippy::too_many_arguments)]
pub fn common_vio(
    state: &mut State,
    db: &FeatureDb,
    ev: &Evidence,
    opts: &EstimatorOptions,
    chi2: &Chi2Table,
    tri: &TriangulationOptions,
    stats: &mut CoopFrameStats,
) -> Vec<u64> {
    if ev.vio.is_empty() {
        return Vec::new();
    }
    let t = Instant::now();
    let w = weights(&opts.cooperation, false);
    let out = updater_common::update(state, db, &ev.vio, &ev.participants, opts, &w, chi2, tri);
    stats.common_vio = out.stats;
    stats.common_vio_ms = t.elapsed().as_secs_f64() * 1e3;
    out.used
}

/// Common SLAM features: the constraint updates, then the peers' measurements.
/// Returns the features used by each, for [`Cooperation::mark_used`].
pub fn common_slam(
    state: &mut State,
    ev: &Evidence,
    opts: &EstimatorOptions,
    chi2: &Chi2Table,
    stats: &mut CoopFrameStats,
) -> (Vec<u64>, Vec<u64>) {
    let mut used_constraints = Vec::new();
    if !ev.constraints.is_empty() {
        let t = Instant::now();
        let w = weights(&opts.cooperation, true);
        let out = updater_common_slam::constraint_update(state, &ev.constraints, opts, &w, chi2);
        stats.constraints = out.stats;
        stats.constraint_ms = t.elapsed().as_secs_f64() * 1e3;
        used_constraints = out.used;
    }
    let mut used = Vec::new();
    if !ev.slam.is_empty() {
        let t = Instant::now();
        let w = weights(&opts.cooperation, false);
        let out = updater_common_slam::measurement_update(
            state,
            &ev.slam,
            &ev.participants,
            opts,
            &w,
            chi2,
        );
        stats.common_slam = out.stats;
        stats.common_slam_ms = t.elapsed().as_secs_f64() * 1e3;
        used = out.used;
    }
    (used, used_constraints)
}

/// Records which participants were involved, and marks the used measurements.
pub fn finish(
    coop: &mut Cooperation,
    ev: &Evidence,
    used: (&[u64], &[u64], &[u64]),
    stats: &mut CoopFrameStats,
) {
    stats.participants = ev.participants.len();
    stats.historical_participants = ev.historical.iter().filter(|h| **h).count();
    coop.mark_used(ev, used.0, used.1, used.2);
}
