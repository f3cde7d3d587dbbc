//! `sim-fleet montecarlo` as a user runs it, on a short synthetic loop.

use integration_tests::{bin, read_json, write_loop_trajectory};
use serde_json::Value;
use std::path::{Path, PathBuf};
use std::process::Command;

type Result<T> = std::result::Result<T, Box<dyn std::error::Error>>;

/// Writes the one-robot loop scenario into `dir` and returns its path.
fn loop_scenario(dir: &Path) -> Result<PathBuf> {
    write_loop_trajectory(&dir.join("loop.txt"), 30.0)?;
    let scenario = dir.join("scenario.yaml");
    std::fs::write(
        &scenario,
        "name: loop\nrobots:\n  - trajectory: loop.txt\nestimator:\n  max_slam_features: 10\n",
    )?;
    Ok(scenario)
}

/// Runs the study with `jobs` workers into `out`; returns `out/summary.json`.
fn montecarlo(scenario: &Path, jobs: &str, out: &Path) -> Result<Value> {
    let output = Command::new(bin("sim-fleet"))
        .arg("montecarlo")
        .arg(scenario)
        .args([
            "--runs",
            "2",
            "--variants",
            "indp,indp-slam",
            "--jobs",
            jobs,
            "--baseline",
            "indp",
            "--out",
        ])
        .arg(out)
        .output()?;
    assert!(
        output.status.success(),
        "montecarlo failed: {}",
        String::from_utf8_lossy(&output.stderr)
    );
    let stdout = String::from_utf8_lossy(&output.stdout);
    assert!(
        stdout.contains("| indp-slam | mean |"),
        "the table is printed: {stdout}"
    );
    let ratios = stdout
        .split_once("Ratio of each variant's mean to `indp`'s")
        .map(|(_, r)| r)
        .unwrap_or_default();
    assert!(
        ratios.contains("| indp-slam | ") && !ratios.contains("| indp | "),
        "the ratios to the baseline follow the table: {stdout}"
    );
    Ok(serde_json::from_str(&std::fs::read_to_string(
        out.join("summary.json"),
    )?)?)
}

/// The `mean` of every variant without the timing, latency and CPU-time keys
/// (which depend on the load).
fn means_without_timing(summary: &Value) -> Vec<(String, Value)> {
    let Some(variants) = summary["variants"].as_object() else {
        return Vec::new();
    };
    variants
        .iter()
        .map(|(name, v)| {
            let mut mean = v["mean"].as_object().cloned().unwrap_or_default();
            mean.retain(|k, _| {
                !k.starts_with("ms_per_frame") && !k.starts_with("latency") && k != "cpu_s"
            });
            (name.clone(), Value::Object(mean))
        })
        .collect()
}

