//! Short end-to-end runs of one simulated robot through its estimator, with
//! asserted accuracy (ATE) and consistency (NEES) bounds.
//!
//! The robot walks a 40 s loop (about 1.2 m/s, rolling and pitching while it turns)
//! in the simulator's default setup: 400 Hz IMU with thesis Table 5.1 noise, 10 Hz
//! EuRoC cam0 with 1 px noise (TUM-VI's fisheye in one test), a perturbed initial
//! calibration estimated online.
//! The bounds were set at about 2-3x the values measured over seeds 1-3 (release
//! build); see each constant.

// Helpers outside `#[test]` functions: a failed setup is a failed test.
#![allow(clippy::expect_used)]

mod sim_drive;

use agent::central::run::run_central;
use agent::runner::{options_for, run_robot, RobotRun, Variant};
use common::summary::MetricSet;
use nalgebra::UnitQuaternion;
use sim_drive::drive_robot0;
use simulator::{Fleet, Scenario};
use std::path::Path;
use std::time::Instant;

/// Seeds every accuracy figure is averaged over.
const SEEDS: [u64; 3] = [1, 2, 3];

/// Length of the synthetic trajectory, s.
const DURATION_S: f64 = 40.0;

/// Writes the synthetic walk (TUM text, 20 Hz): a 4 m radius circle at 0.3 rad/s
/// (1.2 m/s), height, roll and pitch oscillating, yaw following the circle.
fn write_walk(path: &Path) {
    write_walk_from(path, 0.0);
}

/// [`write_walk`] starting `phase_rad` further along the circle.
fn write_walk_from(path: &Path, phase_rad: f64) {
    write_circle(path, DURATION_S, |s| (0.3 * s + phase_rad, 1.0));
}

/// Writes a 4 m radius circle (TUM text, 20 Hz, `duration_s`): `along(s)` gives
/// the angle travelled at time `s` and the gain of the height's oscillation;
/// roll and pitch oscillate, yaw follows the circle.
fn write_circle(path: &Path, duration_s: f64, along: impl Fn(f64) -> (f64, f64)) {
    let mut text = String::from("# timestamp tx ty tz qx qy qz qw\n");
    let n = (duration_s * 20.0) as usize;
    for k in 0..=n {
        let s = k as f64 / 20.0;
        let (a, gain) = along(s);
        let (x, y, z) = (
            4.0 * a.cos(),
            4.0 * a.sin(),
            1.2 + 0.3 * (0.6 * s).sin() * gain,
        );
        let roll = 0.15 * (0.7 * s).sin();
        let pitch = 0.12 * (0.9 * s + 1.0).sin();
        let yaw = a + std::f64::consts::FRAC_PI_2;
        let q = UnitQuaternion::from_euler_angles(roll, pitch, yaw);
        text.push_str(&format!(
            "{:.6} {x:.6} {y:.6} {z:.6} {:.9} {:.9} {:.9} {:.9}\n",
            100.0 + s,
            q.i,
            q.j,
            q.k,
            q.w
        ));
    }
    std::fs::write(path, text).expect("write trajectory");
}

/// A one-robot scenario on the synthetic walk, with extra `estimator` settings
/// (a YAML flow mapping, `{}` for the defaults), in `dir`.
fn scenario(dir: &Path, estimator: &str) -> Scenario {
    write_walk(&dir.join("walk.txt"));
    let path = dir.join("walk.yaml");
    std::fs::write(
        &path,
        format!("name: walk\nrobots:\n  - trajectory: walk.txt\nestimator: {estimator}\n"),
    )
    .expect("write scenario");
    Scenario::load(&path).expect("load scenario")
}

/// TUM-VI's cam0 (512_16 calibration): a 512x512 equidistant fisheye with a
/// 190 px focal length, as a scenario's `sensors: camera:` keys.
const TUM_VI_FISHEYE: &str = "{model: equidistant, width_px: 512, height_px: 512, \
     intrinsics_px: [190.978, 190.973, 254.932, 256.897], \
     distortion: [0.00348238940225, 0.000715034845216, -0.00205323614187, 0.000202936735918]}";

/// [`scenario`] seen through the camera `camera` (a YAML flow mapping of
/// `sensors: camera:` keys over the defaults).
fn scenario_with_camera(dir: &Path, camera: &str, estimator: &str) -> Scenario {
    write_walk(&dir.join("walk.txt"));
    let path = dir.join("walk.yaml");
    std::fs::write(
        &path,
        format!(
            "name: walk\nrobots:\n  - trajectory: walk.txt\nsensors:\n  camera: {camera}\n\
             estimator: {estimator}\n"
        ),
    )
    .expect("write scenario");
    Scenario::load(&path).expect("load scenario")
}

/// One run of robot 0 with `seed` and `variant`.
fn run(scenario: &Scenario, seed: u64, variant: Variant) -> RobotRun {
    let fleet = Fleet::build(scenario, seed).expect("build fleet");
    let opts = options_for(&scenario.estimator, &fleet, 0, variant);
    run_robot(&fleet, 0, opts).expect("run robot")
}

/// Largest position error of the run, m.
fn max_position_error(run: &RobotRun) -> f64 {
    run.estimate
        .iter()
        .zip(&run.truth)
        .map(|(e, g)| (e.pos - g.pos).norm())
        .fold(0.0, f64::max)
}

