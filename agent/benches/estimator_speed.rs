//! Estimator speed: milliseconds per camera frame (propagation + updates +
//! marginalization, one thread) with and without SLAM features, side by side,
//! with the SLAM features kept as anchored inverse depths instead of the
//! scenario's representation, and with the README's four settings for slow
//! platforms (keyframe rule at 4 px, inverse depths, observability-constrained
//! MSCKF and SLAM Jacobians).
//!
//! `cargo bench -p agent --bench estimator_speed [-- SCENARIO [ROUNDS]]`
//! (default `sim-fleet/scenarios/v1_01_easy.yaml`, 3 rounds). The variants run
//! alternately so a noisy machine affects both alike; per-stage means and the
//! p50/p95 of the frame total are printed for each.
use agent::runner::{options_for, run_robot, Variant};
use common::estimator_options::{EstimatorOptions, FeatureRepresentation, MsckfJacobians};
use simulator::{Fleet, Scenario};
use std::path::PathBuf;

fn main() -> anyhow::Result<()> {
    let args: Vec<String> = std::env::args()
        .skip(1)
        .filter(|a| !a.starts_with('-'))
        .collect();
    let path = args.first().map(PathBuf::from).unwrap_or_else(|| {
        PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("../sim-fleet/scenarios/v1_01_easy.yaml")
    });
    let rounds: usize = args.get(1).and_then(|r| r.parse().ok()).unwrap_or(3);
    let scenario = Scenario::load(&path)?;
    let fleet = Fleet::build(&scenario, scenario.seed)?;
    // Each variant's settings on top of the scenario's.
    type Tweak = fn(&mut EstimatorOptions);
    let variants: [(&str, Variant, Tweak); 4] = [
        ("indp-slam", Variant::IndpSlam, |_| {}),
        ("indp", Variant::Indp, |_| {}),
        ("indp-slam, inverse depth", Variant::IndpSlam, |o| {
            o.feature_representation = FeatureRepresentation::AnchoredInverseDepth;
        }),
        ("indp-slam, slow platform", Variant::IndpSlam, slow_platform),
    ];
    let mut frames: Vec<Vec<agent::estimator::FrameRecord>> = vec![Vec::new(); variants.len()];
    for _ in 0..rounds {
        for (i, (_, v, tweak)) in variants.iter().enumerate() {
            let mut opts = options_for(&scenario.estimator, &fleet, 0, *v);
            tweak(&mut opts);
            let run = run_robot(&fleet, 0, opts)?;
            frames[i].extend(run.frames);
        }
    }
    println!(
        "scenario {}, robot 0, {rounds} rounds, ms per camera frame (one thread):",
        scenario.name
    );
    println!(
        "variant                     frames  propagate  msckf  slam_upd  slam_init  marg    mean    p50     p95"
    );
    for ((label, _, _), f) in variants.iter().zip(&frames) {
        let n = f.len().max(1) as f64;
        let mean = |g: fn(&agent::estimator::vio::FrameTiming) -> f64| {
            f.iter().map(|o| g(&o.timing)).sum::<f64>() / n
        };
        let mut tot: Vec<f64> = f.iter().map(|o| o.timing.total_ms).collect();
        tot.sort_by(f64::total_cmp);
        let q = |p: f64| {
            tot.get(((tot.len() as f64 - 1.0) * p) as usize)
                .copied()
                .unwrap_or(f64::NAN)
        };
        println!(
            "{:<26} {:>7} {:>10.3} {:>6.3} {:>9.3} {:>10.3} {:>5.3} {:>7.3} {:>6.3} {:>7.3}",
            label,
            f.len(),
            mean(|t| t.propagate_ms),
            mean(|t| t.msckf_ms),
            mean(|t| t.slam_update_ms),
            mean(|t| t.slam_init_ms),
            mean(|t| t.marginalize_ms),
            mean(|t| t.total_ms),
            q(0.5),
            q(0.95)
        );
    }
    Ok(())
}

/// README, "Settings for slow platforms".
fn slow_platform(o: &mut EstimatorOptions) {
    o.keyframe_parallax_px = 4.0;
    o.feature_representation = FeatureRepresentation::AnchoredInverseDepth;
    o.msckf_jacobians = MsckfJacobians::ObservabilityConstrained;
    o.slam_jacobians = MsckfJacobians::ObservabilityConstrained;
}
