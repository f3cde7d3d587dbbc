//! The estimator's options (defined in `common` so scenarios share the defaults).

pub use common::estimator_options::{
    CalibrationPrior, EstimatorOptions, FeatureRepresentation, ImuNoise, MsckfJacobians,
};
