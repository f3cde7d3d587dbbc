//! Input validation: what the estimators accept from sensors and what they
//! reject (with a reason, changing nothing).

use common::measurement::{FeatureFrame, ImuSample};
use thiserror::Error;

/// Why an input was rejected. The estimator's state is unchanged.
#[derive(Debug, Error, PartialEq)]
pub enum InputError {
    /// A value is NaN or infinite.
    #[error("{what} at t={t} has a non-finite value")]
    NonFinite {
        /// Which input.
        what: &'static str,
        /// Its time stamp.
        t: f64,
    },
    /// Time went backwards (or stood still).
    #[error("{what} at t={t} is not after the previous one at t={previous}")]
    TimeBackwards {
        /// Which input.
        what: &'static str,
        /// Its time.
        t: f64,
        /// The previous time.
        previous: f64,
    },
    /// A gap in the IMU stream larger than allowed.
    #[error("IMU gap of {gap_s:.3} s before t={t} (max {max_s} s)")]
    ImuGap {
        /// The gap.
        gap_s: f64,
        /// Time of the sample after the gap.
        t: f64,
        /// The limit.
        max_s: f64,
    },
    /// A frame without features.
    #[error("frame at t={t} has no features")]
    EmptyFrame {
        /// Its time.
        t: f64,
    },
    /// The same track id twice in one frame.
    #[error("frame at t={t} repeats feature id {id}")]
    DuplicateId {
        /// Frame time.
        t: f64,
        /// The repeated id.
        id: u64,
    },
}

/// Checks an IMU sample after `prev` (the last accepted one): finite, after it,
/// and no longer after it than `max_gap_s`.
pub fn check_imu(
    prev: Option<&ImuSample>,
    s: &ImuSample,
    max_gap_s: f64,
) -> Result<(), InputError> {
    if !(s.t.is_finite()
        && s.gyro.iter().all(|v| v.is_finite())
        && s.accel.iter().all(|v| v.is_finite()))
    {
        return Err(InputError::NonFinite {
            what: "IMU sample",
            t: s.t,
        });
    }
    if let Some(prev) = prev {
        if s.t <= prev.t {
            return Err(InputError::TimeBackwards {
                what: "IMU sample",
                t: s.t,
                previous: prev.t,
            });
        }
        if s.t - prev.t > max_gap_s {
            return Err(InputError::ImuGap {
                gap_s: s.t - prev.t,
                t: s.t,
                max_s: max_gap_s,
            });
        }
    }
    Ok(())
}

/// Checks a feature frame after the previous frame time `prev_t`: finite, after
/// it, not empty, no repeated track id.
pub fn check_frame(prev_t: Option<f64>, frame: &FeatureFrame) -> Result<(), InputError> {
    if !frame.t.is_finite()
        || frame
            .features
            .iter()
            .any(|f| !(f.uv.x.is_finite() && f.uv.y.is_finite()))
    {
        return Err(InputError::NonFinite {
            what: "frame",
            t: frame.t,
        });
    }
    if let Some(prev) = prev_t {
        if frame.t <= prev {
            return Err(InputError::TimeBackwards {
                what: "frame",
                t: frame.t,
                previous: prev,
            });
        }
    }
    if frame.features.is_empty() {
        return Err(InputError::EmptyFrame { t: frame.t });
    }
    let mut ids: Vec<u64> = frame.features.iter().map(|f| f.id).collect();
    ids.sort_unstable();
    if let Some(w) = ids.windows(2).find(|w| w[0] == w[1]) {
        return Err(InputError::DuplicateId {
            t: frame.t,
            id: w[0],
        });
    }
    Ok(())
}
