//! An image database: entries (BoW vector and direct index) with an inverted index
//! from each word to the entries containing it, queried by L1 score.

use crate::bow::{common_term, BowVector, FeatureVector};
use crate::tree::WordId;
use crate::vocabulary::Vocabulary;
use common::descriptor::Descriptor;
use serde::{Deserialize, Serialize};
use std::fmt;
use std::sync::Arc;

/// Identifier of an image in a [`Database`]: entries are numbered from 0 in the
/// order they were added.
#[derive(Clone, Copy, Debug, PartialEq, Eq, PartialOrd, Ord, Hash, Serialize, Deserialize)]
pub struct EntryId(pub u32);

impl fmt::Display for EntryId {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        self.0.fmt(f)
    }
}

/// One image of the database.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct Entry {
    /// Its L1-normalized BoW vector.
    pub bow: BowVector,
    /// Its direct index.
    pub features: FeatureVector,
}

/// Images indexed for retrieval with one vocabulary.
#[derive(Clone, Debug)]
pub struct Database {
    vocabulary: Arc<Vocabulary>,
    levels_up: usize,
    entries: Vec<Entry>,
    inverted: Vec<Vec<(EntryId, f64)>>,
}

impl Database {
    /// An empty database. `direct_index_levels_up` chooses the level of the direct
    /// index, counted up from the leaves (see
    /// [`Vocabulary::transform_with_features`]).
    pub fn new(vocabulary: Arc<Vocabulary>, direct_index_levels_up: usize) -> Self {
        let words = vocabulary.word_count();
        Self {
            vocabulary,
            levels_up: direct_index_levels_up,
            entries: Vec::new(),
            inverted: vec![Vec::new(); words],
        }
    }

    /// The vocabulary.
    pub fn vocabulary(&self) -> &Vocabulary {
        &self.vocabulary
    }

    /// The direct index level, counted up from the leaves.
    pub fn direct_index_levels_up(&self) -> usize {
        self.levels_up
    }

    /// Number of entries.
    pub fn len(&self) -> usize {
        self.entries.len()
    }

    /// Whether the database is empty.
    pub fn is_empty(&self) -> bool {
        self.entries.is_empty()
    }

    /// Transforms an image and adds it; returns its id.
    pub fn add(&mut self, descriptors: &[Descriptor]) -> EntryId {
        let (bow, features) = self
            .vocabulary
            .transform_with_features(descriptors, self.levels_up);
        self.add_transformed(bow, features)
    }

    /// Adds an image already transformed with this database's vocabulary (the BoW
    /// vector is normalized here; words unknown to the vocabulary are ignored by
    /// queries).
    pub fn add_transformed(&mut self, bow: BowVector, features: FeatureVector) -> EntryId {
        let id = EntryId(u32::try_from(self.entries.len()).unwrap_or(u32::MAX));
        let bow = bow.normalized();
        for &(w, v) in bow.entries() {
            if let Some(list) = self.inverted.get_mut(w as usize) {
                list.push((id, v));
            }
        }
        self.entries.push(Entry { bow, features });
        id
    }

    /// Approximate heap bytes held: the entries' BoW vectors and direct
    /// indexes, and the inverted index.
    pub fn bytes(&self) -> usize {
        use std::mem::size_of;
        let entries: usize = self
            .entries
            .iter()
            .map(|e| {
                size_of::<Entry>()
                    + e.bow.len() * size_of::<(WordId, f64)>()
                    + e.features
                        .nodes()
                        .iter()
                        .map(|(_, f)| {
                            size_of::<(crate::tree::NodeId, Vec<usize>)>()
                                + f.len() * size_of::<usize>()
                        })
                        .sum::<usize>()
            })
            .sum();
        let postings: usize = self.inverted.iter().map(Vec::len).sum();
        entries + self.fixed_bytes() + postings * size_of::<(EntryId, f64)>()
    }

    /// The part of [`Database::bytes`] an empty database holds already: one
    /// inverted list per word of the vocabulary.
    pub fn fixed_bytes(&self) -> usize {
        self.inverted.len() * std::mem::size_of::<Vec<(EntryId, f64)>>()
    }

    /// One entry, `None` if out of range.
    pub fn entry(&self, id: EntryId) -> Option<&Entry> {
        self.entries.get(id.0 as usize)
    }

    /// An entry's BoW vector.
    pub fn bow(&self, id: EntryId) -> Option<&BowVector> {
        self.entry(id).map(|e| &e.bow)
    }

    /// An entry's direct index.
    pub fn features(&self, id: EntryId) -> Option<&FeatureVector> {
        self.entry(id).map(|e| &e.features)
    }

    /// The inverted index of one word: `(entry, weight)` in insertion order.
    pub fn inverted(&self, word: WordId) -> &[(EntryId, f64)] {
        self.inverted.get(word as usize).map_or(&[], Vec::as_slice)
    }

    /// Transforms an image and queries with it; see [`Database::query_bow`].
    pub fn query(&self, descriptors: &[Descriptor], max_results: usize) -> Vec<(EntryId, f64)> {
        self.query_bow(&self.vocabulary.transform(descriptors), max_results)
    }