/// Asserts that the run went through without diverging, and returns its metrics.
fn checked_metrics(run: &RobotRun, label: &str) -> MetricSet {
    let m = run.metrics();
    let frames = m.frames.unwrap_or(0);
    // About 10 Hz over the walk after the ~1 s start.
    assert!(frames > 350, "{label}: only {frames} frames estimated");
    assert!(
        run.rejected.is_empty(),
        "{label}: rejected inputs: {:?}",
        run.rejected.iter().take(5).collect::<Vec<_>>()
    );
    for e in &run.estimate {
        assert!(
            e.pos.iter().chain(e.rot.iter()).all(|v| v.is_finite()),
            "{label}: non-finite estimate at t={}",
            e.t
        );
    }
    let max_err = max_position_error(run);
    assert!(
        max_err < 1.0,
        "{label}: diverged (max position error {max_err:.3} m)"
    );
    m
}

/// Mean of one metric over runs.
fn mean(ms: &[MetricSet], f: impl Fn(&MetricSet) -> Option<f64>) -> f64 {
    let v: Vec<f64> = ms.iter().map(|m| f(m).expect("metric present")).collect();
    v.iter().sum::<f64>() / v.len() as f64
}

/// Runs `variant` over [`SEEDS`] with extra `estimator` settings and prints
/// each run's figures and the means.
fn runs_over_seeds(variant: Variant, estimator: &str, seeds: &[u64]) -> MetricSet {
    let dir = tempfile::tempdir().expect("tempdir");
    let sc = scenario(dir.path(), estimator);
    let mut ms = Vec::new();
    for &seed in seeds {
        let start = Instant::now();
        let r = run(&sc, seed, variant);
        let label = format!("{} seed {seed}", variant.name());
        let m = checked_metrics(&r, &label);
        println!(
            "{label}: ATE {:.3} deg {:.3} m, NEES ori {:.2} pos {:.2}, max pos err {:.3} m, \
             {} frames, {:.2} ms/frame, run {:.2} s",
            m.ate_ori_deg.unwrap_or(f64::NAN),
            m.ate_pos_m.unwrap_or(f64::NAN),
            m.nees_ori.unwrap_or(f64::NAN),
            m.nees_pos.unwrap_or(f64::NAN),
            max_position_error(&r),
            m.frames.unwrap_or(0),
            m.ms_per_frame_mean.unwrap_or(f64::NAN),
            start.elapsed().as_secs_f64(),
        );
        ms.push(m);
    }
    let mean_set = MetricSet {
        ate_ori_deg: Some(mean(&ms, |m| m.ate_ori_deg)),
        ate_pos_m: Some(mean(&ms, |m| m.ate_pos_m)),
        nees_ori: Some(mean(&ms, |m| m.nees_ori)),
        nees_pos: Some(mean(&ms, |m| m.nees_pos)),
        ..MetricSet::default()
    };
    println!(
        "{} mean over seeds {seeds:?}: ATE {:.3} deg {:.3} m, NEES ori {:.2} pos {:.2}",
        variant.name(),
        mean_set.ate_ori_deg.unwrap_or(f64::NAN),
        mean_set.ate_pos_m.unwrap_or(f64::NAN),
        mean_set.nees_ori.unwrap_or(f64::NAN),
        mean_set.nees_pos.unwrap_or(f64::NAN),
    );
    mean_set
}

/// NEES means (3 DoF, ideal 3) accepted for orientation and position.
const NEES_RANGE: std::ops::RangeInclusive<f64> = 0.3..=6.0;

/// Asserts the seed-averaged figures of `variant` (with extra `estimator`
/// settings) against its bounds.
fn assert_accurate_and_consistent(
    variant: Variant,
    estimator: &str,
    seeds: &[u64],
    max_ate_deg: f64,
    max_ate_m: f64,
) {
    let m = runs_over_seeds(variant, estimator, seeds);
    let name = variant.name();
    let (ori_deg, pos_m) = (
        m.ate_ori_deg.unwrap_or(f64::NAN),
        m.ate_pos_m.unwrap_or(f64::NAN),
    );
    assert!(
        ori_deg < max_ate_deg,
        "{name}: mean ATE orientation {ori_deg:.3} deg"
    );
    assert!(pos_m < max_ate_m, "{name}: mean ATE position {pos_m:.3} m");
    for (what, v) in [("orientation", m.nees_ori), ("position", m.nees_pos)] {
        let v = v.unwrap_or(f64::NAN);
        assert!(
            NEES_RANGE.contains(&v),
            "{name}: mean {what} NEES {v:.2} outside {NEES_RANGE:?}"
        );
    }
}

#[test]
fn msckf_only_runs_are_accurate_and_consistent_over_three_seeds() {
    // Measured means over seeds 1-3: 0.73 deg, 0.164 m; NEES 2.33 (ori), 2.51 (pos).
    assert_accurate_and_consistent(Variant::Indp, "{}", &SEEDS, 1.8, 0.4);
}

#[test]
fn slam_runs_are_accurate_and_consistent_over_three_seeds() {
    // Measured means over seeds 1-3: 0.21 deg, 0.048 m; NEES 2.00 (ori), 0.55 (pos).
    assert_accurate_and_consistent(Variant::IndpSlam, "{}", &SEEDS, 0.5, 0.12);
}

