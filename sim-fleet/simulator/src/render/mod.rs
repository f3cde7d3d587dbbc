//! Rendered camera images: grayscale pictures of a textured room around the
//! trajectories, taken through the true camera model (distortion included) with
//! intensity noise, so the whole image pipeline (detection, KLT, outlier
//! rejection) runs on every scenario with exact ground truth.
//!
//! Each pixel is a ray: its centre `(u, v)` is undistorted once into the
//! normalized direction `[x, y, 1]` in the camera frame `C`; per image the ray
//! goes to the world with `R_CtoG` and leaves the room through one face
//! ([`room::Room::exit`]). The face's texture is sampled there with a mip level
//! chosen from the pixel's footprint on the surface (its width in normalized
//! units times the depth, widened for oblique views), so distant walls blur
//! instead of aliasing, as a real lens and sensor would.

pub mod room;
pub mod texture;

use common::calibration::CameraCalibration;
use common::image::{GrayImage, ImageError};
use common::so3::Se3;
use nalgebra::{Vector2, Vector3};
use rand::Rng;
use rand_chacha::ChaCha8Rng;
use rand_distr::{Distribution, StandardNormal};
use room::Room;
use serde::{Deserialize, Serialize};
use texture::Texture;
use thiserror::Error;

/// Why a renderer could not be built.
#[derive(Debug, Error, PartialEq)]
pub enum RenderError {
    /// A setting is out of range.
    #[error("render: {0}")]
    Invalid(String),
    /// There is no trajectory to build the room around.
    #[error("render: no trajectory to put a room around")]
    NoTrajectory,
}

/// Settings of the rendered images (scenario section `render`).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct RenderSpec {
    /// Render an image for every camera frame (the frame then carries no
    /// simulated features: an image frontend makes them).
    pub enabled: bool,
    /// Horizontal distance from the trajectories' bounding box to the walls, m.
    pub wall_margin_m: f64,
    /// Floor distance below the lowest trajectory point, m.
    pub floor_below_m: f64,
    /// Ceiling distance above the highest trajectory point, m.
    pub ceiling_above_m: f64,
    /// Size of one texel on the surfaces, m.
    pub texel_m: f64,
    /// Texture side in texels (a power of two); a texture repeats every
    /// `texture_px * texel_m` metres.
    pub texture_px: usize,
    /// Standard deviation of the per-pixel intensity noise, gray levels.
    pub intensity_noise_gray: f64,
    /// Exposure time, ms: each pixel averages the scene over this interval,
    /// centred on the frame time, so the camera's motion blurs the image as a
    /// real sensor's does. 0 (the default) takes an instantaneous picture.
    pub exposure_ms: f64,
    /// Camera poses the exposure is averaged over (spread evenly across it);
    /// used when `exposure_ms` is above 0.
    pub exposure_samples: usize,
    /// Chance per image (0..=1) that the camera's auto-exposure steps its
    /// brightness, as real cameras do between images when the scene's light
    /// changes. 0 (the default) keeps the brightness constant.
    pub gain_step_chance: f64,
    /// Largest relative change of one step: the brightness is multiplied by a
    /// factor drawn log-uniformly within `[1 / (1 + max), 1 + max]`.
    pub gain_step_max: f64,
    /// Least brightness relative to the scene's (a darker image).
    pub gain_min: f64,
    /// Most brightness relative to the scene's (a brighter image; the
    /// brightest texels then saturate at 255).
    pub gain_max: f64,
}

impl Default for RenderSpec {
    fn default() -> Self {
        Self {
            enabled: false,
            wall_margin_m: 3.0,
            floor_below_m: 1.0,
            ceiling_above_m: 1.5,
            texel_m: 0.01,
            texture_px: 1024,
            intensity_noise_gray: 2.0,
            exposure_ms: 0.0,
            exposure_samples: 8,
            gain_step_chance: 0.0,
            gain_step_max: 0.2,
            gain_min: 0.6,
            gain_max: 1.4,
        }
    }
}

