//! Cost of the cooperative updates (thesis Table 5.4 and Fig. 5.4), in thread
//! CPU time, on the three-robot EuRoC scenario:
//!
//! 1. common VIO features, proposed two-stage vs combined projection, over the
//!    window (`dc-cmsckf`) and with history (`dc-full-history` without common
//!    SLAM features): ms per frame that had a common-VIO update and nothing else
//!    cooperative;
//! 2. common SLAM features, constraint vs measurement update, over the window
//!    (`dc-full-window` vs `dc-cmsckf-cslam`) and with history
//!    (`dc-full-history` with and without the constraint): ms per frame that had
//!    a common-SLAM update and no common VIO feature;
//! 3. per-robot cost of `dc-full-window` (each agent its own state) against
//!    `ce-cmsckf-cslam` (one joint state) for 2, 4, 8 and 16 robots (the
//!    centralized one up to 8): ms per robot frame, the whole frame.
//!
//! `cargo bench -p sim-fleet --bench cooperative_timing [-- SCENARIO] [--seeds N]
//! [--robots 2,4,8,16]` (defaults: `sim-fleet/scenarios/euroc_vicon_room1.yaml`,
//! 2 seeds). Agents run as threads over the in-process transport in lockstep;
//! thread CPU time keeps their costs apart on a busy machine.
use agent::estimator::FrameRecord;
use agent::runner::Variant;
use anyhow::{bail, Context, Result};
use common::estimator_options::CommonProjection;
use sim_fleet::fleet_run::{agent_configs, derive_scenario, run_inproc, RunArgs};
use simulator::{Fleet, Scenario};
use std::path::{Path, PathBuf};
use std::sync::atomic::AtomicBool;
use std::sync::Arc;

/// A fleet configuration to time.
#[derive(Clone, Copy)]
struct Setup {
    variant: Variant,
    projection: CommonProjection,
    common_slam: Option<bool>,
    slam_constraint: Option<bool>,
}

fn args(scenario: &Path, seed: u64, variant: Variant, out: &Path) -> RunArgs {
    RunArgs {
        scenario: scenario.to_path_buf(),
        robots: None,
        transport: "inproc".into(),
        lockstep: true,
        realtime: None,
        seed: Some(seed),
        variant: variant.name().into(),
        out: out.to_path_buf(),
        fleet_id: Some(format!("bench-{}-{seed}", variant.name())),
        zenoh_config: "loopback".into(),
        tls: false,
        quic: false,
        derived_delay_s: 3.0,
        agent_bin: None,
        dry_run: false,
        history_store: None,
        history: Default::default(),
    }
}

/// Every robot's frame outputs of one in-process lockstep fleet run.
fn fleet_frames(scenario: &Path, n: usize, seed: u64, s: Setup) -> Result<Vec<FrameRecord>> {
    let out = std::env::temp_dir().join(format!("coop-bench-{}", std::process::id()));
    let mut configs = agent_configs(&args(scenario, seed, s.variant, &out), scenario, n, &out)?;
    for c in &mut configs {
        c.mcap_log = false;
        c.status_period_s = 0.0;
        c.estimator.projection = Some(s.projection);
        c.estimator.common_slam = s.common_slam.or(c.estimator.common_slam);
        c.estimator.slam_constraint = s.slam_constraint.or(c.estimator.slam_constraint);
    }
    let stop = Arc::new(AtomicBool::new(false));
    let mut frames = Vec::new();
    for r in run_inproc(&configs, &stop, None)? {
        let report = r.map_err(anyhow::Error::msg)?;
        frames.extend(report.run.frames);
    }
    let _ = std::fs::remove_dir_all(&out);
    Ok(frames)
}

fn mean_std(v: &[f64]) -> (f64, f64, usize) {
    let n = v.len().max(1) as f64;
    let m = v.iter().sum::<f64>() / n;
    let var = v.iter().map(|x| (x - m).powi(2)).sum::<f64>() / n;
    (m, var.sqrt(), v.len())
}

fn fmt((m, s, n): (f64, f64, usize)) -> String {
    format!("{m:.2} ± {s:.2} ({n} frames)")
}

/// Cost of the cooperative update on the frames `keep` selects.
fn coop_cost(frames: &[FrameRecord], keep: impl Fn(&FrameRecord) -> bool) -> (f64, f64, usize) {
    let v: Vec<f64> = frames
        .iter()
        .filter(|f| keep(f))
        .map(|f| {
            let c = &f.coop;
            c.common_vio_ms + c.common_slam_ms + c.constraint_ms + c.ci_update_ms
        })
        .collect();
    mean_std(&v)
}

fn vio_only(f: &FrameRecord) -> bool {
    f.coop.common_vio.used > 0 && f.coop.common_slam.used == 0 && f.coop.constraints.used == 0
}

fn slam_only(f: &FrameRecord) -> bool {
    f.coop.common_vio.used == 0 && (f.coop.common_slam.used > 0 || f.coop.constraints.used > 0)
}

fn frames_over_seeds(scenario: &Path, n: usize, seeds: u64, s: Setup) -> Result<Vec<FrameRecord>> {
    let mut all = Vec::new();
    for seed in 1..=seeds {
        all.extend(fleet_frames(scenario, n, seed, s)?);
    }
    Ok(all)
}

