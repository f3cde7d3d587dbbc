//! The feature database: every tracked feature's observations, keyed by track id.
//!
//! A measurement is tagged with the `clone_key` of its image (the sequence number
//! of the image and of the clone the filter makes for it), so the estimator can ask
//! which features were seen at which clones, which tracks were lost, and drop the
//! measurements of marginalized clones.
//!
//! Features are kept in an ordered map, so every iteration (and every list of ids
//! returned) is in ascending id order: the database behaves identically, bit for
//! bit, from run to run.

use super::triangulation::CameraObservation;
use common::camera::CameraModel;
use nalgebra::{Matrix3, Vector2, Vector3};
use std::collections::BTreeMap;

/// Default of [`FeatureDb::max_pixel_jump_px`], pixels.
pub const DEFAULT_MAX_PIXEL_JUMP_PX: f64 = 150.0;

/// Most rays a track keeps from clones that have left the window
/// ([`Feature::retired`]): the oldest one and the newest others.
pub const MAX_RETIRED_RAYS: usize = 20;

/// How far, in pixels of focal length, the intrinsics may move a stored ray
/// before [`FeatureDb::follow_intrinsics`] undistorts every stored pixel again:
/// a tenth of the pixel noise.
pub const RAY_REFRESH_PX: f64 = 0.1;

/// Fractions of the image's width and height where
/// [`FeatureDb::follow_intrinsics`] measures how far the intrinsics moved the
/// rays: the corners, where the distortion moves them most, the edges' middles
/// and the centre.
const PROBE_FRACTIONS: [f64; 3] = [0.0, 0.5, 1.0];

/// One observation of a feature in one image.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct FeatureMeasurement {
    /// Sequence number of the image (and of the clone made for it).
    pub clone_key: u64,
    /// Camera time of the image, seconds.
    pub t: f64,
    /// Raw (distorted) pixel coordinates, pixels.
    pub uv: Vector2<f64>,
    /// Undistorted normalized coordinates `[x/z, y/z]`, with the intrinsics of
    /// the database's last [`FeatureDb::follow_intrinsics`].
    pub uvn: Vector2<f64>,
}

impl FeatureMeasurement {
    /// Whether the time and all coordinates are finite.
    fn is_finite(&self) -> bool {
        self.t.is_finite()
            && self.uv.iter().all(|v| v.is_finite())
            && self.uvn.iter().all(|v| v.is_finite())
    }
}

/// A tracked feature: its measurements and its last triangulated position.
#[derive(Clone, Debug, PartialEq)]
pub struct Feature {
    /// Track id (unique within the robot).
    pub id: u64,
    /// The measurements in strictly increasing `clone_key` order (callers editing
    /// this through [`FeatureDb::get_mut`] must keep that order).
    pub measurements: Vec<FeatureMeasurement>,
    /// Position of the feature in `G` from its last triangulation, metres.
    pub p_in_g: Option<Vector3<f64>>,
    /// Marks the feature for removal by [`FeatureDb::clean_up`].
    pub to_delete: bool,
    /// The track's views from clones that have left the window, as rays from
    /// the camera poses estimated when they left, oldest first (at most
    /// [`MAX_RETIRED_RAYS`]): a longer baseline to triangulate a slow track's
    /// point from, never measurements of an update
    /// ([`FeatureDb::retire_measurements_before`]).
    pub retired: Vec<RetiredRay>,
}

/// A view of a track from a clone that has left the window.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct RetiredRay {
    /// The camera pose estimated when the clone left, and the normalized
    /// coordinates (kept with the intrinsics as [`FeatureMeasurement::uvn`]).
    pub view: CameraObservation,
    /// Raw (distorted) pixel coordinates, pixels.
    pub uv: Vector2<f64>,
}

impl Feature {
    /// A feature with no measurements, no position, not marked for deletion.
    pub fn new(id: u64) -> Self {
        Self {
            id,
            measurements: Vec::new(),
            p_in_g: None,
            to_delete: false,
            retired: Vec::new(),
        }
    }

    /// The newest measurement (largest `clone_key`).
    pub fn newest(&self) -> Option<&FeatureMeasurement> {
        self.measurements.last()
    }

    /// The oldest measurement (smallest `clone_key`).
    pub fn oldest(&self) -> Option<&FeatureMeasurement> {
        self.measurements.first()
    }

