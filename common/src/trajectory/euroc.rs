//! EuRoC ASL ground-truth CSV: `ns, px, py, pz, qw, qx, qy, qz, ...`.

use std::path::Path;

use nalgebra::Vector3;

use super::parse::{need, number, parse_file, rotation};
use super::{LineError, StampedPose, TrajectoryError};

/// Nanoseconds per second.
const NS_PER_S: u64 = 1_000_000_000;

/// Reads EuRoC ASL ground truth `ns, px, py, pz, qw, qx, qy, qz, ...`
/// (integer nanoseconds, metres, Hamilton quaternion `R_ItoG` scalar **first**).
/// Velocities and biases after the quaternion are ignored. Times are converted
/// to seconds without losing the nanosecond digits.
pub fn read_euroc_csv(path: impl AsRef<Path>) -> Result<Vec<StampedPose>, TrajectoryError> {
    parse_file(
        path.as_ref(),
        |f| {
            need(f, 8)?;
            let v = |i| number(f, i);
            let (qw, qx, qy, qz) = (v(4)?, v(5)?, v(6)?, v(7)?);
            Ok(StampedPose {
                t: seconds_from_ns(f.first().copied().unwrap_or(""))?,
                pos: Vector3::new(v(1)?, v(2)?, v(3)?),
                rot: rotation(qx, qy, qz, qw)?,
            })
        },
        |p| p.t,
    )
}

/// Seconds of an integer nanosecond stamp, splitting whole seconds from the
/// remainder so the `f64` keeps as many digits as it can.
fn seconds_from_ns(text: &str) -> Result<f64, LineError> {
    let ns: u64 = text.parse().map_err(|source| LineError::Nanoseconds {
        column: 1,
        text: text.to_string(),
        source,
    })?;
    Ok((ns / NS_PER_S) as f64 + (ns % NS_PER_S) as f64 * 1e-9)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn nanoseconds_convert_to_seconds_keeping_the_fraction() {
        let t = seconds_from_ns("1403715273262142976").unwrap();
        assert!((t - 1_403_715_273.262_143).abs() < 1e-6);
        assert_eq!(seconds_from_ns("1500000000").unwrap(), 1.5);
        assert!(seconds_from_ns("-5").is_err());
        assert!(seconds_from_ns("1.5e9").is_err());
    }
}
