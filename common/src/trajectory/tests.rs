use std::path::PathBuf;

use nalgebra::{Matrix3, Vector3};

use super::*;
use crate::so3::{exp_so3, log_so3};

fn data(name: &str) -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR"))
        .join("../../shared/data/trajectories")
        .join(name)
}

fn sample_poses() -> Vec<StampedPose> {
    (0..20)
        .map(|i| {
            let s = i as f64;
            StampedPose {
                t: 1_521_753_105.031_429 + 0.05 * s,
                rot: exp_so3(&Vector3::new(0.1 * s, -0.2 + 0.03 * s, 3.0 - 0.3 * s)),
                pos: Vector3::new(s.sin() * 1e3, -1.0 / (1.0 + s), 1e-9 * s),
            }
        })
        .collect()
}

fn write_text(dir: &tempfile::TempDir, name: &str, text: &str) -> PathBuf {
    let path = dir.path().join(name);
    std::fs::write(&path, text).unwrap();
    path
}

fn rot_angle(a: &Matrix3<f64>, b: &Matrix3<f64>) -> f64 {
    log_so3(&(a.transpose() * b)).norm()
}

#[test]
fn a_written_tum_file_reads_back_the_same_poses() {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("traj.txt");
    let poses = sample_poses();
    write_tum(&path, &poses).unwrap();
    let text = std::fs::read_to_string(&path).unwrap();
    assert!(text.starts_with(TUM_HEADER));
    let back = read_tum(&path).unwrap();
    assert_eq!(back.len(), poses.len());
    for (a, b) in poses.iter().zip(&back) {
        assert_eq!(a.t, b.t);
        assert_eq!(a.pos, b.pos);
        assert!(rot_angle(&a.rot, &b.rot) < 1e-14);
    }
}

#[test]
fn a_bad_value_names_the_file_and_the_line() {
    let dir = tempfile::tempdir().unwrap();
    let text = "# header\n\n1.0 0 0 0 0 0 0 1\n2.0 0 abc 0 0 0 0 1\n";
    let path = write_text(&dir, "bad.txt", text);
    let err = read_tum(&path).unwrap_err();
    let msg = err.to_string();
    assert!(msg.contains("bad.txt") && msg.contains("line 4"), "{msg}");
    match err {
        TrajectoryError::Line { line, kind, .. } => {
            assert_eq!(line, 4);
            assert!(
                matches!(kind, LineError::Number { column: 3, .. }),
                "{kind}"
            );
        }
        other => panic!("unexpected error {other}"),
    }
}

#[test]
fn nan_values_zero_quaternions_short_lines_and_time_reversals_are_rejected() {
    let dir = tempfile::tempdir().unwrap();
    let cases = [
        ("1 0 NaN 0 0 0 0 1\n", "not finite"),
        ("1 0 0 inf 0 0 0 1\n", "not finite"),
        ("1 0 0 0 0 0 0 0\n", "quaternion"),
        ("1 0 0 0 0 0 0\n", "at least 8"),
        ("1 0 0 0 0 0 0 1\n1 0 0 0 0 0 0 1\n", "not after"),
        ("2 0 0 0 0 0 0 1\n1 0 0 0 0 0 0 1\n", "not after"),
    ];
    for (text, expected) in cases {
        let path = write_text(&dir, "case.txt", text);
        let err = read_tum(&path).unwrap_err();
        let TrajectoryError::Line { kind, .. } = &err else {
            panic!("unexpected error {err}");
        };
        assert!(kind.to_string().contains(expected), "{text:?}: {kind}");
    }
}

#[test]
fn a_missing_file_is_a_read_error_naming_the_file() {
    let err = read_tum("/nonexistent/traj.txt").unwrap_err();
    assert!(matches!(err, TrajectoryError::Read { .. }));
    assert!(err.to_string().contains("/nonexistent/traj.txt"));
}