impl RenderSpec {
    /// Checks the ranges.
    pub fn validate(&self) -> Result<(), RenderError> {
        let positive = [
            ("wall_margin_m", self.wall_margin_m),
            ("floor_below_m", self.floor_below_m),
            ("ceiling_above_m", self.ceiling_above_m),
            ("texel_m", self.texel_m),
        ];
        for (k, v) in positive {
            if !(v.is_finite() && v > 0.0) {
                return Err(RenderError::Invalid(format!(
                    "{k} must be positive, got {v}"
                )));
            }
        }
        if !(self.intensity_noise_gray.is_finite() && self.intensity_noise_gray >= 0.0) {
            return Err(RenderError::Invalid(format!(
                "intensity_noise_gray must be >= 0, got {}",
                self.intensity_noise_gray
            )));
        }
        if !(self.exposure_ms.is_finite() && (0.0..=MAX_EXPOSURE_MS).contains(&self.exposure_ms)) {
            return Err(RenderError::Invalid(format!(
                "exposure_ms must be within 0..={MAX_EXPOSURE_MS}, got {}",
                self.exposure_ms
            )));
        }
        if !(1..=MAX_EXPOSURE_SAMPLES).contains(&self.exposure_samples) {
            return Err(RenderError::Invalid(format!(
                "exposure_samples must be within 1..={MAX_EXPOSURE_SAMPLES}, got {}",
                self.exposure_samples
            )));
        }
        if !(self.gain_step_chance.is_finite() && (0.0..=1.0).contains(&self.gain_step_chance)) {
            return Err(RenderError::Invalid(format!(
                "gain_step_chance must be within 0..=1, got {}",
                self.gain_step_chance
            )));
        }
        if !(self.gain_step_max.is_finite() && (0.0..=1.0).contains(&self.gain_step_max)) {
            return Err(RenderError::Invalid(format!(
                "gain_step_max must be within 0..=1, got {}",
                self.gain_step_max
            )));
        }
        let gains = self.gain_min.is_finite()
            && self.gain_max.is_finite()
            && 0.1 <= self.gain_min
            && self.gain_min <= 1.0
            && 1.0 <= self.gain_max
            && self.gain_max <= 10.0;
        if !gains {
            return Err(RenderError::Invalid(format!(
                "gain_min must be within 0.1..=1 and gain_max within 1..=10, got {} and {}",
                self.gain_min, self.gain_max
            )));
        }
        if !self.texture_px.is_power_of_two() || !(8..=8192).contains(&self.texture_px) {
            return Err(RenderError::Invalid(format!(
                "texture_px must be a power of two in 8..=8192, got {}",
                self.texture_px
            )));
        }
        Ok(())
    }

    /// The times whose camera poses one exposure averages, for a frame at `t`:
    /// `[t]` without exposure, else `exposure_samples` times spread evenly over
    /// `[t - exposure / 2, t + exposure / 2]` (the centre of each slice).
    pub fn exposure_times(&self, t: f64) -> Vec<f64> {
        if self.exposure_ms <= 0.0 {
            return vec![t];
        }
        let e = self.exposure_ms * 1e-3;
        let n = self.exposure_samples.max(1);
        (0..n)
            .map(|i| t - 0.5 * e + (i as f64 + 0.5) * e / n as f64)
            .collect()
    }

    /// The brightness of the next image, from that of the last one (1 for the
    /// first): a step with probability `gain_step_chance`, else the same.
    /// Draws nothing from `rng` when steps are off, so a scenario without them
    /// renders byte for byte as before.
    pub fn next_gain(&self, gain: f64, rng: &mut ChaCha8Rng) -> f64 {
        if self.gain_step_chance <= 0.0 {
            return gain;
        }
        if rng.random::<f64>() >= self.gain_step_chance {
            return gain;
        }
        let span = (1.0 + self.gain_step_max).ln();
        let factor = rng.random_range(-span..=span).exp();
        (gain * factor).clamp(self.gain_min, self.gain_max)
    }
}

/// Longest exposure a scenario may ask for, ms.
pub const MAX_EXPOSURE_MS: f64 = 100.0;
/// Most camera poses one exposure may average.
pub const MAX_EXPOSURE_SAMPLES: usize = 64;
/// Most threads shading one image (the machine's cores up to this).
const MAX_RENDER_THREADS: usize = 8;
/// Rows of an image one thread shades at a time.
const RENDER_BAND_ROWS: usize = 16;

/// One pixel's ray: normalized direction `[x, y, 1]` and its footprint (the
/// pixel's width in normalized units); `fp` is NaN where undistortion fails.
#[derive(Clone, Copy, Debug)]
struct PixelRay {
    x: f64,
    y: f64,
    fp: f64,
}

