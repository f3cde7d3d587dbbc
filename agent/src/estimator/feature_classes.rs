//! What happens to each feature of a frame: its measurement is recorded, it is
//! sorted into one class (thesis Section 5.3: VIO/MSCKF, SLAM update, SLAM
//! initialization), and after the updates the used or lost ones are cleaned up.

use super::feature_db::{FeatureDb, FeatureMeasurement};
use super::feature_system::camera_pose;
use super::filter::Filter;
use super::options::EstimatorOptions;
use super::slam_feature;
use super::state::{Means, Var};
use common::measurement::FeatureFrame;
use nalgebra::Vector3;

/// The features of one frame by the update they go to. A feature is in at most
/// one of `slam_seen`, `slam_candidates`, `msckf_ids`.
#[derive(Clone, Debug, Default)]
pub struct FeatureClasses {
    /// SLAM features observed in this frame.
    pub slam_seen: Vec<u64>,
    /// Tracks spanning the window that become SLAM features (if there is room).
    pub slam_candidates: Vec<u64>,
    /// Lost tracks and tracks leaving the window, longest first: the MSCKF's
    /// candidates, taken in this order up to its per-update cap.
    pub msckf_ids: Vec<u64>,
    /// The candidates the MSCKF did not reach once its cap was full ([`Self::defer`])
    /// and the untriangulated ones still seen ([`Self::retry_untriangulated`]): their
    /// tracks go on (the measurement at the leaving clone leaves with it) and come
    /// back as candidates in a later frame, as OpenVINS keeps them. Dropping them
    /// instead emptied the whole window at once after the first full update on
    /// slow starts.
    pub deferred: Vec<u64>,
    /// The second-newest clone when it leaves the window instead of the oldest
    /// (which then stays): it moved less than `keyframe_parallax_px` from the clone before it
    /// ([`non_keyframe`]). Its views leave with it unused, and no track is sent
    /// to the MSCKF for it.
    pub dropped_clone: Option<u64>,
}

impl FeatureClasses {
    /// Keeps the tracks of `ids`, candidates the MSCKF did not reach this frame.
    pub fn defer(&mut self, ids: &[u64]) {
        for id in ids {
            if !self.deferred.contains(id) {
                self.deferred.push(*id);
            }
        }
    }

    /// The MSCKF's candidates and then the SLAM candidates.
    pub fn candidates(&self) -> Vec<u64> {
        self.msckf_ids
            .iter()
            .chain(&self.slam_candidates)
            .copied()
            .collect()
    }

    /// Keeps the tracks of every MSCKF and SLAM candidate, for a first update
    /// that waits (`slow_start`).
    pub fn keep_all_candidates(&mut self) {
        self.defer(&self.candidates());
    }

    /// Takes `ids` out of [`Self::deferred`]: another update (e.g. a cooperative
    /// one) has used their measurements, which must not be used again.
    pub fn mark_used(&mut self, ids: &[u64]) {
        self.deferred.retain(|id| !ids.contains(id));
    }

    /// Keeps the tracks of `untriangulated` MSCKF features and SLAM candidates
    /// that frame `key` still sees, like [`Self::deferred`]: they lacked the
    /// parallax (slow motion) and are tried again next frame with a wider
    /// baseline (their retired rays, `feature_system::build`), instead of
    /// restarting from one view. Lost tracks go as before. On V1_01's slow
    /// flight a quarter of the window-spanning tracks fail the condition limit
    /// (20 seeds: 0.453 -> 0.356 deg, 0.064 -> 0.052 m with SLAM features). A
    /// SLAM candidate dropped on its first failure left a slow flight nothing to
    /// update with: every track that came to span the window was tried once and
    /// deleted (V1_01 at 0.4 of its speed, 10 seeds: 5 runs diverged, none with
    /// the candidates kept and the retired rays).
    pub fn retry_untriangulated(&mut self, db: &FeatureDb, key: u64, untriangulated: &[u64]) {
        for id in untriangulated {
            let seen = db.get(*id).is_some_and(|f| f.has_measurement_at(key));
            if seen && !self.deferred.contains(id) {
                self.deferred.push(*id);
            }
        }
    }
}

