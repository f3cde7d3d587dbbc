//! Rendered images of the single-robot V1_01 scenario through the frontend and
//! the estimator, next to the feature-level simulation of the same seed.

#![allow(clippy::expect_used, clippy::unwrap_used)]

use agent::frontend::{FirstPatch, Frontend, FrontendOptions};
use agent::image_runner::{run_robot_rendered, TrackQuality, TrackScorer};
use agent::runner::{options_for, run_robot, Variant};
use simulator::camera_sim::CameraEvent;
use simulator::{Fleet, Scenario, SimEvent};
use std::path::PathBuf;

#[test]
fn rendered_v1_01_stays_within_twice_the_feature_level_ate_of_the_same_seed() {
    let path =
        PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("../sim-fleet/scenarios/v1_01_easy.yaml");
    let mut sc = Scenario::load(&path).expect("scenario");
    let seed = 1;
    let features = Fleet::build(&sc, seed).expect("fleet");
    let opts = options_for(&sc.estimator, &features, 0, Variant::IndpSlam);
    let feature_level = run_robot(&features, 0, opts.clone())
        .expect("feature run")
        .metrics();
    sc.render.enabled = true;
    let rendered_fleet = Fleet::build(&sc, seed).expect("rendered fleet");
    // Camera images: the SLAM updates take 2 px, and are paced on a keyframe
    // window, unless the scenario says otherwise.
    let rendered_opts = options_for(&sc.estimator, &rendered_fleet, 0, Variant::IndpSlam);
    assert_eq!(
        (opts.slam_sigma_px(), rendered_opts.slam_sigma_px()),
        (1.0, 2.0)
    );
    assert_eq!(
        (
            opts.slam_keyframe_updates,
            rendered_opts.slam_keyframe_updates
        ),
        (false, true)
    );
    let mut set = sc.estimator.clone();
    set.slam_pixel_sigma_px = Some(1.5);
    set.slam_keyframe_updates = Some(false);
    let set_opts = options_for(&set, &rendered_fleet, 0, Variant::IndpSlam);
    assert_eq!(set_opts.slam_sigma_px(), 1.5);
    assert!(!set_opts.slam_keyframe_updates);
    let r = run_robot_rendered(
        &rendered_fleet,
        0,
        rendered_opts,
        FrontendOptions::default(),
        |_, _| {},
    )
    .expect("rendered run");
    let rendered = r.run.metrics();
    let q = &r.tracks;
    println!(
        "seed {seed}: feature-level ATE {:.3} deg / {:.3} m, NEES {:.2} / {:.2}; rendered ATE {:.3} deg / {:.3} m, NEES {:.2} / {:.2}",
        feature_level.ate_ori_deg.unwrap(),
        feature_level.ate_pos_m.unwrap(),
        feature_level.nees_ori.unwrap(),
        feature_level.nees_pos.unwrap(),
        rendered.ate_ori_deg.unwrap(),
        rendered.ate_pos_m.unwrap(),
        rendered.nees_ori.unwrap(),
        rendered.nees_pos.unwrap(),
    );
    println!("tracks (held to their first patch, the default): {q:?}");
    assert!(rendered.frames.unwrap() > 1000);
    let (fa, ra) = (
        feature_level.ate_pos_m.unwrap(),
        rendered.ate_pos_m.unwrap(),
    );
    assert!(
        ra <= 2.0 * fa,
        "rendered ATE {ra} m vs feature-level {fa} m"
    );
    assert!(rendered.ate_ori_deg.unwrap() <= 2.0 * feature_level.ate_ori_deg.unwrap());
    assert!(q.features_per_frame > 150.0, "{q:?}");
    assert!(q.reprojection_median_px < 1.0, "{q:?}");
    assert!(q.outlier_fraction < 0.1, "{q:?}");
    // The default frontend holds each track to its first patch: 0.09 px off the
    // truth on average here, against the KLT alone's 0.74.
    assert!(q.reprojection_mean_px < 0.2, "{q:?}");
    // The per-image series adds up to the summary.
    let per = &r.per_frame;
    let n: usize = per.iter().map(|f| f.observations).sum();
    assert_eq!(n, q.observations);
    let mean = per
        .iter()
        .map(|f| f.mean_px * f.observations as f64)
        .sum::<f64>()
        / n as f64;
    assert!(
        (mean - q.reprojection_mean_px).abs() < 1e-9,
        "{mean} vs {q:?}"
    );
    let over: usize = per.iter().map(|f| f.over_3px).sum();
    assert!((over as f64 / n as f64 - q.outlier_fraction).abs() < 1e-12);
    assert!(per.windows(2).all(|w| w[0].t_s < w[1].t_s));
    let worst = per
        .iter()
        .map(|f| f.common_px[0].hypot(f.common_px[1]))
        .fold(0.0, f64::max);
    println!("largest common shift of one image: {worst:.3} px");
}

