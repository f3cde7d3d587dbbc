//! Bag-of-words vectors, the direct index of an image, and the L1 score.
//!
//! An image's BoW vector holds, for every word its descriptors fall into, the sum
//! of that word's IDF weight over its occurrences (TF-IDF), L1-normalized. Words of
//! weight 0 are left out. The direct index ([`FeatureVector`]) groups the image's
//! features by their ancestor node a few levels above the leaves, so that matching
//! between two images only compares features under the same node.

use crate::tree::{NodeId, WordId};
use crate::vocabulary::Vocabulary;
use common::descriptor::Descriptor;
use serde::{Deserialize, Serialize};

/// A sparse BoW vector: `(word, weight)` sorted by word, one entry per word, no
/// zero weights.
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct BowVector {
    entries: Vec<(WordId, f64)>,
}

impl BowVector {
    /// Builds a vector from `(word, weight)` pairs in any order: weights of the same
    /// word are summed; zero and non-finite results are dropped. Not normalized.
    pub fn from_pairs<I: IntoIterator<Item = (WordId, f64)>>(pairs: I) -> Self {
        let mut entries: Vec<(WordId, f64)> = pairs.into_iter().collect();
        entries.sort_unstable_by_key(|e| e.0);
        let mut merged: Vec<(WordId, f64)> = Vec::with_capacity(entries.len());
        for (w, v) in entries {
            match merged.last_mut() {
                Some(last) if last.0 == w => last.1 += v,
                _ => merged.push((w, v)),
            }
        }
        merged.retain(|e| e.1 != 0.0 && e.1.is_finite());
        Self { entries: merged }
    }

    /// The `(word, weight)` entries, sorted by word.
    pub fn entries(&self) -> &[(WordId, f64)] {
        &self.entries
    }

    /// Number of distinct words.
    pub fn len(&self) -> usize {
        self.entries.len()
    }

    /// Whether no word has a weight.
    pub fn is_empty(&self) -> bool {
        self.entries.is_empty()
    }

    /// The weight of `word` (0 if absent).
    pub fn get(&self, word: WordId) -> f64 {
        self.entries
            .binary_search_by_key(&word, |e| e.0)
            .map_or(0.0, |i| self.entries[i].1)
    }

    /// The L1 norm `Σ |v_i|`.
    pub fn l1_norm(&self) -> f64 {
        self.entries.iter().map(|e| e.1.abs()).sum()
    }

    /// This vector divided by its L1 norm (unchanged if the norm is 0).
    pub fn normalized(mut self) -> Self {
        let n = self.l1_norm();
        if n > 0.0 && n.is_finite() {
            for e in &mut self.entries {
                e.1 /= n;
            }
        }
        self
    }

    /// The L1 score against `other`; see [`l1_score`].
    pub fn score(&self, other: &BowVector) -> f64 {
        l1_score(self, other)
    }
}

/// DBoW2's L1 score `s(v, w) = 1 - 0.5 * | v/|v| - w/|w| |_1`, in `[0, 1]`: 1 for
/// proportional vectors, 0 for vectors without a common word. A zero vector scores
/// 0 against anything.
///
/// Computed over the common words only, using
/// `|a - b| = |a| + |b| - (|a| + |b| - |a - b|)` for unit-L1 vectors:
/// `s = 0.5 * Σ_common (|a_i| + |b_i| - |a_i - b_i|)`.
pub fn l1_score(v: &BowVector, w: &BowVector) -> f64 {
    let (nv, nw) = (v.l1_norm(), w.l1_norm());
    if !(nv > 0.0 && nw > 0.0 && nv.is_finite() && nw.is_finite()) {
        return 0.0;
    }
    let (a, b) = (&v.entries, &w.entries);
    let (mut i, mut j) = (0, 0);
    let mut acc = 0.0;
    while i < a.len() && j < b.len() {
        match a[i].0.cmp(&b[j].0) {
            std::cmp::Ordering::Less => i += 1,
            std::cmp::Ordering::Greater => j += 1,
            std::cmp::Ordering::Equal => {
                acc += common_term(a[i].1 / nv, b[j].1 / nw);
                i += 1;
                j += 1;
            }
        }
    }
    (0.5 * acc).clamp(0.0, 1.0)
}

/// The contribution of one common word to `2 * s`: `|a| + |b| - |a - b|`.
pub(crate) fn common_term(a: f64, b: f64) -> f64 {
    a.abs() + b.abs() - (a - b).abs()
}

/// The direct index of one image: for each node at the chosen level, the indices
/// of the image's features under it. Sorted by node id; indices ascending.
#[derive(Clone, Debug, Default, PartialEq, Eq, Serialize, Deserialize)]
pub struct FeatureVector {
    nodes: Vec<(NodeId, Vec<usize>)>,
}

impl FeatureVector {
    /// Builds a direct index from `(node, feature index)` pairs in any order.
    pub fn from_pairs<I: IntoIterator<Item = (NodeId, usize)>>(pairs: I) -> Self {
        let mut pairs: Vec<(NodeId, usize)> = pairs.into_iter().collect();
        pairs.sort_unstable();
        pairs.dedup();
        let mut nodes: Vec<(NodeId, Vec<usize>)> = Vec::new();
        for (n, i) in pairs {
            match nodes.last_mut() {
                Some(last) if last.0 == n => last.1.push(i),
                _ => nodes.push((n, vec![i])),
            }
        }
        Self { nodes }
    }

