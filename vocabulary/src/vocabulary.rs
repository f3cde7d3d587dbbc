//! The vocabulary: a trained tree plus the IDF weight of every word.

use crate::tree::{TrainError, TrainParams, VocabularyTree, WordId};
use crate::weights::{document_frequencies, idf_weights};
use common::descriptor::Descriptor;
use serde::{Deserialize, Serialize};
use thiserror::Error;

/// A vocabulary that breaks an invariant (from a corrupt or foreign file).
#[derive(Debug, Error, Clone, PartialEq, Eq)]
#[error("invalid vocabulary: {0}")]
pub struct InvalidVocabulary(pub String);

/// A bag-of-binary-words vocabulary: the k-majority tree and the IDF weight of
/// each word.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct Vocabulary {
    tree: VocabularyTree,
    idf: Vec<f64>,
    training_images: u64,
}

impl Vocabulary {
    /// Trains a vocabulary: the tree on every descriptor of every image, then the
    /// IDF weights with each image as one document. Deterministic for given images
    /// and parameters.
    pub fn train<I: AsRef<[Descriptor]>>(
        images: &[I],
        params: &TrainParams,
    ) -> Result<Self, TrainError> {
        let all: Vec<Descriptor> = images
            .iter()
            .flat_map(|i| i.as_ref().iter().copied())
            .collect();
        let tree = VocabularyTree::build(&all, params)?;
        let df = document_frequencies(&tree, images);
        let training_images = images.len() as u64;
        let idf = idf_weights(training_images, &df);
        tracing::info!(
            descriptors = all.len(),
            images = images.len(),
            words = tree.word_count(),
            "vocabulary trained"
        );
        Ok(Self {
            tree,
            idf,
            training_images,
        })
    }

    /// Assembles a vocabulary from its parts, checking every invariant.
    pub fn from_parts(
        tree: VocabularyTree,
        idf: Vec<f64>,
        training_images: u64,
    ) -> Result<Self, InvalidVocabulary> {
        let v = Self {
            tree,
            idf,
            training_images,
        };
        v.validate()?;
        Ok(v)
    }

    /// Checks the tree's structure and that there is one finite, non-negative
    /// weight per word.
    pub fn validate(&self) -> Result<(), InvalidVocabulary> {
        self.tree.validate().map_err(InvalidVocabulary)?;
        if self.idf.len() != self.tree.word_count() {
            return Err(InvalidVocabulary(format!(
                "{} weights for {} words",
                self.idf.len(),
                self.tree.word_count()
            )));
        }
        if let Some(w) = self.idf.iter().position(|w| !w.is_finite() || *w < 0.0) {
            return Err(InvalidVocabulary(format!(
                "word {w} has weight {}",
                self.idf[w]
            )));
        }
        Ok(())
    }

    /// The tree.
    pub fn tree(&self) -> &VocabularyTree {
        &self.tree
    }

    /// Branching factor `k`.
    pub fn k(&self) -> usize {
        self.tree.k()
    }

    /// Depth `L`.
    pub fn levels(&self) -> usize {
        self.tree.levels()
    }

    /// Number of words.
    pub fn word_count(&self) -> usize {
        self.tree.word_count()
    }

    /// Number of images the IDF weights were learnt from.
    pub fn training_images(&self) -> u64 {
        self.training_images
    }

    /// The IDF weight of every word, indexed by word id.
    pub fn weights(&self) -> &[f64] {
        &self.idf
    }

    /// The IDF weight of one word (0 for an unknown id).
    pub fn weight(&self, word: WordId) -> f64 {
        self.idf.get(word as usize).copied().unwrap_or(0.0)
    }

    /// The word of one descriptor.
    pub fn word(&self, d: &Descriptor) -> WordId {
        self.tree.transform(d)
    }
}