    /// The measurement at `clone_key`, if any (binary search).
    pub fn measurement_at(&self, clone_key: u64) -> Option<&FeatureMeasurement> {
        self.measurements
            .binary_search_by_key(&clone_key, |m| m.clone_key)
            .ok()
            .and_then(|i| self.measurements.get(i))
    }

    /// Whether the feature has a measurement at `clone_key`.
    pub fn has_measurement_at(&self, clone_key: u64) -> bool {
        self.measurements
            .binary_search_by_key(&clone_key, |m| m.clone_key)
            .is_ok()
    }
}

/// Errors of the feature database; each names the feature id concerned.
#[derive(Clone, Debug, PartialEq, thiserror::Error)]
pub enum FeatureDbError {
    /// The measurement has a NaN or infinite time or coordinate.
    #[error("feature {id}: measurement at clone {clone_key} has a non-finite time or coordinate")]
    NonFinite {
        /// Feature id.
        id: u64,
        /// Clone key of the rejected measurement.
        clone_key: u64,
    },
    /// The measurement's clone key is not strictly after the feature's last one.
    #[error(
        "feature {id}: measurement at clone {clone_key} is not after the feature's \
         last clone {last_clone_key}"
    )]
    NotAfterLast {
        /// Feature id.
        id: u64,
        /// Clone key of the rejected measurement.
        clone_key: u64,
        /// Clone key of the feature's newest measurement.
        last_clone_key: u64,
    },
    /// The pixel moved more than the allowed jump between consecutive images: the
    /// id was probably reused for another feature.
    #[error(
        "feature {id}: pixel jumped {jump_px:.1} px from clone {previous_clone_key} to \
         clone {clone_key} (at most {max_px} px allowed): feature id reused with an \
         impossible jump"
    )]
    PixelJump {
        /// Feature id.
        id: u64,
        /// Clone key of the rejected measurement.
        clone_key: u64,
        /// Clone key of the previous measurement (`clone_key - 1`).
        previous_clone_key: u64,
        /// Distance between the two raw pixels, pixels.
        jump_px: f64,
        /// The allowed maximum, pixels.
        max_px: f64,
    },
    /// [`FeatureDb::with_max_pixel_jump_px`] got a NaN, zero or negative value.
    #[error("the maximum pixel jump must be positive (infinite disables the check), got {value}")]
    InvalidMaxPixelJump {
        /// The rejected value, pixels.
        value: f64,
    },
}

/// The features currently tracked, keyed by track id, iterated in ascending id order.
#[derive(Clone, Debug, PartialEq)]
pub struct FeatureDb {
    /// The features by id.
    features: BTreeMap<u64, Feature>,
    /// Largest pixel motion accepted between measurements of consecutive clones.
    max_pixel_jump_px: f64,
    /// Probe pixels and their rays with the intrinsics the stored normalized
    /// coordinates hold ([`Self::follow_intrinsics`]); `None` before the first call.
    probe_rays: Option<Vec<(Vector2<f64>, Vector2<f64>)>>,
}

impl Default for FeatureDb {
    /// An empty database with [`DEFAULT_MAX_PIXEL_JUMP_PX`].
    fn default() -> Self {
        Self::new()
    }
}

impl FeatureDb {
    /// An empty database with the default maximum pixel jump
    /// ([`DEFAULT_MAX_PIXEL_JUMP_PX`]).
    pub fn new() -> Self {
        Self {
            features: BTreeMap::new(),
            max_pixel_jump_px: DEFAULT_MAX_PIXEL_JUMP_PX,
            probe_rays: None,
        }
    }

    /// An empty database rejecting pixel jumps larger than `max_px` between
    /// consecutive clones; `f64::INFINITY` disables the check.
    pub fn with_max_pixel_jump_px(max_px: f64) -> Result<Self, FeatureDbError> {
        if max_px.is_nan() || max_px <= 0.0 {
            return Err(FeatureDbError::InvalidMaxPixelJump { value: max_px });
        }
        Ok(Self {
            features: BTreeMap::new(),
            max_pixel_jump_px: max_px,
            probe_rays: None,
        })
    }

    /// Largest pixel motion accepted between measurements of consecutive clones.
    pub fn max_pixel_jump_px(&self) -> f64 {
        self.max_pixel_jump_px
    }