    /// `(node, feature indices)` sorted by node.
    pub fn nodes(&self) -> &[(NodeId, Vec<usize>)] {
        &self.nodes
    }

    /// The features under `node` (empty if none).
    pub fn get(&self, node: NodeId) -> &[usize] {
        self.nodes
            .binary_search_by_key(&node, |e| e.0)
            .map_or(&[], |i| &self.nodes[i].1)
    }

    /// Number of nodes holding features.
    pub fn len(&self) -> usize {
        self.nodes.len()
    }

    /// Whether no feature is indexed.
    pub fn is_empty(&self) -> bool {
        self.nodes.is_empty()
    }

    /// Total number of indexed features.
    pub fn feature_count(&self) -> usize {
        self.nodes.iter().map(|n| n.1.len()).sum()
    }
}

impl Vocabulary {
    /// The L1-normalized TF-IDF BoW vector of an image's descriptors.
    pub fn transform(&self, descriptors: &[Descriptor]) -> BowVector {
        BowVector::from_pairs(
            descriptors
                .iter()
                .map(|d| {
                    let w = self.word(d);
                    (w, self.weight(w))
                })
                .filter(|p| p.1 > 0.0),
        )
        .normalized()
    }

    /// The BoW vector and the direct index of an image. The direct index groups
    /// every feature (whatever its word's weight) by its ancestor `levels_up`
    /// levels above the leaves (see
    /// [`crate::tree::VocabularyTree::transform_with_node`]): 0 groups by word,
    /// `>= L` puts every feature under the root.
    pub fn transform_with_features(
        &self,
        descriptors: &[Descriptor],
        levels_up: usize,
    ) -> (BowVector, FeatureVector) {
        let mut words = Vec::with_capacity(descriptors.len());
        let mut nodes = Vec::with_capacity(descriptors.len());
        for (i, d) in descriptors.iter().enumerate() {
            let (w, n) = self.tree().transform_with_node(d, levels_up);
            let weight = self.weight(w);
            if weight > 0.0 {
                words.push((w, weight));
            }
            nodes.push((n, i));
        }
        (
            BowVector::from_pairs(words).normalized(),
            FeatureVector::from_pairs(nodes),
        )
    }

    /// The L1 score of two BoW vectors; see [`l1_score`].
    pub fn score(&self, a: &BowVector, b: &BowVector) -> f64 {
        l1_score(a, b)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use proptest::prelude::*;

    fn naive_score(v: &BowVector, w: &BowVector) -> f64 {
        let (nv, nw) = (v.l1_norm(), w.l1_norm());
        let mut words: Vec<WordId> = v.entries.iter().chain(&w.entries).map(|e| e.0).collect();
        words.sort_unstable();
        words.dedup();
        let d: f64 = words
            .iter()
            .map(|&x| (v.get(x) / nv - w.get(x) / nw).abs())
            .sum();
        1.0 - 0.5 * d
    }

    #[test]
    fn identical_and_disjoint() {
        let a = BowVector::from_pairs([(3, 0.5), (1, 0.25), (7, 2.0)]);
        assert!((l1_score(&a, &a) - 1.0).abs() < 1e-12);
        let scaled = BowVector::from_pairs(a.entries().iter().map(|e| (e.0, 3.0 * e.1)));
        assert!((l1_score(&a, &scaled) - 1.0).abs() < 1e-12);
        let b = BowVector::from_pairs([(2, 0.5), (4, 1.0)]);
        assert_eq!(l1_score(&a, &b), 0.0);
        assert_eq!(l1_score(&a, &BowVector::default()), 0.0);
        assert_eq!(l1_score(&BowVector::default(), &BowVector::default()), 0.0);
    }

    #[test]
    fn from_pairs_merges_and_sorts() {
        let a = BowVector::from_pairs([(5, 1.0), (2, 1.0), (5, 2.0), (9, 0.0)]);
        assert_eq!(a.entries(), &[(2, 1.0), (5, 3.0)]);
        let n = a.normalized();
        assert!((n.l1_norm() - 1.0).abs() < 1e-12);
        let f = FeatureVector::from_pairs([(4, 2), (1, 0), (4, 1), (1, 3)]);
        assert_eq!(f.nodes(), &[(1, vec![0, 3]), (4, vec![1, 2])]);
        assert_eq!(f.get(4), &[1, 2]);
        assert!(f.get(2).is_empty());
        assert_eq!(f.feature_count(), 4);
    }

    proptest! {
        #[test]
        fn score_is_in_unit_interval_and_matches_definition(
            a in proptest::collection::vec((0u32..40, 0.001f64..10.0), 0..30),
            b in proptest::collection::vec((0u32..40, 0.001f64..10.0), 0..30),
        ) {
            let (a, b) = (BowVector::from_pairs(a), BowVector::from_pairs(b));
            let s = l1_score(&a, &b);
            prop_assert!((0.0..=1.0).contains(&s));
            prop_assert!((s - l1_score(&b, &a)).abs() < 1e-12);
            if !a.is_empty() && !b.is_empty() {
                prop_assert!((s - naive_score(&a, &b)).abs() < 1e-9);
            }
            if !a.is_empty() {
                prop_assert!((l1_score(&a, &a) - 1.0).abs() < 1e-9);
            }
        }
    }
}