/// Adds the frame's observations (undistorted with the current intrinsics) to the
/// database under clone `key`, the stored ones undistorted again first if the
/// intrinsics moved ([`FeatureDb::follow_intrinsics`]). A track with an
/// impossible jump restarts.
pub fn record_measurements(db: &mut FeatureDb, state: &Means, frame: &FeatureFrame, key: u64) {
    db.follow_intrinsics(&state.calib.camera);
    for f in &frame.features {
        let Ok(uvn) = state.calib.camera.undistort(&f.uv) else {
            continue;
        };
        let m = FeatureMeasurement {
            clone_key: key,
            t: frame.t,
            uv: f.uv,
            uvn,
        };
        if db.insert(f.id, m).is_err() {
            // An impossible jump: the track restarts from this observation.
            db.remove(f.id);
            let _ = db.insert(f.id, m);
        }
    }
}

/// Sorts the tracks after frame `key` into classes (OpenVINS's selection: lost
/// tracks and tracks seen by the clone about to leave go to the MSCKF, unless they
/// span the whole window and there is room for a SLAM feature).
pub fn classify(
    db: &FeatureDb,
    state: &Means,
    key: u64,
    opts: &EstimatorOptions,
    slam_allowed: bool,
) -> FeatureClasses {
    let oldest = state.clones.keys().next().copied().unwrap_or(key);
    let lost = db.ids_not_seen_since(key);
    let dropped_clone = non_keyframe(db, state, opts.keyframe_parallax_px);
    let at_marg = if state.clones.len() > opts.max_clones && dropped_clone.is_none() {
        db.ids_with_measurement_at(oldest)
    } else {
        Vec::new()
    };
    let slam_seen: Vec<u64> = state
        .features
        .keys()
        .copied()
        .filter(|id| db.get(*id).is_some_and(|f| f.has_measurement_at(key)))
        .collect();
    let room = if slam_allowed {
        opts.max_slam_features
            .saturating_sub(state.features.len())
            .min(opts.max_slam_in_update)
    } else {
        0
    };
    let mut c = FeatureClasses {
        slam_seen,
        dropped_clone,
        ..FeatureClasses::default()
    };
    for id in lost.iter().chain(at_marg.iter()) {
        if state.features.contains_key(id) {
            continue;
        }
        let Some(f) = db.get(*id) else {
            continue;
        };
        let spans = f.measurements.len() > opts.max_clones;
        if spans && !lost.contains(id) && c.slam_candidates.len() < room {
            c.slam_candidates.push(*id);
        } else if !c.msckf_ids.contains(id) {
            c.msckf_ids.push(*id);
        }
    }
    // The longest tracks first: the MSCKF takes them in this order up to its cap.
    c.msckf_ids.sort_by_key(|id| {
        std::cmp::Reverse(db.get(*id).map(|f| f.measurements.len()).unwrap_or(0))
    });
    c
}

/// Tracks a parallax is measured over, at least: fewer say little about the
/// scene, and the clone stays.
const MIN_TRACKS_FOR_PARALLAX: usize = 10;

/// The second-newest clone, when the median rotation-compensated angle between
/// its views and those of the clone before it (the last one kept) is under
/// `min_parallax_px` pixels: it adds little baseline to the window, so it leaves
/// rather than the oldest, and the window keeps the span that lets a slow
/// flight's tracks triangulate (VINS-Mono's keyframe rule; README, Slow flights).
/// `None` when the rule is off (0), the window holds fewer than three clones, or
/// fewer than [`MIN_TRACKS_FOR_PARALLAX`] tracks join the two views.
pub fn non_keyframe(db: &FeatureDb, state: &Means, min_parallax_px: f64) -> Option<u64> {
    let mut keys = state.clones.keys().rev();
    let (_newest, second, kept) = (keys.next()?, *keys.next()?, *keys.next()?);
    if min_parallax_px <= 0.0 {
        return None;
    }
    (parallax_px(db, state, kept, second)? < min_parallax_px).then_some(second)
}

