//! Place recognition across robots on simulated EuRoC Vicon Room 1 flights: the
//! top result for a frame of one robot, among the other robots' frames, should
//! see some of the same landmarks.

use std::collections::HashSet;
use std::path::Path;
use std::sync::Arc;
use std::time::Instant;
use vocabulary::simdata::{simulate_images, SimImage};
use vocabulary::{Database, TrainParams, Vocabulary};

fn shared(a: &SimImage, b: &SimImage) -> usize {
    let a: HashSet<u64> = a.landmark_ids.iter().copied().collect();
    b.landmark_ids.iter().filter(|l| a.contains(l)).count()
}

#[test]
fn frames_retrieve_frames_of_other_robots_at_the_same_place() {
    let start = Instant::now();
    let scenario =
        Path::new(env!("CARGO_MANIFEST_DIR")).join("../sim-fleet/scenarios/euroc_vicon_room1.yaml");
    let all = simulate_images(&scenario, None, 1).unwrap();
    let sim_s = start.elapsed().as_secs_f64();
    // Training and database: every 5th frame; queries: other frames (offset 2).
    let train: Vec<&SimImage> = all.iter().filter(|i| i.frame % 5 == 0).collect();
    let queries: Vec<&SimImage> = all.iter().filter(|i| i.frame % 5 == 2).collect();
    let robots = all.iter().map(|i| i.robot).max().unwrap() + 1;
    assert_eq!(robots, 3);

    let t = Instant::now();
    let images: Vec<&[vocabulary::Descriptor]> =
        train.iter().map(|i| i.descriptors.as_slice()).collect();
    let vocab = Arc::new(Vocabulary::train(&images, &TrainParams::default()).unwrap());
    let train_s = t.elapsed().as_secs_f64();

    let (mut answerable, mut hit, mut strong_hit, mut total_queries) = (0, 0, 0, 0);
    // Chance levels: the fraction of database frames a random pick would get right.
    let (mut chance_hit, mut chance_strong) = (0.0, 0.0);
    let t = Instant::now();
    for robot in 0..robots {
        // The database: every other robot's training frames.
        let members: Vec<&SimImage> = train.iter().copied().filter(|i| i.robot != robot).collect();
        let mut db = Database::new(Arc::clone(&vocab), 2);
        for m in &members {
            db.add(&m.descriptors);
        }
        for q in queries.iter().filter(|q| q.robot == robot) {
            total_queries += 1;
            // Only queries whose place some other robot saw can be answered.
            let overlaps: Vec<usize> = members.iter().map(|m| shared(q, m)).collect();
            let best_possible = overlaps.iter().copied().max().unwrap_or(0);
            if best_possible == 0 {
                continue;
            }
            answerable += 1;
            let n = overlaps.len() as f64;
            chance_hit += overlaps.iter().filter(|&&o| o > 0).count() as f64 / n;
            chance_strong +=
                overlaps.iter().filter(|&&o| 2 * o >= best_possible).count() as f64 / n;
            let Some(&(top, _)) = db.query(&q.descriptors, 1).first() else {
                continue;
            };
            let s = shared(q, members[top.0 as usize]);
            if s > 0 {
                hit += 1;
            }
            if 2 * s >= best_possible {
                strong_hit += 1;
            }
        }
    }
    let query_s = t.elapsed().as_secs_f64();
    let rate = hit as f64 / answerable as f64;
    println!(
        "simulator retrieval: {} training frames, {} words; {total_queries} queries, \
         {answerable} answerable; top result shares landmarks for {hit} ({:.1}%), \
         at least half the best possible overlap for {strong_hit} ({:.1}%) \
         (chance levels {:.1}% and {:.1}%); simulate {sim_s:.2} s, train {train_s:.2} s, query {query_s:.2} s",
        train.len(),
        vocab.word_count(),
        100.0 * rate,
        100.0 * strong_hit as f64 / answerable as f64,
        100.0 * chance_hit / answerable as f64,
        100.0 * chance_strong / answerable as f64,
    );
    assert!(answerable * 2 > total_queries, "the robots share a room");
    assert!(rate >= 0.9, "top result shares landmarks for {rate}");
    let strong = strong_hit as f64 / answerable as f64;
    assert!(
        strong >= 0.8,
        "top result near the best overlap for {strong}"
    );
}