#[test]
fn montecarlo_writes_every_run_an_aggregated_summary_and_a_table_independent_of_the_job_count() {
    let dir = tempfile::tempdir().unwrap();
    let scenario = loop_scenario(dir.path()).unwrap();
    let out1 = dir.path().join("mc1");
    let one = montecarlo(&scenario, "1", &out1).unwrap();

    assert_eq!(one["scenario"], "loop");
    assert_eq!(one["runs"], 2);
    assert_eq!(one["seeds"], serde_json::json!([1, 2]));
    let indp = &one["variants"]["indp"];
    let ate = indp["mean"]["ate_pos_m"].as_f64().expect("a number");
    assert!(ate < 1.0, "indp mean ATE {ate} m");
    assert!(indp["mean_spread"]["ate_pos_m"]["max"].as_f64().unwrap() >= ate);
    assert_eq!(indp["diverged"], 0);
    let slam_robot = &one["variants"]["indp-slam"]["robots"][0];
    assert!(slam_robot.is_object(), "indp-slam robots[0] missing: {one}");
    assert_eq!(slam_robot["id"], 0);
    assert_eq!(slam_robot["trajectory"], "loop");
    assert_eq!(slam_robot["runs"], 2);
    assert!(slam_robot["metrics"]["ate_ori_deg"].is_number());
    assert!(slam_robot["spread"]["nees_pos"]["min"].is_number());
    assert!(out1.join("table.md").is_file());
    // --baseline indp: the comparison of every other variant, as JSON too.
    let baseline = read_json(&out1.join("baseline.json"));
    assert_eq!(baseline["baseline"], "indp");
    let slam = &baseline["variants"][0];
    assert_eq!(slam[0], "indp-slam");
    assert_eq!(slam[1]["seeds"], serde_json::json!([1, 2]));
    assert!(
        slam[1]["rows"][1]["stats"]["ratio"].is_number(),
        "{baseline}"
    );
    // Per-seed values (for paired comparisons) and the 95 % intervals of the means.
    assert_eq!(indp["run_means"].as_array().map(Vec::len), Some(2));
    assert_eq!(slam_robot["per_run"].as_array().map(Vec::len), Some(2));
    assert!(indp["mean_ci95"]["ate_pos_m"]
        .as_f64()
        .is_some_and(|h| h >= 0.0));
    assert!(slam_robot["ci95"]["ate_ori_deg"].is_number());
    // The position-and-yaw aligned ATE, never above the unaligned one in
    // position (the alignment minimizes it), and each run's CPU time.
    let aligned = indp["mean"]["ate_posyaw_pos_m"]
        .as_f64()
        .expect("aligned ATE");
    assert!(aligned <= ate + 1e-12, "aligned {aligned} > plain {ate}");
    assert!(slam_robot["metrics"]["ate_posyaw_ori_deg"].is_number());
    assert!(indp["mean_ci95"]["ate_posyaw_pos_m"].is_number());
    for v in ["indp", "indp-slam"] {
        let cpu = one["variants"][v]["mean"]["cpu_s"].as_f64().unwrap_or(-1.0);
        assert!(cpu > 0.0 && cpu < 600.0, "{v}: cpu_s {cpu}");
    }

    // `paired` compares the two variants of the study seed by seed.
    let side = |v: &str| format!("{v}={}", out1.display());
    let output = Command::new(bin("sim-fleet"))
        .args(["paired", "--a", &side("indp"), "--b", &side("indp-slam")])
        .output()
        .unwrap();
    let table = String::from_utf8_lossy(&output.stdout);
    assert!(output.status.success(), "paired failed: {output:?}");
    assert!(
        table.contains("| mean | ATE pos m | 2 |") && table.contains("| 0 loop | NEES ori | 2 |"),
        "{table}"
    );
    let output = Command::new(bin("sim-fleet"))
        .args([
            "paired",
            "--a",
            &side("indp"),
            "--b",
            &side("dc-full-history"),
        ])
        .output()
        .unwrap();
    assert!(!output.status.success());
    let err = String::from_utf8_lossy(&output.stderr);
    assert!(err.contains("no variant `dc-full-history`"), "{err}");

    for variant in ["indp", "indp-slam"] {
        for seed in ["seed1", "seed2"] {
            let run = out1.join("runs").join(variant).join(seed);
            for file in [
                "estimate.txt",
                "groundtruth.txt",
                "covariance.txt",
                "imu_state.txt",
            ] {
                assert!(
                    run.join("robot0").join(file).is_file(),
                    "{variant}/{seed}/{file}"
                );
            }
            let summary = read_json(&run.join("summary.json"));
            assert_eq!(summary["variant"], variant);
            assert!(summary["transport"].is_null());
            assert!(summary["robots"][0]["ate_pos_m"].is_number());
        }
    }

    // The NEES averaged over the runs at each camera frame against the band
    // of a consistent filter, per robot: in the summary, as CSV, and from
    // `sim-fleet anees` on any runs.
    let band = &slam_robot["anees"];
    assert_eq!(band["runs"], 2, "{band}");
    for kind in [
        "ori",
        "pos",
        "tilt",
        "yaw",
        "vel",
        "bias_gyro",
        "bias_accel",
    ] {
        let share = &band[kind];
        assert!(share["epochs"].as_u64().is_some_and(|n| n > 10), "{band}");
        let total: f64 = ["inside", "below", "above"]
            .iter()
            .map(|k| share[k].as_f64().unwrap_or(f64::NAN))
            .sum();
        assert!((total - 1.0).abs() < 1e-9, "{kind}: {share}");
    }
    assert!(out1.join("anees/indp-slam/robot0.svg").is_file());
    let csv = std::fs::read_to_string(out1.join("anees/indp-slam/robot0.csv")).unwrap();
    assert!(
        csv.starts_with("t_s,ori,ori_runs,ori_low,ori_high,"),
        "{csv}"
    );
    let runs = out1.join("runs/indp-slam");
    let plot = dir.path().join("anees.svg");
    let output = Command::new(bin("sim-fleet"))
        .arg("anees")
        .args([runs.join("seed1/robot0"), runs.join("seed2/robot0")])
        .arg("--plot")
        .arg(&plot)
        .arg("--json")
        .output()
        .unwrap();
    assert!(output.status.success(), "anees failed: {output:?}");
    let again: Value = serde_json::from_slice(&output.stdout).unwrap();
    assert_eq!(&again, band, "the subcommand and the study agree");
    assert!(plot.is_file());
    let output = Command::new(bin("sim-fleet"))
        .args(["anees", &out1.join("no-such-run").display().to_string()])
        .output()
        .unwrap();
    assert!(!output.status.success());
    let err = String::from_utf8_lossy(&output.stderr);
    assert!(err.contains("no-such-run"), "{err}");

    let two = montecarlo(&scenario, "2", &dir.path().join("mc2")).unwrap();
    assert_eq!(means_without_timing(&one).len(), 2);
    assert_eq!(means_without_timing(&one), means_without_timing(&two));
}

