//! TUM / OpenVINS trajectory text: `timestamp tx ty tz qx qy qz qw`.

use std::path::Path;

use super::parse::{need, number, parse_file, rotation, write_lines};
use super::{StampedPose, TrajectoryError};
use crate::so3::xyzw_from_rot;
use nalgebra::Vector3;

/// The header comment [`write_tum`] puts on the first line.
pub const TUM_HEADER: &str = "# timestamp tx ty tz qx qy qz qw";

/// Reads a TUM / OpenVINS trajectory `timestamp tx ty tz qx qy qz qw`
/// (seconds, metres, Hamilton quaternion `R_ItoG` scalar last, normalized).
/// Values after the eighth are ignored.
pub fn read_tum(path: impl AsRef<Path>) -> Result<Vec<StampedPose>, TrajectoryError> {
    parse_file(
        path.as_ref(),
        |f| {
            need(f, 8)?;
            let v = |i| number(f, i);
            Ok(StampedPose {
                t: v(0)?,
                pos: Vector3::new(v(1)?, v(2)?, v(3)?),
                rot: rotation(v(4)?, v(5)?, v(6)?, v(7)?)?,
            })
        },
        |p| p.t,
    )
}

/// Writes a TUM trajectory that `evo` and [`read_tum`] read directly: a
/// [`TUM_HEADER`] comment, timestamps with 9 decimals, and the other values in
/// the shortest form that reads back to the same `f64`. Quaternions have `qw >= 0`.
pub fn write_tum(path: impl AsRef<Path>, poses: &[StampedPose]) -> Result<(), TrajectoryError> {
    write_lines(path.as_ref(), TUM_HEADER, poses.iter().map(tum_row))
}

/// One line of [`write_tum`] (no newline): for writers that append a pose at
/// a time, so that a file written as a run goes is the file written at its end.
pub fn tum_row(p: &StampedPose) -> String {
    let [qx, qy, qz, qw] = xyzw_from_rot(&p.rot);
    format!(
        "{:.9} {} {} {} {} {} {} {}",
        p.t, p.pos.x, p.pos.y, p.pos.z, qx, qy, qz, qw
    )
}