    /// Keeps the stored normalized coordinates (of the window's measurements and
    /// of the retired rays) those of `camera`'s intrinsics: when a probe pixel's
    /// ray moved more than [`RAY_REFRESH_PX`] since the last refresh, every
    /// stored pixel is undistorted again. Returns whether they were.
    ///
    /// A measurement's coordinates are undistorted when it is recorded, with the
    /// intrinsics online calibration holds then; while those converge, a small
    /// change in the distortion moves a ray near the image's corners by tens of
    /// pixels (rendered V1_01 at 0.3x, seed 2: 27-30 px in one second), and
    /// whatever compares rays of different times (the keyframe parallax, the
    /// retired rays) would read that drift as motion. A pixel the intrinsics
    /// cannot undistort now keeps its coordinates.
    pub fn follow_intrinsics(&mut self, camera: &CameraModel) -> bool {
        let fx = camera.fx();
        // The largest probe move, pixels. With no probe the intrinsics could
        // undistort (a fisheye's corners beyond its field of view) it is
        // infinite: every call refreshes.
        let moved_px = self.probe_rays.as_ref().map_or(f64::INFINITY, |probes| {
            let none = if probes.is_empty() {
                f64::INFINITY
            } else {
                0.0
            };
            probes
                .iter()
                .filter_map(|(uv, ray)| {
                    camera.undistort(uv).ok().map(|now| (now - ray).norm() * fx)
                })
                .fold(none, f64::max)
        });
        if moved_px <= RAY_REFRESH_PX {
            return false;
        }
        let (w, h) = (f64::from(camera.width), f64::from(camera.height));
        let probes = PROBE_FRACTIONS
            .iter()
            .flat_map(|fu| {
                PROBE_FRACTIONS
                    .iter()
                    .map(move |fv| Vector2::new(fu * w, fv * h))
            })
            .filter_map(|uv| Some((uv, camera.undistort(&uv).ok()?)))
            .collect();
        self.probe_rays = Some(probes);
        let mut rays = 0;
        for f in self.features.values_mut() {
            rays += f.measurements.len() + f.retired.len();
            for m in &mut f.measurements {
                if let Ok(uvn) = camera.undistort(&m.uv) {
                    m.uvn = uvn;
                }
            }
            for r in &mut f.retired {
                if let Ok(uvn) = camera.undistort(&r.uv) {
                    r.view.uvn = uvn;
                }
            }
        }
        tracing::debug!(
            moved_px,
            rays,
            "stored rays undistorted again: the intrinsics moved them"
        );
        true
    }

    /// Appends a measurement to feature `id`, creating the feature if new.
    ///
    /// Rejects (leaving the database unchanged) a measurement with a non-finite
    /// value, one whose `clone_key` is not strictly after the feature's newest, and
    /// one whose raw pixel is more than [`FeatureDb::max_pixel_jump_px`] from the
    /// feature's newest measurement when that one is at the immediately preceding
    /// clone key.
    pub fn insert(&mut self, id: u64, m: FeatureMeasurement) -> Result<(), FeatureDbError> {
        if !m.is_finite() {
            return Err(FeatureDbError::NonFinite {
                id,
                clone_key: m.clone_key,
            });
        }
        let feature = match self.features.get_mut(&id) {
            Some(f) => f,
            None => {
                let mut f = Feature::new(id);
                f.measurements.push(m);
                self.features.insert(id, f);
                return Ok(());
            }
        };
        if let Some(last) = feature.newest() {
            if m.clone_key <= last.clone_key {
                return Err(FeatureDbError::NotAfterLast {
                    id,
                    clone_key: m.clone_key,
                    last_clone_key: last.clone_key,
                });
            }
            let jump_px = (m.uv - last.uv).norm();
            if last.clone_key.checked_add(1) == Some(m.clone_key)
                && jump_px > self.max_pixel_jump_px
            {
                return Err(FeatureDbError::PixelJump {
                    id,
                    clone_key: m.clone_key,
                    previous_clone_key: last.clone_key,
                    jump_px,
                    max_px: self.max_pixel_jump_px,
                });
            }
        }
        feature.measurements.push(m);
        Ok(())
    }

    /// The feature `id`, if present.
    pub fn get(&self, id: u64) -> Option<&Feature> {
        self.features.get(&id)
    }