    /// The `max_results` entries with the highest L1 score against `bow`, best
    /// first (ties by entry id). Only entries sharing at least one word with `bow`
    /// are scored (through the inverted index); the others score 0 and are not
    /// returned. The scores equal [`crate::bow::l1_score`].
    pub fn query_bow(&self, bow: &BowVector, max_results: usize) -> Vec<(EntryId, f64)> {
        let norm = bow.l1_norm();
        if max_results == 0 || !(norm > 0.0 && norm.is_finite()) {
            return Vec::new();
        }
        let mut acc = vec![0.0f64; self.entries.len()];
        let mut touched_flag = vec![false; self.entries.len()];
        let mut touched: Vec<u32> = Vec::new();
        for &(w, q) in bow.entries() {
            let q = q / norm;
            for &(e, v) in self.inverted(w) {
                let i = e.0 as usize;
                if !touched_flag[i] {
                    touched_flag[i] = true;
                    touched.push(e.0);
                }
                acc[i] += common_term(q, v);
            }
        }
        let mut results: Vec<(EntryId, f64)> = touched
            .into_iter()
            .map(|e| (EntryId(e), (0.5 * acc[e as usize]).clamp(0.0, 1.0)))
            .collect();
        let order =
            |a: &(EntryId, f64), b: &(EntryId, f64)| b.1.total_cmp(&a.1).then(a.0.cmp(&b.0));
        if results.len() > max_results {
            results.select_nth_unstable_by(max_results - 1, order);
            results.truncate(max_results);
        }
        results.sort_unstable_by(order);
        results
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::bow::l1_score;
    use crate::tree::TrainParams;
    use rand::{Rng, SeedableRng};
    use rand_chacha::ChaCha8Rng;

    fn images(n: usize, size: usize, seed: u64) -> Vec<Vec<Descriptor>> {
        let mut rng = ChaCha8Rng::seed_from_u64(seed);
        (0..n)
            .map(|_| {
                (0..size)
                    .map(|_| Descriptor([rng.random(), rng.random(), rng.random(), rng.random()]))
                    .collect()
            })
            .collect()
    }

    #[test]
    fn inverted_index_scores_equal_l1_scores() {
        let imgs = images(40, 50, 1);
        // A small vocabulary (at most 36 words), so that images share words.
        let params = TrainParams {
            k: 6,
            levels: 2,
            ..TrainParams::default()
        };
        let vocab = Arc::new(Vocabulary::train(&imgs, &params).unwrap());
        let mut db = Database::new(Arc::clone(&vocab), 1);
        for (i, img) in imgs.iter().enumerate() {
            assert_eq!(db.add(img), EntryId(i as u32));
        }
        assert_eq!(db.len(), 40);
        for (i, img) in imgs.iter().enumerate() {
            let q = vocab.transform(img);
            let all = db.query_bow(&q, usize::MAX);
            assert!((all[0].1 - 1.0).abs() < 1e-9);
            assert!(all
                .iter()
                .any(|r| r.0 == EntryId(i as u32) && r.1 == all[0].1));
            assert!(all.len() > 30, "{} entries share a word", all.len());
            // Sorted, and every entry with a common word is present with its L1 score.
            assert!(all.windows(2).all(|w| w[0].1 >= w[1].1));
            for (e, entry) in db.entries.iter().enumerate() {
                let s = l1_score(&q, &entry.bow);
                match all.iter().find(|r| r.0 .0 as usize == e) {
                    Some(r) => assert!((r.1 - s).abs() < 1e-9),
                    None => assert_eq!(s, 0.0),
                }
            }
            let top3 = db.query(img, 3);
            assert_eq!(top3.as_slice(), &all[..3]);
            assert!(db.query(img, 0).is_empty());
        }
        // Memory grows with each entry: its words, once in its vector and once
        // in the inverted index.
        let words: usize = db.entries.iter().map(|e| e.bow.len()).sum();
        assert!(db.bytes() >= 2 * words * std::mem::size_of::<(WordId, f64)>());
        let mut one_more = db.clone();
        one_more.add(&imgs[0]);
        assert!(one_more.bytes() > db.bytes());
        let fv = db.features(EntryId(3)).unwrap();
        assert_eq!(fv.feature_count(), 50);
        assert!(db.features(EntryId(40)).is_none());
        for &(w, _) in db.bow(EntryId(0)).unwrap().entries() {
            assert!(db.inverted(w).iter().any(|x| x.0 == EntryId(0)));
        }
    }

    #[test]
    fn empty_database_and_query() {
        let imgs = images(5, 20, 2);
        let vocab = Arc::new(Vocabulary::train(&imgs, &TrainParams::default()).unwrap());
        let mut db = Database::new(vocab, 2);
        assert!(db.is_empty());
        assert!(db.query(&imgs[0], 5).is_empty());
        db.add(&[]);
        assert!(db.query(&imgs[0], 5).is_empty());
        assert!(db.query(&[], 5).is_empty());
    }
}