/// The median rotation-compensated angle between the views of clones `a` and
/// `b` over the tracks both saw, in pixels of focal length; `None` when fewer
/// than [`MIN_TRACKS_FOR_PARALLAX`] tracks join them.
pub fn parallax_px(db: &FeatureDb, state: &Means, a: u64, b: u64) -> Option<f64> {
    let (r_a, _) = camera_pose(state, a)?;
    let (r_b, _) = camera_pose(state, b)?;
    let mut angles: Vec<f64> = db
        .iter()
        .filter_map(|f| {
            let ua = f.measurement_at(a)?.uvn;
            let ub = f.measurement_at(b)?.uvn;
            let ray_a = r_a * Vector3::new(ua.x, ua.y, 1.0);
            let ray_b = r_b * Vector3::new(ub.x, ub.y, 1.0);
            Some(ray_a.angle(&ray_b))
        })
        .collect();
    if angles.len() < MIN_TRACKS_FOR_PARALLAX {
        return None;
    }
    let mid = angles.len() / 2;
    let (_, median, _) = angles.select_nth_unstable_by(mid, f64::total_cmp);
    Some(*median * state.calib.camera.fx())
}

/// The parallax between the window's oldest and newest clones ([`parallax_px`]).
pub fn window_parallax_px(db: &FeatureDb, state: &Means) -> Option<f64> {
    let oldest = *state.clones.keys().next()?;
    let newest = *state.clones.keys().next_back()?;
    parallax_px(db, state, oldest, newest)
}

/// Drops the second-newest clone if it is not a keyframe ([`non_keyframe`]), as
/// a frame with no update does while the window fills: the window fills with
/// keyframes, and the first update has their baseline.
pub fn drop_non_keyframe<F: Filter + ?Sized>(
    db: &mut FeatureDb,
    state: &mut F,
    min_parallax_px: f64,
) {
    if let Some(key) = non_keyframe(db, state.means(), min_parallax_px) {
        drop_clone(db, state, key);
    }
}

/// Marginalizes clone `key` and drops its views unused (its anchored features
/// move to the newest clone first).
fn drop_clone<F: Filter + ?Sized>(db: &mut FeatureDb, state: &mut F, key: u64) {
    if let Some(&newest) = state.means().clones.keys().next_back() {
        slam_feature::reanchor(state, key, newest);
    }
    let _ = state.marginalize(Var::Clone(key));
    db.remove_measurements_at(key);
}

