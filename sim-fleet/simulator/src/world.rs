//! The shared landmark world of the fleet.
//!
//! Landmarks are grown along every robot's trajectory as OpenVINS's simulator does:
//! every `check_interval_s`, if fewer than `min_visible` landmarks project into the
//! robot's image, new ones are made at uniformly random pixels, undistorted, at a
//! uniformly random depth. Robots flying through the same room therefore see the
//! same landmarks. Each landmark carries a random 256-bit descriptor.

use crate::scenario::{SelectionOrder, WorldSpec};
use crate::truth::RobotTruth;
use common::calibration::CameraCalibration;
use common::descriptor::Descriptor;
use common::so3::Se3;
use nalgebra::{Vector2, Vector3};
use rand::Rng;
use rand_chacha::ChaCha8Rng;

/// One 3-D landmark.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Landmark {
    /// Landmark id (its index in the world).
    pub id: u64,
    /// Position `p_FinG`, metres.
    pub p_in_g: Vector3<f64>,
    /// Its true descriptor; observations flip a few bits.
    pub descriptor: Descriptor,
}

/// A landmark seen in one image, before noise.
#[derive(Clone, Copy, Debug)]
pub struct Visible {
    /// Landmark id.
    pub id: u64,
    /// True raw pixel.
    pub uv: Vector2<f64>,
}

/// The world: all landmarks, ids are indices.
#[derive(Clone, Debug, Default)]
pub struct World {
    /// The landmarks in id order.
    pub landmarks: Vec<Landmark>,
    /// Selection rank of each landmark (lower is kept first); empty: id order.
    rank: Vec<u32>,
}

/// Fast rejection bounds of a camera: the normalized coordinates of the image lie
/// inside `[min, max]` (computed from undistorted border pixels, with a margin).
#[derive(Clone, Copy, Debug)]
pub struct ViewBounds {
    min: Vector2<f64>,
    max: Vector2<f64>,
    min_depth: f64,
    max_depth: f64,
}

impl ViewBounds {
    /// Bounds for a calibration and a depth range (metres).
    pub fn new(calib: &CameraCalibration, min_depth: f64, max_depth: f64) -> Self {
        let cam = &calib.camera;
        let (w, h) = (cam.width as f64, cam.height as f64);
        let mut min = Vector2::repeat(f64::INFINITY);
        let mut max = Vector2::repeat(f64::NEG_INFINITY);
        let steps = 32;
        for k in 0..=steps {
            let s = k as f64 / steps as f64;
            for uv in [
                Vector2::new(s * w, 0.0),
                Vector2::new(s * w, h),
                Vector2::new(0.0, s * h),
                Vector2::new(w, s * h),
            ] {
                if let Ok(n) = cam.undistort(&uv) {
                    min = min.inf(&n);
                    max = max.sup(&n);
                }
            }
        }
        let margin = (max - min) * 0.05;
        Self {
            min: min - margin,
            max: max + margin,
            min_depth,
            max_depth,
        }
    }
}

/// The camera pose `T_CtoG` of a robot at IMU time `t`.
pub fn camera_pose(truth: &RobotTruth, calib: &CameraCalibration, t: f64) -> Option<Se3> {
    let pose = truth.spline.pose(t)?;
    Some(pose.compose(&calib.t_c_to_i()))
}

impl World {
    /// Sets the order in which an image keeps its visible landmarks (call once the
    /// world is complete).
    pub fn set_selection_order(&mut self, order: SelectionOrder) {
        self.rank = match order {
            SelectionOrder::LowestId => Vec::new(),
            SelectionOrder::OpenvinsMap => gcc_unordered_map_rank(self.landmarks.len()),
        };
    }

    /// Keeps the first `max` of `visible` (in id order) in the selection order.
    pub fn select(&self, visible: &mut Vec<Visible>, max: usize) {
        if !self.rank.is_empty() {
            visible.sort_by_key(|v| self.rank.get(v.id as usize).copied().unwrap_or(u32::MAX));
        }
        visible.truncate(max);
    }

    /// Landmarks visible from camera pose `t_c_to_g`, with their true raw pixels, in
    /// increasing id order.
    pub fn visible(
        &self,
        t_c_to_g: &Se3,
        calib: &CameraCalibration,
        bounds: &ViewBounds,
    ) -> Vec<Visible> {
        let t_g_to_c = t_c_to_g.inverse();
        let mut out = Vec::new();
        for lm in &self.landmarks {
            let p = t_g_to_c.transform_point(&lm.p_in_g);
            if p.z < bounds.min_depth || p.z > bounds.max_depth {
                continue;
            }
            let n = Vector2::new(p.x / p.z, p.y / p.z);
            if n.x < bounds.min.x || n.y < bounds.min.y || n.x > bounds.max.x || n.y > bounds.max.y
            {
                continue;
            }
            let uv = calib.camera.distort(&n);
            if calib.camera.in_image(&uv) {
                out.push(Visible { id: lm.id, uv });
            }
        }
        out
    }

