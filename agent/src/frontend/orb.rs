//! ORB descriptors (256-bit rBRIEF) of given points, oriented by the intensity
//! centroid of their patch (Rublee et al. 2011, Eq. 2-3) so they match across
//! in-plane rotations, as the peers' and the vocabulary's matching needs.

use common::descriptor::Descriptor;
use nalgebra::Vector2;
use opencv::core::{KeyPoint, Mat, Ptr, Vector};
use opencv::features2d::{ORB_ScoreType, ORB};
use opencv::prelude::*;

/// ORB's patch side, pixels.
const PATCH_SIZE: i32 = 31;
/// Radius of the patch for the orientation, pixels.
const HALF_PATCH: i32 = PATCH_SIZE / 2;
/// ORB drops keypoints closer than this to the border.
const EDGE_THRESHOLD: i32 = 19;

/// Computes ORB descriptors at given points of one image.
pub struct OrbDescriber {
    orb: Ptr<ORB>,
}

impl OrbDescriber {
    /// A describer on the full-resolution image only (the points are tracked
    /// features at their own scale).
    pub fn new() -> opencv::Result<Self> {
        let orb = ORB::create(
            1000,
            1.2,
            1,
            EDGE_THRESHOLD,
            0,
            2,
            ORB_ScoreType::HARRIS_SCORE,
            PATCH_SIZE,
            20,
        )?;
        Ok(Self { orb })
    }

    /// The descriptor of each point (`None` where ORB cannot describe it, too
    /// near the border). `gray` is the image's pixels, `width` its row length.
    pub fn describe(
        &mut self,
        img: &Mat,
        gray: &[u8],
        width: usize,
        points: &[Vector2<f64>],
    ) -> opencv::Result<Vec<Option<Descriptor>>> {
        let mut kps = Vector::<KeyPoint>::new();
        for (i, p) in points.iter().enumerate() {
            let angle = ic_angle_deg(gray, width, p).unwrap_or(0.0);
            let class_id = i32::try_from(i).unwrap_or(i32::MAX);
            kps.push(KeyPoint::new_coords(
                p.x as f32,
                p.y as f32,
                PATCH_SIZE as f32,
                angle,
                0.0,
                0,
                class_id,
            )?);
        }
        let mut desc = Mat::default();
        self.orb.compute(img, &mut kps, &mut desc)?;
        let mut out = vec![None; points.len()];
        let bytes = if desc.empty() {
            &[][..]
        } else {
            desc.data_bytes()?
        };
        for (row, kp) in kps.iter().enumerate() {
            let Some(chunk) = bytes.get(row * 32..row * 32 + 32) else {
                break;
            };
            let mut b = [0u8; 32];
            b.copy_from_slice(chunk);
            if let Some(slot) = usize::try_from(kp.class_id())
                .ok()
                .and_then(|i| out.get_mut(i))
            {
                *slot = Some(Descriptor::from_bytes(&b));
            }
        }
        Ok(out)
    }
}

/// Orientation of the patch around `p`: the angle of its intensity centroid
/// `atan2(m01, m10)` with `m_pq = Σ x^p y^q I(x, y)` over a disc of radius 15,
/// in degrees in `[0, 360)`; `None` when the disc leaves the image.
fn ic_angle_deg(gray: &[u8], width: usize, p: &Vector2<f64>) -> Option<f32> {
    let height = gray.len() / width.max(1);
    let (cx, cy) = (p.x.round() as i64, p.y.round() as i64);
    let r = i64::from(HALF_PATCH);
    if cx < r || cy < r || cx + r >= width as i64 || cy + r >= height as i64 {
        return None;
    }
    let (mut m01, mut m10) = (0i64, 0i64);
    for dy in -r..=r {
        for dx in -r..=r {
            if dx * dx + dy * dy > r * r {
                continue;
            }
            let v = i64::from(gray[((cy + dy) as usize) * width + (cx + dx) as usize]);
            m10 += dx * v;
            m01 += dy * v;
        }
    }
    let deg = (m01 as f64).atan2(m10 as f64).to_degrees();
    Some(deg.rem_euclid(360.0) as f32)
}