/// Renders images of the textured room through one camera.
#[derive(Clone)]
pub struct Renderer {
    room: Room,
    textures: Vec<Texture>,
    /// Per face: texture offset (texels) and brightness gain.
    offsets: [[f32; 2]; 6],
    gains: [f32; 6],
    texel_m: f64,
    noise: f64,
    calib: CameraCalibration,
    rays: Vec<PixelRay>,
    /// Threads that shade an image (bands of rows taken in turn).
    threads: usize,
}

impl std::fmt::Debug for Renderer {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("Renderer")
            .field("room", &self.room)
            .field("texel_m", &self.texel_m)
            .finish_non_exhaustive()
    }
}

impl Renderer {
    /// A room around `positions` (the trajectories), textured from `rng`, seen
    /// through the true calibration `calib`.
    pub fn new(
        spec: &RenderSpec,
        calib: &CameraCalibration,
        positions: impl IntoIterator<Item = Vector3<f64>>,
        rng: &mut ChaCha8Rng,
    ) -> Result<Self, RenderError> {
        spec.validate()?;
        check_image_size(calib)?;
        let room = Room::around(
            positions,
            spec.wall_margin_m,
            spec.floor_below_m,
            spec.ceiling_above_m,
        )
        .ok_or(RenderError::NoTrajectory)?;
        let textures: Vec<Texture> = (0..6)
            .map(|_| Texture::dead_leaves(spec.texture_px, rng))
            .collect();
        let side = spec.texture_px as f32;
        let offsets =
            std::array::from_fn(|_| [rng.random_range(0.0..side), rng.random_range(0.0..side)]);
        let gains = std::array::from_fn(|_| rng.random_range(0.75..1.0));
        Ok(Self {
            room,
            textures,
            offsets,
            gains,
            texel_m: spec.texel_m,
            noise: spec.intensity_noise_gray,
            calib: calib.clone(),
            rays: pixel_rays(calib),
            threads: std::thread::available_parallelism()
                .map_or(1, std::num::NonZeroUsize::get)
                .min(MAX_RENDER_THREADS),
        })
    }

    /// The same room and textures seen through another camera `calib` (a
    /// robot of the fleet with its own lens).
    pub fn with_camera(&self, calib: &CameraCalibration) -> Result<Self, RenderError> {
        check_image_size(calib)?;
        Ok(Self {
            calib: calib.clone(),
            rays: pixel_rays(calib),
            ..self.clone()
        })
    }

    /// The room.
    pub fn room(&self) -> &Room {
        &self.room
    }

    /// The image seen from camera pose `t_c_to_g`, with intensity noise from
    /// `rng`. Fails only for an image size [`GrayImage`] does not hold.
    pub fn render(&self, t_c_to_g: &Se3, rng: &mut ChaCha8Rng) -> Result<GrayImage, ImageError> {
        self.render_exposed(std::slice::from_ref(t_c_to_g), 1.0, rng)
    }

    /// The image of an exposure during which the camera took the poses
    /// `t_c_to_g` (each pixel the mean of their intensities: motion blur),
    /// brightened by `gain` (the auto-exposure's: the scene's light scaled
    /// before the sensor's noise, saturating at 255), with intensity noise from
    /// `rng`. One pose at gain 1 is [`Renderer::render`]; none gives a black
    /// image.
    pub fn render_exposed(
        &self,
        t_c_to_g: &[Se3],
        gain: f64,
        rng: &mut ChaCha8Rng,
    ) -> Result<GrayImage, ImageError> {
        let cam = &self.calib.camera;
        let (w, h) = (cam.width, cam.height);
        let poses: Vec<_> = t_c_to_g.iter().map(|p| (p.rot, p.trans)).collect();
        // The noise is drawn first, in pixel order (the order it always had),
        // so the image is the same however many threads shade it.
        let noise: Vec<f64> = (0..self.rays.len())
            .map(|_| StandardNormal.sample(rng))
            .collect();
        let mut data = vec![0u8; self.rays.len()];
        // Bands of rows, taken in turn by this thread and its helpers.
        let band = (RENDER_BAND_ROWS * w as usize).max(1);
        let bands = std::sync::Mutex::new(
            data.chunks_mut(band)
                .zip(self.rays.chunks(band).zip(noise.chunks(band))),
        );
        let work = || loop {
            let next = match bands.lock() {
                Ok(mut it) => it.next(),
                Err(_) => None,
            };
            let Some((out, (rays, noise))) = next else {
                break;
            };
            self.shade_pixels(&poses, gain, rays, noise, out);
        };
        std::thread::scope(|scope| {
            for _ in 1..self.threads {
                // A helper that cannot be started leaves its bands to the others.
                if std::thread::Builder::new()
                    .spawn_scoped(scope, work)
                    .is_err()
                {
                    break;
                }
            }
            work();
        });
        GrayImage::new(w, h, data)
    }

