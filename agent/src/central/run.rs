//! Runs the centralized estimator on a simulated fleet: every robot's sensor
//! stream merged in time order into one process, each robot started at the
//! true state once it has moved (as the standalone runs), its estimate scored
//! against its own truth.

use super::{CentralEstimator, PixelNoise};
use crate::runner::{
    initial_state, options_for, record, thread_cpu_s, RobotRun, RunError, Variant,
};
use simulator::scenario::StartFrame;
use simulator::{Fleet, SimEvent};

fn time_of(e: &SimEvent) -> f64 {
    match e {
        SimEvent::Imu(s) => s.t,
        SimEvent::Camera(c) => c.truth.t,
    }
}

/// Runs `variant` (a `ce-*` variant) over every robot of `fleet`; one run per
/// robot, in robot order.
pub fn run_central(fleet: &Fleet, variant: Variant) -> Result<Vec<RobotRun>, RunError> {
    let cpu_start = cpu_time::ThreadTime::try_now().ok();
    let n = fleet.robot_count();
    let spec = &fleet.scenario.estimator;
    // One joint state holds every robot in one frame: the reference that
    // knows the robots' relative start poses by construction.
    if spec.start_frame != StartFrame::Fleet {
        return Err(RunError::NeedsFleetFrame(variant.name()));
    }
    // Rendered frames carry images and no features: the joint filter would
    // fly on the IMUs alone, and say nothing.
    if fleet.renders() {
        return Err(RunError::RendersImages(
            variant.name(),
            "it has no image frontend; run the agents' variants, or set render.enabled: false",
        ));
    }
    let opts = options_for(spec, fleet, 0, variant);
    let calibs = (0..n).map(|r| fleet.initial_calibration(r)).collect();
    let mut est = CentralEstimator::new(opts, calibs);
    // Each robot's pixels weigh at its camera's noise.
    for r in 0..n {
        est.set_pixel_noise(r, PixelNoise::of(&options_for(spec, fleet, r, variant)));
    }
    let mut streams = Vec::with_capacity(n);
    let mut starts = Vec::with_capacity(n);
    for r in 0..n {
        streams.push(fleet.stream(r)?.peekable());
        starts.push(
            fleet
                .estimator_start_time(r)
                .ok_or(simulator::SimError::NoSuchRobot(r))?,
        );
    }
    let mut runs: Vec<RobotRun> = (0..n).map(|_| RobotRun::default()).collect();
    let mut initialized = vec![false; n];
    loop {
        // The robot whose next event is earliest (ties to the lowest index).
        let mut next: Option<(usize, f64)> = None;
        for (r, s) in streams.iter_mut().enumerate() {
            if let Some(e) = s.peek() {
                let t = time_of(e);
                if next.is_none_or(|(_, best)| t < best) {
                    next = Some((r, t));
                }
            }
        }
        let Some((r, _)) = next else {
            break;
        };
        let Some(ev) = streams[r].next() else {
            continue;
        };
        match ev {
            SimEvent::Imu(s) => {
                if let Err(e) = est.feed_imu(r, s) {
                    runs[r].rejected.push(e.to_string());
                }
            }
            SimEvent::Camera(c) => {
                runs[r].note_true_biases(c.truth.t, c.truth.biases);
                if !initialized[r] {
                    if c.truth.t >= starts[r] {
                        est.initialize(r, &initial_state(fleet, r, &c.truth));
                        initialized[r] = true;
                    }
                    continue;
                }
                if let Err(e) = est.feed_frame(r, c.frame) {
                    runs[r].rejected.push(e.to_string());
                }
            }
        }
        for out in est.poll(r) {
            match out {
                Ok(o) => record(&mut runs[r], &fleet.truths[r], o),
                Err(e) => runs[r].rejected.push(e.to_string()),
            }
        }
    }
    if let Some(r) = initialized.iter().position(|i| !i) {
        return Err(RunError::NeverStarted(r));
    }
    // One joint estimator serves every robot: each gets an equal share.
    let share = thread_cpu_s(cpu_start.as_ref()).map(|s| s / n.max(1) as f64);
    for run in &mut runs {
        run.cpu_s = share;
    }
    Ok(runs)
}
