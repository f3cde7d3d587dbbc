//! Descriptor matching between two images, sped up by their direct indices: a
//! feature is only compared with the other image's features under the same
//! vocabulary node.

use crate::bow::FeatureVector;
use common::descriptor::Descriptor;
use serde::{Deserialize, Serialize};

/// Acceptance rules of a match.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct MatchParams {
    /// Lowe's ratio: the best distance must be below `ratio` times the second best
    /// (among the candidates compared). A feature with a single candidate passes.
    pub ratio: f32,
    /// Largest accepted Hamming distance of the best candidate.
    pub max_distance: u32,
}

impl Default for MatchParams {
    /// Ratio 0.8, at most 64 differing bits of 256.
    fn default() -> Self {
        Self {
            ratio: 0.8,
            max_distance: 64,
        }
    }
}

/// Best and second best distance and the best index over `candidates`.
fn best_two<I: IntoIterator<Item = usize>>(
    d: &Descriptor,
    others: &[Descriptor],
    candidates: I,
) -> Option<(usize, u32, Option<u32>)> {
    let mut best: Option<(usize, u32)> = None;
    let mut second: Option<u32> = None;
    for j in candidates {
        let Some(o) = others.get(j) else { continue };
        let dist = d.distance(o);
        match best {
            Some((_, b)) if dist >= b => {
                if second.is_none_or(|s| dist < s) {
                    second = Some(dist);
                }
            }
            _ => {
                second = best.map(|b| b.1);
                best = Some((j, dist));
            }
        }
    }
    best.map(|(j, b)| (j, b, second))
}

/// Keeps the accepted candidates, one per feature of `b`: the closest (ties to
/// the lowest index of `a`). Returns pairs sorted by the index in `a`.
struct Collector {
    params: MatchParams,
    by_b: Vec<Option<(u32, usize)>>,
}

impl Collector {
    fn new(params: MatchParams, b_len: usize) -> Self {
        Self {
            params,
            by_b: vec![None; b_len],
        }
    }

    fn offer(&mut self, i: usize, found: Option<(usize, u32, Option<u32>)>) {
        let Some((j, best, second)) = found else {
            return;
        };
        if best > self.params.max_distance {
            return;
        }
        if let Some(s) = second {
            if best as f32 >= self.params.ratio * s as f32 {
                return;
            }
        }
        let slot = &mut self.by_b[j];
        if slot.is_none_or(|(d, a)| (best, i) < (d, a)) {
            *slot = Some((best, i));
        }
    }

    fn finish(self) -> Vec<(usize, usize)> {
        let mut out: Vec<(usize, usize)> = self
            .by_b
            .iter()
            .enumerate()
            .filter_map(|(j, s)| s.map(|(_, i)| (i, j)))
            .collect();
        out.sort_unstable();
        out
    }
}

/// Matches the features of image `a` to those of image `b`, comparing only
/// features under the same node of the two direct indices (which must come from
/// the same vocabulary and level). Each feature of `a` takes its nearest neighbour
/// by Hamming distance among the candidates, kept if it passes
/// [`MatchParams`]; each feature of `b` keeps at most one match (the closest).
/// Returns `(index in a, index in b)` pairs sorted by the index in `a`. Indices
/// out of range of the descriptor slices are skipped.
pub fn match_features(
    a: &[Descriptor],
    a_index: &FeatureVector,
    b: &[Descriptor],
    b_index: &FeatureVector,
    params: &MatchParams,
) -> Vec<(usize, usize)> {
    let mut out = Collector::new(*params, b.len());
    let (na, nb) = (a_index.nodes(), b_index.nodes());
    let (mut x, mut y) = (0, 0);
    while x < na.len() && y < nb.len() {
        match na[x].0.cmp(&nb[y].0) {
            std::cmp::Ordering::Less => x += 1,
            std::cmp::Ordering::Greater => y += 1,
            std::cmp::Ordering::Equal => {
                for &i in &na[x].1 {
                    if let Some(d) = a.get(i) {
                        out.offer(i, best_two(d, b, nb[y].1.iter().copied()));
                    }
                }
                x += 1;
                y += 1;
            }
        }
    }
    out.finish()
}

/// The same rules as [`match_features`] with every feature of `b` as a candidate
/// (the brute-force reference).
pub fn match_brute_force(
    a: &[Descriptor],
    b: &[Descriptor],
    params: &MatchParams,
) -> Vec<(usize, usize)> {
    let mut out = Collector::new(*params, b.len());
    for (i, d) in a.iter().enumerate() {
        out.offer(i, best_two(d, b, 0..b.len()));
    }
    out.finish()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn ratio_and_distance_rules() {
        let z = Descriptor([0; 4]);
        let mut near = z;
        near.flip(1);
        let mut far = z;
        for i in 0..100 {
            far.flip(i);
        }
        let p = MatchParams::default();
        // Clear best: accepted.
        assert_eq!(match_brute_force(&[z], &[far, near], &p), vec![(0, 1)]);
        // Two equally good candidates: rejected by the ratio test.
        assert!(match_brute_force(&[z], &[near, near], &p).is_empty());
        // Too far: rejected.
        assert!(match_brute_force(&[z], &[far], &p).is_empty());
        // Two features wanting the same one: the closer wins.
        assert_eq!(match_brute_force(&[near, z], &[z], &p), vec![(1, 0)]);
        // Same node only.
        let fa = FeatureVector::from_pairs([(3, 0)]);
        let fb = FeatureVector::from_pairs([(4, 0)]);
        assert!(match_features(&[z], &fa, &[z], &fb, &p).is_empty());
        let fb = FeatureVector::from_pairs([(3, 0), (3, 7)]);
        assert_eq!(match_features(&[z], &fa, &[z], &fb, &p), vec![(0, 0)]);
    }
}
