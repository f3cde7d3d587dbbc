//! TF-IDF weighting: the inverse document frequency of each word, learnt from the
//! training images.
//!
//! `idf(w) = ln(N / n_w)` with `N` the number of training images and `n_w` the
//! number of those images in which word `w` occurs at least once. A word that no
//! training image contains (possible only for vocabularies built elsewhere) gets
//! weight 0, like a word that occurs in every image: neither says anything about
//! which image is which. Words of weight 0 are left out of BoW vectors.

use crate::tree::VocabularyTree;
use common::descriptor::Descriptor;

/// For each word, the number of `images` that contain it at least once.
pub fn document_frequencies<I: AsRef<[Descriptor]>>(
    tree: &VocabularyTree,
    images: &[I],
) -> Vec<u32> {
    let mut counts = vec![0u32; tree.word_count()];
    let mut last_seen = vec![usize::MAX; tree.word_count()];
    for (i, image) in images.iter().enumerate() {
        for d in image.as_ref() {
            let w = tree.transform(d) as usize;
            if let Some(seen) = last_seen.get_mut(w) {
                if *seen != i {
                    *seen = i;
                    counts[w] = counts[w].saturating_add(1);
                }
            }
        }
    }
    counts
}

/// IDF weights `ln(N / n_w)` from the document frequencies `n_w` of `N` images;
/// 0 where `n_w == 0`.
pub fn idf_weights(images: u64, document_frequencies: &[u32]) -> Vec<f64> {
    document_frequencies
        .iter()
        .map(|&n| {
            if n == 0 || images == 0 {
                0.0
            } else {
                (images as f64 / f64::from(n)).ln().max(0.0)
            }
        })
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn idf_is_log_ratio() {
        let w = idf_weights(10, &[0, 1, 5, 10]);
        assert_eq!(w[0], 0.0);
        assert!((w[1] - 10f64.ln()).abs() < 1e-12);
        assert!((w[2] - 2f64.ln()).abs() < 1e-12);
        assert_eq!(w[3], 0.0);
    }
}
