//! Seeded random streams. Every random draw of the simulator comes from one of
//! these, so a measurement stream is a pure function of (scenario, robot, seed).

use rand::SeedableRng;
use rand_chacha::ChaCha8Rng;

/// Which independent stream to draw from.
#[derive(Clone, Copy, Debug)]
pub enum Stream {
    /// The shared landmark world.
    World,
    /// A robot's IMU noise and bias random walk.
    Imu(usize),
    /// A robot's pixel noise, descriptor noise and outliers.
    Camera(usize),
    /// A robot's perturbed initial calibration.
    Calibration(usize),
    /// The textures of the rendered world.
    Texture,
    /// A robot's rendered image noise.
    Render(usize),
    /// The error a robot's estimator starts with (`initial_error: sampled`).
    InitialState(usize),
    /// A robot's rendered images' brightness steps (`render.gain_step_chance`).
    Lighting(usize),
}

/// A ChaCha8 generator for `stream` of `seed`; streams never overlap.
pub fn stream_rng(seed: u64, stream: Stream) -> ChaCha8Rng {
    let id = match stream {
        Stream::World => 0,
        Stream::Imu(r) => 1 + 4 * r as u64,
        Stream::Camera(r) => 2 + 4 * r as u64,
        Stream::Calibration(r) => 3 + 4 * r as u64,
        // 4 + 4r is free for every r (the world took only 0).
        Stream::Render(r) => 4 + 4 * r as u64,
        // Above every 4r + k of any realistic fleet.
        Stream::InitialState(r) => (1 << 40) + r as u64,
        Stream::Lighting(r) => (1 << 41) + r as u64,
        Stream::Texture => u64::MAX,
    };
    let mut rng = ChaCha8Rng::seed_from_u64(seed);
    rng.set_stream(id);
    rng
}
