//! Simulator speed: simulated seconds per wall second for one robot at the
//! reference settings (400 Hz IMU, 10 Hz camera, 100 features per frame).
//!
//! `cargo bench -p sim-fleet --bench simulator_speed [-- SCENARIO]`
//! (default: `sim-fleet/scenarios/v1_01_easy.yaml`). Prints the world build time
//! and, over 5 passes of robot 0's whole stream, min / median / max of the rate.
use simulator::{Fleet, Scenario, SimEvent};
use std::path::PathBuf;
use std::time::Instant;

fn main() -> anyhow::Result<()> {
    let arg = std::env::args().skip(1).find(|a| !a.starts_with('-'));
    let path = arg.map(PathBuf::from).unwrap_or_else(|| {
        PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("scenarios/v1_01_easy.yaml")
    });
    let scenario = Scenario::load(&path)?;
    let t = Instant::now();
    let fleet = Fleet::build(&scenario, scenario.seed)?;
    let build_s = t.elapsed().as_secs_f64();
    println!(
        "scenario {}: world of {} landmarks built in {:.3} s",
        scenario.name,
        fleet.world.landmarks.len(),
        build_s
    );
    let mut rates = Vec::new();
    for _ in 0..5 {
        let t = Instant::now();
        let (mut imu, mut frames, mut feats) = (0u64, 0u64, 0u64);
        let (mut first, mut last) = (None, 0.0);
        for ev in fleet.stream(0)? {
            match ev {
                SimEvent::Imu(s) => {
                    imu += 1;
                    first.get_or_insert(s.t);
                    last = s.t;
                }
                SimEvent::Camera(c) => {
                    frames += 1;
                    feats += c.frame.features.len() as u64;
                }
            }
        }
        let wall = t.elapsed().as_secs_f64();
        let sim = last - first.unwrap_or(last);
        rates.push(sim / wall);
        println!(
            "  {imu} IMU samples, {frames} frames ({:.1} features/frame), {sim:.1} s simulated in {wall:.3} s",
            feats as f64 / frames.max(1) as f64
        );
    }
    rates.sort_by(f64::total_cmp);
    println!(
        "simulated seconds per wall second (robot 0, 1 thread): min {:.0}, median {:.0}, max {:.0}",
        rates[0],
        rates[rates.len() / 2],
        rates[rates.len() - 1]
    );
    Ok(())
}