#[test]
fn a_fisheye_lens_is_accurate_and_consistent_over_three_seeds() {
    // TUM-VI's fisheye on the walk; its rays are triangulated by angle
    // (`RayResidual::Angle`). Measured means over seeds 1-3: MSCKF only 0.576
    // deg, 0.201 m, NEES 1.67 / 1.82; with SLAM features 0.229 deg, 0.059 m,
    // NEES 1.80 / 0.49. With normalized-coordinate residuals, as before,
    // the MSCKF alone gave 1.077 deg, 0.335 m, NEES 3.89 / 5.59: the bounds
    // without SLAM features sit between the two, and the NEES range is the
    // issue's.
    let dir = tempfile::tempdir().expect("tempdir");
    let sc = scenario_with_camera(dir.path(), TUM_VI_FISHEYE, "{}");
    for (variant, max_deg, max_m) in [(Variant::Indp, 0.9, 0.3), (Variant::IndpSlam, 0.5, 0.12)] {
        let name = variant.name();
        let ms: Vec<MetricSet> = SEEDS
            .iter()
            .map(|&seed| {
                checked_metrics(
                    &run(&sc, seed, variant),
                    &format!("fisheye {name} seed {seed}"),
                )
            })
            .collect();
        let (deg, m) = (mean(&ms, |m| m.ate_ori_deg), mean(&ms, |m| m.ate_pos_m));
        let (nees_ori, nees_pos) = (mean(&ms, |m| m.nees_ori), mean(&ms, |m| m.nees_pos));
        println!(
            "fisheye {name}: ATE {deg:.3} deg {m:.3} m, NEES ori {nees_ori:.2} pos {nees_pos:.2}"
        );
        assert!(
            deg < max_deg,
            "fisheye {name}: mean ATE orientation {deg:.3} deg"
        );
        assert!(m < max_m, "fisheye {name}: mean ATE position {m:.3} m");
        for (what, v) in [("orientation", nees_ori), ("position", nees_pos)] {
            assert!(
                (0.3..=4.5).contains(&v),
                "fisheye {name}: mean {what} NEES {v:.2} outside [0.3, 4.5]"
            );
        }
    }
}

/// The body twist each frame reports (published as `nav_msgs/Odometry` on live
/// sensors) is consistent with the truth: the velocity in the IMU frame and
/// the angular rate (the gyro's reading less the estimated bias), each a 3-dof
/// NEES against the spline's analytic velocity and rate, over seeds 1-3 from
/// the truth start. Measured: 3.38 and 1.85 (the walk's images fall between
/// gyro samples, and a reading interpolated between two has on average 2/3
/// of one reading's noise variance). From a start drawn from an initializer's prior the velocity NEES
/// is 5.65 (seed 1: 9.6), the walk's excess that
/// `slam_runs_started_off_the_truth_are_consistent` bounds in position.
#[test]
fn the_body_twist_is_consistent_with_the_truth() {
    let dir = tempfile::tempdir().expect("tempdir");
    let sc = scenario(dir.path(), "{}");
    let (mut lin, mut ang, mut n) = (0.0, 0.0, 0usize);
    for seed in SEEDS {
        let fleet = Fleet::build(&sc, seed).expect("fleet");
        let opts = options_for(&sc.estimator, &fleet, 0, Variant::IndpSlam);
        let (mut seed_lin, mut seed_ang, mut seed_n) = (0.0, 0.0, 0usize);
        drive_robot0(&fleet, opts, |_, o| {
            let Some(truth) = fleet.truths[0].state(o.t()) else {
                return true;
            };
            let tw = &o.twist;
            let e_lin = tw.linear - truth.rot.transpose() * truth.vel;
            let e_ang = tw.angular - truth.omega;
            let p_lin = tw.cov.fixed_view::<3, 3>(0, 0).into_owned();
            let p_ang = tw.cov.fixed_view::<3, 3>(3, 3).into_owned();
            seed_lin += e_lin.dot(&(p_lin.try_inverse().expect("SPD") * e_lin));
            seed_ang += e_ang.dot(&(p_ang.try_inverse().expect("SPD") * e_ang));
            seed_n += 1;
            true
        });
        assert!(seed_n > 350, "seed {seed}: {seed_n} frames");
        println!(
            "seed {seed}: body velocity NEES {:.2}, angular rate NEES {:.2} over {seed_n} frames",
            seed_lin / seed_n as f64,
            seed_ang / seed_n as f64
        );
        (lin, ang, n) = (lin + seed_lin, ang + seed_ang, n + seed_n);
    }
    let (lin, ang) = (lin / n as f64, ang / n as f64);
    println!("seeds 1-3: body velocity NEES {lin:.2}, angular rate NEES {ang:.2} (3 ideal)");
    assert!((1.5..4.5).contains(&lin), "velocity NEES {lin}");
    assert!((1.5..4.5).contains(&ang), "angular rate NEES {ang}");
}

