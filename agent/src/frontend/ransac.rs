//! Outlier rejection between two frames: a fundamental matrix fitted with
//! RANSAC to the undistorted matches. Undistorted points are mapped back to
//! "ideal" pixels `K · [x, y, 1]` (the camera's focal lengths and centre, no
//! distortion), so the epipolar threshold keeps its meaning in pixels over the
//! whole image, also where the lens distortion is strong.

use common::camera::CameraModel;
use nalgebra::Vector2;
use opencv::calib3d;
use opencv::core::{Mat, Point2f, Vector};
use opencv::prelude::*;

/// RANSAC needs more matches than the 8-point minimum to mean anything.
const MIN_MATCHES: usize = 12;
/// RANSAC confidence.
const CONFIDENCE: f64 = 0.999;
/// RANSAC iterations at most.
const MAX_ITERATIONS: i32 = 500;

/// The ideal pixel of a raw pixel, `None` where undistortion fails.
fn ideal(camera: &CameraModel, uv: &Vector2<f64>) -> Option<Point2f> {
    let n = camera.undistort(uv).ok()?;
    Some(Point2f::new(
        (camera.fx() * n.x + camera.cx()) as f32,
        (camera.fy() * n.y + camera.cy()) as f32,
    ))
}

/// Which of the matches `prev[i] ↔ cur[i]` (raw pixels) are epipolar inliers.
/// Matches that do not undistort are outliers; with fewer than 12 usable
/// matches every usable one is kept (too few to tell).
pub fn epipolar_inliers(
    camera: &CameraModel,
    prev: &[Vector2<f64>],
    cur: &[Vector2<f64>],
    threshold_px: f64,
) -> opencv::Result<Vec<bool>> {
    let mut usable = Vec::with_capacity(prev.len());
    let (mut a, mut b) = (Vector::<Point2f>::new(), Vector::<Point2f>::new());
    for (p, c) in prev.iter().zip(cur) {
        match (ideal(camera, p), ideal(camera, c)) {
            (Some(p), Some(c)) => {
                a.push(p);
                b.push(c);
                usable.push(true);
            }
            _ => usable.push(false),
        }
    }
    if a.len() < MIN_MATCHES {
        return Ok(usable);
    }
    let mut mask = Mat::default();
    let f = calib3d::find_fundamental_mat(
        &a,
        &b,
        calib3d::FM_RANSAC,
        threshold_px,
        CONFIDENCE,
        MAX_ITERATIONS,
        &mut mask,
    )?;
    // No model (degenerate motion, e.g. no parallax at all): keep everything.
    if f.empty() || mask.empty() {
        return Ok(usable);
    }
    let flags = mask.data_bytes()?;
    let mut k = 0;
    Ok(usable
        .into_iter()
        .map(|u| {
            if !u {
                return false;
            }
            let inlier = flags.get(k).is_some_and(|&m| m != 0);
            k += 1;
            inlier
        })
        .collect())
}
