//! New features on a grid: corner candidates from FAST or Shi-Tomasi, taken
//! strongest first, at most an equal share per grid cell (so the features
//! spread over the image), never closer than `min_distance_px` to each other
//! or to a tracked feature, and never within `border_px` of the border.

use super::{Detector, FrontendOptions};
use nalgebra::Vector2;
use opencv::core::{KeyPoint, Mat, Point2f, Vector};
use opencv::prelude::*;
use opencv::{features2d, imgproc};

/// Shi-Tomasi quality level: corners weaker than this fraction of the best
/// are not candidates.
const SHI_TOMASI_QUALITY: f64 = 0.005;

/// A candidate corner and its strength (higher is better).
struct Candidate {
    uv: Vector2<f64>,
    strength: f32,
}

/// Occupancy of the image by features, on cells of `min_distance` pixels, for
/// constant-time "is anything closer than `min_distance`" checks.
struct Occupancy {
    cell: f64,
    cols: usize,
    rows: usize,
    points: Vec<Vec<Vector2<f64>>>,
}

impl Occupancy {
    fn new(width: u32, height: u32, min_distance: f64) -> Self {
        let cols = (f64::from(width) / min_distance).ceil() as usize + 1;
        let rows = (f64::from(height) / min_distance).ceil() as usize + 1;
        Self {
            cell: min_distance,
            cols,
            rows,
            points: vec![Vec::new(); cols * rows],
        }
    }

    fn cell_of(&self, p: &Vector2<f64>) -> (usize, usize) {
        let c = (p.x / self.cell).floor().clamp(0.0, (self.cols - 1) as f64) as usize;
        let r = (p.y / self.cell).floor().clamp(0.0, (self.rows - 1) as f64) as usize;
        (c, r)
    }

    fn free(&self, p: &Vector2<f64>) -> bool {
        let (c, r) = self.cell_of(p);
        let d2 = self.cell * self.cell;
        for rr in r.saturating_sub(1)..=(r + 1).min(self.rows - 1) {
            for cc in c.saturating_sub(1)..=(c + 1).min(self.cols - 1) {
                if self.points[rr * self.cols + cc]
                    .iter()
                    .any(|q| (q - p).norm_squared() < d2)
                {
                    return false;
                }
            }
        }
        true
    }

    fn add(&mut self, p: Vector2<f64>) {
        let (c, r) = self.cell_of(&p);
        self.points[r * self.cols + c].push(p);
    }
}

/// Up to `want` new features in `img`, given the tracked ones.
pub fn detect_new(
    img: &Mat,
    existing: &[Vector2<f64>],
    want: usize,
    opts: &FrontendOptions,
) -> opencv::Result<Vec<Vector2<f64>>> {
    if want == 0 {
        return Ok(Vec::new());
    }
    let (width, height) = (img.cols().max(0) as u32, img.rows().max(0) as u32);
    let mut candidates = candidates(img, want, opts)?;
    candidates.sort_by(|a, b| b.strength.total_cmp(&a.strength));
    let border = f64::from(opts.border_px);
    let inside = |p: &Vector2<f64>| {
        p.x >= border
            && p.y >= border
            && p.x < f64::from(width) - border
            && p.y < f64::from(height) - border
    };
    let mut occupancy = Occupancy::new(width, height, opts.min_distance_px);
    let cells = opts.grid_cols * opts.grid_rows;
    let mut per_cell = vec![0usize; cells];
    let grid_cell = |p: &Vector2<f64>| {
        let c = ((p.x / f64::from(width)) * opts.grid_cols as f64).floor() as usize;
        let r = ((p.y / f64::from(height)) * opts.grid_rows as f64).floor() as usize;
        r.min(opts.grid_rows - 1) * opts.grid_cols + c.min(opts.grid_cols - 1)
    };
    for p in existing {
        occupancy.add(*p);
        per_cell[grid_cell(p)] += 1;
    }
    let quota = opts.num_features.div_ceil(cells);
    let mut out = Vec::with_capacity(want);
    // First pass: the grid quota spreads the features; second pass: fill up
    // where texture allows, if some cells had too little.
    for respect_quota in [true, false] {
        for cand in &candidates {
            if out.len() >= want {
                return Ok(out);
            }
            let p = cand.uv;
            if !inside(&p) || !occupancy.free(&p) {
                continue;
            }
            let cell = grid_cell(&p);
            if respect_quota && per_cell[cell] >= quota {
                continue;
            }
            per_cell[cell] += 1;
            occupancy.add(p);
            out.push(p);
        }
    }
    Ok(out)
}

/// Corner candidates of the configured detector.
fn candidates(img: &Mat, want: usize, opts: &FrontendOptions) -> opencv::Result<Vec<Candidate>> {
    match opts.detector {
        Detector::Fast => {
            let mut kps = Vector::<KeyPoint>::new();
            features2d::fast(img, &mut kps, opts.fast_threshold, true)?;
            Ok(kps
                .iter()
                .map(|k| Candidate {
                    uv: Vector2::new(f64::from(k.pt().x), f64::from(k.pt().y)),
                    strength: k.response(),
                })
                .collect())
        }
        Detector::ShiTomasi => {
            let mut corners = Vector::<Point2f>::new();
            let max = i32::try_from(4 * want + 4 * opts.num_features).unwrap_or(i32::MAX);
            imgproc::good_features_to_track(
                img,
                &mut corners,
                max,
                SHI_TOMASI_QUALITY,
                opts.min_distance_px,
                &Mat::default(),
                3,
                false,
                0.04,
            )?;
            // Returned strongest first: rank is the strength.
            let n = corners.len() as f32;
            Ok(corners
                .iter()
                .enumerate()
                .map(|(i, p)| Candidate {
                    uv: Vector2::new(f64::from(p.x), f64::from(p.y)),
                    strength: n - i as f32,
                })
                .collect())
        }
    }
}