    /// The same renderer shading each image on `threads` threads (at least
    /// one); the images do not depend on it.
    pub fn with_threads(mut self, threads: usize) -> Self {
        self.threads = threads.max(1);
        self
    }

    /// Gray levels of the pixels `rays`, with their noise draws `noise`: the
    /// mean over `poses`, brightened by `gain`.
    fn shade_pixels(
        &self,
        poses: &[(nalgebra::Matrix3<f64>, Vector3<f64>)],
        gain: f64,
        rays: &[PixelRay],
        noise: &[f64],
        out: &mut [u8],
    ) {
        let n = poses.len().max(1) as f64;
        for ((px, ray), noise) in out.iter_mut().zip(rays).zip(noise) {
            let value = poses
                .iter()
                .map(|(r, o)| self.shade(r, o, ray))
                .sum::<f64>()
                * gain
                / n;
            *px = gray_level(value + self.noise * noise);
        }
    }

    /// Noise-free intensity of one pixel.
    fn shade(&self, r: &nalgebra::Matrix3<f64>, o: &Vector3<f64>, ray: &PixelRay) -> f64 {
        if ray.fp.is_nan() {
            return 0.0;
        }
        let d = r * Vector3::new(ray.x, ray.y, 1.0);
        let Some(hit) = self.room.exit(o, &d) else {
            return 0.0;
        };
        let a = hit.face.axis;
        let (i, j) = ((a + 1) % 3, (a + 2) % 3);
        let k = hit.face.index();
        // Footprint: `s · fp / |d|` across the ray (its angular width times the
        // range), stretched on the surface by `|d| / |d_a|` along the slope and
        // not across it; the geometric mean of the two stretches is used.
        let footprint = hit.s * ray.fp / (d.norm() * d[a].abs()).sqrt();
        // A footprint within one texel is the finest level: the texture clamps
        // a negative level to 0, so the logarithm (a libm call for most pixels
        // of a room seen from inside it) is only taken above 1.
        let texels = footprint / self.texel_m;
        let level = if texels > 1.0 {
            texels.log2() as f32
        } else {
            0.0
        };
        let u = (hit.point[i] / self.texel_m) as f32 + self.offsets[k][0];
        let v = (hit.point[j] / self.texel_m) as f32 + self.offsets[k][1];
        f64::from(self.textures[k].sample(u, v, level) * self.gains[k])
    }

    /// The 3-D point (world frame, m) seen at raw pixel `uv` from `t_c_to_g`,
    /// `None` if the pixel does not undistort or the camera is outside the room.
    pub fn raycast(&self, t_c_to_g: &Se3, uv: &Vector2<f64>) -> Option<Vector3<f64>> {
        let n = self.calib.camera.undistort(uv).ok()?;
        let d = t_c_to_g.rot * Vector3::new(n.x, n.y, 1.0);
        self.room.exit(&t_c_to_g.trans, &d).map(|h| h.point)
    }
}

/// Refuses an image size [`GrayImage`] cannot hold.
fn check_image_size(calib: &CameraCalibration) -> Result<(), RenderError> {
    let cam = &calib.camera;
    let side = 1..=common::image::MAX_IMAGE_SIDE;
    if !side.contains(&cam.width) || !side.contains(&cam.height) {
        return Err(RenderError::Invalid(format!(
            "image size {}x{} is out of range",
            cam.width, cam.height
        )));
    }
    Ok(())
}

/// `x.round().clamp(0.0, 255.0) as u8`, exactly, without libm's `round`
/// (baseline x86-64 has no rounding instruction; it was 4 % of a rendered
/// run): negative and NaN give 0, and below 255 the fraction after the
/// truncation is exact, so halves round up as `round` rounds them.
fn gray_level(x: f64) -> u8 {
    if x.is_nan() || x <= 0.0 {
        return 0;
    }
    if x >= 255.0 {
        return 255;
    }
    let whole = x as u8;
    whole + u8::from(x - f64::from(whole) >= 0.5)
}

