//! Radial-tangential (plumb-bob, OpenCV "pinhole") distortion in normalized
//! coordinates.
//!
//! With `r² = x² + y²` and `d = [k1, k2, p1, p2]`:
//! ```text
//! x_d = x (1 + k1 r² + k2 r⁴) + 2 p1 x y + p2 (r² + 2 x²)
//! y_d = y (1 + k1 r² + k2 r⁴) + p1 (r² + 2 y²) + 2 p2 x y
//! ```

use nalgebra::{Matrix2, Matrix2x4, Vector2, Vector4};

/// Distorted normalized point of the undistorted normalized point `n`.
pub(super) fn distort(d: &Vector4<f64>, n: &Vector2<f64>) -> Vector2<f64> {
    let (k1, k2, p1, p2) = (d[0], d[1], d[2], d[3]);
    let (x, y) = (n.x, n.y);
    let r2 = x * x + y * y;
    let radial = 1.0 + k1 * r2 + k2 * r2 * r2;
    Vector2::new(
        x * radial + 2.0 * p1 * x * y + p2 * (r2 + 2.0 * x * x),
        y * radial + p1 * (r2 + 2.0 * y * y) + 2.0 * p2 * x * y,
    )
}

/// Distorted normalized point with its Jacobians with respect to the
/// undistorted normalized point (2x2) and to `d = [k1, k2, p1, p2]` (2x4).
pub(super) fn distort_with_jacobians(
    d: &Vector4<f64>,
    n: &Vector2<f64>,
) -> (Vector2<f64>, Matrix2<f64>, Matrix2x4<f64>) {
    let (k1, k2, p1, p2) = (d[0], d[1], d[2], d[3]);
    let (x, y) = (n.x, n.y);
    let r2 = x * x + y * y;
    let r4 = r2 * r2;
    let radial = 1.0 + k1 * r2 + k2 * r4;
    let nd = distort(d, n);

    // d(radial)/dx = 2x (k1 + 2 k2 r²), likewise for y.
    let dr = k1 + 2.0 * k2 * r2;
    let cross = 2.0 * x * y * dr + 2.0 * p1 * x + 2.0 * p2 * y;
    let d_nd_d_n = Matrix2::new(
        radial + 2.0 * x * x * dr + 2.0 * p1 * y + 6.0 * p2 * x,
        cross,
        cross,
        radial + 2.0 * y * y * dr + 6.0 * p1 * y + 2.0 * p2 * x,
    );

    let d_nd_d_dist = Matrix2x4::new(
        x * r2,
        x * r4,
        2.0 * x * y,
        r2 + 2.0 * x * x,
        y * r2,
        y * r4,
        r2 + 2.0 * y * y,
        2.0 * x * y,
    );
    (nd, d_nd_d_n, d_nd_d_dist)
}
