//! How far a Monte-Carlo mean can be trusted. Results vary 2-4x between seeds,
//! so a mean over N seeds comes with its 95 % confidence interval (Student t on
//! the runs), and two variants (or two studies) run on the same seeds are
//! compared pairwise, seed by seed: the mean difference with its t interval, and
//! the ratio of the means with a seeded bootstrap interval. Pairing removes the
//! noise both share (the same trajectory, IMU and pixel noise), so a paired
//! interval is much narrower than the two unpaired ones side by side.

use serde::{Deserialize, Serialize};

/// Two-sided 95 % quantiles of Student's t for 1..=30 degrees of freedom.
const T975: [f64; 30] = [
    12.706, 4.303, 3.182, 2.776, 2.571, 2.447, 2.365, 2.306, 2.262, 2.228, 2.201, 2.179, 2.160,
    2.145, 2.131, 2.120, 2.110, 2.101, 2.093, 2.086, 2.080, 2.074, 2.069, 2.064, 2.060, 2.056,
    2.052, 2.048, 2.045, 2.042,
];

/// The two-sided 95 % quantile of Student's t with `dof` degrees of freedom
/// (`dof >= 1`): a table up to 30, the Cornish-Fisher expansion beyond (within
/// 1e-4 of the exact value there).
pub fn t975(dof: usize) -> f64 {
    if let Some(t) = dof.checked_sub(1).and_then(|i| T975.get(i)) {
        return *t;
    }
    let z = 1.959_963_984_540_054_f64;
    let v = dof.max(1) as f64;
    z + (z.powi(3) + z) / (4.0 * v)
        + (5.0 * z.powi(5) + 16.0 * z.powi(3) + 3.0 * z) / (96.0 * v * v)
}

/// A mean over runs with the half-width of its 95 % confidence interval.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct MeanCi {
    /// Number of values.
    pub n: usize,
    /// Their mean.
    pub mean: f64,
    /// Half-width of the 95 % interval of the mean (`t · s / √n`); `None` for
    /// fewer than two values.
    pub half_width: Option<f64>,
}

/// The mean of the finite `values` and its 95 % interval; `None` when there
/// is none.
pub fn mean_ci95(values: impl IntoIterator<Item = f64>) -> Option<MeanCi> {
    let v: Vec<f64> = values.into_iter().filter(|x| x.is_finite()).collect();
    let n = v.len();
    if n == 0 {
        return None;
    }
    let mean = v.iter().sum::<f64>() / n as f64;
    let half_width = (n >= 2).then(|| {
        let var = v.iter().map(|x| (x - mean).powi(2)).sum::<f64>() / (n - 1) as f64;
        t975(n - 1) * (var / n as f64).sqrt()
    });
    Some(MeanCi {
        n,
        mean,
        half_width,
    })
}

/// A paired comparison of `b` against `a` over the seeds both have.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct Paired {
    /// Seeds in the comparison.
    pub n: usize,
    /// Mean of `a`.
    pub mean_a: f64,
    /// Mean of `b`.
    pub mean_b: f64,
    /// Mean of `b − a`, seed by seed.
    pub diff: f64,
    /// Half-width of the 95 % t interval of `diff` (`None` for one seed).
    pub diff_ci95: Option<f64>,
    /// `mean_b / mean_a` (`None` when `mean_a` is 0).
    pub ratio: Option<f64>,
    /// The 2.5 % and 97.5 % bootstrap quantiles of the ratio of means (seeds
    /// resampled in pairs; `None` for one seed or a zero mean of `a`).
    pub ratio_ci95: Option<(f64, f64)>,
}

/// Bootstrap resamples of [`paired`].
pub const BOOTSTRAP_RESAMPLES: usize = 4000;

/// Compares `b` with `a` seed by seed (`pairs` = `(a, b)` per seed; pairs
/// with a non-finite side are left out). The bootstrap draws from a fixed
/// seed: the same pairs give the same interval, bit for bit.
pub fn paired(pairs: &[(f64, f64)]) -> Option<Paired> {
    let p: Vec<(f64, f64)> = pairs
        .iter()
        .copied()
        .filter(|(a, b)| a.is_finite() && b.is_finite())
        .collect();
    let n = p.len();
    let d = mean_ci95(p.iter().map(|(a, b)| b - a))?;
    let mean_a = p.iter().map(|(a, _)| a).sum::<f64>() / n as f64;
    let mean_b = p.iter().map(|(_, b)| b).sum::<f64>() / n as f64;
    let ratio = (mean_a != 0.0).then(|| mean_b / mean_a);
    let ratio_ci95 = if n >= 2 && ratio.is_some() {
        let mut rng = SplitMix64(0x5EED_B007_57A9_0F00);
        let mut ratios: Vec<f64> = (0..BOOTSTRAP_RESAMPLES)
            .filter_map(|_| {
                let (mut sa, mut sb) = (0.0, 0.0);
                for _ in 0..n {
                    let (a, b) = p[rng.below(n)];
                    sa += a;
                    sb += b;
                }
                (sa != 0.0).then(|| sb / sa)
            })
            .collect();
        ratios.sort_by(f64::total_cmp);
        quantile(&ratios, 0.025).zip(quantile(&ratios, 0.975))
    } else {
        None
    };
    Some(Paired {
        n,
        mean_a,
        mean_b,
        diff: d.mean,
        diff_ci95: d.half_width,
        ratio,
        ratio_ci95,
    })
}