fn table_5_4(scenario: &Path, n: usize, seeds: u64) -> Result<()> {
    let setup = |variant, projection, common_slam, slam_constraint| Setup {
        variant,
        projection,
        common_slam,
        slam_constraint,
    };
    use CommonProjection::{Combined, TwoStage};
    println!("\nCommon VIO update, ms per frame (thread CPU): proposed (two-stage) vs combined projection");
    for (label, variant, slam) in [
        ("window ", Variant::DcCmsckf, None),
        ("history", Variant::DcFullHistory, Some(false)),
    ] {
        let two = frames_over_seeds(scenario, n, seeds, setup(variant, TwoStage, slam, slam))?;
        let comb = frames_over_seeds(scenario, n, seeds, setup(variant, Combined, slam, slam))?;
        println!(
            "  {label}: proposed {}   combined {}",
            fmt(coop_cost(&two, vio_only)),
            fmt(coop_cost(&comb, vio_only))
        );
    }
    println!("\nCommon SLAM update, ms per frame (thread CPU): constraint vs measurement update");
    let window_c = frames_over_seeds(
        scenario,
        n,
        seeds,
        setup(Variant::DcFullWindow, TwoStage, None, None),
    )?;
    let window_m = frames_over_seeds(
        scenario,
        n,
        seeds,
        setup(Variant::DcCmsckfCslam, TwoStage, None, None),
    )?;
    println!(
        "  window : constraint {}   measurement {}",
        fmt(coop_cost(&window_c, slam_only)),
        fmt(coop_cost(&window_m, slam_only))
    );
    let hist_c = frames_over_seeds(
        scenario,
        n,
        seeds,
        setup(Variant::DcFullHistory, TwoStage, None, None),
    )?;
    let hist_m = frames_over_seeds(
        scenario,
        n,
        seeds,
        setup(Variant::DcFullHistory, TwoStage, None, Some(false)),
    )?;
    println!(
        "  history: constraint {}   measurement {}",
        fmt(coop_cost(&hist_c, slam_only)),
        fmt(coop_cost(&hist_m, slam_only))
    );
    Ok(())
}

fn scaling(base: &Scenario, robots: &[usize], seed: u64) -> Result<()> {
    println!("\nPer-robot cost, ms per robot frame (thread CPU, whole frame), seed {seed}");
    println!(
        "  robots | dc-full-window | ce-cmsckf-cslam | dc: matching ms, common rows ms, CI update ms, common features, CI participants (per frame)"
    );
    let dir = std::env::temp_dir().join(format!("coop-scaling-{}", std::process::id()));
    std::fs::create_dir_all(&dir)?;
    for &n in robots {
        let sc = derive_scenario(base, n, 3.0);
        let path = dir.join(format!("fleet{n}.yaml"));
        std::fs::write(&path, serde_yaml::to_string(&sc)?)?;
        let dc = fleet_frames(
            &path,
            n,
            seed,
            Setup {
                variant: Variant::DcFullWindow,
                projection: CommonProjection::TwoStage,
                common_slam: None,
                slam_constraint: None,
            },
        )?;
        let dc_ms = mean_std(&dc.iter().map(|f| f.timing.cpu_ms).collect::<Vec<_>>());
        // The joint state of more than 8 robots takes minutes per run; its
        // growth is plain by then.
        let ce: Vec<f64> = if n <= 8 {
            let fleet = Fleet::build(&Scenario::load(&path)?, seed)?;
            let runs = agent::central::run::run_central(&fleet, Variant::CeCmsckfCslam)?;
            runs.iter()
                .flat_map(|r| r.frames.iter().map(|f| f.timing.cpu_ms))
                .collect()
        } else {
            vec![f64::NAN]
        };
        let avg =
            |g: &dyn Fn(&FrameRecord) -> f64| mean_std(&dc.iter().map(g).collect::<Vec<_>>()).0;
        println!(
            "  {n:6} | {:14.2} | {:15.2} | {:.3}, {:.3}, {:.3}, {:.2}, {:.2}",
            dc_ms.0,
            mean_std(&ce).0,
            avg(&|f| f.coop.matching_ms),
            avg(&|f| f.coop.common_vio_ms + f.coop.common_slam_ms + f.coop.constraint_ms),
            avg(&|f| f.coop.ci_update_ms),
            avg(&|f| f.coop.updates() as f64),
            avg(&|f| f.coop.ci_participants as f64),
        );
    }
    let _ = std::fs::remove_dir_all(&dir);
    Ok(())
}

fn main() -> Result<()> {
    let args: Vec<String> = std::env::args().skip(1).collect();
    let mut scenario =
        PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("scenarios/euroc_vicon_room1.yaml");
    let mut seeds = 2u64;
    let mut robots = vec![2, 4, 8, 16];
    let mut it = args.iter().filter(|a| *a != "--bench");
    while let Some(a) = it.next() {
        match a.as_str() {
            "--seeds" => seeds = it.next().context("--seeds N")?.parse()?,
            "--robots" => {
                robots = it
                    .next()
                    .context("--robots 2,4,8,16")?
                    .split(',')
                    .map(str::parse)
                    .collect::<Result<_, _>>()?
            }
            other if other.starts_with('-') => bail!("unknown option {other}"),
            other => scenario = PathBuf::from(other),
        }
    }
    let base = Scenario::load(&scenario)?;
    let n = base.robots.len();
    println!("scenario {} ({n} robots), seeds 1..={seeds}", base.name);
    table_5_4(&scenario, n, seeds)?;
    scaling(&base, &robots, 1)?;
    Ok(())
}