#[test]
fn montecarlo_rejects_an_unknown_variant_before_running_anything() {
    let dir = tempfile::tempdir().unwrap();
    let scenario = loop_scenario(dir.path()).unwrap();
    let out = dir.path().join("mc");
    let output = Command::new(bin("sim-fleet"))
        .args([
            "montecarlo",
            scenario.to_str().unwrap(),
            "--runs",
            "1",
            "--variants",
            "indp,collaborative",
            "--out",
            out.to_str().unwrap(),
        ])
        .output()
        .unwrap();
    assert!(!output.status.success());
    let stderr = String::from_utf8_lossy(&output.stderr);
    assert!(
        stderr.contains("unknown variant `collaborative`"),
        "{stderr}"
    );
    assert!(!out.join("summary.json").exists());

    // A baseline the study does not run is an error before anything runs too.
    let output = Command::new(bin("sim-fleet"))
        .args(["montecarlo", scenario.to_str().unwrap(), "--runs", "1"])
        .args(["--variants", "indp", "--baseline", "indp-slam", "--out"])
        .arg(&out)
        .output()
        .unwrap();
    assert!(!output.status.success());
    let stderr = String::from_utf8_lossy(&output.stderr);
    assert!(
        stderr.contains("the baseline indp-slam is not one of the study's variants"),
        "{stderr}"
    );
    assert!(!out.join("summary.json").exists());
}

/// A cooperative study: each seed's fleet runs as in-process agents in lockstep
/// (and the centralized variant in one estimator), every robot's files are
/// written, and the aggregated accuracy does not depend on the job count.
#[test]
fn cooperative_variants_run_whole_fleets_and_aggregate_per_robot() {
    let dir = tempfile::tempdir().unwrap();
    write_loop_trajectory(&dir.path().join("loop.txt"), 24.0).unwrap();
    let scenario = dir.path().join("two.yaml");
    std::fs::write(
        &scenario,
        "name: two\nrobots:\n  - trajectory: loop.txt\n  - trajectory: loop.txt\n    start_time_s: 3.0\nestimator:\n  max_slam_features: 5\n",
    )
    .unwrap();
    let study = |jobs: &str, out: &Path| -> Value {
        let output = Command::new(bin("sim-fleet"))
            .arg("montecarlo")
            .arg(&scenario)
            .args([
                "--runs",
                "2",
                "--variants",
                "dc-full-history,ce-cmsckf-cslam",
                "--jobs",
                jobs,
                "--out",
            ])
            .arg(out)
            .output()
            .unwrap();
        assert!(
            output.status.success(),
            "montecarlo failed: {}",
            String::from_utf8_lossy(&output.stderr)
        );
        read_json(&out.join("summary.json"))
    };
    let one = study("1", &dir.path().join("one"));
    let two = study("2", &dir.path().join("two"));
    for v in ["dc-full-history", "ce-cmsckf-cslam"] {
        assert_eq!(one["variants"][v]["runs"], 2, "{v}: 2 seeds");
        for robot in [0, 1] {
            assert_eq!(
                one["variants"][v]["robots"][robot]["runs"], 2,
                "{v} robot {robot}"
            );
        }
        assert_eq!(one["variants"][v]["failed"], 0, "{v}");
        for seed in [1, 2] {
            for robot in [0, 1] {
                let f = dir
                    .path()
                    .join(format!("one/runs/{v}/seed{seed}/robot{robot}/estimate.txt"));
                assert!(f.is_file(), "{}", f.display());
            }
        }
    }
    for v in ["dc-full-history", "ce-cmsckf-cslam"] {
        let cpu = one["variants"][v]["mean"]["cpu_s"].as_f64().unwrap_or(-1.0);
        assert!(cpu > 0.0 && cpu < 600.0, "{v}: cpu_s {cpu}");
    }
    assert!(
        one["variants"]["dc-full-history"]["mean"]["common_feature_updates"]
            .as_f64()
            .unwrap()
            > 0.0
    );
    // On a loss-free link every agent ends with its peer's whole history; the
    // traffic table says so, and is left out for the centralized estimator.
    let dc = &one["variants"]["dc-full-history"];
    assert_eq!(dc["histories_complete"], 4, "2 seeds x 2 agents");
    assert!(one["variants"]["ce-cmsckf-cslam"]["histories_complete"].is_null());
    let published = dc["mean"]["peer_windows_published"].as_u64().unwrap_or(0);
    assert!(published > 5, "{}", dc["mean"]);
    assert_eq!(dc["mean"]["peer_windows_whole"].as_u64(), Some(published));
    let table = std::fs::read_to_string(dir.path().join("one/table.md")).unwrap();
    // The traffic section's rows: up to the blank line that ends them.
    let traffic: Vec<&str> = table
        .lines()
        .skip_while(|l| !l.starts_with("Traffic"))
        .skip(2)
        .take_while(|l| l.starts_with("| "))
        .collect();
    assert_eq!(traffic.len(), 3, "{table}");
    assert!(traffic[2].starts_with("| dc-full-history |"), "{table}");
    assert!(traffic[2].contains("| 4 of 4 |"), "{table}");
    assert_eq!(means_without_timing(&one), means_without_timing(&two));
}

