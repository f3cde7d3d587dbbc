//! Equidistant (Kannala-Brandt, OpenCV "fisheye") distortion in normalized
//! coordinates.
//!
//! With `r = √(x² + y²)`, `θ = atan(r)` and `d = [k1, k2, k3, k4]`:
//! ```text
//! θ_d = θ (1 + k1 θ² + k2 θ⁴ + k3 θ⁶ + k4 θ⁸)
//! x_d = (θ_d / r) x,   y_d = (θ_d / r) y
//! ```
//! As `r → 0`, `θ_d / r → 1`; the code uses the series below [`SMALL_RADIUS`].

use nalgebra::{Matrix2, Matrix2x4, Vector2, Vector4};

/// Below this normalized radius the ratios `θ/r`, `θ_d/r` and the radial
/// derivative use their Taylor series (the closed forms divide by `r`).
const SMALL_RADIUS: f64 = 1e-8;

/// `θ_d(θ)` and `dθ_d/dθ`.
fn theta_d_and_derivative(d: &Vector4<f64>, theta: f64) -> (f64, f64) {
    let t2 = theta * theta;
    let t4 = t2 * t2;
    let t6 = t4 * t2;
    let t8 = t4 * t4;
    let poly = 1.0 + d[0] * t2 + d[1] * t4 + d[2] * t6 + d[3] * t8;
    let dpoly = 1.0 + 3.0 * d[0] * t2 + 5.0 * d[1] * t4 + 7.0 * d[2] * t6 + 9.0 * d[3] * t8;
    (theta * poly, dpoly)
}

/// The radial scale `s = θ_d / r` (so that `n_d = s n`).
fn scale(d: &Vector4<f64>, r: f64) -> f64 {
    if r < SMALL_RADIUS {
        // θ = r - r³/3 + …, θ_d = θ + k1 θ³ + … ⇒ s = 1 + (k1 - 1/3) r² + O(r⁴).
        1.0 + (d[0] - 1.0 / 3.0) * r * r
    } else {
        theta_d_and_derivative(d, r.atan()).0 / r
    }
}

/// Distorted normalized point of the undistorted normalized point `n`.
pub(super) fn distort(d: &Vector4<f64>, n: &Vector2<f64>) -> Vector2<f64> {
    n * scale(d, n.norm())
}

/// Distorted normalized point with its Jacobians with respect to the
/// undistorted normalized point (2x2) and to `d = [k1, k2, k3, k4]` (2x4).
pub(super) fn distort_with_jacobians(
    d: &Vector4<f64>,
    n: &Vector2<f64>,
) -> (Vector2<f64>, Matrix2<f64>, Matrix2x4<f64>) {
    let r = n.norm();
    // s = θ_d / r, g = (ds/dr) / r, theta_over_r = θ / r, theta2 = θ².
    let (s, g, theta_over_r, theta2) = if r < SMALL_RADIUS {
        let r2 = r * r;
        let s = 1.0 + (d[0] - 1.0 / 3.0) * r2;
        (s, 2.0 * (d[0] - 1.0 / 3.0), 1.0 - r2 / 3.0, r2)
    } else {
        let theta = r.atan();
        let (theta_d, dtheta_d) = theta_d_and_derivative(d, theta);
        let dtheta_dr = 1.0 / (1.0 + r * r);
        let s = theta_d / r;
        // ds/dr = (θ_d'(θ) θ'(r) r - θ_d) / r²; the cancellation in the numerator
        // is harmless: g multiplies n nᵀ, whose size is r².
        let g = (dtheta_d * dtheta_dr * r - theta_d) / (r * r * r);
        (s, g, theta / r, theta * theta)
    };
    let nd = n * s;
    // d(s n)/dn = s I + n (ds/dr) (n / r)ᵀ = s I + g n nᵀ.
    let d_nd_d_n = Matrix2::identity() * s + (n * n.transpose()) * g;
    // dθ_d/dk_i = θ^(2i+1) ⇒ dn_d/dk_i = n (θ/r) θ^(2i).
    let t2 = theta2;
    let t4 = t2 * t2;
    let powers = Vector4::new(t2, t4, t4 * t2, t4 * t4) * theta_over_r;
    let d_nd_d_dist = n * powers.transpose();
    (nd, d_nd_d_n, d_nd_d_dist)
}
