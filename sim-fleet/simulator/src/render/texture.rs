//! Seamless (toroidal) grayscale textures with a mip pyramid, sampled
//! trilinearly so that far or grazing surfaces do not alias.
//!
//! The pattern is a "dead leaves" image: overlapping discs and squares whose
//! radii follow a `r⁻³` density, the size distribution that makes the image
//! look alike at every scale (the statistics of natural images). It has edges
//! and corners at every distance, which is what corner detectors and KLT need.

use rand::Rng;
use rand_chacha::ChaCha8Rng;

/// Smallest shape radius, texels.
const MIN_RADIUS_TEXELS: f64 = 1.5;
/// Each texel is painted this many times on average: enough that no
/// background shows through.
const COVERAGE: f64 = 6.0;
/// The coarsest mip level has this many texels per side.
const COARSEST_SIDE: usize = 4;

/// A square texture of side `2^k` with its mip pyramid (level 0 is full size).
#[derive(Clone, Debug)]
pub struct Texture {
    levels: Vec<Vec<u8>>,
    side: usize,
}

impl Texture {
    /// A dead-leaves texture of `side` texels (a power of two, at least 8).
    pub fn dead_leaves(side: usize, rng: &mut ChaCha8Rng) -> Self {
        let side = side.next_power_of_two().max(8);
        let mut img = vec![128u8; side * side];
        let (a, b) = (MIN_RADIUS_TEXELS, side as f64 / 8.0);
        // Inverse CDF of p(r) ∝ r⁻³ on [a, b].
        let (ia, ib) = (a.powi(-2), b.powi(-2));
        // Mean area of a shape, E[π r²] = 2π ln(b/a) / (a⁻² - b⁻²).
        let mean_area = 2.0 * std::f64::consts::PI * (b / a).ln() / (ia - ib);
        let count = (COVERAGE * (side * side) as f64 / mean_area) as usize;
        for _ in 0..count {
            let u: f64 = rng.random();
            let r = (ia - u * (ia - ib)).powf(-0.5);
            let cx = rng.random_range(0.0..side as f64);
            let cy = rng.random_range(0.0..side as f64);
            let gray = rng.random_range(10..=245u8);
            let square = rng.random::<bool>();
            paint(&mut img, side, (cx, cy), r, square, gray);
        }
        let mut levels = vec![img];
        let mut s = side;
        while s > COARSEST_SIDE {
            let next = downsample(levels.last().map(Vec::as_slice).unwrap_or(&[]), s);
            levels.push(next);
            s /= 2;
        }
        Self { levels, side }
    }

    /// Texels per side at level 0.
    pub fn side(&self) -> usize {
        self.side
    }

    /// Intensity (0-255) at texel coordinates `(u, v)` of level 0 (wrapping),
    /// filtered for a footprint of `2^level` texels (trilinear).
    pub fn sample(&self, u: f32, v: f32, level: f32) -> f32 {
        let max = (self.levels.len() - 1) as f32;
        let level = level.clamp(0.0, max);
        // Non-negative: truncation is the floor.
        let l0 = level as usize;
        let w = level - l0 as f32;
        let s0 = self.bilinear(l0, u, v);
        if w <= 0.0 || l0 + 1 >= self.levels.len() {
            return s0;
        }
        s0 * (1.0 - w) + self.bilinear(l0 + 1, u, v) * w
    }

    fn bilinear(&self, level: usize, u: f32, v: f32) -> f32 {
        let side = self.side >> level;
        let mask = side as i64 - 1;
        let scale = 1.0 / (1u32 << level) as f32;
        // Texel centres at integer coordinates of their level.
        let (x, y) = (u * scale, v * scale);
        let (x0, y0) = (floor_i64(x), floor_i64(y));
        let (fx, fy) = (x - x0 as f32, y - y0 as f32);
        let img = &self.levels[level];
        let at =
            |xi: i64, yi: i64| f32::from(img[((yi & mask) * side as i64 + (xi & mask)) as usize]);
        let top = at(x0, y0) * (1.0 - fx) + at(x0 + 1, y0) * fx;
        let bottom = at(x0, y0 + 1) * (1.0 - fx) + at(x0 + 1, y0 + 1) * fx;
        top * (1.0 - fy) + bottom * fy
    }
}

