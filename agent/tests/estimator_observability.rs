//! The estimator must not learn what no measurement observes: global position
//! and yaw (thesis Section 2.2.2). Along those four directions `N` of the whole
//! state (evaluated at the first estimates), the information `Nᵀ P⁻¹ N` can only
//! fall (process noise, marginalization) and never grow through an update; a
//! filter that gains it is inconsistent in exactly the way FEJ exists to prevent.

// Helpers outside `#[test]` functions: a failed setup is a failed test.
#![allow(clippy::expect_used)]

mod sim_drive;

use agent::estimator::state::{State, Var};
use agent::runner::{options_for, Variant};
use nalgebra::{DMatrix, Matrix3, Matrix4, UnitQuaternion, Vector3};
use sim_drive::drive_robot0;
use simulator::{Fleet, Scenario};
use std::path::Path;

/// A figure-eight at 1 m/s, 1.5 m up, with some roll and pitch (TUM, 20 Hz).
fn write_eight(path: &Path) {
    let mut text = String::from("# timestamp tx ty tz qx qy qz qw\n");
    for k in 0..=(30 * 20) {
        let s = k as f64 / 20.0;
        let a = 0.25 * s;
        let (x, y, z) = (
            4.0 * a.sin(),
            2.0 * (2.0 * a).sin(),
            1.5 + 0.2 * (0.5 * s).sin(),
        );
        let q = UnitQuaternion::from_euler_angles(
            0.1 * (0.8 * s).sin(),
            0.08 * (0.6 * s).cos(),
            0.3 * a,
        );
        text.push_str(&format!(
            "{:.6} {x:.6} {y:.6} {z:.6} {:.9} {:.9} {:.9} {:.9}\n",
            50.0 + s,
            q.i,
            q.j,
            q.k,
            q.w
        ));
    }
    std::fs::write(path, text).expect("write trajectory");
}

/// The unobservable directions at the first estimates: global yaw (column 0)
/// and global position (columns 1-3), one row per error-state entry.
fn unobservable(state: &State) -> DMatrix<f64> {
    let m = &state.means;
    let n = state.cov().nrows();
    let mut out = DMatrix::zeros(n, 4);
    let ez = Vector3::z();
    if let Some(o) = state.offset(Var::Imu) {
        set_pose(&mut out, o, Some(&m.imu_fej.rot), &m.imu_fej.pos);
        out.view_mut((o + 6, 0), (3, 1))
            .copy_from(&ez.cross(&m.imu_fej.vel));
    }
    for (k, c) in &m.clones {
        if let Some(o) = state.offset(Var::Clone(*k)) {
            set_pose(&mut out, o, Some(&c.rot_fej), &c.pos_fej);
        }
    }
    for (id, f) in &m.features {
        if let Some(o) = state.offset(Var::Feature(*id)) {
            set_pose(&mut out, o, None, &f.pos_fej);
        }
    }
    out
}

/// The rows of a pose (orientation, when given, then position) or a point at
/// offset `o`: yaw turns the orientation about the vertical and moves the
/// position about the origin; a global shift moves the position.
fn set_pose(out: &mut DMatrix<f64>, o: usize, rot: Option<&Matrix3<f64>>, pos: &Vector3<f64>) {
    let ez = Vector3::z();
    if let Some(r) = rot {
        out.view_mut((o, 0), (3, 1))
            .copy_from(&(r.transpose() * ez));
    }
    let p = if rot.is_some() { o + 3 } else { o };
    out.view_mut((p, 0), (3, 1)).copy_from(&ez.cross(pos));
    out.view_mut((p, 1), (3, 3)).fill_with_identity();
}

/// `Nᵀ P⁺ N`, with the pseudo-inverse: right after cloning, the clone and the
/// IMU pose are one variable twice, and `N` does not see that null direction.
fn information(state: &State) -> Matrix4<f64> {
    let n = unobservable(state);
    let eig = state.cov().clone().symmetric_eigen();
    let top = eig.eigenvalues.max();
    let inv = eig
        .eigenvalues
        .map(|l| if l > 1e-12 * top { 1.0 / l } else { 0.0 });
    let vt_n = eig.eigenvectors.transpose() * &n;
    let mut scaled = vt_n.clone();
    for (r, w) in inv.iter().enumerate() {
        scaled.row_mut(r).scale_mut(*w);
    }
    let i = vt_n.transpose() * scaled;
    Matrix4::from_fn(|r, c| i[(r, c)])
}

/// Runs 150 frames of the figure-eight (calibration perturbed and estimated
/// online, SLAM features from 1 s) and returns the largest growth of the
/// information along `N` over one frame, relative to the information before.
fn largest_growth(use_fej: bool) -> f64 {
    let dir = tempfile::tempdir().expect("tempdir");
    write_eight(&dir.path().join("eight.txt"));
    let path = dir.path().join("eight.yaml");
    std::fs::write(
        &path,
        format!("name: eight\nrobots:\n  - trajectory: eight.txt\nestimator: {{max_slam_features: 20, slam_delay_s: 1.0, use_fej: {use_fej}}}\n"),
    )
    .expect("write scenario");
    let sc = Scenario::load(&path).expect("scenario");
    let fleet = Fleet::build(&sc, 1).expect("fleet");
    let opts = options_for(&sc.estimator, &fleet, 0, Variant::IndpSlam);
    let mut prev: Option<Matrix4<f64>> = None;
    let mut frames = 0;
    let mut worst = f64::NEG_INFINITY;
    drive_robot0(&fleet, opts, |est, _| {
        let state = est.state().expect("initialized");
        let info = information(state);
        if let Some(p) = prev {
            // Growth relative to what was known: information along the
            // unobservable directions may only fall.
            let grew = (info - p).symmetric_eigenvalues().max();
            let scale = p.symmetric_eigenvalues().max().max(1e-12);
            let rel = grew / scale;
            if rel > 1e-3 {
                println!(
                    "frame {frames}: yaw information {:.4e} -> {:.4e}, relative growth {rel:.2e}",
                    p[(0, 0)],
                    info[(0, 0)]
                );
            }
            worst = worst.max(rel);
        }
        prev = Some(info);
        frames += 1;
        frames <= 150
    });
    println!(
        "FEJ {use_fej}: {frames} frames, largest relative growth of the information along N: {worst:.2e}"
    );
    assert!(frames > 100, "only {frames} frames");
    worst
}

#[test]
fn no_update_adds_information_on_global_yaw_or_position() {
    let worst = largest_growth(true);
    assert!(
        worst < 1e-6,
        "an update added information along N: {worst:.3e}"
    );
}

#[test]
fn without_fej_the_filter_learns_what_nothing_observes() {
    // The test above can fail: without first estimates the Jacobians' nullspace
    // drifts from N and the updates gain information along it.
    let worst = largest_growth(false);
    assert!(worst > 0.1, "largest growth without FEJ: {worst:.3e}");
}
