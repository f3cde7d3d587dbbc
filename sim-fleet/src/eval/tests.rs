use super::*;
use clap::Parser;
use common::so3::exp_so3;
use common::trajectory::{write_covariances, write_tum};
use nalgebra::Matrix3;

/// A 20 Hz circle of radius 10 m with a gentle climb, heading along the path.
fn circle(n: usize) -> Vec<StampedPose> {
    (0..n)
        .map(|i| {
            let t = 1000.0 + 0.05 * i as f64;
            let a = 0.1 * (t - 1000.0);
            StampedPose {
                t,
                rot: exp_so3(&Vector3::new(0.0, 0.0, a + std::f64::consts::FRAC_PI_2)),
                pos: Vector3::new(10.0 * a.cos(), 10.0 * a.sin(), 0.02 * (t - 1000.0)),
            }
        })
        .collect()
}

fn offset(traj: &[StampedPose], d: Vector3<f64>) -> Vec<StampedPose> {
    traj.iter()
        .map(|p| StampedPose {
            pos: p.pos + d,
            ..*p
        })
        .collect()
}

fn covariances(traj: &[StampedPose], sigma_pos: f64) -> Vec<StampedCovariance> {
    traj.iter()
        .map(|p| StampedCovariance {
            t: p.t,
            ori: Matrix3::identity() * 1e-4,
            pos: Matrix3::identity() * sigma_pos * sigma_pos,
        })
        .collect()
}

#[test]
fn a_known_offset_gives_the_known_ate_nees_and_all_four_plots() {
    let gt = circle(1300);
    let est = offset(&gt, Vector3::new(0.1, 0.0, 0.0));
    let covs = covariances(&est, 0.1);
    let report = evaluate(
        &gt,
        &est,
        Some(&covs),
        Alignment::None,
        &DEFAULT_RPE_SEGMENTS_M,
    );
    assert_eq!(report.pairs, 1300);
    assert!((report.ate_pos_m.unwrap() - 0.1).abs() < 1e-9, "{report:?}");
    assert!(report.ate_ori_deg.unwrap() < 1e-9);
    // δp = −0.1 x with σ = 0.1: NEES 1 at every pose; no orientation error.
    assert!((report.nees_pos.unwrap() - 1.0).abs() < 1e-9);
    assert!(report.nees_ori.unwrap() < 1e-12);
    assert_eq!((report.nees_unmatched, report.nees_singular), (0, 0));
    assert!((report.per_pose[0].pos_err[0] + 0.1).abs() < 1e-12);
    assert!((report.per_pose[0].pos_sigma.unwrap()[1] - 0.1).abs() < 1e-12);
    // The path is 65 m long: 8..48 m segments fit, and a constant offset has no RPE.
    assert_eq!(report.rpe.len(), 6);
    for r in &report.rpe {
        assert!(r.count > 0, "{r:?}");
        assert!(r.pos_m_mean.unwrap() < 1e-9);
    }
    let se3 = evaluate(&gt, &est, None, Alignment::Se3, &[8.0]);
    assert!(se3.ate_pos_m.unwrap() < 1e-9);
    assert_eq!((se3.nees_ori, se3.nees_pos), (None, None));
    assert!((se3.align_trans[0] + 0.1).abs() < 1e-9);

    let dir = tempfile::tempdir().unwrap();
    let files = crate::plots::write_plots(&report, &dir.path().join("plots")).unwrap();
    let names: Vec<String> = files
        .iter()
        .map(|f| f.file_name().unwrap().to_string_lossy().into_owned())
        .collect();
    assert_eq!(
        names,
        [
            "trajectory_xy.svg",
            "error_pos.svg",
            "error_ori.svg",
            "nees.svg"
        ]
    );
    for f in &files {
        let text = std::fs::read_to_string(f).unwrap();
        assert!(
            text.contains("<svg") && text.contains("<polyline"),
            "{}",
            f.display()
        );
    }
    let without_cov = crate::plots::write_plots(&se3, dir.path()).unwrap();
    assert_eq!(without_cov.len(), 3);
}