/// `--history-mib-per-peer` and `--history-retention` reach every agent of a
/// cooperative study: with a bound of a few windows each agent drops most of its
/// peer's keyframe windows and keeps within the bound; without, it drops none.
#[test]
fn a_history_bound_given_to_a_study_bounds_every_agents_history() -> Result<()> {
    let dir = tempfile::tempdir()?;
    write_loop_trajectory(&dir.path().join("loop.txt"), 24.0)?;
    let scenario = dir.path().join("two.yaml");
    std::fs::write(
        &scenario,
        "name: two\nrobots:\n  - trajectory: loop.txt\n  - trajectory: loop.txt\n    start_time_s: 3.0\nestimator:\n  max_slam_features: 5\n",
    )?;
    let bound_mib = 0.15;
    let histories = |name: &str, extra: &[&str]| -> Result<Vec<Value>> {
        let out = dir.path().join(name);
        let output = Command::new(bin("sim-fleet"))
            .arg("montecarlo")
            .arg(&scenario)
            .args(["--runs", "1", "--variants", "dc-full-history"])
            .args(extra)
            .arg("--out")
            .arg(&out)
            .output()?;
        assert!(
            output.status.success(),
            "montecarlo failed: {}",
            String::from_utf8_lossy(&output.stderr)
        );
        (0..2)
            .map(|r| {
                let stats = read_json(&out.join(format!(
                    "runs/dc-full-history/seed1/robot{r}/transport_stats.json"
                )));
                Ok(stats["histories"][(1 - r).to_string()].clone())
            })
            .collect()
    };
    let free = histories("free", &[])?;
    for h in &free {
        assert!(h["stored"].as_u64().unwrap_or(0) > 5, "{h}");
        assert_eq!(h["dropped"], 0, "{h}");
    }
    let growth = |h: &Value| h["bytes_per_peer_hour"].as_f64().unwrap_or(f64::NAN);
    let bound = bound_mib.to_string();
    for retention in ["oldest", "informed"] {
        let args = [
            "--history-mib-per-peer",
            bound.as_str(),
            "--history-retention",
            retention,
        ];
        for (h, f) in histories(retention, &args)?.iter().zip(&free) {
            let (kept, dropped) = (h["keyframes"].as_u64(), h["dropped"].as_u64());
            assert!(
                kept.is_some_and(|k| k > 0) && dropped.is_some_and(|d| d > kept.unwrap_or(0)),
                "{retention}: {h}"
            );
            // History windows within the bound; the recent frames and recent
            // descriptors get 128 KiB each on top (the newest snapshot a little).
            let bytes = h["bytes"].as_f64().unwrap_or(f64::INFINITY);
            let limit = (bound_mib * 1024.0 + 2.0 * 128.0 + 32.0) * 1024.0;
            assert!(bytes <= limit, "{retention}: {h}");
            // The reported growth is the peer's, not what the bound left of it.
            let ratio = growth(h) / growth(f);
            assert!(
                (0.95..1.05).contains(&ratio),
                "{retention}: {h} against {f}"
            );
        }
    }
    // A bound no agent would accept is refused, not run.
    let output = Command::new(bin("sim-fleet"))
        .arg("montecarlo")
        .arg(&scenario)
        .args(["--runs", "1", "--variants", "dc-full-history"])
        .arg("--history-mib-per-peer=-1")
        .arg("--out")
        .arg(dir.path().join("negative"))
        .output()?;
    let err = String::from_utf8_lossy(&output.stderr);
    assert!(
        !output.status.success() && err.contains("history.max_mib_per_peer"),
        "{err}"
    );
    Ok(())
}

