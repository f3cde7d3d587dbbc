//! New features on a grid: corner candidates from FAST or Shi-Tomasi, taken
//! strongest first, at most an equal share per grid cell (so the features
//! spread over the image), never closer than `min_distance_px` to each other
//! or to a tracked feature, and never within `border_px` of the border.

use super::{Detector, FrontendOptions};
use nalgebra::Vector2;
use opencv::core::{KeyPoint, Mat, Point2f, Rect, ToInputArray, Vector};
use opencv::prelude::*;
use opencv::{features2d, imgproc};

/// Shi-Tomasi quality level: corners weaker than this fraction of the best
/// are not candidates.
const SHI_TOMASI_QUALITY: f64 = 0.005;
/// A cell's search area reaches this far into its neighbours, pixels (FAST's
/// circle radius is 3).
const CELL_PAD_PX: f64 = 4.0;

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

/// The detection grid over an image: cell index of a point and pixel rectangle
/// of a cell.
struct Grid {
    cols: usize,
    rows: usize,
    width: f64,
    height: f64,
}

impl Grid {
    fn cell(&self, p: &Vector2<f64>) -> usize {
        let c = ((p.x / self.width) * self.cols as f64).floor().max(0.0) as usize;
        let r = ((p.y / self.height) * self.rows as f64).floor().max(0.0) as usize;
        r.min(self.rows - 1) * self.cols + c.min(self.cols - 1)
    }

    /// Pixel rectangle `[x0, x1) x [y0, y1)` of cell `k`, cut to `border` from
    /// the image edges and grown by `pad` (so corner detectors see whole
    /// neighbourhoods at the cell's edges).
    fn rect(&self, k: usize, border: f64, pad: f64) -> Option<Rect> {
        let (c, r) = ((k % self.cols) as f64, (k / self.cols) as f64);
        let (cw, ch) = (
            self.width / self.cols as f64,
            self.height / self.rows as f64,
        );
        let x0 = (c * cw - pad).max(border).floor();
        let y0 = (r * ch - pad).max(border).floor();
        let x1 = ((c + 1.0) * cw + pad).min(self.width - border).ceil();
        let y1 = ((r + 1.0) * ch + pad).min(self.height - border).ceil();
        (x1 - x0 >= 8.0 && y1 - y0 >= 8.0)
            .then(|| Rect::new(x0 as i32, y0 as i32, (x1 - x0) as i32, (y1 - y0) as i32))
    }
}

/// Up to `want` new features in `img`, given the tracked ones. Only the grid
/// cells below their share are searched (most cells are full in steady state,
/// which keeps detection cheap).
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
    let grid = Grid {
        cols: opts.grid_cols,
        rows: opts.grid_rows,
        width: f64::from(width),
        height: f64::from(height),
    };
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
    for p in existing {
        occupancy.add(*p);
        per_cell[grid.cell(p)] += 1;
    }
    let quota = opts.num_features.div_ceil(cells);
    let mut candidates = Vec::new();
    for (k, &n) in per_cell.iter().enumerate() {
        if n >= quota {
            continue;
        }
        if let Some(rect) = grid.rect(k, border, CELL_PAD_PX) {
            let roi = Mat::roi(img, rect)?;
            let offset = Vector2::new(f64::from(rect.x), f64::from(rect.y));
            for mut c in cell_candidates(&roi, quota, opts)? {
                c.uv += offset;
                if grid.cell(&c.uv) == k {
                    candidates.push(c);
                }
            }
        }
    }
    candidates.sort_by(|a, b| b.strength.total_cmp(&a.strength));
    let mut out = Vec::with_capacity(want);
    // First pass: the grid quota spreads the features; second pass: fill up
    // from the same cells if some had too little texture for their share.
    for respect_quota in [true, false] {
        for cand in &candidates {
            if out.len() >= want {
                return Ok(out);
            }
            let p = cand.uv;
            if !inside(&p) || !occupancy.free(&p) {
                continue;
            }
            let cell = grid.cell(&p);
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

/// Corner candidates of the configured detector in one cell's image.
fn cell_candidates(
    img: &impl ToInputArray,
    quota: usize,
    opts: &FrontendOptions,
) -> opencv::Result<Vec<Candidate>> {
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
            let max = i32::try_from(4 * quota).unwrap_or(i32::MAX);
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
            // Returned strongest first: the rank is the strength.
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