/// The runs above start at the true state, so the errors in the unobservable
/// directions (global position, yaw) stay near zero while the covariance keeps
/// the prior: their NEES says little. Here every start is drawn from the prior
/// the filter states (an initializer's accuracy: 0.17 deg, 5 cm, 1 cm/s, 0.002
/// per bias axis), and the NEES must still hold.
#[test]
fn slam_runs_started_off_the_truth_are_consistent() {
    let estimator = "{initial_error: sampled, init_sigma_ori_rad: 0.003, init_sigma_bias: 0.002}";
    let dir = tempfile::tempdir().expect("tempdir");
    let sc = scenario(dir.path(), estimator);
    let r = run(&sc, SEEDS[0], Variant::IndpSlam);
    let (first, truth) = (r.estimate.first(), r.truth.first());
    let (Some(first), Some(truth)) = (first, truth) else {
        panic!("no estimate");
    };
    let start_err = (first.pos - truth.pos).norm();
    assert!(
        start_err > 1e-3,
        "the start is the truth ({start_err} m off)"
    );
    // A NEES means something over more seeds than three: eight runs of 0.4 s.
    // Measured means over seeds 1-8: 0.20 deg, 0.124 m; NEES 3.36 (ori), 4.36
    // (pos, ideal 3: a little overconfident on this rolling walk); the
    // position error keeps the start's (global position is unobservable).
    let seeds: Vec<u64> = (1..=8).collect();
    assert_accurate_and_consistent(Variant::IndpSlam, estimator, &seeds, 0.5, 0.2);
}

/// Runs `metrics_of(iterations)` with the first update as one plain step and
/// iterated twice, prints both, and asserts that iterating keeps the mean NEES
/// in range and lowers it.
fn assert_iterating_the_first_update_helps(
    label: &str,
    metrics_of: impl Fn(usize) -> Vec<MetricSet>,
) {
    let mut nees = Vec::new();
    for iterations in [0, 2] {
        let ms = metrics_of(iterations);
        let (ori, pos) = (mean(&ms, |m| m.nees_ori), mean(&ms, |m| m.nees_pos));
        println!(
            "{label}, first update iterated {iterations} times: ATE {:.3} deg {:.3} m, \
             NEES ori {ori:.2} pos {pos:.2}",
            mean(&ms, |m| m.ate_ori_deg),
            mean(&ms, |m| m.ate_pos_m),
        );
        nees.push(ori + pos);
        if iterations > 0 {
            for (what, v) in [("orientation", ori), ("position", pos)] {
                assert!(NEES_RANGE.contains(&v), "{label}: mean {what} NEES {v:.2}");
            }
        }
    }
    assert!(
        nees[1] < nees[0],
        "{label}: NEES sums: one step {:.2}, iterated {:.2}",
        nees[0],
        nees[1]
    );
}

/// The estimator settings of a start drawn from the reference's 1 deg prior
/// (biases 0.002) with the first update iterated `iterations` times.
fn tilted_start(iterations: usize) -> String {
    format!(
        "{{initial_error: sampled, init_sigma_bias: 0.002, first_update_iterations: {iterations}}}"
    )
}

/// From a start tilted by up to a degree (the orientation drawn from the
/// reference's 1 deg prior), the first update comes after a whole window of
/// flight on that tilt: one linearized step leaves part of it while the
/// covariance claims it gone, and iterating that update (the default) keeps
/// the filter consistent.
#[test]
fn a_tilted_start_stays_consistent_with_the_iterated_first_update() {
    let dir = tempfile::tempdir().expect("tempdir");
    // Measured (seeds 1-8): one step 0.55 deg / 0.158 m, NEES 4.89 / 6.84;
    // iterated twice 0.58 / 0.138, NEES 3.78 / 4.92.
    assert_iterating_the_first_update_helps("one robot, seeds 1-8", |iterations| {
        let sc = scenario(dir.path(), &tilted_start(iterations));
        (1..=8)
            .map(|seed| {
                let r = run(&sc, seed, Variant::IndpSlam);
                checked_metrics(&r, &format!("{iterations} iterations, seed {seed}"))
            })
            .collect()
    });
}

/// The centralized estimator iterates each robot's first update too (its prior
/// and every redo are the whole joint state): two robots on opposite sides of
/// the walk, each started off the truth by a draw from the 1 deg prior.
#[test]
fn the_centralized_filter_iterates_each_robots_first_update_too() {
    let dir = tempfile::tempdir().expect("tempdir");
    write_walk_from(&dir.path().join("a.txt"), 0.0);
    write_walk_from(&dir.path().join("b.txt"), std::f64::consts::PI);
    // Measured (seeds 1-6, both robots): one step 0.529 deg / 0.081 m, NEES
    // 5.85 / 4.06; iterated twice 0.522 / 0.080, NEES 5.27 / 3.77.
    assert_iterating_the_first_update_helps("centralized, two robots, seeds 1-6", |iterations| {
        let path = dir.path().join(format!("pair{iterations}.yaml"));
        let robots = "robots:\n  - trajectory: a.txt\n  - trajectory: b.txt\n";
        let yaml = format!(
            "name: pair\n{robots}estimator: {}\n",
            tilted_start(iterations)
        );
        std::fs::write(&path, yaml).expect("write scenario");
        let sc = Scenario::load(&path).expect("load scenario");
        let mut ms = Vec::new();
        for seed in 1..=6 {
            let fleet = Fleet::build(&sc, seed).expect("build fleet");
            let runs = run_central(&fleet, Variant::CeCmsckf).expect("run fleet");
            for (r, run) in runs.iter().enumerate() {
                let label = format!("{iterations} iterations, seed {seed}, robot {r}");
                ms.push(checked_metrics(run, &label));
            }
        }
        ms
    });
}