    /// Perceptual aliasing: `count` times, the landmarks within `radius` of a
    /// random landmark `b` are moved and re-described to become a rigid copy of
    /// the landmarks around another random landmark `a` at least 4 radii away
    /// (ids and counts unchanged, so the copies are seen as often as the
    /// originals were).
    pub fn alias_places(&mut self, count: usize, radius: f64, rng: &mut ChaCha8Rng) {
        let n = self.landmarks.len();
        if n < 2 || radius <= 0.0 {
            return;
        }
        let near = |w: &World, c: Vector3<f64>| -> Vec<usize> {
            let mut v: Vec<(f64, usize)> = w
                .landmarks
                .iter()
                .enumerate()
                .map(|(i, l)| ((l.p_in_g - c).norm(), i))
                .filter(|(d, _)| *d <= radius)
                .collect();
            v.sort_by(|x, y| x.0.total_cmp(&y.0).then(x.1.cmp(&y.1)));
            v.into_iter().map(|(_, i)| i).collect()
        };
        for _ in 0..count {
            let a = self.landmarks[rng.random_range(0..n)].p_in_g;
            let b = self.landmarks[rng.random_range(0..n)].p_in_g;
            if (a - b).norm() < 4.0 * radius {
                continue;
            }
            let (src, dst) = (near(self, a), near(self, b));
            for (s, d) in src.iter().zip(dst.iter()) {
                let original = self.landmarks[*s];
                let l = &mut self.landmarks[*d];
                l.p_in_g = b + (original.p_in_g - a);
                l.descriptor = original.descriptor;
            }
        }
    }

    /// Grows the world along `truth`: every `spec.check_interval_s` of its span, fills
    /// the view up to `spec.min_visible` landmarks.
    pub fn grow_along(
        &mut self,
        truth: &RobotTruth,
        calib: &CameraCalibration,
        bounds: &ViewBounds,
        spec: &WorldSpec,
        rng: &mut ChaCha8Rng,
    ) {
        let cam = &calib.camera;
        let mut t = truth.start_time();
        while t <= truth.end_time() {
            if let Some(t_c_to_g) = camera_pose(truth, calib, t) {
                let seen = self.visible(&t_c_to_g, calib, bounds).len();
                for _ in seen..spec.min_visible {
                    let uv = Vector2::new(
                        rng.random_range(0.0..cam.width as f64),
                        rng.random_range(0.0..cam.height as f64),
                    );
                    let depth =
                        rng.random_range(spec.new_point_depth_m[0]..=spec.new_point_depth_m[1]);
                    let descriptor =
                        Descriptor([rng.random(), rng.random(), rng.random(), rng.random()]);
                    // A pixel that does not undistort (outside a fisheye's valid
                    // region) makes no landmark; the draw is still consumed.
                    let Ok(n) = cam.undistort(&uv) else { continue };
                    let p_in_c = Vector3::new(n.x, n.y, 1.0) * depth;
                    self.landmarks.push(Landmark {
                        id: self.landmarks.len() as u64,
                        p_in_g: t_c_to_g.transform_point(&p_in_c),
                        descriptor,
                    });
                }
            }
            t += spec.check_interval_s;
        }
    }
}

/// libstdc++'s bucket-count primes (`__prime_list`) from 13 up to about 10⁵: the
/// sizes its rehash policy can pick.
const GCC_BUCKET_PRIMES: [usize; 114] = [
    13, 17, 19, 23, 29, 31, 37, 41, 43, 47, 53, 59, 61, 67, 71, 73, 79, 83, 89, 97, 103, 109, 113,
    127, 137, 139, 149, 157, 167, 179, 193, 199, 211, 227, 241, 257, 277, 293, 313, 337, 359, 383,
    409, 439, 467, 503, 541, 577, 619, 661, 709, 761, 823, 887, 953, 1031, 1109, 1193, 1289, 1381,
    1493, 1613, 1741, 1879, 2029, 2179, 2357, 2549, 2753, 2971, 3209, 3469, 3739, 4027, 4349, 4703,
    5087, 5503, 5953, 6427, 6949, 7517, 8123, 8783, 9497, 10273, 11113, 12011, 12983, 14033, 15173,
    16411, 17749, 19183, 20753, 22447, 24281, 26267, 28411, 30727, 33223, 35933, 38873, 42043,
    45481, 49201, 53201, 57557, 62233, 67307, 72817, 78779, 85229, 92203,
];

