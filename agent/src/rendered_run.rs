//! One robot of a scenario that renders images, through the image frontend,
//! for tools that link the agent with or without the `vision` feature
//! (`sim-fleet montecarlo`): built without it, the run is refused with the
//! build that has it, instead of the tool failing to compile.

use crate::estimator::EstimatorOptions;
use crate::frontend::FrontendOptions;
use crate::runner::{RobotRun, RunError};
use simulator::Fleet;
use std::path::Path;

/// Whether this build has the image frontend (cargo feature `vision`).
pub const AVAILABLE: bool = cfg!(feature = "vision");

/// A rendered robot run.
#[derive(Clone, Debug, Default)]
pub struct RenderedRun {
    /// The estimator's outputs.
    pub run: RobotRun,
    /// The tracks' mean error against the rendered truth, px (`None` when no
    /// track could be scored).
    pub track_error_mean_px: Option<f64>,
    /// The tracks' error image by image, the text of `track_errors.csv`.
    pub track_errors_csv: String,
}

/// Runs robot `robot` of `fleet` (which renders images) through the image
/// frontend with `frontend`'s settings.
#[cfg(feature = "vision")]
pub fn run(
    fleet: &Fleet,
    robot: usize,
    opts: EstimatorOptions,
    frontend: FrontendOptions,
) -> Result<RenderedRun, RunError> {
    let r = crate::image_runner::run_robot_rendered(fleet, robot, opts, frontend, |_, _| {})?;
    Ok(RenderedRun {
        track_error_mean_px: r.tracks.mean_error_px(),
        run: r.run,
        track_errors_csv: crate::image_runner::track_errors_csv(&r.per_frame),
    })
}

/// Built without the image frontend: refused, with the build that has it.
#[cfg(not(feature = "vision"))]
pub fn run(
    _: &Fleet,
    _: usize,
    _: EstimatorOptions,
    _: FrontendOptions,
) -> Result<RenderedRun, RunError> {
    Err(RunError::NoImageFrontend)
}

/// The image frontend's settings: the defaults, or those of `path` (a file
/// with the keys of an agent configuration's `images.frontend:` block; an
/// unknown key or a value out of range is an error naming it).
pub fn frontend_options(path: Option<&Path>) -> Result<FrontendOptions, String> {
    let Some(path) = path else {
        return Ok(FrontendOptions::default());
    };
    let text =
        std::fs::read_to_string(path).map_err(|e| format!("reading {}: {e}", path.display()))?;
    let o: FrontendOptions = serde_yaml::from_str(&text)
        .map_err(|e| format!("{}: not an `images.frontend:` block: {e}", path.display()))?;
    o.validate()
        .map_err(|e| format!("{}: frontend settings: {e}", path.display()))?;
    Ok(o)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn frontend_settings_are_read_and_bad_ones_refused_by_name() {
        let dir = tempfile::tempdir().unwrap();
        let p = dir.path().join("fe.yaml");
        assert_eq!(frontend_options(None), Ok(FrontendOptions::default()));
        std::fs::write(&p, "num_features: 150\n").unwrap();
        assert_eq!(frontend_options(Some(&p)).unwrap().num_features, 150);
        std::fs::write(&p, "num_features: 0\n").unwrap();
        let e = frontend_options(Some(&p)).unwrap_err();
        assert!(e.contains("num_features"), "{e}");
        std::fs::write(&p, "num_feature: 150\n").unwrap();
        let e = frontend_options(Some(&p)).unwrap_err();
        assert!(e.contains("num_feature"), "{e}");
        let e = frontend_options(Some(&dir.path().join("none.yaml"))).unwrap_err();
        assert!(e.contains("none.yaml"), "{e}");
    }
}
