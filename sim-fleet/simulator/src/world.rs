//! The shared landmark world of the fleet.
//!
//! Landmarks are grown along every robot's trajectory as OpenVINS's simulator does:
//! every `check_interval_s`, if fewer than `min_visible` landmarks project into the
//! robot's image, new ones are made at uniformly random pixels, undistorted, at a
//! uniformly random depth. Robots flying through the same room therefore see the
//! same landmarks. Each landmark carries a random 256-bit descriptor.

use crate::scenario::WorldSpec;
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
