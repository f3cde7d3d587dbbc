//! Conventions of the whole workspace, stated once.
//!
//! Every module in every crate follows these; a name that breaks them is a bug.
//!
//! # Frames and names
//! * `G`: the global (world) frame, **z up**; gravity is `[0, 0, -GRAVITY_MPS2]` in `G`.
//! * `I`: the IMU (body) frame. `C`: the camera frame (z forward, x right, y down).
//! * Names say the direction: `R_ItoG` maps a vector expressed in `I` into `G`
//!   (`v_G = R_ItoG * v_I`); `p_IinG` is the position of the origin of `I` in `G`.
//!   In Rust identifiers this reads `rot_i_to_g`, `p_i_in_g`.
//!
//! # Stored orientations
//! * Orientations are stored as rotation matrices (or Hamilton unit quaternions)
//!   **from the child frame to the parent frame**: the pose of the IMU is
//!   `(R_ItoG, p_IinG)`, the camera extrinsic is `(R_CtoI, p_CinI)`.
//! * Quaternions are Hamilton (`i*j = k`), as nalgebra's `UnitQuaternion`.
//!
//! # Error state (the filter and the NEES use the same definition)
//! * Rotations are perturbed on the **right**, in the local (child) frame:
//!   `R_ItoG = R̂_ItoG · Exp(δθ)`, so `δθ = Log(R̂_ItoGᵀ R_ItoG)`. This is the same
//!   error as OpenVINS's JPL `δq ⊗ q̂_GtoI`, so covariances are comparable with it.
//! * Vectors (positions, velocities, biases, intrinsics, time offset) are additive:
//!   `p = p̂ + δp`.
//! * Orientation NEES uses `δθ` above with the filter's 3x3 orientation block;
//!   position NEES uses `δp` in `G`.
//!
//! # Time
//! * Seconds as `f64` everywhere inside the system.
//! * Camera-IMU time offset `t_d`: a camera stamp `t_cam` corresponds to IMU time
//!   `t_imu = t_cam + t_d` (as OpenVINS).
//!
//! # Files
//! * TUM / OpenVINS trajectory text: `timestamp tx ty tz qx qy qz qw`, scalar **last**,
//!   the quaternion is `R_ItoG`.
//! * EuRoC ASL CSV ground truth: `ns, px, py, pz, qw, qx, qy, qz, ...`, scalar **first**,
//!   the quaternion is `R_ItoG` (body `S` to world `R`).
//!
//! # IMU model
//! * `ω_m = ω_I + b_g + n_g`, `a_m = R_ItoGᵀ (a_G + [0, 0, g]) + b_a + n_a`, with
//!   white noise densities in `rad/s/√Hz`, `m/s²/√Hz` and random walks in
//!   `rad/s²/√Hz`, `m/s³/√Hz` (discrete std: density / √dt and rw · √dt).

/// Gravity magnitude in m/s² used by the simulator and the estimator (thesis Table 5.1).
pub const GRAVITY_MPS2: f64 = 9.81;
