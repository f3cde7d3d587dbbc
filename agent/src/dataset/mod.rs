//! Real sensor data: datasets in the EuRoC ASL folder layout (EuRoC MAV,
//! TUM-VI), read into the same events the simulator produces, so one agent
//! loop serves both.

pub mod euroc;
pub mod sensor_yaml;

pub use euroc::{mav0_root, DatasetError, EurocDataset, ImageStamp, SensorSetup};
