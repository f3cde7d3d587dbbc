//! Rendered images of a robot that walks, stands, creeps at 3 cm/s and walks
//! on, through the image frontend and the estimator: the standstill found from
//! the images (tracks still since the last clone) must hold the robot while it
//! stands, also when its IMU shakes far beyond the filter's noise (rotors,
//! engine), and must not take the creep or the walk for a standstill.

#![allow(clippy::expect_used, clippy::unwrap_used)]

mod circle_walk;

use agent::frontend::FrontendOptions;
use agent::image_runner::run_robot_rendered;
use agent::runner::{options_for, Variant};
use simulator::{Fleet, Scenario};
use std::path::Path;

/// Speed profile, fraction of 1.5 m/s: walk, ease to a stop at 14-16 s, stand
/// until 26 s, ease into a 3 cm/s creep by 27 s, creep until 37 s, ease back to
/// walking by 39 s, walk until 50 s.
fn speed(t: f64) -> f64 {
    use std::f64::consts::PI;
    let ease = |from: f64, to: f64, t0: f64, dt: f64, t: f64| {
        from + (to - from) * 0.5 * (1.0 - (PI * (t - t0) / dt).cos())
    };
    const CREEP: f64 = 0.02;
    match t {
        t if t < 14.0 => 1.0,
        t if t < 16.0 => ease(1.0, 0.0, 14.0, 2.0, t),
        t if t < 26.0 => 0.0,
        t if t < 27.0 => ease(0.0, CREEP, 26.0, 1.0, t),
        t if t < 37.0 => CREEP,
        t if t < 39.0 => ease(CREEP, 1.0, 37.0, 2.0, t),
        _ => 1.0,
    }
}

/// Standstill frames while standing, creeping and walking (of how many), and
/// the position ATE, m.
struct Outcome {
    standing: (usize, usize),
    creeping: (usize, usize),
    walking: (usize, usize),
    ate_pos_m: f64,
}

/// One rendered run: the simulated IMU's noise is `shake` times the filter's.
fn run(dir: &Path, shake: f64, disparity_px: f64) -> Outcome {
    // 50 s on the 3 m circle.
    circle_walk::write_circle_walk(&dir.join("walk.txt"), 1000, 1.0 / 3.0, speed);
    let imu = format!(
        "sensors:\n  imu:\n    gyro_noise_density: {}\n    accel_noise_density: {}\n",
        1.6968e-4 * shake,
        2.0e-3 * shake
    );
    let path = dir.join("walk.yaml");
    std::fs::write(
        &path,
        format!("name: walk\nrobots:\n  - trajectory: walk.txt\n{imu}render:\n  enabled: true\n"),
    )
    .expect("write scenario");
    let scenario = Scenario::load(&path).expect("scenario");
    let fleet = Fleet::build(&scenario, 1).expect("fleet");
    let mut opts = options_for(&scenario.estimator, &fleet, 0, Variant::IndpSlam);
    // The filter keeps the datasheet's noise whatever the IMU does.
    opts.imu.gyro_noise_density = 1.6968e-4;
    opts.imu.accel_noise_density = 2.0e-3;
    opts.zupt_max_disparity_px = disparity_px;
    let r = run_robot_rendered(&fleet, 0, opts, FrontendOptions::default(), |_, _| {})
        .expect("rendered run");
    println!(
        "frames {:.2}..{:.2} s",
        r.run.frames.first().map_or(0.0, |f| f.t),
        r.run.frames.last().map_or(0.0, |f| f.t)
    );
    let count = |lo: f64, hi: f64| {
        let frames: Vec<bool> = r
            .run
            .frames
            .iter()
            .filter(|f| f.t >= lo && f.t < hi)
            .map(|f| f.zero_velocity)
            .collect();
        (frames.iter().filter(|z| **z).count(), frames.len())
    };
    let m = r.run.metrics();
    let out = Outcome {
        standing: count(16.5, 26.0),
        creeping: count(27.5, 37.0),
        walking: {
            let (a, n) = count(0.0, 13.5);
            let (b, k) = count(39.5, 60.0);
            (a + b, n + k)
        },
        ate_pos_m: m.ate_pos_m.unwrap(),
    };
    println!(
        "shake {shake}, disparity {disparity_px} px: standstills standing {:?}, creeping {:?}, walking {:?}; ATE {:.3} deg / {:.3} m, NEES {:.2} / {:.2}",
        out.standing,
        out.creeping,
        out.walking,
        m.ate_ori_deg.unwrap(),
        out.ate_pos_m,
        m.nees_ori.unwrap(),
        m.nees_pos.unwrap()
    );
    out
}

/// Measured (seed 1, 95 frames standing, 95 creeping, 230 walking):
/// honest IMU 94 / 0 / 0 standstills (89 / 0 / 0 by the IMU alone);
/// shaking IMU 62 / 0 / 0 with the images, none by the IMU alone, ATE 0.079
/// vs 0.081 m. Judged one frame apart instead of over 0.3 s, the shaking
/// run took 10 creeping frames for standstills.
#[test]
fn a_robot_standing_is_held_by_its_images_and_a_creeping_one_is_not_stopped() {
    let dir = tempfile::tempdir().expect("tempdir");
    let honest = run(dir.path(), 1.0, 1.0);
    assert!(
        honest.standing.0 * 10 >= honest.standing.1 * 9,
        "{:?}",
        honest.standing
    );
    assert_eq!((honest.creeping.0, honest.walking.0), (0, 0));

    let shaking = run(dir.path(), 10.0, 1.0);
    let imu_only = run(dir.path(), 10.0, 0.0);
    assert_eq!(imu_only.standing.0, 0, "the IMU test passes a shaking IMU");
    assert!(
        shaking.standing.0 * 2 >= shaking.standing.1,
        "{:?}",
        shaking.standing
    );
    assert_eq!((shaking.creeping.0, shaking.walking.0), (0, 0));
    assert!(shaking.ate_pos_m <= imu_only.ate_pos_m * 1.05);
}