#[test]
fn the_same_scenario_and_seed_give_bit_identical_estimates() {
    let dir = tempfile::tempdir().expect("tempdir");
    let sc = scenario(dir.path(), "{}");
    // Each run builds its own fleet: simulator and estimator are both covered.
    let a = run(&sc, 7, Variant::IndpSlam);
    let b = run(&sc, 7, Variant::IndpSlam);
    assert!(a.estimate.len() > 350, "{} estimates", a.estimate.len());
    assert_eq!(a.estimate.len(), b.estimate.len());
    for (x, y) in a.estimate.iter().zip(&b.estimate) {
        assert_eq!(x, y, "estimates differ at t={}", x.t);
    }
    assert_eq!(a.covariance, b.covariance);
    assert_eq!(a.rejected, b.rejected);
}

#[test]
fn a_run_without_first_estimates_jacobians_completes() {
    let dir = tempfile::tempdir().expect("tempdir");
    let sc = scenario(dir.path(), "{ use_fej: false }");
    assert!(!sc.estimator.use_fej);
    let fleet = Fleet::build(&sc, 1).expect("build fleet");
    let opts = options_for(&sc.estimator, &fleet, 0, Variant::IndpSlam);
    assert!(!opts.use_fej);
    let r = run_robot(&fleet, 0, opts).expect("run robot");
    let m = r.metrics();
    // No consistency bound: FEJ is what keeps the filter consistent.
    println!(
        "indp-slam without FEJ, seed 1: ATE {:.3} deg {:.3} m, NEES ori {:.2} pos {:.2}, {} frames",
        m.ate_ori_deg.unwrap_or(f64::NAN),
        m.ate_pos_m.unwrap_or(f64::NAN),
        m.nees_ori.unwrap_or(f64::NAN),
        m.nees_pos.unwrap_or(f64::NAN),
        m.frames.unwrap_or(0),
    );
    assert!(m.frames.unwrap_or(0) > 350, "{m:?}");
    assert!(m.ate_pos_m.is_some_and(f64::is_finite), "{m:?}");
}

#[test]
fn no_feature_update_before_the_oldest_clone_leaves_and_no_track_is_lost_meanwhile() {
    let dir = tempfile::tempdir().expect("tempdir");
    let sc = scenario(dir.path(), "{}");
    assert_eq!(
        sc.estimator.first_update_clones(),
        sc.estimator.max_clones + 1
    );
    let r = run(&sc, 1, Variant::Indp);
    let updated = |f: &agent::estimator::FrameRecord| f.msckf.used + f.msckf.rejected_chi2;
    // Frames 1-11 fill the window: nothing is updated, nothing is thrown away.
    let full = sc.estimator.max_clones;
    assert!(
        r.frames[..full].iter().all(|f| updated(f) == 0),
        "{:?}",
        &r.frames[..full]
    );
    // The twelfth frame, whose oldest clone leaves, takes the tracks lost
    // meanwhile and the ones that span the window: many at once.
    assert!(updated(&r.frames[full]) >= 10, "{:?}", r.frames[full].msckf);

    // With the gate at one clone, tracks are used as soon as they are lost.
    let eager = scenario(dir.path(), "{ min_clones_to_update: 1 }");
    let r = run(&eager, 1, Variant::Indp);
    let early: usize = r.frames[..4].iter().map(updated).sum();
    assert!(early > 0);

    // A longer window moves the first update with it, unless it is set.
    let long = scenario(dir.path(), "{ max_clones: 15 }");
    assert_eq!(long.estimator.first_update_clones(), 16);
    let set = scenario(dir.path(), "{ max_clones: 15, min_clones_to_update: 8 }");
    assert_eq!(set.estimator.first_update_clones(), 8);
}

/// Writes a slow start (TUM text, 20 Hz, 50 s): the walk's circle and rolling,
/// its speed rising from rest towards 1.2 m/s with a time constant of
/// `ramp_s`, as a platform that sets off gently (EuRoC V1_01). The filter
/// starts after 1.1 m of travel, still at a walking pace.
fn write_slow_start(path: &Path, ramp_s: f64) {
    write_circle(path, 50.0, |s| {
        let ease = 1.0 - (-s / ramp_s).exp();
        (0.3 * (s - ramp_s * ease), ease)
    });
}

/// A one-robot scenario on the `slow.txt` of `dir` (see [`write_slow_start`]),
/// with `settings` (YAML top-level sections) after its robot, saved as `file`.
fn slow_start_scenario(dir: &Path, file: &str, settings: &str) -> Scenario {
    let path = dir.join(file);
    let yaml = format!("name: slow\nrobots:\n  - trajectory: slow.txt\n{settings}");
    std::fs::write(&path, yaml).expect("write scenario");
    Scenario::load(&path).expect("load scenario")
}