/// Element counts at which a GCC `std::unordered_map`, filled one key at a time,
/// rehashes (before inserting that element): it starts with 13 buckets (room for
/// 11 is asked for), and when the count would exceed the bucket count it moves
/// to the first listed prime at or above twice the bucket count.
fn gcc_rehash_points(n: usize) -> Vec<usize> {
    let mut points = Vec::new();
    let mut buckets = 13;
    while buckets < n {
        points.push(buckets);
        let want = buckets * 2;
        match GCC_BUCKET_PRIMES.iter().find(|&&p| p >= want) {
            Some(&p) => buckets = p,
            // Beyond the table: keep doubling (only the shape of the order matters).
            None => buckets = want + 1,
        }
    }
    points
}

/// The position of each key `0..n` in the iteration order of a GCC
/// `std::unordered_map<size_t, _>` filled with the keys in increasing order, as
/// OpenVINS's simulator fills its map. With the identity hash and at least as many
/// buckets as keys, every key lands in an empty bucket and is linked at the front
/// of the node list; a rehash relinks the nodes in list order, each at the front,
/// which reverses the list. So the final order is built segment by segment:
/// `L ← (keys since the last rehash, newest first) + reverse(L)`.
fn gcc_unordered_map_rank(n: usize) -> Vec<u32> {
    let mut list: std::collections::VecDeque<usize> = std::collections::VecDeque::with_capacity(n);
    // `reversed`: the logical list is `list` read back to front.
    let mut reversed = false;
    let mut rehash = gcc_rehash_points(n).into_iter().peekable();
    for key in 0..n {
        if rehash.next_if_eq(&key).is_some() {
            reversed = !reversed;
        }
        if reversed {
            list.push_back(key);
        } else {
            list.push_front(key);
        }
    }
    let mut rank = vec![0_u32; n];
    if reversed {
        list.make_contiguous().reverse();
    }
    for (pos, &key) in list.iter().enumerate() {
        rank[key] = pos as u32;
    }
    rank
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn gcc_map_order_reverses_the_list_at_each_rehash() {
        // 13 buckets until the 14th key, 29 until the 30th: keys 0-12 newest
        // first, reversed when 13 arrives, 13-28 in front of them, reversed again
        // when 29 arrives, then 29-39 in front.
        assert_eq!(gcc_rehash_points(40), vec![13, 29]);
        let rank = gcc_unordered_map_rank(40);
        let mut order = vec![0; 40];
        for (key, &r) in rank.iter().enumerate() {
            order[r as usize] = key;
        }
        let expected: Vec<usize> = (29..40).rev().chain((0..13).rev()).chain(13..29).collect();
        assert_eq!(order, expected);
    }

    #[test]
    fn selection_keeps_the_first_visible_landmarks_in_the_chosen_order() {
        let mut world = World::default();
        for id in 0..40 {
            world.landmarks.push(Landmark {
                id,
                p_in_g: Vector3::zeros(),
                descriptor: Descriptor::default(),
            });
        }
        let visible = |ids: &[u64]| -> Vec<Visible> {
            ids.iter()
                .map(|&id| Visible {
                    id,
                    uv: Vector2::zeros(),
                })
                .collect()
        };
        let ids = |v: &[Visible]| v.iter().map(|v| v.id).collect::<Vec<_>>();
        let mut v = visible(&[2, 5, 14, 30, 35]);
        world.select(&mut v, 3);
        assert_eq!(ids(&v), vec![2, 5, 14]);
        world.set_selection_order(SelectionOrder::OpenvinsMap);
        let mut v = visible(&[2, 5, 14, 30, 35]);
        world.select(&mut v, 3);
        // 29-39 newest first, then 12-0, then 13-28.
        assert_eq!(ids(&v), vec![35, 30, 5]);
    }

    #[test]
    fn gcc_map_grows_through_libstdcxx_primes() {
        assert_eq!(
            gcc_rehash_points(6000),
            vec![13, 29, 59, 127, 257, 541, 1109, 2357, 5087]
        );
        let rank = gcc_unordered_map_rank(6000);
        let mut seen = rank.clone();
        seen.sort_unstable();
        assert!(seen.iter().enumerate().all(|(i, &r)| r as usize == i));
    }
}
