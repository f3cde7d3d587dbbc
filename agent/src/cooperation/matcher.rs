//! Cross-robot feature matching: descriptors first (nearest neighbour by Hamming
//! distance, ratio test, mutual best), then the epipolar check that keeps only
//! matches agreeing on one two-view geometry (thesis Section 4.4.1).

use common::descriptor::Descriptor;
use common::epipolar::{ransac_fundamental, RansacParams};
use nalgebra::Vector2;

/// Rules of a descriptor match.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct MatchRules {
    /// Largest Hamming distance, bits.
    pub max_distance: u32,
    /// The best distance must be below this fraction of the second best.
    pub ratio: f64,
}

/// Best and second-best distances of `d` among `others`.
fn best_two(d: &Descriptor, others: &[Descriptor]) -> Option<(usize, u32, u32)> {
    let mut best: Option<(usize, u32)> = None;
    let mut second = u32::MAX;
    for (j, o) in others.iter().enumerate() {
        let dist = d.distance(o);
        match best {
            Some((_, b)) if dist >= b => second = second.min(dist),
            _ => {
                if let Some((_, b)) = best {
                    second = second.min(b);
                }
                best = Some((j, dist));
            }
        }
    }
    best.map(|(j, b)| (j, b, second))
}

/// Matches `a` to `b` by brute force: each feature of `a` takes its nearest in
/// `b` if within `max_distance` and clearly better than the second nearest, and
/// the pair is kept only if it is also the nearest of that feature of `b` in `a`
/// (mutual). Returns `(index in a, index in b)` pairs, sorted by `a`.
pub fn match_descriptors(
    a: &[Descriptor],
    b: &[Descriptor],
    rules: &MatchRules,
) -> Vec<(usize, usize)> {
    let passes = |best: u32, second: u32| {
        best <= rules.max_distance
            && (second == u32::MAX || f64::from(best) < rules.ratio * f64::from(second))
    };
    let mut out = Vec::new();
    for (i, d) in a.iter().enumerate() {
        let Some((j, best, second)) = best_two(d, b) else {
            continue;
        };
        if !passes(best, second) {
            continue;
        }
        // Mutual: i must be b[j]'s nearest in a.
        if best_two(&b[j], a).is_some_and(|(back, _, _)| back == i) {
            out.push((i, j));
        }
    }
    out
}

/// Keeps the pairs `(x₁, x₂)` (normalized coordinates in the two views) that
/// agree on one fundamental matrix, if at least `min_inliers` do: the inlier
/// flags, or `None` when the check fails.
pub fn epipolar_inliers(
    x1: &[Vector2<f64>],
    x2: &[Vector2<f64>],
    threshold: f64,
    min_inliers: usize,
    seed: u64,
) -> Option<Vec<bool>> {
    if x1.len() < min_inliers.max(common::epipolar::MIN_POINTS) {
        return None;
    }
    let params = RansacParams {
        threshold,
        seed,
        ..RansacParams::default()
    };
    let fit = ransac_fundamental(x1, x2, &params).ok()?;
    (fit.inlier_count >= min_inliers).then_some(fit.inliers)
}

#[cfg(test)]
mod tests {
    use super::*;
    use rand::{Rng, SeedableRng};
    use rand_chacha::ChaCha8Rng;

    fn random(rng: &mut ChaCha8Rng) -> Descriptor {
        Descriptor([rng.random(), rng.random(), rng.random(), rng.random()])
    }

    #[test]
    fn noisy_copies_are_matched_and_strangers_are_not() {
        let mut rng = ChaCha8Rng::seed_from_u64(4);
        let a: Vec<Descriptor> = (0..40).map(|_| random(&mut rng)).collect();
        // b: 30 of them with 10 bits flipped, in another order, and 20 strangers.
        let mut b: Vec<Descriptor> = Vec::new();
        let mut truth = Vec::new();
        for i in (0..30).rev() {
            let mut d = a[i];
            for _ in 0..10 {
                d.flip(rng.random_range(0..256));
            }
            truth.push((i, b.len()));
            b.push(d);
        }
        b.extend((0..20).map(|_| random(&mut rng)));
        let rules = MatchRules {
            max_distance: 64,
            ratio: 0.8,
        };
        let mut m = match_descriptors(&a, &b, &rules);
        m.sort_unstable();
        truth.sort_unstable();
        assert_eq!(m, truth);
    }
}