/// `x.floor() as i64`, without libm's `floorf` (baseline x86-64 has no
/// rounding instruction; it was 4 % of a rendered run). Exact: an `f32` of
/// magnitude 2^23 or more is an integer, and below that the truncation and
/// its conversion back are exact.
fn floor_i64(x: f32) -> i64 {
    let t = x as i64;
    if t as f32 > x {
        t - 1
    } else {
        t
    }
}

/// Paints a disc or an axis-aligned square of radius `r` centred at `c`,
/// wrapping around the borders.
fn paint(img: &mut [u8], side: usize, c: (f64, f64), r: f64, square: bool, gray: u8) {
    let n = side as i64;
    let (x0, x1) = ((c.0 - r).floor() as i64, (c.0 + r).ceil() as i64);
    let (y0, y1) = ((c.1 - r).floor() as i64, (c.1 + r).ceil() as i64);
    for y in y0..=y1 {
        let dy = y as f64 + 0.5 - c.1;
        for x in x0..=x1 {
            let dx = x as f64 + 0.5 - c.0;
            let inside = if square {
                dx.abs() <= r && dy.abs() <= r
            } else {
                dx * dx + dy * dy <= r * r
            };
            if inside {
                img[(y.rem_euclid(n) * n + x.rem_euclid(n)) as usize] = gray;
            }
        }
    }
}

/// The next mip level: means of 2x2 blocks.
fn downsample(img: &[u8], side: usize) -> Vec<u8> {
    let half = side / 2;
    let mut out = vec![0u8; half * half];
    for y in 0..half {
        for x in 0..half {
            let p = |dx: usize, dy: usize| u32::from(img[(2 * y + dy) * side + 2 * x + dx]);
            out[y * half + x] = ((p(0, 0) + p(1, 0) + p(0, 1) + p(1, 1) + 2) / 4) as u8;
        }
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;
    use rand::SeedableRng;

    #[test]
    fn floor_without_libm_is_the_floor() {
        let mut xs = vec![
            -0.0,
            0.0,
            -1.0,
            1.0,
            8_388_607.5,
            8_388_608.0,
            -8_388_608.5,
            16_777_217.0,
            -3.0e9,
            3.0e9,
        ];
        for k in -2000..=2000 {
            let x = k as f32 * 0.25;
            xs.extend([x, x.next_up(), x.next_down()]);
        }
        for x in xs {
            assert_eq!(floor_i64(x), x.floor() as i64, "{x:e}");
            // The fraction the bilinear weights take is the same number.
            assert_eq!(x - floor_i64(x) as f32, x - x.floor(), "{x:e}");
        }
    }

    #[test]
    fn texture_has_contrast_at_every_level_and_wraps() {
        let mut rng = ChaCha8Rng::seed_from_u64(3);
        let t = Texture::dead_leaves(256, &mut rng);
        assert_eq!(t.side(), 256);
        for level in [0.0, 2.0, 4.0] {
            let samples: Vec<f32> = (0..200)
                .map(|i| t.sample(i as f32 * 7.3, i as f32 * 3.1, level))
                .collect();
            let mean = samples.iter().sum::<f32>() / samples.len() as f32;
            let var = samples.iter().map(|s| (s - mean).powi(2)).sum::<f32>() / 200.0;
            assert!(var.sqrt() > 5.0, "level {level}: std {}", var.sqrt());
        }
        // One period further is the same texel.
        assert_eq!(
            t.sample(10.0, 20.0, 0.0),
            t.sample(266.0, 20.0 - 256.0, 0.0)
        );
    }
}