/// A slow flight: the walk's circle at 0.12 m/s (0.03 rad/s) for a minute,
/// points 5-7 m away, so the window's second of views sees a point's rays
/// about 1 deg apart and most tracks fail the condition limit on the window
/// alone. A track that goes on keeps the rays of the clones that left
/// (`Feature::retired`) to triangulate from, and a SLAM candidate that could
/// not be triangulated is tried again instead of dropped. Before, seeds 1-6
/// diverged in one run of each variant (up to 288 m) and the position NEES of
/// every run but one was 20-520. An update starved of tracks (nearly all fail)
/// then asks those with retired rays for the window's depth precision
/// (`TriangulationOptions::starved`): seeds 1-10, ATE 0.08-0.35 m without
/// SLAM features (mean 0.193 m, position NEES 8.0; 0.195 m and 7.3 without
/// the starved rule), 0.02-0.32 m with (seed 8: 0.218 m, NEES 11.2, where it
/// was 0.513 m, NEES 66). Since its first update waits for parallax
/// (`slow_start`, stop 75), seeds 1-3 keep 0.045-0.091 m, NEES 0.56-2.01,
/// without SLAM features and 0.037-0.063 m, NEES 0.38-0.96, with them; since
/// such a start also takes the settings for slow platforms
/// (`slow_platform_settings`, stop 79), 0.048-0.102 m, NEES 0.43-1.76, and
/// 0.018-0.058 m, NEES 0.09-0.89.
#[test]
fn a_slow_flight_does_not_diverge() {
    let dir = tempfile::tempdir().expect("tempdir");
    write_circle(&dir.path().join("slow.txt"), 60.0, |s| (0.03 * s, 1.0));
    let sc = slow_start_scenario(dir.path(), "slow_flight.yaml", "estimator: {}\n");
    for variant in [Variant::Indp, Variant::IndpSlam] {
        for seed in SEEDS {
            let label = format!("slow flight, {variant:?}, seed {seed}");
            let r = run(&sc, seed, variant);
            let m = checked_metrics(&r, &label);
            let ate = m.ate_pos_m.expect("position ATE");
            println!(
                "{label}: ATE {:.3} deg / {ate:.3} m, NEES {:.2} / {:.2}, max error {:.3} m",
                m.ate_ori_deg.unwrap_or(f64::NAN),
                m.nees_ori.unwrap_or(f64::NAN),
                m.nees_pos.unwrap_or(f64::NAN),
                max_position_error(&r),
            );
            assert!(ate < 0.4, "{label}: position ATE {ate:.3} m");
        }
    }
}

/// The circle at 0.12 m/s for a minute, in `dir`, with the slow-start rule
/// on (the default) and off (`slow_start_keyframe_px: 0`).
fn slow_circle_with_the_rule_on_and_off(dir: &Path) -> (Scenario, Scenario) {
    write_circle(&dir.join("slow.txt"), 60.0, |s| (0.03 * s, 1.0));
    (
        slow_start_scenario(dir, "on.yaml", "estimator: {}\n"),
        slow_start_scenario(dir, "off.yaml", "estimator: {slow_start_keyframe_px: 0}\n"),
    )
}

/// A slow first window (`agent::estimator::slow_start`): the slow flight's
/// circle at 0.12 m/s, whose first window of consecutive frames spans a few
/// pixels of parallax, so nearly every track fails the ray limits. The first
/// update waits for the window to gain baseline (and the window keeps
/// keyframes from then on), where with the rule off it comes at the full
/// window and takes the few tracks that pass.
#[test]
fn a_slow_first_window_waits_for_parallax() {
    let dir = tempfile::tempdir().expect("tempdir");
    let (on, off) = slow_circle_with_the_rule_on_and_off(dir.path());
    let first_update = |r: &RobotRun| {
        r.frames
            .iter()
            .position(|f| f.msckf.used > 0)
            .expect("an update")
    };
    for seed in SEEDS {
        let (waited, plain) = (
            run(&on, seed, Variant::Indp),
            run(&off, seed, Variant::Indp),
        );
        let label = format!("slow first window, seed {seed}");
        let m = checked_metrics(&waited, &label);
        let (a, b) = (first_update(&waited), first_update(&plain));
        let off = plain.metrics();
        println!(
            "{label}: first update at frame {a} (rule off: {b}); ATE {:.3} deg / {:.3} m, \
             NEES {:.2} / {:.2} (rule off: {:.3} m, NEES {:.2})",
            m.ate_ori_deg.unwrap_or(f64::NAN),
            m.ate_pos_m.unwrap_or(f64::NAN),
            m.nees_ori.unwrap_or(f64::NAN),
            m.nees_pos.unwrap_or(f64::NAN),
            off.ate_pos_m.unwrap_or(f64::NAN),
            off.nees_pos.unwrap_or(f64::NAN),
        );
        assert!(
            a > b,
            "{label}: the first update did not wait ({a} and {b})"
        );
        assert!(m.ate_pos_m.is_some_and(|e| e < 0.4), "{label}: {m:?}");
    }
}

/// The centralized filter's robots wait on a slow first window as the agents'
/// filter does: with one robot, `ce-cmsckf` (SLAM features on, no other robot
/// to share them with) follows `indp-slam` bit for bit on the slow circle,
/// whose first update waits. Before the rule reached `central/`, V1_01 played
/// at 0.4 of its speed (10 seeds) gave 0.559 deg / 0.128 m, NEES 3.30 / 6.99
/// there, against 0.355 / 0.052, 2.61 / 1.11 in the agents.
#[test]
fn the_centralized_filter_waits_on_a_slow_first_window_too() {
    let dir = tempfile::tempdir().expect("tempdir");
    let (sc, off) = slow_circle_with_the_rule_on_and_off(dir.path());
    let seed = SEEDS[0];
    let fleet = Fleet::build(&sc, seed).expect("build fleet");
    let central = run_central(&fleet, Variant::CeCmsckf).expect("run fleet");
    let [joint] = central.as_slice() else {
        panic!("{} robots from a one-robot scenario", central.len());
    };
    let agent = run(&sc, seed, Variant::IndpSlam);
    let first_update = |r: &RobotRun| r.frames.iter().position(|f| f.msckf.used > 0);
    let plain = run(&off, seed, Variant::IndpSlam);
    assert!(
        first_update(&agent) > first_update(&plain),
        "the agents' first update did not wait"
    );
    assert_eq!(first_update(joint), first_update(&agent));
    assert_eq!(joint.estimate.len(), agent.estimate.len());
    for (x, y) in joint.estimate.iter().zip(&agent.estimate) {
        assert_eq!(x, y, "the centralized estimate differs at t={}", x.t);
    }
}