    /// The feature `id` for modification, if present (keep its measurements in
    /// increasing `clone_key` order).
    pub fn get_mut(&mut self, id: u64) -> Option<&mut Feature> {
        self.features.get_mut(&id)
    }

    /// Removes and returns the feature `id`, if present.
    pub fn remove(&mut self, id: u64) -> Option<Feature> {
        self.features.remove(&id)
    }

    /// Whether the feature `id` is present.
    pub fn contains(&self, id: u64) -> bool {
        self.features.contains_key(&id)
    }

    /// Number of features.
    pub fn len(&self) -> usize {
        self.features.len()
    }

    /// Whether there are no features.
    pub fn is_empty(&self) -> bool {
        self.features.is_empty()
    }

    /// The features in ascending id order.
    pub fn iter(&self) -> impl Iterator<Item = &Feature> + '_ {
        self.features.values()
    }

    /// All feature ids, ascending.
    pub fn ids(&self) -> Vec<u64> {
        self.features.keys().copied().collect()
    }

    /// Ids (ascending) of the features whose newest measurement is older than
    /// `clone_key` (lost tracks); a feature with no measurement is included.
    pub fn ids_not_seen_since(&self, clone_key: u64) -> Vec<u64> {
        self.ids_where(|f| f.newest().is_none_or(|m| m.clone_key < clone_key))
    }

    /// Ids (ascending) of the features with a measurement at `clone_key`.
    pub fn ids_with_measurement_at(&self, clone_key: u64) -> Vec<u64> {
        self.ids_where(|f| f.has_measurement_at(clone_key))
    }

    /// Ids (ascending) of the features with a measurement at every one of
    /// `clone_keys` (all features when `clone_keys` is empty).
    pub fn ids_spanning(&self, clone_keys: &[u64]) -> Vec<u64> {
        self.ids_where(|f| clone_keys.iter().all(|&k| f.has_measurement_at(k)))
    }

    /// Ids (ascending) of the features for which `keep` holds.
    fn ids_where(&self, mut keep: impl FnMut(&Feature) -> bool) -> Vec<u64> {
        self.features
            .iter()
            .filter(|(_, f)| keep(f))
            .map(|(&id, _)| id)
            .collect()
    }

    /// Drops every measurement older than `clone_key` (the clones that were
    /// marginalized), then every feature left without measurements. Each
    /// dropped measurement whose clone `camera_pose` still knows (`R_CtoG`,
    /// `p_CinG`) stays as a ray in [`Feature::retired`]. When a track holds
    /// more than [`MAX_RETIRED_RAYS`], the second oldest goes: the oldest ray
    /// gives the widest baseline.
    pub fn retire_measurements_before(
        &mut self,
        clone_key: u64,
        camera_pose: impl Fn(u64) -> Option<(Matrix3<f64>, Vector3<f64>)>,
    ) {
        self.features.retain(|_, f| {
            let n_old = f.measurements.partition_point(|m| m.clone_key < clone_key);
            for m in f.measurements.drain(..n_old) {
                let Some((r_c_to_g, p_c_in_g)) = camera_pose(m.clone_key) else {
                    continue;
                };
                f.retired.push(RetiredRay {
                    view: CameraObservation {
                        r_c_to_g,
                        p_c_in_g,
                        uvn: m.uvn,
                    },
                    uv: m.uv,
                });
                if f.retired.len() > MAX_RETIRED_RAYS {
                    f.retired.remove(1);
                }
            }
            !f.measurements.is_empty()
        });
    }

    /// Drops the measurement at `clone_key` of every feature (e.g. when a clone
    /// other than the oldest is marginalized), then every feature left without
    /// measurements.
    pub fn remove_measurements_at(&mut self, clone_key: u64) {
        self.features.retain(|_, f| {
            if let Ok(i) = f
                .measurements
                .binary_search_by_key(&clone_key, |m| m.clone_key)
            {
                f.measurements.remove(i);
            }
            !f.measurements.is_empty()
        });
    }

    /// Removes the features marked [`Feature::to_delete`]; returns how many.
    pub fn clean_up(&mut self) -> usize {
        let before = self.features.len();
        self.features.retain(|_, f| !f.to_delete);
        before - self.features.len()
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use rand::seq::SliceRandom;
    use rand::SeedableRng;
    use rand_chacha::ChaCha8Rng;

    fn meas(clone_key: u64, u: f64, v: f64) -> FeatureMeasurement {
        FeatureMeasurement {
            clone_key,
            t: clone_key as f64 * 0.1,
            uv: Vector2::new(u, v),
            uvn: Vector2::new((u - 376.0) / 458.0, (v - 240.0) / 457.0),
        }
    }

    /// Feature 1 seen at clones 0..=4, 2 at 2..=5, 3 at 0..=1, 4 at 1 and 3.
    fn sample_db() -> FeatureDb {
        let mut db = FeatureDb::new();
        for k in 0..=4 {
            db.insert(1, meas(k, 100.0 + k as f64, 100.0)).unwrap();
        }
        for k in 2..=5 {
            db.insert(2, meas(k, 200.0, 200.0 + k as f64)).unwrap();
        }
        for k in 0..=1 {
            db.insert(3, meas(k, 300.0, 300.0)).unwrap();
        }
        db.insert(4, meas(1, 50.0, 50.0)).unwrap();
        db.insert(4, meas(3, 60.0, 50.0)).unwrap();
        db
    }

    #[test]
    fn inserted_measurements_build_a_track_in_clone_order() {
        let db = sample_db();
        assert_eq!(db.len(), 4);
        assert!(!db.is_empty());
        let f = db.get(1).unwrap();
        assert_eq!(f.id, 1);
        let keys: Vec<u64> = f.measurements.iter().map(|m| m.clone_key).collect();
        assert_eq!(keys, vec![0, 1, 2, 3, 4]);
        assert_eq!(f.oldest().unwrap().clone_key, 0);
        assert_eq!(f.newest().unwrap().clone_key, 4);
        assert_eq!(f.measurement_at(2).unwrap().uv, Vector2::new(102.0, 100.0));
        assert!(f.measurement_at(7).is_none());
        assert!(f.p_in_g.is_none());
        assert!(!f.to_delete);
        assert!(db.get(99).is_none());
    }

    #[test]
    fn a_measurement_not_after_the_last_clone_is_rejected_naming_the_id() {
        let mut db = sample_db();
        for k in [4, 2] {
            let err = db.insert(1, meas(k, 104.0, 100.0)).unwrap_err();
            assert_eq!(
                err,
                FeatureDbError::NotAfterLast {
                    id: 1,
                    clone_key: k,
                    last_clone_key: 4
                }
            );
            assert!(err.to_string().contains("feature 1"), "{err}");
        }
        assert_eq!(db.get(1).unwrap().measurements.len(), 5);
    }

    #[test]
    fn an_impossible_jump_between_consecutive_clones_is_rejected_as_a_reused_id() {
        let mut db = sample_db();
        let err = db.insert(2, meas(6, 200.0, 500.0)).unwrap_err();
        assert!(matches!(
            err,
            FeatureDbError::PixelJump {
                id: 2,
                clone_key: 6,
                previous_clone_key: 5,
                ..
            }
        ));
        assert!(err.to_string().contains("feature 2"), "{err}");
        assert_eq!(db.get(2).unwrap().measurements.len(), 4);
        // A jump under the limit is accepted.
        db.insert(2, meas(6, 200.0, 300.0)).unwrap();
    }

    #[test]
    fn a_large_jump_after_a_gap_in_clones_is_accepted() {
        let mut db = sample_db();
        db.insert(2, meas(8, 600.0, 400.0)).unwrap();
        assert_eq!(db.get(2).unwrap().newest().unwrap().clone_key, 8);
    }

    #[test]
    fn the_maximum_pixel_jump_is_configurable_and_validated() {
        let mut db = FeatureDb::with_max_pixel_jump_px(10.0).unwrap();
        assert_eq!(db.max_pixel_jump_px(), 10.0);
        db.insert(7, meas(0, 0.0, 0.0)).unwrap();
        assert!(db.insert(7, meas(1, 11.0, 0.0)).is_err());
        db.insert(7, meas(1, 9.0, 0.0)).unwrap();
        assert_eq!(
            FeatureDb::new().max_pixel_jump_px(),
            DEFAULT_MAX_PIXEL_JUMP_PX
        );
        assert!(FeatureDb::with_max_pixel_jump_px(f64::INFINITY).is_ok());
        for bad in [0.0, -1.0, f64::NAN] {
            assert!(FeatureDb::with_max_pixel_jump_px(bad).is_err());
        }
    }

    #[test]
    fn non_finite_measurements_are_rejected_naming_the_id() {
        let mut db = FeatureDb::new();
        let mut m = meas(0, 10.0, 10.0);
        m.uvn.x = f64::NAN;
        let err = db.insert(5, m).unwrap_err();
        assert_eq!(
            err,
            FeatureDbError::NonFinite {
                id: 5,
                clone_key: 0
            }
        );
        assert!(err.to_string().contains("feature 5"));
        let mut m = meas(0, 10.0, 10.0);
        m.t = f64::INFINITY;
        assert!(db.insert(5, m).is_err());
        let mut m = meas(0, 10.0, 10.0);
        m.uv.y = f64::NEG_INFINITY;
        assert!(db.insert(5, m).is_err());
        assert!(db.is_empty());
    }

    #[test]
    fn lost_tracks_are_the_features_not_seen_since_a_clone() {
        let db = sample_db();
        assert_eq!(db.ids_not_seen_since(5), vec![1, 3, 4]);
        assert_eq!(db.ids_not_seen_since(4), vec![3, 4]);
        assert_eq!(db.ids_not_seen_since(0), Vec::<u64>::new());
    }

    #[test]
    fn features_are_found_by_the_clones_they_were_seen_at() {
        let db = sample_db();
        assert_eq!(db.ids_with_measurement_at(1), vec![1, 3, 4]);
        assert_eq!(db.ids_with_measurement_at(2), vec![1, 2]);
        assert_eq!(db.ids_with_measurement_at(9), Vec::<u64>::new());
        assert_eq!(db.ids_spanning(&[1, 3]), vec![1, 4]);
        assert_eq!(db.ids_spanning(&[2, 3, 4]), vec![1, 2]);
        assert_eq!(db.ids_spanning(&[0, 5]), Vec::<u64>::new());
        assert_eq!(db.ids_spanning(&[]), vec![1, 2, 3, 4]);
    }

    #[test]
    fn removing_old_measurements_drops_features_left_empty() {
        let mut db = sample_db();
        db.retire_measurements_before(2, |_| None);
        assert_eq!(db.ids(), vec![1, 2, 4]);
        let keys: Vec<u64> = db
            .get(1)
            .unwrap()
            .measurements
            .iter()
            .map(|m| m.clone_key)
            .collect();
        assert_eq!(keys, vec![2, 3, 4]);
        assert_eq!(db.get(4).unwrap().measurements.len(), 1);
        db.retire_measurements_before(4, |_| None);
        assert_eq!(db.ids(), vec![1, 2]);
    }

    #[test]
    fn retired_measurements_stay_as_rays_oldest_first_and_bounded() {
        let mut db = FeatureDb::new();
        let n = MAX_RETIRED_RAYS as u64 + 5;
        for k in 0..=n {
            db.insert(1, meas(k, 100.0 + k as f64, 100.0)).unwrap();
        }
        // Clone k's camera sits at x = k; clone 3's pose is no longer known.
        let pose =
            |k: u64| (k != 3).then(|| (Matrix3::identity(), Vector3::new(k as f64, 0.0, 0.0)));
        for k in 1..=n {
            db.retire_measurements_before(k, pose);
        }
        let f = db.get(1).unwrap();
        assert_eq!(f.measurements.len(), 1);
        assert_eq!(f.retired.len(), MAX_RETIRED_RAYS);
        // The oldest ray stays (the widest baseline), then the newest others.
        let xs: Vec<f64> = f.retired.iter().map(|r| r.view.p_c_in_g.x).collect();
        assert_eq!(xs[0], 0.0);
        assert_eq!(xs[MAX_RETIRED_RAYS - 1], (n - 1) as f64);
        assert!(xs.windows(2).all(|w| w[0] < w[1]));
        assert!(!xs.contains(&3.0));
        assert_eq!(f.retired[0].view.uvn, meas(0, 100.0, 100.0).uvn);
        assert_eq!(f.retired[0].uv, meas(0, 100.0, 100.0).uv);
    }

    #[test]
    fn stored_rays_follow_the_intrinsics_once_they_move_a_tenth_of_a_pixel() {
        let mut camera = CameraModel::euroc_cam0();
        let mut db = FeatureDb::new();
        // A track at the image's corner and one at its centre, one view each
        // retired, their coordinates undistorted with `camera`.
        for (id, u, v) in [(1, 5.0, 8.0), (2, 376.0, 240.0)] {
            for k in 0..3 {
                let uv = Vector2::new(u + k as f64, v);
                let uvn = camera.undistort(&uv).expect("undistorts");
                let m = FeatureMeasurement {
                    clone_key: k,
                    t: 0.1 * k as f64,
                    uv,
                    uvn,
                };
                db.insert(id, m).expect("valid");
            }
        }
        let pose = |_| Some((Matrix3::identity(), Vector3::zeros()));
        db.retire_measurements_before(1, pose);
        assert!(
            db.follow_intrinsics(&camera),
            "the first call sets the reference"
        );
        assert!(!db.follow_intrinsics(&camera));
        let rays = |db: &FeatureDb| -> Vec<Vector2<f64>> {
            db.iter()
                .flat_map(|f| {
                    let window = f.measurements.iter().map(|m| m.uvn);
                    f.retired.iter().map(|r| r.view.uvn).chain(window)
                })
                .collect()
        };
        let exact = |db: &FeatureDb, camera: &CameraModel| -> f64 {
            db.iter()
                .flat_map(|f| {
                    let window = f.measurements.iter().map(|m| (m.uv, m.uvn));
                    f.retired.iter().map(|r| (r.uv, r.view.uvn)).chain(window)
                })
                .map(|(uv, uvn)| (camera.undistort(&uv).expect("undistorts") - uvn).norm())
                .fold(0.0, f64::max)
                * camera.fx()
        };
        // A distortion step too small to move any ray a tenth of a pixel: kept.
        let before = rays(&db);
        camera.distortion.x += 1e-6;
        assert!(!db.follow_intrinsics(&camera));
        assert_eq!(rays(&db), before);
        assert!(exact(&db, &camera) < RAY_REFRESH_PX);
        // Online calibration's distortion moving as in the first second of a
        // flight: the corner's rays are pixels stale, and all are redone.
        camera.distortion += nalgebra::Vector4::new(0.0016, 0.0021, 0.0028, -0.0067);
        let stale = exact(&db, &camera);
        assert!(stale > 1.0, "{stale} px");
        assert!(db.follow_intrinsics(&camera));
        assert!(exact(&db, &camera) < 1e-9, "{} px", exact(&db, &camera));
        assert!(!db.follow_intrinsics(&camera));
    }

    #[test]
    fn removing_the_measurements_of_one_clone_drops_features_left_empty() {
        let mut db = sample_db();
        db.retire_measurements_before(3, |_| None);
        db.remove_measurements_at(3);
        assert_eq!(db.ids(), vec![1, 2]);
        assert!(!db.get(1).unwrap().has_measurement_at(3));
        assert!(db.get(1).unwrap().has_measurement_at(4));
    }

    #[test]
    fn clean_up_removes_only_the_features_marked_for_deletion() {
        let mut db = sample_db();
        db.get_mut(2).unwrap().to_delete = true;
        db.get_mut(4).unwrap().to_delete = true;
        assert_eq!(db.clean_up(), 2);
        assert_eq!(db.ids(), vec![1, 3]);
        assert_eq!(db.clean_up(), 0);
        assert!(db.remove(3).is_some());
        assert!(db.remove(3).is_none());
        assert!(!db.contains(3));
        assert!(db.contains(1));
    }

    #[test]
    fn ids_come_back_sorted_whatever_the_insertion_order() {
        let mut rng = ChaCha8Rng::seed_from_u64(3);
        let mut ids: Vec<u64> = (0..500).map(|i| i * 7919 % 10007).collect();
        ids.shuffle(&mut rng);
        let mut db = FeatureDb::new();
        for &id in &ids {
            db.insert(id, meas(id % 3, 10.0, 10.0)).unwrap();
        }
        let mut sorted = ids.clone();
        sorted.sort_unstable();
        assert_eq!(db.ids(), sorted);
        let iterated: Vec<u64> = db.iter().map(|f| f.id).collect();
        assert_eq!(iterated, sorted);
        for list in [
            db.ids_not_seen_since(2),
            db.ids_with_measurement_at(1),
            db.ids_spanning(&[0]),
        ] {
            assert!(!list.is_empty());
            assert!(list.windows(2).all(|w| w[0] < w[1]));
        }
    }
}