#[test]
fn the_json_output_has_the_metric_keys_with_null_nees_without_covariances() {
    let gt = circle(200);
    let report = evaluate(&gt, &gt, None, Alignment::PosYaw, &[1.0, 500.0]);
    let value: serde_json::Value = serde_json::from_str(&report.to_json().unwrap()).unwrap();
    for key in ["ate_ori_deg", "ate_pos_m", "nees_ori", "nees_pos", "rpe"] {
        assert!(value.get(key).is_some(), "missing {key}");
    }
    assert!(value["nees_ori"].is_null() && value["nees_pos"].is_null());
    assert_eq!(value["rpe"].as_array().unwrap().len(), 2);
    assert!(value["rpe"][1]["pos_m_mean"].is_null());
    assert_eq!(value["align"], "posyaw");
    let table = report.table();
    assert!(table.contains("ATE") && table.contains("RPE") && !table.contains("NEES"));
    let metrics = report.metric_set();
    assert_eq!(metrics.ate_pos_m, report.ate_pos_m);
    assert_eq!(metrics.rpe.unwrap().len(), 2);
}

#[derive(Parser)]
struct Cli {
    #[command(flatten)]
    eval: EvalArgs,
}

#[test]
fn the_command_line_defaults_to_no_alignment_and_the_thesis_segments() {
    let cli = Cli::try_parse_from(["eval", "--gt", "gt.txt", "--est", "dir/run.txt"]).unwrap();
    assert_eq!(cli.eval.align, Alignment::None);
    assert_eq!(cli.eval.segments, DEFAULT_RPE_SEGMENTS_M.to_vec());
    assert!(!cli.eval.json && !cli.eval.no_plots && cli.eval.cov.is_none());
    assert_eq!(
        default_plots_dir(&cli.eval.est),
        PathBuf::from("dir/run_plots")
    );
    let cli = Cli::try_parse_from([
        "eval",
        "--gt",
        "g",
        "--est",
        "e",
        "--align",
        "se3",
        "--segments",
        "1,2.5",
    ])
    .unwrap();
    assert_eq!(cli.eval.align, Alignment::Se3);
    assert_eq!(cli.eval.segments, vec![1.0, 2.5]);
    assert!(Cli::try_parse_from(["eval", "--gt", "g", "--est", "e", "--align", "sim3"]).is_err());
}

#[test]
fn run_eval_reads_files_and_writes_plots_next_to_the_estimate() {
    let dir = tempfile::tempdir().unwrap();
    let gt = circle(400);
    let est = offset(&gt, Vector3::new(0.0, 0.05, 0.0));
    let (gt_path, est_path, cov_path) = (
        dir.path().join("gt.txt"),
        dir.path().join("robot0.txt"),
        dir.path().join("robot0_cov.txt"),
    );
    write_tum(&gt_path, &gt).unwrap();
    write_tum(&est_path, &est).unwrap();
    write_covariances(&cov_path, &covariances(&est, 0.05)).unwrap();
    let cli = Cli::try_parse_from([
        "eval",
        "--gt",
        gt_path.to_str().unwrap(),
        "--est",
        est_path.to_str().unwrap(),
        "--cov",
        cov_path.to_str().unwrap(),
        "--json",
    ])
    .unwrap();
    run_eval(&cli.eval).unwrap();
    for name in [
        "trajectory_xy.svg",
        "error_pos.svg",
        "error_ori.svg",
        "nees.svg",
    ] {
        assert!(
            dir.path().join("robot0_plots").join(name).is_file(),
            "{name}"
        );
    }
}

#[test]
fn run_eval_fails_clearly_when_the_times_do_not_overlap() {
    let dir = tempfile::tempdir().unwrap();
    let gt = circle(50);
    let late: Vec<StampedPose> = gt
        .iter()
        .map(|p| StampedPose { t: p.t + 1e4, ..*p })
        .collect();
    let (gt_path, est_path) = (dir.path().join("gt.txt"), dir.path().join("est.txt"));
    write_tum(&gt_path, &gt).unwrap();
    write_tum(&est_path, &late).unwrap();
    let cli = Cli::try_parse_from([
        "eval",
        "--gt",
        gt_path.to_str().unwrap(),
        "--est",
        est_path.to_str().unwrap(),
        "--no-plots",
    ])
    .unwrap();
    let err = run_eval(&cli.eval).unwrap_err().to_string();
    assert!(err.contains("no estimated pose matches"), "{err}");
    let missing = Cli::try_parse_from(["eval", "--gt", "/nonexistent.txt", "--est", "x"]).unwrap();
    let err = format!("{:#}", run_eval(&missing.eval).unwrap_err());
    assert!(
        err.contains("ground truth") && err.contains("/nonexistent.txt"),
        "{err}"
    );
}