/// The `q` quantile of sorted values (linear interpolation).
fn quantile(sorted: &[f64], q: f64) -> Option<f64> {
    let last = sorted.len().checked_sub(1)?;
    let x = q.clamp(0.0, 1.0) * last as f64;
    let (i, f) = (x.floor() as usize, x.fract());
    let lo = *sorted.get(i)?;
    let hi = *sorted.get((i + 1).min(last))?;
    Some(lo + f * (hi - lo))
}

/// SplitMix64: a small seeded generator for the bootstrap (statistics only).
struct SplitMix64(u64);

impl SplitMix64 {
    fn next(&mut self) -> u64 {
        self.0 = self.0.wrapping_add(0x9E37_79B9_7F4A_7C15);
        let mut z = self.0;
        z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
        z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
        z ^ (z >> 31)
    }

    /// Uniform in `0..n` (`n >= 1`; the modulo bias is below 1e-17 for the
    /// seed counts of a study).
    fn below(&mut self, n: usize) -> usize {
        (self.next() % n.max(1) as u64) as usize
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn t_quantiles_match_the_tables_and_the_expansion_beyond_them() {
        assert_eq!(t975(1), 12.706);
        assert_eq!(t975(19), 2.093);
        // Exact values: t(0.975; 40) = 2.0211, 59: 2.0010, 120: 1.9799.
        assert!((t975(40) - 2.0211).abs() < 2e-4, "{}", t975(40));
        assert!((t975(59) - 2.0010).abs() < 2e-4, "{}", t975(59));
        assert!((t975(120) - 1.9799).abs() < 2e-4, "{}", t975(120));
        assert!(t975(30) > t975(31) && t975(31) > t975(1000));
    }

    #[test]
    fn the_mean_interval_is_t_times_the_standard_error() {
        let c = mean_ci95([1.0, 2.0, 3.0, 4.0]).unwrap();
        assert_eq!(c.n, 4);
        assert_eq!(c.mean, 2.5);
        // s = sqrt(5/3), t(3) = 3.182.
        let expected = 3.182 * (5.0_f64 / 3.0 / 4.0).sqrt();
        assert!((c.half_width.unwrap() - expected).abs() < 1e-12);
        let one = mean_ci95([f64::NAN, 7.0]).unwrap();
        assert_eq!((one.n, one.mean, one.half_width), (1, 7.0, None));
        assert!(mean_ci95([f64::INFINITY]).is_none());
    }

    #[test]
    fn pairing_sees_a_constant_ratio_through_large_seed_to_seed_spread() {
        // Seeds differ 4x, b is always 0.6 a: the paired interval is tight
        // where the unpaired intervals overlap.
        let a = [0.1, 0.4, 0.2, 0.35, 0.15, 0.3, 0.25, 0.12];
        let pairs: Vec<(f64, f64)> = a.iter().map(|&x| (x, 0.6 * x)).collect();
        let p = paired(&pairs).unwrap();
        assert_eq!(p.n, 8);
        assert!((p.ratio.unwrap() - 0.6).abs() < 1e-12);
        let (lo, hi) = p.ratio_ci95.unwrap();
        assert!(
            (lo - 0.6).abs() < 1e-9 && (hi - 0.6).abs() < 1e-9,
            "{lo} {hi}"
        );
        let ua = mean_ci95(a).unwrap();
        let ub = mean_ci95(a.iter().map(|x| 0.6 * x)).unwrap();
        assert!(ub.mean + ub.half_width.unwrap() > ua.mean - ua.half_width.unwrap());
        assert!(
            p.diff + p.diff_ci95.unwrap() < 0.0,
            "b is smaller on every seed"
        );
    }

    #[test]
    fn the_bootstrap_is_deterministic_and_brackets_the_ratio() {
        let pairs: Vec<(f64, f64)> = (0..20)
            .map(|i| {
                let a = 0.05 + 0.01 * ((i * 7) % 11) as f64;
                (a, a * 0.5 + 0.004 * ((i * 5) % 7) as f64 - 0.012)
            })
            .collect();
        let p1 = paired(&pairs).unwrap();
        let p2 = paired(&pairs).unwrap();
        assert_eq!(p1, p2);
        let (lo, hi) = p1.ratio_ci95.unwrap();
        let r = p1.ratio.unwrap();
        assert!(lo < r && r < hi, "{lo} {r} {hi}");
        assert!(hi - lo < 0.2, "{lo} {hi}");
    }

    #[test]
    fn non_finite_pairs_are_left_out_and_nothing_left_gives_none() {
        let p = paired(&[
            (1.0, 2.0),
            (f64::NAN, 1.0),
            (2.0, f64::INFINITY),
            (3.0, 4.0),
        ])
        .unwrap();
        assert_eq!(p.n, 2);
        assert_eq!(p.diff, 1.0);
        assert!(paired(&[(f64::NAN, 1.0)]).is_none());
        let single = paired(&[(2.0, 1.0)]).unwrap();
        assert_eq!((single.diff_ci95, single.ratio_ci95), (None, None));
        assert_eq!(single.ratio, Some(0.5));
    }
}
