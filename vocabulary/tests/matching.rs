//! Direct-index matching between two noisy views of one place: precision, recall
//! and speed against brute force.
#![allow(clippy::unwrap_used)] // helpers outside #[test] functions

mod support;

use std::time::Instant;
use support::{noisy_view, places, rng};
use vocabulary::{match_brute_force, match_features, MatchParams, TrainParams, Vocabulary};

struct Stats {
    correct: usize,
    matches: usize,
    possible: usize,
    seconds: f64,
}

impl Stats {
    fn precision(&self) -> f64 {
        self.correct as f64 / self.matches.max(1) as f64
    }
    fn recall(&self) -> f64 {
        self.correct as f64 / self.possible.max(1) as f64
    }
}

/// Matches `pairs` view pairs of `places` both ways and scores them.
fn run(places_count: usize, size: usize, levels_up: usize, seed: u64) -> (Stats, Stats) {
    let mut r = rng(seed);
    let places = places(places_count, size, &mut r);
    let vocab = Vocabulary::train(&places, &TrainParams::default()).unwrap();
    let params = MatchParams::default();
    let mut direct = Stats {
        correct: 0,
        matches: 0,
        possible: 0,
        seconds: 0.0,
    };
    let mut brute = Stats {
        correct: 0,
        matches: 0,
        possible: 0,
        seconds: 0.0,
    };
    for p in &places {
        let (a, ra) = noisy_view(p, 0.05, 0.2, &mut r);
        let (b, rb) = noisy_view(p, 0.05, 0.2, &mut r);
        let possible = ra.iter().zip(&rb).filter(|(x, y)| !**x && !**y).count();
        let (_, fa) = vocab.transform_with_features(&a, levels_up);
        let (_, fb) = vocab.transform_with_features(&b, levels_up);
        let good = |m: &[(usize, usize)]| m.iter().filter(|(i, j)| i == j && !ra[*i]).count();

        let t = Instant::now();
        let m = match_features(&a, &fa, &b, &fb, &params);
        direct.seconds += t.elapsed().as_secs_f64();
        direct.correct += good(&m);
        direct.matches += m.len();
        direct.possible += possible;

        let t = Instant::now();
        let m = match_brute_force(&a, &b, &params);
        brute.seconds += t.elapsed().as_secs_f64();
        brute.correct += good(&m);
        brute.matches += m.len();
        brute.possible += possible;
    }
    (direct, brute)
}

#[test]
fn direct_index_matching_is_precise_and_fast() {
    for (count, size) in [(200, 80), (20, 1000)] {
        for levels_up in [1, 2, 3] {
            let (d, b) = run(count, size, levels_up, 77);
            println!(
                "matching {count} pairs of {size} features, direct index {levels_up} levels up: \
                 precision {:.3} recall {:.3} in {:.2} ms; brute force precision {:.3} recall \
                 {:.3} in {:.2} ms ({:.1}x)",
                d.precision(),
                d.recall(),
                1e3 * d.seconds,
                b.precision(),
                b.recall(),
                1e3 * b.seconds,
                b.seconds / d.seconds.max(1e-12),
            );
            assert!(d.precision() >= 0.8, "precision {}", d.precision());
            assert!(d.recall() > 0.1, "recall {}", d.recall());
        }
    }
}
