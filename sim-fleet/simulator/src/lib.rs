//! The fleet simulator.
#![warn(missing_docs)]