/// After the updates: forgets used tracks (all but the deferred candidates), keeps
/// SLAM features' tracks empty
/// (each measurement is used once), marginalizes lost SLAM features, and slides
/// the window (re-anchoring anchored features first). The views of the clone
/// that leaves stay with the tracks that go on as rays from its last pose
/// ([`FeatureDb::retire_measurements_before`]).
pub fn clean_up<F: Filter + ?Sized>(
    db: &mut FeatureDb,
    state: &mut F,
    c: &FeatureClasses,
    max_clones: usize,
) {
    let done = c
        .msckf_ids
        .iter()
        .chain(c.slam_candidates.iter())
        .filter(|id| !c.deferred.contains(id));
    for id in done {
        if !state.means().features.contains_key(id) {
            db.remove(*id);
        }
    }
    let slam_candidates = c
        .slam_candidates
        .iter()
        .filter(|id| !c.deferred.contains(id));
    for id in c.slam_seen.iter().chain(slam_candidates) {
        if let Some(f) = db.get_mut(*id) {
            f.measurements.clear();
        }
    }
    let lost_slam: Vec<u64> = state
        .means()
        .features
        .keys()
        .copied()
        .filter(|id| !c.slam_seen.contains(id) && !c.slam_candidates.contains(id))
        .collect();
    for id in lost_slam {
        let _ = state.marginalize(Var::Feature(id));
        db.remove(id);
    }
    if let Some(dropped) = c.dropped_clone {
        drop_clone(db, state, dropped);
    }
    while state.means().clones.len() > max_clones {
        let Some(&old) = state.means().clones.keys().next() else {
            break;
        };
        if let Some(&newest) = state.means().clones.keys().next_back() {
            slam_feature::reanchor(state, old, newest);
        }
        // The leaving camera's pose, kept with the views it leaves behind: a
        // slow track triangulates over a longer baseline (`feature_system::build`).
        let pose = camera_pose(state.means(), old);
        let _ = state.marginalize(Var::Clone(old));
        if let Some(&next) = state.means().clones.keys().next() {
            db.retire_measurements_before(next, |k| pose.filter(|_| k == old));
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::estimator::test_scene::scene;

    #[test]
    fn candidates_beyond_the_cap_keep_their_tracks_for_a_later_frame() {
        // 12 clones, one more than the window: every track is seen by the leaving
        // clone, so all 6 are MSCKF candidates; an update capped at 2 reaches 2.
        let mut s = scene(12, 6, 1e-4, 1e-4);
        let opts = EstimatorOptions {
            max_clones: 11,
            max_msckf_in_update: 2,
            ..EstimatorOptions::default()
        };
        let key = 12;
        let mut c = classify(&s.db, &s.state.means, key, &opts, false);
        assert_eq!(c.msckf_ids.len(), 6);
        assert!(c.deferred.is_empty());
        let ids = c.msckf_ids.clone();
        let (used, unreached) = ids.split_at(2);
        c.defer(unreached);
        assert_eq!(c.deferred.len(), 4);
        // A cooperative update took one of the deferred tracks.
        let taken = c.deferred[0];
        c.mark_used(&[taken]);

        clean_up(&mut s.db, &mut s.state, &c, opts.max_clones);
        assert_eq!(s.state.means.clones.len(), 11);
        for id in used.iter().chain([&taken]) {
            assert!(!s.db.contains(*id), "used track {id} kept");
        }
        for id in &c.deferred {
            let f = s.db.get(*id).expect("deferred track dropped");
            // Only the measurement of the marginalized clone went away.
            assert_eq!(f.measurements.len(), 11, "track {id}");
            assert!(f.measurements.iter().all(|m| m.clone_key >= 2));
        }
    }

    #[test]
    fn untriangulated_tracks_still_seen_are_tried_again_lost_ones_go() {
        let mut s = scene(12, 6, 1e-4, 1e-4);
        let opts = EstimatorOptions {
            max_clones: 11,
            ..EstimatorOptions::default()
        };
        let key = 12;
        let mut c = classify(&s.db, &s.state.means, key, &opts, false);
        let (seen, lost) = (c.msckf_ids[0], c.msckf_ids[1]);
        // `lost` was not seen by the newest image.
        if let Some(f) = s.db.get_mut(lost) {
            f.measurements.retain(|m| m.clone_key != key);
        }
        c.retry_untriangulated(&s.db, key, &[seen, lost, seen]);
        assert_eq!(c.deferred, vec![seen]);

        clean_up(&mut s.db, &mut s.state, &c, opts.max_clones);
        let f = s.db.get(seen).expect("a track still seen is kept");
        assert_eq!(f.measurements.len(), 11);
        assert!(!s.db.contains(lost), "a lost track is dropped");
    }

    #[test]
    fn a_clone_that_moved_too_little_leaves_instead_of_the_oldest() {
        let mut s = scene(12, 12, 1e-4, 1e-4);
        let key = 12;
        let second = 11;
        // Off, or a threshold every clone passes: the oldest leaves as before.
        for px in [0.0, 1e-9] {
            assert_eq!(non_keyframe(&s.db, &s.state.means, px), None);
        }
        let opts = EstimatorOptions {
            max_clones: 11,
            keyframe_parallax_px: 1e9,
            ..EstimatorOptions::default()
        };
        let c = classify(&s.db, &s.state.means, key, &opts, false);
        assert_eq!(c.dropped_clone, Some(second));
        // No track goes to the MSCKF for the clone that leaves.
        assert!(c.msckf_ids.is_empty(), "{:?}", c.msckf_ids);
        let oldest = *s.state.means.clones.keys().next().expect("clones");
        clean_up(&mut s.db, &mut s.state, &c, opts.max_clones);
        let keys: Vec<u64> = s.state.means.clones.keys().copied().collect();
        assert_eq!(keys.len(), 11);
        assert!(keys.contains(&oldest) && keys.contains(&key));
        assert!(!keys.contains(&second));
        for f in s.db.iter() {
            assert!(
                !f.has_measurement_at(second),
                "track {} keeps a dropped view",
                f.id
            );
            assert_eq!(f.measurements.len(), 11);
        }
    }
}