/// From OpenVINS's own prior (1 deg, 5 cm, 1 cm/s, 0.02 per bias axis) on a
/// slow start, the window's clones can be bent so far by the drawn tilt and
/// gyro bias that the first update's step, taken with the Jacobians at their
/// first estimates, goes the wrong way: its features no longer triangulate
/// after it and the filter diverges (seed 1 here). Redone at the current
/// estimate (`rescue_first_update`, the default) it stays on the path; a start
/// whose first step is fine (seed 2) is left bit for bit as it was.
#[test]
fn a_first_update_whose_step_leaves_the_rays_apart_is_redone() {
    let dir = tempfile::tempdir().expect("tempdir");
    write_slow_start(&dir.path().join("slow.txt"), 20.0);
    let runs_with = |rescue: bool, seed: u64| {
        let sc = slow_start_scenario(
            dir.path(),
            &format!("slow_{rescue}.yaml"),
            &format!(
                "estimator: {{initial_error: sampled, init_sigma_ori_rad: 0.017, \
                 init_sigma_bias: 0.02, rescue_first_update: {rescue}}}\n"
            ),
        );
        let r = run(&sc, seed, Variant::IndpSlam);
        let m = r.metrics();
        println!(
            "rescue {rescue}, seed {seed}: ATE {:.3} deg {:.3} m, NEES {:.2} / {:.2}, \
             max pos err {:.3} m",
            m.ate_ori_deg.unwrap_or(f64::NAN),
            m.ate_pos_m.unwrap_or(f64::NAN),
            m.nees_ori.unwrap_or(f64::NAN),
            m.nees_pos.unwrap_or(f64::NAN),
            max_position_error(&r),
        );
        r
    };
    // Measured: without the rescue 23 deg / 1327 m (max error 3042 m); with it
    // 0.62 deg / 0.516 m, NEES 2.46 / 38.6 (max 0.81 m: the slow start leaves
    // the scale weakly observed, and the position NEES is poor with or without
    // the rescue on this path).
    let rescued_frames = |r: &RobotRun| r.frames.iter().filter(|f| f.msckf.rescued).count();
    let plain = runs_with(false, 1);
    let diverged = max_position_error(&plain);
    assert!(
        diverged > 100.0,
        "seed 1 without the rescue: {diverged:.3} m"
    );
    assert_eq!(rescued_frames(&plain), 0);
    let rescued = runs_with(true, 1);
    // Its frame says so (`timing.csv`'s `first_update_rescued`).
    assert_eq!(rescued_frames(&rescued), 1);
    let m = checked_metrics(&rescued, "seed 1 with the rescue");
    let ori = m.nees_ori.unwrap_or(f64::NAN);
    assert!(NEES_RANGE.contains(&ori), "orientation NEES {ori:.2}");
    let (a, b) = (runs_with(false, 2), runs_with(true, 2));
    assert_eq!(rescued_frames(&b), 0);
    assert_eq!(a.estimate, b.estimate, "seed 2 changed");
    assert_eq!(a.covariance, b.covariance, "seed 2 changed");
}

/// On a slow start without SLAM features, the MSCKF's Jacobians at the clones'
/// first estimates misplace the scale and the filter claims it; evaluated at
/// the current estimate with the unobservable directions projected out
/// (`msckf_jacobians: observability_constrained`) the position error is
/// smaller and its NEES in range.
#[test]
fn observability_constrained_msckf_jacobians_keep_a_slow_start_consistent() {
    let dir = tempfile::tempdir().expect("tempdir");
    write_slow_start(&dir.path().join("slow.txt"), 20.0);
    let mut figures = Vec::new();
    for jacobians in ["first_estimates", "observability_constrained"] {
        let sc = slow_start_scenario(
            dir.path(),
            &format!("{jacobians}.yaml"),
            // The setting alone: a start that waits would take the constrained
            // Jacobians whatever the file says (`slow_platform_settings`).
            &format!(
                "estimator: {{msckf_jacobians: {jacobians}, slow_platform_settings: false}}\n"
            ),
        );
        let ms: Vec<MetricSet> = (1..=8)
            .map(|seed| {
                let r = run(&sc, seed, Variant::Indp);
                if jacobians == "first_estimates" {
                    r.metrics()
                } else {
                    checked_metrics(&r, &format!("{jacobians}, seed {seed}"))
                }
            })
            .collect();
        let (ate, ori, pos) = (
            mean(&ms, |m| m.ate_pos_m),
            mean(&ms, |m| m.nees_ori),
            mean(&ms, |m| m.nees_pos),
        );
        println!("{jacobians}, seeds 1-8: ATE {ate:.3} m, NEES {ori:.2} / {pos:.2}");
        figures.push((ate, ori, pos));
    }
    // Measured (stop 79): first estimates 0.347 m, NEES 1.59 / 10.12;
    // observability-constrained 0.216 m, NEES 1.40 / 1.27.
    let [(fej_ate, _, fej_pos), (oc_ate, oc_ori, oc_pos)] = figures[..] else {
        panic!("two settings");
    };
    assert!(fej_pos > 6.0, "first estimates: position NEES {fej_pos:.2}");
    assert!(
        oc_ate < 0.8 * fej_ate,
        "ATE {oc_ate:.3} m against {fej_ate:.3} m"
    );
    for (what, v) in [("orientation", oc_ori), ("position", oc_pos)] {
        assert!(NEES_RANGE.contains(&v), "{what} NEES {v:.2}");
    }
}

