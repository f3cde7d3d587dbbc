//! Image frontend cost: ms per 752x480 frame with 200 tracks, on one core.
//!
//! The frames are rendered images of the V1_01 flight (10 Hz), rendered before
//! timing starts; OpenCV runs on one thread. Prints mean, median and 95th
//! percentile per stage-complete frame, and the features per frame.
//!
//! `cargo bench -p agent --features vision --bench frontend_speed`

#![allow(clippy::expect_used, clippy::unwrap_used)]

use agent::frontend::{Frontend, FrontendOptions};
use simulator::{Fleet, Scenario, SimEvent};
use std::path::PathBuf;

/// Frames rendered and tracked.
const FRAMES: usize = 300;

fn main() {
    opencv::core::set_num_threads(1).expect("one OpenCV thread");
    let path =
        PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("../sim-fleet/scenarios/v1_01_easy.yaml");
    let mut sc = Scenario::load(&path).expect("scenario");
    sc.render.enabled = true;
    let fleet = Fleet::build(&sc, 1).expect("fleet");
    let start = fleet.estimator_start_time(0).expect("start");
    let frames: Vec<_> = fleet
        .stream(0)
        .expect("stream")
        .filter_map(|e| match e {
            SimEvent::Camera(c) if c.truth.t >= start => {
                Some((c.frame.t, c.image.expect("rendered")))
            }
            _ => None,
        })
        .take(FRAMES)
        .collect();
    for (name, opts) in [
        (
            "FAST, equalized, held (the default)",
            FrontendOptions::default(),
        ),
        (
            "Shi-Tomasi, CLAHE, held",
            FrontendOptions {
                detector: agent::frontend::Detector::ShiTomasi,
                histogram: agent::frontend::Histogram::Clahe,
                ..FrontendOptions::default()
            },
        ),
        (
            "FAST, equalized, KLT alone (first_patch: off)",
            FrontendOptions {
                first_patch: agent::frontend::FirstPatch::Off,
                ..FrontendOptions::default()
            },
        ),
    ] {
        let mut fe = Frontend::new(opts, fleet.initial_calibration(0).camera).expect("frontend");
        let mut ms = Vec::new();
        let mut features = 0usize;
        let mut stages = [0.0; 4];
        let mut refused = 0usize;
        for (t, img) in &frames {
            let out = fe.process(*t, img).expect("frame");
            ms.push(out.stats.ms);
            features += out.frame.features.len();
            stages[0] += out.stats.track_ms;
            stages[1] += out.stats.detect_ms;
            stages[2] += out.stats.describe_ms;
            stages[3] += out.stats.refine_ms;
            refused += out.stats.refused_patch;
        }
        let n = frames.len() as f64;
        // The first frame only detects: leave it out.
        ms.remove(0);
        ms.sort_by(f64::total_cmp);
        let mean = ms.iter().sum::<f64>() / ms.len() as f64;
        println!(
            "frontend ({name}), 752x480, one thread: {:.2} ms/frame mean, {:.2} median, {:.2} p95 over {} frames, {:.0} features/frame; stages (mean ms): track {:.2} (of which first-patch refinement {:.2}, {:.1} refused a frame), detect {:.2}, describe {:.2}",
            mean,
            ms[ms.len() / 2],
            ms[(ms.len() as f64 * 0.95) as usize],
            ms.len(),
            features as f64 / n,
            stages[0] / n,
            stages[3] / n,
            refused as f64 / n,
            stages[1] / n,
            stages[2] / n,
        );
    }
}
