//! SLAM updates paced by image motion on a keyframe window.
//!
//! A SLAM feature in the state takes its newest view in every frame's update
//! (`updater_slam::update`), each view weighed as independent of the last.
//! A feature tracked in camera images is not: the tracker's error persists
//! from one frame to the next (KLT drift, docs/evidence/single_robot.md,
//! stop 59), so a platform that moves slowly, and sees the same views over
//! many frames, counts that error again at every frame and grows
//! overconfident. V1_01 played at 0.3 of its speed and rendered, with SLAM
//! features, seeds 1-8: orientation NEES 3.94 (2.5-6.7 a run), against 1.2-2.0
//! at full speed (stop 78); paced as below, 3.04, lower in every seed (README,
//! Slow flights).
//!
//! On a keyframe window (a slow start, a flight found slow, or
//! `keyframe_parallax_px` set), the window keeps only the views that moved;
//! with `EstimatorOptions::slam_keyframe_updates` a SLAM feature then takes a
//! view only once its image point has moved the keyframe parallax since the
//! last view it took. Simulated features have white pixel noise, where every
//! frame is new information, so the option is off for them and on for
//! tracked images (`EstimatorOptions::for_tracked_images`, rendered fleets).

use super::feature_db::FeatureDb;
use super::options::EstimatorOptions;
use super::state::Means;
use nalgebra::Vector2;
use std::collections::BTreeMap;

/// The view each SLAM feature last took, as its raw pixel: compared in
/// normalized coordinates with the intrinsics of the frame that compares,
/// since online calibration moves the rays of a pixel while it converges
/// (`FeatureDb::follow_intrinsics`).
#[derive(Clone, Debug, Default)]
pub struct SlamPacing {
    last_uv: BTreeMap<u64, Vector2<f64>>,
}

impl SlamPacing {
    /// The SLAM features of `seen` that take their view in clone `key` this
    /// frame; `None` when every one does (no keyframe window, or
    /// `slam_keyframe_updates` off). `opts` are this frame's (after
    /// `SlowStart::apply`).
    pub fn due_in_frame(
        &mut self,
        db: &FeatureDb,
        means: &Means,
        seen: &[u64],
        key: u64,
        opts: &EstimatorOptions,
    ) -> Option<Vec<u64>> {
        if !opts.slam_keyframe_updates || opts.keyframe_parallax_px <= 0.0 {
            return None;
        }
        // A SLAM feature not seen now has left the state (`clean_up`).
        self.retain(|id| seen.contains(&id));
        let views = seen.iter().filter_map(|&id| {
            let m = db.get(id)?.measurement_at(key)?;
            Some((id, m.uv))
        });
        let camera = &means.calib.camera;
        let min_normalized = opts.keyframe_parallax_px / camera.fx();
        Some(self.due(views, |uv| camera.undistort(uv).ok(), min_normalized))
    }

    /// The features of `seen` (id and this frame's raw pixel) whose point, as
    /// `ray` (the current intrinsics) undistorts it, moved at least
    /// `min_normalized` from the view each took last, or that took none yet
    /// (or whose views `ray` cannot undistort); those are remembered as taking
    /// this view. With `min_normalized` 0 (no pacing) every feature is due.
    pub fn due(
        &mut self,
        seen: impl IntoIterator<Item = (u64, Vector2<f64>)>,
        ray: impl Fn(&Vector2<f64>) -> Option<Vector2<f64>>,
        min_normalized: f64,
    ) -> Vec<u64> {
        let mut due = Vec::new();
        for (id, uv) in seen {
            let moved = self
                .last_uv
                .get(&id)
                .is_none_or(|last| match (ray(&uv), ray(last)) {
                    (Some(now), Some(then)) => (now - then).norm() >= min_normalized,
                    _ => true,
                });
            if moved {
                self.last_uv.insert(id, uv);
                due.push(id);
            }
        }
        due
    }

    /// Forgets the features `keep` says are gone.
    pub fn retain(&mut self, keep: impl Fn(u64) -> bool) {
        self.last_uv.retain(|id, _| keep(*id));
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::estimator::test_scene::scene;
    use common::camera::CameraModel;

    #[test]
    fn only_a_keyframe_window_of_tracked_images_paces_the_slam_updates() {
        let s = scene(4, 6, 1e-4, 1e-4);
        let means = &s.state.means;
        let key = *means.clones.keys().next_back().expect("clones");
        let seen: Vec<u64> = s.db.iter().map(|f| f.id).collect();
        let mut p = SlamPacing::default();
        let tracked = EstimatorOptions::for_tracked_images();
        assert_eq!(tracked.keyframe_parallax_px, 0.0);
        assert_eq!(p.due_in_frame(&s.db, means, &seen, key, &tracked), None);
        let window = EstimatorOptions {
            keyframe_parallax_px: 4.0,
            ..tracked
        };
        let simulated = EstimatorOptions {
            slam_keyframe_updates: false,
            ..window.clone()
        };
        assert_eq!(p.due_in_frame(&s.db, means, &seen, key, &simulated), None);
        // The first view of each is taken; the same view again is not.
        assert_eq!(
            p.due_in_frame(&s.db, means, &seen, key, &window),
            Some(seen.clone())
        );
        assert_eq!(
            p.due_in_frame(&s.db, means, &seen, key, &window),
            Some(Vec::new())
        );
    }

    #[test]
    fn intrinsics_that_move_the_rays_of_a_still_pixel_do_not_make_its_view_due() {
        let before = CameraModel::euroc_cam0();
        let mut after = before.clone();
        after.distortion += nalgebra::Vector4::new(0.0016, 0.0021, 0.0028, -0.0067);
        let corner = Vector2::new(5.0, 8.0);
        let shift = (after.undistort(&corner).expect("ray")
            - before.undistort(&corner).expect("ray"))
        .norm()
            * before.fx();
        assert!(shift > 4.0, "{shift} px");
        let mut p = SlamPacing::default();
        let min = 4.0 / before.fx();
        assert_eq!(
            p.due([(1, corner)], |uv| before.undistort(uv).ok(), min),
            vec![1]
        );
        // The pixel stays: its ray moved only with the intrinsics.
        assert!(p
            .due([(1, corner)], |uv| after.undistort(uv).ok(), min)
            .is_empty());
        // It moves the parallax in the image: due.
        let moved = corner + Vector2::new(5.0, 0.0);
        assert_eq!(
            p.due([(1, moved)], |uv| after.undistort(uv).ok(), min),
            vec![1]
        );
    }

    #[test]
    fn a_feature_takes_a_view_only_once_its_point_moved_the_parallax() {
        let mut p = SlamPacing::default();
        let at = |x: f64| Vector2::new(x, 0.0);
        let same = |uv: &Vector2<f64>| Some(*uv);
        // New features are due.
        assert_eq!(p.due([(1, at(0.0)), (2, at(0.5))], same, 0.01), vec![1, 2]);
        // Feature 1 moved less than the parallax: not due, and its last view
        // stays the one it took, so small moves add up.
        assert_eq!(p.due([(1, at(0.006)), (2, at(0.52))], same, 0.01), vec![2]);
        assert_eq!(p.due([(1, at(0.012)), (2, at(0.525))], same, 0.01), vec![1]);
        // No pacing: every feature, every frame.
        assert_eq!(
            p.due([(1, at(0.012)), (2, at(0.525))], same, 0.0),
            vec![1, 2]
        );
        // A feature that left the state starts afresh if its id comes back.
        p.retain(|id| id != 1);
        assert_eq!(p.due([(1, at(0.012))], same, 0.01), vec![1]);
    }
}
