//! A vocabulary for uniformly random 256-bit descriptors, the kind the fleet
//! simulator gives its landmarks: trained on seeded random "images", so every
//! agent of a simulated fleet builds the same one without a file.

use crate::tree::{TrainError, TrainParams};
use crate::vocabulary::Vocabulary;
use common::descriptor::Descriptor;
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;

/// Trains on `images` images of `per_image` uniformly random descriptors drawn
/// from `seed`. Deterministic.
pub fn random_descriptor_vocabulary(
    seed: u64,
    images: usize,
    per_image: usize,
    params: &TrainParams,
) -> Result<Vocabulary, TrainError> {
    let mut rng = ChaCha8Rng::seed_from_u64(seed);
    let data: Vec<Vec<Descriptor>> = (0..images)
        .map(|_| {
            (0..per_image)
                .map(|_| Descriptor([rng.random(), rng.random(), rng.random(), rng.random()]))
                .collect()
        })
        .collect();
    Vocabulary::train(&data, params)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::database::Database;
    use std::sync::Arc;

    #[test]
    fn noisy_views_of_random_places_are_found_again() {
        let voc = random_descriptor_vocabulary(1, 100, 100, &TrainParams::default()).unwrap();
        let voc = Arc::new(voc);
        let mut rng = ChaCha8Rng::seed_from_u64(9);
        let places: Vec<Vec<Descriptor>> = (0..50)
            .map(|_| {
                (0..60)
                    .map(|_| Descriptor([rng.random(), rng.random(), rng.random(), rng.random()]))
                    .collect()
            })
            .collect();
        let mut db = Database::new(voc, 1);
        for p in &places {
            db.add(p);
        }
        let mut hits = 0;
        for (i, p) in places.iter().enumerate() {
            // 3 % of the bits flipped, as the simulator does per observation.
            let noisy: Vec<Descriptor> = p
                .iter()
                .map(|d| {
                    let mut d = *d;
                    for b in 0..256 {
                        if rng.random::<f64>() < 0.03 {
                            d.flip(b);
                        }
                    }
                    d
                })
                .collect();
            let res = db.query(&noisy, 1);
            if res.first().map(|r| r.0 .0 as usize) == Some(i) {
                hits += 1;
            }
        }
        assert!(hits >= 48, "{hits} of 50");
    }
}
