//! Training and test images from the fleet simulator: every `every`-th camera
//! frame of every robot of a scenario, with the ground-truth landmark of each
//! feature.

use common::descriptor::Descriptor;
use simulator::scenario::ScenarioError;
use simulator::{Fleet, Scenario, SimError, SimEvent};
use std::path::Path;
use thiserror::Error;

/// Why the simulator could not provide images.
#[derive(Debug, Error)]
pub enum SimDataError {
    /// The scenario could not be loaded.
    #[error(transparent)]
    Scenario(#[from] ScenarioError),
    /// The fleet could not be simulated.
    #[error(transparent)]
    Sim(#[from] SimError),
}

/// One simulated image.
#[derive(Clone, Debug, PartialEq)]
pub struct SimImage {
    /// The robot's index in the scenario.
    pub robot: usize,
    /// The frame's index in the robot's camera stream (0-based, all frames).
    pub frame: usize,
    /// Camera time in seconds.
    pub t: f64,
    /// The features' descriptors.
    pub descriptors: Vec<Descriptor>,
    /// The landmark behind each feature (same order); ground truth.
    pub landmark_ids: Vec<u64>,
}

/// Simulates the scenario at `path` with `seed` (the scenario's own seed if
/// `None`) and keeps every `every`-th frame (`every` of 0 counts as 1) of each
/// robot, robots in order.
pub fn simulate_images(
    path: &Path,
    seed: Option<u64>,
    every: usize,
) -> Result<Vec<SimImage>, SimDataError> {
    let scenario = Scenario::load(path)?;
    let seed = seed.unwrap_or(scenario.seed);
    let fleet = Fleet::build(&scenario, seed)?;
    let every = every.max(1);
    let mut images = Vec::new();
    for robot in 0..fleet.robot_count() {
        let mut frame = 0;
        for event in fleet.stream(robot)? {
            let SimEvent::Camera(cam) = event else {
                continue;
            };
            if frame % every == 0 {
                images.push(SimImage {
                    robot,
                    frame,
                    t: cam.frame.t,
                    descriptors: cam.frame.features.iter().map(|f| f.descriptor).collect(),
                    landmark_ids: cam.landmark_ids.clone(),
                });
            }
            frame += 1;
        }
        tracing::debug!(robot, frames = frame, "robot simulated");
    }
    Ok(images)
}