#[test]
fn commas_tabs_and_unnormalized_quaternions_are_accepted() {
    let dir = tempfile::tempdir().unwrap();
    let text = "1.0,1,2,3,0,0,0,2\n2.0\t4\t5\t6\t0\t0\t3\t3 extra\n";
    let poses = read_tum(write_text(&dir, "mixed.txt", text)).unwrap();
    assert_eq!(poses.len(), 2);
    assert_eq!(poses[0].pos, Vector3::new(1.0, 2.0, 3.0));
    assert!((poses[0].rot - Matrix3::identity()).norm() < 1e-15);
    let expected = exp_so3(&Vector3::new(0.0, 0.0, std::f64::consts::FRAC_PI_2));
    assert!(rot_angle(&poses[1].rot, &expected) < 1e-12);
}

#[test]
fn euroc_csv_and_tum_text_of_v1_01_easy_give_the_same_poses() {
    let csv = read_trajectory(data("V1_01_easy.csv")).unwrap();
    let txt = read_trajectory(data("V1_01_easy.txt")).unwrap();
    assert_eq!(csv.len(), 2895);
    assert_eq!(csv.len(), txt.len());
    for (a, b) in csv.iter().zip(&txt) {
        // The text file keeps 5 decimals of time and 6 digits of the quaternion.
        assert!((a.t - b.t).abs() < 1e-5, "{} vs {}", a.t, b.t);
        assert!((a.pos - b.pos).norm() < 1e-5);
        assert!(rot_angle(&a.rot, &b.rot) < 1e-5);
    }
    assert!((csv[0].t - 1_403_715_273.262_143).abs() < 1e-6);
}

#[test]
fn udel_gore_with_six_extra_columns_reads() {
    let poses = read_trajectory(data("udel_gore.txt")).unwrap();
    assert!(poses.len() > 3000, "{}", poses.len());
    assert_eq!(poses[0].pos, Vector3::zeros());
    let q0 = crate::so3::xyzw_from_rot(&poses[0].rot);
    assert!((q0[0] - 0.806_813_511_9).abs() < 1e-9);
}

#[test]
fn covariances_round_trip_and_are_symmetric() {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("cov.txt");
    let covs: Vec<StampedCovariance> = (0..5)
        .map(|i| {
            let s = 1.0 + i as f64;
            let a = Matrix3::new(s, 0.1, -0.2, 0.3, 2.0 * s, 0.01, 0.0, 0.5, s / 3.0);
            StampedCovariance {
                t: 100.0 + 0.25 * s,
                ori: a * a.transpose() * 1e-5,
                pos: a.transpose() * a,
            }
        })
        .collect();
    write_covariances(&path, &covs).unwrap();
    let back = read_covariances(&path).unwrap();
    assert_eq!(back, covs);
    let text = std::fs::read_to_string(&path).unwrap();
    assert!(text.starts_with(COVARIANCE_HEADER));
}

#[test]
fn a_short_covariance_line_is_rejected_with_its_line_number() {
    let dir = tempfile::tempdir().unwrap();
    let text = format!("{COVARIANCE_HEADER}\n1 1 0 0 1 0 1 1 0 0 1 0\n");
    let err = read_covariances(write_text(&dir, "cov.txt", &text)).unwrap_err();
    assert!(matches!(
        err,
        TrajectoryError::Line {
            line: 2,
            kind: LineError::TooFewColumns {
                expected: 13,
                found: 12
            },
            ..
        }
    ));
}