/// A scenario that renders images: each run goes through the image frontend
/// (with the settings `--frontend` gives), writes its tracks' error against
/// the rendered truth, and the study reports it. A build without the image
/// frontend refuses the study by name before anything runs, and so does any
/// build for what cannot run on images.
#[test]
fn a_rendered_study_runs_its_images_through_the_frontend() -> Result<()> {
    let dir = tempfile::tempdir()?;
    write_loop_trajectory(&dir.path().join("loop.txt"), 14.0)?;
    let scenario = dir.path().join("rendered.yaml");
    std::fs::write(
        &scenario,
        "name: rendered\nrobots:\n  - trajectory: loop.txt\nrender:\n  enabled: true\n",
    )?;
    let frontend = dir.path().join("frontend.yaml");
    std::fs::write(&frontend, "num_features: 120\n")?;
    let study = |extra: &[&str], out: &Path| -> Result<std::process::Output> {
        Ok(Command::new(bin("sim-fleet"))
            .arg("montecarlo")
            .arg(&scenario)
            .args(["--runs", "2", "--jobs", "2"])
            .args(extra)
            .arg("--out")
            .arg(out)
            .output()?)
    };

    let out = dir.path().join("mc");
    let fe = frontend.to_str().ok_or("path")?;
    let output = study(&["--variants", "indp-slam", "--frontend", fe], &out)?;
    let stderr = String::from_utf8_lossy(&output.stderr);
    if stderr.contains("this build has no image frontend") {
        assert!(!output.status.success());
        assert!(stderr.contains("--features agent/vision"), "{stderr}");
        assert!(!out.join("summary.json").exists());
    } else {
        assert!(output.status.success(), "{stderr}");
        let stdout = String::from_utf8_lossy(&output.stdout);
        assert!(stdout.contains("against the rendered truth"), "{stdout}");
        for seed in [1, 2] {
            let csv = out.join(format!("runs/indp-slam/seed{seed}/robot0/track_errors.csv"));
            let text = std::fs::read_to_string(&csv)?;
            assert!(text.starts_with("t_s,observations,mean_px"), "{text}");
            assert!(text.lines().count() > 50, "a row per image: {text}");
        }
        let summary = read_json(&out.join("summary.json"));
        let v = &summary["variants"]["indp-slam"];
        assert_eq!(v["diverged"], 0, "{v}");
        let px = v["mean"]["track_error_px"]
            .as_f64()
            .ok_or("track_error_px")?;
        assert!(px > 0.0 && px < 1.0, "tracks within a pixel: {px}");
        let deg = v["mean"]["ate_ori_deg"].as_f64().ok_or("ate_ori_deg")?;
        assert!(deg < 2.0, "{deg}");
    }

    // Refused before anything runs, whatever the build.
    let refused = |extra: &[&str], what: &str| -> Result<()> {
        let out = dir.path().join("refused");
        let output = study(extra, &out)?;
        let stderr = String::from_utf8_lossy(&output.stderr);
        assert!(
            !output.status.success() && stderr.contains(what),
            "{stderr}"
        );
        assert!(!out.join("summary.json").exists());
        Ok(())
    };
    refused(
        &["--variants", "ce-cmsckf"],
        "ce-cmsckf has no image frontend",
    )?;
    std::fs::write(&frontend, "num_feature: 120\n")?;
    refused(&["--variants", "indp", "--frontend", fe], "num_feature")?;
    let plain = loop_scenario(dir.path())?;
    let output = Command::new(bin("sim-fleet"))
        .arg("montecarlo")
        .arg(&plain)
        .args([
            "--runs",
            "1",
            "--variants",
            "indp",
            "--frontend",
            fe,
            "--out",
        ])
        .arg(dir.path().join("plain"))
        .output()?;
    let stderr = String::from_utf8_lossy(&output.stderr);
    assert!(
        !output.status.success() && stderr.contains("needs a scenario that renders images"),
        "{stderr}"
    );
    Ok(())
}