/// The ray of every pixel centre (row-major), with its footprint.
fn pixel_rays(calib: &CameraCalibration) -> Vec<PixelRay> {
    let cam = &calib.camera;
    let (w, h) = (cam.width as usize, cam.height as usize);
    let normalized: Vec<Option<Vector2<f64>>> = (0..h)
        .flat_map(|y| (0..w).map(move |x| (x, y)))
        .map(|(x, y)| cam.undistort(&Vector2::new(x as f64, y as f64)).ok())
        .collect();
    let at = |x: usize, y: usize| normalized[y * w + x];
    (0..h)
        .flat_map(|y| (0..w).map(move |x| (x, y)))
        .map(|(x, y)| {
            let Some(n) = at(x, y) else {
                return PixelRay {
                    x: 0.0,
                    y: 0.0,
                    fp: f64::NAN,
                };
            };
            // Pixel width from the neighbours (backwards at the last column/row).
            let nx = if x + 1 < w {
                at(x + 1, y)
            } else {
                at(x.saturating_sub(1), y)
            };
            let ny = if y + 1 < h {
                at(x, y + 1)
            } else {
                at(x, y.saturating_sub(1))
            };
            let fp = match (nx, ny) {
                (Some(a), Some(b)) => ((a - n).norm() * (b - n).norm()).sqrt(),
                _ => 1.0 / cam.fx(),
            };
            PixelRay { x: n.x, y: n.y, fp }
        })
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::world::camera_pose;
    use crate::{Fleet, Scenario, SimEvent};
    use rand::SeedableRng;
    use std::path::PathBuf;

    fn rendered_v1_01() -> Fleet {
        let path = PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("../scenarios/v1_01_easy.yaml");
        let mut sc = Scenario::load(&path).expect("scenario");
        sc.render.enabled = true;
        Fleet::build(&sc, 7).expect("fleet")
    }

    #[test]
    fn rendered_frames_are_textured_and_pixels_cast_back_onto_their_points() {
        let fleet = rendered_v1_01();
        let renderer = Renderer::clone(fleet.renderer(0).expect("renderer"));
        let truth = &fleet.truths[0];
        let cam = fleet.true_calibrations[0].clone();
        let mut checked = 0;
        for ev in fleet.stream(0).expect("stream").take(4000) {
            let SimEvent::Camera(c) = ev else { continue };
            assert!(
                c.frame.features.is_empty(),
                "rendered frames carry no simulated features"
            );
            let img = c.image.as_ref().expect("image");
            assert_eq!((img.width(), img.height()), (752, 480));
            let px = img.data();
            let mean = px.iter().map(|&v| f64::from(v)).sum::<f64>() / px.len() as f64;
            let var = px
                .iter()
                .map(|&v| (f64::from(v) - mean).powi(2))
                .sum::<f64>()
                / px.len() as f64;
            assert!(var.sqrt() > 20.0, "a textured image, std {}", var.sqrt());
            let black = px.iter().filter(|&&v| v == 0).count();
            assert!(
                black < px.len() / 100,
                "the room surrounds the camera: {black} black pixels"
            );
            let pose = camera_pose(truth, &cam, c.truth.t).expect("pose");
            for uv in [
                Vector2::new(5.0, 7.0),
                Vector2::new(376.0, 240.0),
                Vector2::new(740.5, 470.25),
            ] {
                let p = renderer.raycast(&pose, &uv).expect("hit");
                let back = cam
                    .camera
                    .project(&pose.inverse().transform_point(&p))
                    .expect("in front");
                assert!((back - uv).norm() < 1e-6, "{uv} -> {back}");
            }
            checked += 1;
        }
        assert!(checked >= 3, "{checked} frames");
    }

    #[test]
    fn gray_levels_round_and_saturate_as_libm_round_does() {
        let libm = |x: f64| x.round().clamp(0.0, 255.0) as u8;
        let mut xs = vec![
            f64::NAN,
            f64::NEG_INFINITY,
            f64::INFINITY,
            -0.0,
            0.0,
            -0.5,
            -0.4999999999999999,
            0.49999999999999994,
            0.5,
            254.49999999999997,
            254.5,
            254.99999999999997,
            255.0,
            255.49999999999997,
            255.5,
            1e300,
            f64::MIN_POSITIVE,
        ];
        // Every half step and its neighbours on either side.
        for k in -20..=540 {
            let x = f64::from(k) * 0.5;
            xs.extend([x, x.next_up(), x.next_down()]);
        }
        xs.extend((0..100_000).map(|i| -10.0 + f64::from(i) * 0.002_777_7));
        for x in xs {
            assert_eq!(gray_level(x), libm(x), "{x:e}");
        }
    }

    #[test]
    fn rendering_is_a_pure_function_of_the_seed() {
        let a = rendered_v1_01();
        let b = rendered_v1_01();
        let first = |f: &Fleet| {
            f.stream(0)
                .expect("stream")
                .find_map(|e| match e {
                    SimEvent::Camera(c) => c.image.clone(),
                    SimEvent::Imu(_) => None,
                })
                .expect("image")
        };
        assert_eq!(first(&a), first(&b));
    }

    #[test]
    fn images_do_not_depend_on_the_threads_that_shade_them() {
        let fleet = rendered_v1_01();
        let renderer = Renderer::clone(fleet.renderer(0).expect("renderer"));
        let (truth, cam) = (&fleet.truths[0], &fleet.true_calibrations[0]);
        let poses: Vec<Se3> = [30.0, 30.004, 30.008]
            .iter()
            .map(|&t| camera_pose(truth, cam, t).expect("pose"))
            .collect();
        let image = |threads: usize| {
            let mut rng = ChaCha8Rng::seed_from_u64(5);
            let r = Renderer::clone(&renderer).with_threads(threads);
            let img = r.render_exposed(&poses, 1.3, &mut rng).expect("image");
            // The next draw too: each image takes as many as it has pixels.
            (img, rng.random::<u64>())
        };
        let one = image(1);
        for threads in [0, 2, 3, 7] {
            assert!(image(threads) == one, "{threads} threads");
        }
    }

    /// Mean absolute difference of horizontally neighbouring pixels.
    fn sharpness(img: &GrayImage) -> f64 {
        let (w, px) = (img.width() as usize, img.data());
        let mut sum = 0.0;
        let mut n = 0usize;
        for row in px.chunks(w) {
            for pair in row.windows(2) {
                sum += (f64::from(pair[0]) - f64::from(pair[1])).abs();
                n += 1;
            }
        }
        sum / n as f64
    }

    #[test]
    fn an_exposure_blurs_a_moving_camera_and_not_a_still_one() {
        let fleet = rendered_v1_01();
        let renderer = Renderer::clone(fleet.renderer(0).expect("renderer"));
        let truth = &fleet.truths[0];
        let cam = fleet.true_calibrations[0].clone();
        let spec = RenderSpec {
            exposure_ms: 20.0,
            exposure_samples: 8,
            ..RenderSpec::default()
        };
        let times = spec.exposure_times(30.0);
        assert_eq!(times.len(), 8);
        assert!((times.iter().sum::<f64>() / 8.0 - 30.0).abs() < 1e-12);
        assert!((times[7] - times[0] - 0.0175).abs() < 1e-12);
        assert_eq!(RenderSpec::default().exposure_times(30.0), vec![30.0]);
        let rng = || ChaCha8Rng::seed_from_u64(3);
        let pose = |t| camera_pose(truth, &cam, t).expect("pose");
        // V1_01 at 30 s moves; 20 ms of it smears the texture.
        let sharp = renderer.render(&pose(30.0), &mut rng()).expect("image");
        let poses: Vec<Se3> = times.iter().map(|&t| pose(t)).collect();
        let blurred = renderer
            .render_exposed(&poses, 1.0, &mut rng())
            .expect("image");
        let (s, b) = (sharpness(&sharp), sharpness(&blurred));
        println!("sharpness: {s:.2} sharp, {b:.2} over 20 ms");
        assert!(b < 0.8 * s, "sharpness {b} blurred against {s}");
        // A camera that does not move during the exposure takes the same picture.
        let still = renderer
            .render_exposed(&[pose(30.0), pose(30.0), pose(30.0)], 1.0, &mut rng())
            .expect("image");
        let diff = still
            .data()
            .iter()
            .zip(sharp.data())
            .filter(|(a, b)| a != b)
            .count();
        assert!(diff * 1000 < sharp.data().len(), "{diff} pixels differ");
        assert_eq!(
            renderer
                .render_exposed(&[pose(30.0)], 1.0, &mut rng())
                .expect("image"),
            sharp
        );
    }

    #[test]
    fn auto_exposure_steps_brighten_and_darken_within_their_bounds() {
        let spec = RenderSpec {
            gain_step_chance: 0.25,
            gain_step_max: 0.2,
            ..RenderSpec::default()
        };
        let mut rng = ChaCha8Rng::seed_from_u64(5);
        let mut gain = 1.0;
        let (mut steps, mut largest) = (0usize, 0.0f64);
        let (mut lo, mut hi) = (1.0f64, 1.0f64);
        for _ in 0..4000 {
            let next = spec.next_gain(gain, &mut rng);
            if next != gain {
                steps += 1;
                largest = largest.max((next / gain).ln().abs());
            }
            (lo, hi) = (lo.min(next), hi.max(next));
            gain = next;
        }
        // About a quarter of the images step, none by more than 20 %, and the
        // brightness wanders over its whole range without leaving it.
        assert!((800..1200).contains(&steps), "{steps} steps");
        assert!(largest <= 1.2f64.ln() + 1e-12, "step {largest}");
        assert!(lo >= 0.6 && hi <= 1.4, "{lo}..{hi}");
        assert!(lo < 0.75 && hi > 1.25, "{lo}..{hi}");
        // Off, nothing is drawn: the noise stream is untouched.
        let mut a = ChaCha8Rng::seed_from_u64(5);
        assert_eq!(RenderSpec::default().next_gain(0.9, &mut a), 0.9);
        assert_eq!(a, ChaCha8Rng::seed_from_u64(5));
        // The gain scales the scene before the noise and saturates at 255.
        let fleet = rendered_v1_01();
        let renderer = Renderer::clone(fleet.renderer(0).expect("renderer"));
        let pose = camera_pose(&fleet.truths[0], &fleet.true_calibrations[0], 30.0).expect("pose");
        let quiet = Renderer {
            noise: 0.0,
            ..renderer.clone()
        };
        let mut rng = ChaCha8Rng::seed_from_u64(3);
        let base = quiet.render_exposed(&[pose], 1.0, &mut rng).expect("image");
        let bright = quiet.render_exposed(&[pose], 1.3, &mut rng).expect("image");
        let mean = |img: &GrayImage| {
            img.data().iter().map(|&v| f64::from(v)).sum::<f64>() / img.data().len() as f64
        };
        let ratio = mean(&bright) / mean(&base);
        let saturated = bright.data().iter().filter(|&&v| v == 255).count();
        println!("gain 1.3: mean ratio {ratio:.3}, {saturated} pixels saturated");
        assert!(ratio > 1.25 && ratio < 1.31, "ratio {ratio}");
        assert!(saturated > 0);
    }

    #[test]
    fn bad_render_settings_are_refused() {
        let bad = RenderSpec {
            texture_px: 1000,
            ..RenderSpec::default()
        };
        assert!(bad
            .validate()
            .unwrap_err()
            .to_string()
            .contains("power of two"));
        let bad = RenderSpec {
            texel_m: -1.0,
            ..RenderSpec::default()
        };
        assert!(bad.validate().is_err());
        for (exposure_ms, exposure_samples) in [(-1.0, 8), (f64::NAN, 8), (500.0, 8), (5.0, 0)] {
            let bad = RenderSpec {
                exposure_ms,
                exposure_samples,
                ..RenderSpec::default()
            };
            assert!(bad.validate().unwrap_err().to_string().contains("exposure"));
        }
        for (chance, max, lo, hi) in [
            (-0.1, 0.2, 0.6, 1.4),
            (f64::NAN, 0.2, 0.6, 1.4),
            (0.1, 2.0, 0.6, 1.4),
            (0.1, 0.2, 1.2, 1.4),
            (0.1, 0.2, 0.6, 0.9),
        ] {
            let bad = RenderSpec {
                gain_step_chance: chance,
                gain_step_max: max,
                gain_min: lo,
                gain_max: hi,
                ..RenderSpec::default()
            };
            assert!(bad.validate().unwrap_err().to_string().contains("gain"));
        }
    }
}