/// The tracks' accuracy against the rendered truth when robot 0's `images` go
/// through the default frontend with `first_patch`.
fn track_quality(
    fleet: &Fleet,
    images: &[Box<CameraEvent>],
    first_patch: FirstPatch,
) -> TrackQuality {
    let opts = FrontendOptions {
        first_patch,
        ..FrontendOptions::default()
    };
    let mut fe = Frontend::new(opts, fleet.initial_calibration(0).camera).expect("frontend");
    let mut scorer = TrackScorer::new(fleet, 0).expect("renders");
    for c in images {
        let image = c.image.as_ref().expect("rendered");
        let out = fe.process(c.frame.t, image).expect("frame");
        scorer.score(c, &out);
    }
    scorer.quality()
}

/// Robot 0's `images` through both frontends: the held tracks keep at least
/// `kept` of the KLT's observations, with under a third of its mean error, a
/// median under 0.15 px and almost none over 3 px.
fn held_tracks_beat_klt(fleet: &Fleet, images: &[Box<CameraEvent>], kept: f64) {
    let (klt, held) = (
        track_quality(fleet, images, FirstPatch::Off),
        track_quality(fleet, images, FirstPatch::Drop),
    );
    println!("frame to frame: {klt:?}\nheld to the first patch: {held:?}");
    assert!(held.features_per_frame > 150.0, "{held:?}");
    assert!(held.observations as f64 > kept * klt.observations as f64);
    assert!(
        held.reprojection_mean_px < klt.reprojection_mean_px / 3.0,
        "{held:?} vs {klt:?}"
    );
    assert!(held.reprojection_median_px < 0.15, "{held:?}");
    assert!(held.outlier_fraction < 0.002, "{held:?}");
}

/// Frame-to-frame KLT adds an error at every image, and along a track they add
/// up; a track held to its first patch (`first_patch`) does not drift.
#[test]
fn tracks_held_to_their_first_patch_drift_a_fraction_of_frame_to_frame_klt() {
    let path =
        PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("../sim-fleet/scenarios/v1_01_easy.yaml");
    let mut sc = Scenario::load(&path).expect("scenario");
    sc.render.enabled = true;
    let fleet = Fleet::build(&sc, 1).expect("rendered fleet");
    let start = fleet.estimator_start_time(0).expect("start");
    // 40 s of the flight.
    let images: Vec<Box<CameraEvent>> = fleet
        .stream(0)
        .expect("stream")
        .filter_map(|e| match e {
            SimEvent::Camera(c) if c.truth.t >= start => Some(c),
            _ => None,
        })
        .take(400)
        .collect();
    held_tracks_beat_klt(&fleet, &images, 0.9);
}

/// A camera that rolls about its own axis (here one looking up at the ceiling
/// of a robot turning at 1 rad/s, as the simulated TUM-VI corridor's cameras
/// do) turns every KLT window between images, and translation-only windows
/// drift with it; held tracks follow the roll with their affine warp.
#[test]
fn tracks_held_to_their_first_patch_follow_a_camera_rolling_about_its_axis() {
    use common::trajectory::{write_tum, StampedPose};
    use nalgebra::Vector3;
    let dir = tempfile::tempdir().expect("tempdir");
    let path = dir.path().join("turning.txt");
    // A 0.5 m circle at 1 rad/s, the body's z (the camera's axis, within
    // 2 degrees) up, with a little pitch, roll and height change.
    let poses: Vec<StampedPose> = (0..=2000)
        .map(|k| {
            let t = k as f64 * 0.01;
            let yaw = t;
            let tilt = Vector3::new(0.1 * (0.9 * t).sin(), 0.1 * (1.1 * t).sin(), 0.0);
            StampedPose {
                t,
                rot: common::so3::exp_so3(&Vector3::new(0.0, 0.0, yaw))
                    * common::so3::exp_so3(&tilt),
                pos: Vector3::new(
                    0.5 * yaw.cos(),
                    0.5 * yaw.sin(),
                    1.2 + 0.1 * (0.7 * t).sin(),
                ),
            }
        })
        .collect();
    write_tum(&path, &poses).expect("trajectory");
    let scenario =
        PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("../sim-fleet/scenarios/v1_01_easy.yaml");
    let mut sc = Scenario::load(&scenario).expect("scenario");
    sc.robots.truncate(1);
    sc.robots[0].trajectory = path;
    sc.render.enabled = true;
    let fleet = Fleet::build(&sc, 1).expect("rendered fleet");
    let images: Vec<Box<CameraEvent>> = fleet
        .stream(0)
        .expect("stream")
        .filter_map(|e| match e {
            SimEvent::Camera(c) => Some(c),
            SimEvent::Imu(_) => None,
        })
        .collect();
    assert!(images.len() > 150, "{} images", images.len());
    held_tracks_beat_klt(&fleet, &images, 0.8);
}