#[test]
fn interpolation_is_slerp_and_linear_and_none_outside_the_span() {
    let a = StampedPose {
        t: 10.0,
        rot: Matrix3::identity(),
        pos: Vector3::new(0.0, 0.0, 0.0),
    };
    let b = StampedPose {
        t: 12.0,
        rot: exp_so3(&Vector3::new(0.0, 0.0, 1.0)),
        pos: Vector3::new(2.0, -4.0, 6.0),
    };
    let traj = [a, b];
    let mid = interpolate_pose(&traj, 10.5).unwrap();
    assert_eq!(mid.t, 10.5);
    assert!((mid.pos - Vector3::new(0.5, -1.0, 1.5)).norm() < 1e-15);
    assert!(rot_angle(&mid.rot, &exp_so3(&Vector3::new(0.0, 0.0, 0.25))) < 1e-15);
    assert_eq!(interpolate_pose(&traj, 10.0).unwrap(), a);
    assert_eq!(interpolate_pose(&traj, 12.0).unwrap(), b);
    assert!(interpolate_pose(&traj, 9.999).is_none());
    assert!(interpolate_pose(&traj, 12.001).is_none());
    assert!(interpolate_pose(&traj, f64::NAN).is_none());
    assert!(interpolate_pose(&[], 1.0).is_none());
}

#[test]
fn laps_retrace_the_path_backwards_then_forwards_with_time_running_on() {
    let pose = |t: f64, x: f64| StampedPose {
        t,
        rot: crate::so3::exp_so3(&nalgebra::Vector3::new(0.0, 0.0, x)),
        pos: nalgebra::Vector3::new(x, 2.0 * x, 0.0),
    };
    let traj = vec![pose(10.0, 0.0), pose(10.5, 1.0), pose(12.0, 3.0)];
    assert_eq!(laps(&traj, 1), traj);
    assert_eq!(laps(&traj, 0), traj);
    assert_eq!(laps(&traj[..1], 5), traj[..1].to_vec());
    let three = laps(&traj, 3);
    let times: Vec<f64> = three.iter().map(|p| p.t).collect();
    // Back: 3 -> 1 -> 0 at the forward speeds, then forward again.
    assert_eq!(times, [10.0, 10.5, 12.0, 13.5, 14.0, 14.5, 16.0]);
    let xs: Vec<f64> = three.iter().map(|p| p.pos.x).collect();
    assert_eq!(xs, [0.0, 1.0, 3.0, 1.0, 0.0, 1.0, 3.0]);
    assert_eq!(three[3].rot, traj[1].rot);
    assert!(three.windows(2).all(|w| w[1].t > w[0].t));
}

#[test]
fn an_unfinished_last_line_is_dropped_and_a_finished_bad_one_is_not() {
    let dir = tempfile::tempdir().unwrap();
    // TUM, cut off mid-line: the two whole poses are kept.
    let text = "1 0 0 0 0 0 0 1\n2 0 0 0 0 0 0 1\n3 0 0.5";
    let poses = read_tum(write_text(&dir, "cut.txt", text)).unwrap();
    assert_eq!(poses.len(), 2);
    // EuRoC ground truth cut inside its nanosecond stamp: the stamp would go
    // back in time, and the line is dropped too.
    let text = "#timestamp,x,y,z,qw,qx,qy,qz\n\
                1403715273262142976,0,0,0,1,0,0,0\n\
                1403715273267142912,0,0,0,1,0,0,0\n\
                14037152";
    let poses = read_euroc_csv(write_text(&dir, "gt.csv", text)).unwrap();
    assert_eq!(poses.len(), 2);
    // The same lines with a newline after the bad one were written whole:
    // an error naming the line.
    let text = "1 0 0 0 0 0 0 1\n2 0 0 0 0 0 0 1\n3 0 0.5\n";
    let err = read_tum(write_text(&dir, "bad.txt", text)).unwrap_err();
    assert!(
        matches!(err, TrajectoryError::Line { line: 3, .. }),
        "{err}"
    );
    // A bad line before the last is an error whatever the ending.
    let text = "1 0 0 0 0 0 0 1\n2 0 x 0 0 0 0 1\n3 0 0 0 0 0 0 1";
    let err = read_tum(write_text(&dir, "mid.txt", text)).unwrap_err();
    assert!(
        matches!(err, TrajectoryError::Line { line: 2, .. }),
        "{err}"
    );
}
