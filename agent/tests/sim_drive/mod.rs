//! Drives one simulated robot through its estimator frame by frame, for tests
//! that look at every output (and at the state behind it), not only at what
//! a run records.

use agent::estimator::{Estimator, EstimatorOptions, FrameOutput};
use agent::runner::initial_state;
use simulator::{Fleet, SimEvent};

/// Runs robot 0 of `fleet` with `opts`, started where the runner starts it
/// (the fleet's start time, [`initial_state`]), and calls `each` with the
/// estimator and every frame's output until it returns `false` or the stream
/// ends. Panics on rejected input or a failed frame: the simulator's stream
/// is valid.
pub fn drive_robot0(
    fleet: &Fleet,
    opts: EstimatorOptions,
    mut each: impl FnMut(&Estimator, FrameOutput) -> bool,
) {
    let start = fleet.estimator_start_time(0).expect("robot 0");
    let mut est = Estimator::new(opts, fleet.initial_calibration(0));
    let mut started = false;
    for ev in fleet.stream(0).expect("stream") {
        match ev {
            SimEvent::Imu(s) => est.feed_imu(s).expect("imu"),
            SimEvent::Camera(c) => {
                if !started {
                    if c.truth.t >= start {
                        est.initialize(&initial_state(fleet, 0, &c.truth));
                        started = true;
                    }
                    continue;
                }
                est.feed_frame(c.frame).expect("frame");
            }
        }
        for out in est.poll() {
            if !each(&est, out.expect("frame processed")) {
                return;
            }
        }
    }
}
