//! Place recognition on synthetic places: train on 200 places of 80 random
//! descriptors, index one noisy view of each, query with another.

mod support;

use std::sync::Arc;
use std::time::Instant;
use support::{noisy_view, places, rng};
use vocabulary::{l1_score, Database, TrainParams, Vocabulary};

#[test]
fn noisy_views_retrieve_their_place() {
    let mut r = rng(2024);
    let places = places(200, 80, &mut r);
    let start = Instant::now();
    let vocab = Arc::new(Vocabulary::train(&places, &TrainParams::default()).unwrap());
    let train_s = start.elapsed().as_secs_f64();

    let mut db = Database::new(Arc::clone(&vocab), 2);
    for p in &places {
        db.add(&noisy_view(p, 0.05, 0.2, &mut r).0);
    }
    let mut correct = 0;
    let mut true_scores = 0.0;
    let mut runner_up = 0.0;
    for (i, p) in places.iter().enumerate() {
        let query = noisy_view(p, 0.05, 0.2, &mut r).0;
        let results = db.query(&query, 5);
        if results.first().map(|x| x.0 .0 as usize) == Some(i) {
            correct += 1;
            true_scores += results[0].1;
            runner_up += results.get(1).map_or(0.0, |x| x.1);
        }
        // The inverted-index scores are the L1 scores.
        let q = vocab.transform(&query);
        for &(e, s) in &results {
            let direct = l1_score(&q, db.bow(e).unwrap());
            assert!((s - direct).abs() < 1e-9, "{s} vs {direct}");
        }
    }
    let accuracy = correct as f64 / places.len() as f64;
    println!(
        "synthetic retrieval: {} words, trained in {train_s:.2} s; top-1 {correct}/{} = {:.1}%, \
         mean score of the right place {:.3}, of the runner-up {:.3}",
        vocab.word_count(),
        places.len(),
        100.0 * accuracy,
        true_scores / correct.max(1) as f64,
        runner_up / correct.max(1) as f64,
    );
    assert!(accuracy >= 0.95, "top-1 accuracy {accuracy}");
}

#[test]
fn scores_are_bounded_identical_is_one() {
    let mut r = rng(5);
    let places = places(50, 60, &mut r);
    let vocab = Vocabulary::train(&places, &TrainParams::default()).unwrap();
    let bows: Vec<_> = places.iter().map(|p| vocab.transform(p)).collect();
    for a in &bows {
        assert!((l1_score(a, a) - 1.0).abs() < 1e-9);
        for b in &bows {
            let s = l1_score(a, b);
            assert!((0.0..=1.0).contains(&s));
        }
    }
}
