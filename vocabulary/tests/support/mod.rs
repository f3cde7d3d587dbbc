//! Synthetic places and noisy views for the integration tests.
#![allow(dead_code)]

use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use vocabulary::Descriptor;

/// A seeded RNG.
pub fn rng(seed: u64) -> ChaCha8Rng {
    ChaCha8Rng::seed_from_u64(seed)
}

/// A uniformly random descriptor.
pub fn random_descriptor(rng: &mut impl Rng) -> Descriptor {
    Descriptor([rng.random(), rng.random(), rng.random(), rng.random()])
}

/// `count` places of `size` random descriptors each.
pub fn places(count: usize, size: usize, rng: &mut impl Rng) -> Vec<Vec<Descriptor>> {
    (0..count)
        .map(|_| (0..size).map(|_| random_descriptor(rng)).collect())
        .collect()
}

/// A noisy view of a place: each bit flipped with probability `flip`, each
/// descriptor replaced by a random one with probability `replace`. Returns the
/// view and, per descriptor, whether it was replaced.
pub fn noisy_view(
    place: &[Descriptor],
    flip: f64,
    replace: f64,
    rng: &mut impl Rng,
) -> (Vec<Descriptor>, Vec<bool>) {
    place
        .iter()
        .map(|d| {
            if rng.random::<f64>() < replace {
                (random_descriptor(rng), true)
            } else {
                let mut d = *d;
                for i in 0..Descriptor::BITS {
                    if rng.random::<f64>() < flip {
                        d.flip(i);
                    }
                }
                (d, false)
            }
        })
        .unzip()
}