/// With noise-free pixels on the slow start, a SLAM feature kept as a 3-D point
/// is linearized at the point it was triangulated at, and on a short baseline
/// that point's depth is far off: in seed 9 the position error then grows
/// frame by frame while every update passes its gate (`docs/evidence`). Kept as
/// an inverse depth in its anchor camera (thesis Appendix A.6.5), the same
/// measurements are nearly linear in the parameter and the run stays on the path.
#[test]
fn inverse_depth_slam_features_keep_a_noise_free_slow_start_on_its_path() {
    let dir = tempfile::tempdir().expect("tempdir");
    write_slow_start(&dir.path().join("slow.txt"), 30.0);
    let mut figures = Vec::new();
    for representation in ["global", "anchored_inverse_depth"] {
        let sc = slow_start_scenario(
            dir.path(),
            &format!("{representation}.yaml"),
            &format!(
                "sensors:\n  calibration_perturbation:\n    enabled: false\n  camera:\n    \
                 pixel_noise_px: 0.0\nestimator: {{calib_extrinsics: false, \
                 calib_intrinsics: false, calib_time_offset: false, pixel_sigma_px: 1.0, \
                 feature_representation: {representation}, slow_platform_settings: false}}\n"
            ),
        );
        let r = run(&sc, 9, Variant::IndpSlam);
        let m = r.metrics();
        let (ate, nees) = (
            m.ate_pos_m.unwrap_or(f64::NAN),
            m.nees_pos.unwrap_or(f64::NAN),
        );
        println!(
            "{representation}, seed 9: ATE {ate:.3} m, position NEES {nees:.2}, max error {:.3} m",
            max_position_error(&r)
        );
        figures.push((ate, nees));
    }
    // Measured (stop 79): 3-D points 0.733 m, position NEES 153 (largest error 1.28 m);
    // inverse depth 0.037 m, NEES 0.12 (the filter weighs the exact pixels at
    // 1 px, so it ought to be underconfident here).
    let [(xyz_ate, xyz_nees), (inv_ate, inv_nees)] = figures[..] else {
        panic!("two representations");
    };
    assert!(xyz_nees > 20.0, "3-D points: position NEES {xyz_nees:.2}");
    assert!(
        inv_ate < 0.25 * xyz_ate,
        "inverse depth {inv_ate:.3} m against {xyz_ate:.3} m"
    );
    assert!(inv_nees < 3.0, "inverse depth: position NEES {inv_nees:.2}");
}

/// The centralized estimator has no image frontend: a scenario that renders
/// images is refused with the reason, not run on the IMUs alone.
#[test]
fn the_centralized_estimator_refuses_rendered_images() {
    let dir = tempfile::tempdir().expect("tempdir");
    write_walk_from(&dir.path().join("a.txt"), 0.0);
    write_walk_from(&dir.path().join("b.txt"), std::f64::consts::PI);
    let path = dir.path().join("rendered.yaml");
    let yaml = "name: rendered\nrobots:\n  - trajectory: a.txt\n  - trajectory: b.txt\nrender:\n  enabled: true\n";
    std::fs::write(&path, yaml).expect("write scenario");
    let sc = Scenario::load(&path).expect("load scenario");
    let fleet = Fleet::build(&sc, 1).expect("build fleet");
    let e = run_central(&fleet, Variant::CeCmsckfCslam)
        .expect_err("a rendered fleet must be refused")
        .to_string();
    assert!(
        e.contains("renders images") && e.contains("ce-cmsckf-cslam"),
        "{e}"
    );
}

/// The centralized filter weighs each robot's pixels at its own camera's
/// noise (until stop 96 it refused such fleets): two robots on one walk, the
/// second with a 3 px camera, both stay accurate and neither is overconfident.
#[test]
fn the_centralized_filter_weighs_each_robot_at_its_own_pixel_noise() {
    let dir = tempfile::tempdir().expect("tempdir");
    write_walk_from(&dir.path().join("a.txt"), 0.0);
    write_walk_from(&dir.path().join("b.txt"), std::f64::consts::PI);
    let path = dir.path().join("noise.yaml");
    let yaml = "name: noise\nrobots:\n  - trajectory: a.txt\n  - trajectory: b.txt\n    \
                camera:\n      pixel_noise_px: 3.0\n";
    std::fs::write(&path, yaml).expect("write scenario");
    let sc = Scenario::load(&path).expect("load scenario");
    let fleet = Fleet::build(&sc, 1).expect("build fleet");
    let runs = run_central(&fleet, Variant::CeCmsckfCslam).expect("a mixed-noise fleet runs");
    assert_eq!(runs.len(), 2);
    for (r, run) in runs.iter().enumerate() {
        let m = run.metrics();
        println!("robot {r}: {m:?}");
        let (ate, nees) = (
            m.ate_pos_m.unwrap_or(f64::NAN),
            m.nees_pos.unwrap_or(f64::NAN),
        );
        assert!(ate < 0.3, "robot {r}: ATE {ate} m");
        assert!(nees < 6.0, "robot {r}: position NEES {nees}");
    }
}
