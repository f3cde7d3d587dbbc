//! Real images: the EuRoC V1_01 micro sequence (95 images, standing still, with
//! the whole flight's IMU) through the frontend and the estimator, started by
//! the static initializer and scored against the ground truth.

#![allow(clippy::expect_used, clippy::unwrap_used)]

use agent::dataset::EurocDataset;
use agent::dataset_run::{run_dataset, score};
use agent::estimator::static_init::StaticInitOptions;
use agent::estimator::EstimatorOptions;
use agent::frontend::{Frontend, FrontendError, FrontendOptions};
use common::image::GrayImage;
use std::path::PathBuf;

fn data(rel: &str) -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR"))
        .join("../../shared/data")
        .join(rel)
}

#[test]
fn micro_sequence_is_tracked_through_all_images_and_the_static_start_gets_roll_and_pitch() {
    let gt = data("trajectories/V1_01_easy.csv");
    let ds = EurocDataset::open(&data("euroc_v1_01_micro"), Some(&gt)).expect("dataset");
    let run = run_dataset(
        &ds,
        EstimatorOptions::default(),
        FrontendOptions::default(),
        &StaticInitOptions::default(),
        |_, _| {},
    )
    .expect("run");
    let s = score(&run, &ds);
    println!("{s:?}");
    assert_eq!(s.images, 95);
    assert!(s.min_features >= 150, "{s:?}");
    // Standing still: nearly every track of the first image lives to the last.
    assert!(s.tracks_first_to_last >= 150, "{s:?}");
    let init = s.init_tilt_error_deg.expect("the static start succeeded");
    assert!(init < 1.0, "tilt error at the start {init} deg");
    let last = s.final_tilt_error_deg.expect("estimates");
    assert!(last < 1.0, "tilt error at the end {last} deg");
    assert!(s.estimates > 40, "{s:?}");
}

#[test]
fn the_frontend_refuses_wrong_sizes_and_time_going_backwards() {
    let ds = EurocDataset::open(&data("euroc_v1_01_micro"), None).expect("dataset");
    let mut fe =
        Frontend::new(FrontendOptions::default(), ds.calibration.camera.clone()).expect("frontend");
    let small = GrayImage::new(10, 10, vec![0; 100]).unwrap();
    assert!(matches!(
        fe.process(0.0, &small),
        Err(FrontendError::ImageSize { .. })
    ));
    let img = ds.image(0).expect("image");
    fe.process(1.0, &img).expect("first");
    assert!(matches!(
        fe.process(1.0, &img),
        Err(FrontendError::TimeBackwards { .. })
    ));
    let bad = FrontendOptions {
        klt_window_px: 4,
        ..FrontendOptions::default()
    };
    assert!(Frontend::new(bad, ds.calibration.camera.clone()).is_err());
}
