//! Timed printouts (not assertions): transform time per image of 100
//! descriptors, and query time in a database of 1000 images.

mod support;

use std::sync::Arc;
use std::time::Instant;
use support::{noisy_view, places, rng};
use vocabulary::{Database, TrainParams, Vocabulary};

#[test]
fn transform_and_query_timings() {
    let mut r = rng(1000);
    let images = places(1000, 100, &mut r);
    let t = Instant::now();
    let vocab = Arc::new(Vocabulary::train(&images, &TrainParams::default()).unwrap());
    let train_s = t.elapsed().as_secs_f64();

    let views: Vec<_> = images
        .iter()
        .map(|p| noisy_view(p, 0.05, 0.2, &mut r).0)
        .collect();
    let t = Instant::now();
    let mut bows = Vec::with_capacity(views.len());
    for v in &views {
        bows.push(vocab.transform(v));
    }
    let transform_us = 1e6 * t.elapsed().as_secs_f64() / views.len() as f64;
    let t = Instant::now();
    for v in &views {
        std::hint::black_box(vocab.transform_with_features(v, 2));
    }
    let transform_fv_us = 1e6 * t.elapsed().as_secs_f64() / views.len() as f64;

    let mut db = Database::new(Arc::clone(&vocab), 2);
    let t = Instant::now();
    for v in &views {
        db.add(v);
    }
    let add_us = 1e6 * t.elapsed().as_secs_f64() / views.len() as f64;

    let queries: Vec<_> = images
        .iter()
        .map(|p| noisy_view(p, 0.05, 0.2, &mut r).0)
        .collect();
    let query_bows: Vec<_> = queries.iter().map(|q| vocab.transform(q)).collect();
    let t = Instant::now();
    let mut correct = 0;
    for (i, q) in query_bows.iter().enumerate() {
        let res = db.query_bow(q, 10);
        correct += usize::from(res.first().map(|x| x.0 .0 as usize) == Some(i));
    }
    let query_us = 1e6 * t.elapsed().as_secs_f64() / queries.len() as f64;
    println!(
        "timing: vocabulary of {} words trained on 1000 x 100 descriptors in {train_s:.2} s; \
         transform of 100 descriptors {transform_us:.1} us (with direct index \
         {transform_fv_us:.1} us); add {add_us:.1} us; query (BoW given) in a database of \
         {} images {query_us:.1} us; top-1 {correct}/1000",
        vocab.word_count(),
        db.len(),
    );
}
