//! Measurement-model linear algebra of the MSCKF update (thesis Section 2.3.3.2,
//! as OpenVINS `UpdaterHelper::nullspace_project_inplace` and
//! `measurement_compress_inplace`).
//!
//! A feature's stacked, linearized measurements read `r = H_x δx + H_f δp_f + n`
//! with isotropic noise `n`. [`nullspace_project_in_place`] multiplies the system
//! from the left by the transpose of an orthonormal basis of the left nullspace of
//! `H_f`, which removes the feature error `δp_f` and keeps the noise isotropic.
//! [`compress_in_place`] replaces a tall `H_x` by the square `R` of its thin QR
//! decomposition, which keeps all the information `H_xᵀ H_x`, `H_xᵀ r`.
//!
//! Both are built from Givens rotations of two adjacent rows, applied in place:
//! nothing is allocated inside the loops, and the orthogonal factor is never formed.

use nalgebra::{DMatrix, DVector};

/// A plane rotation `[c s; -s c]` acting on two rows.
#[derive(Clone, Copy, Debug)]
struct Givens {
    c: f64,
    s: f64,
}

impl Givens {
    /// The rotation that maps `(a, b)` to `(hypot(a, b), 0)`, or `None` when `b`
    /// is already zero (the rotation would be the identity).
    fn zeroing(a: f64, b: f64) -> Option<Self> {
        if b == 0.0 {
            return None;
        }
        // Plain square root: the entries are Jacobians of moderate size, so the
        // overflow protection of `hypot` is not needed and it is much slower.
        let r = (a * a + b * b).sqrt();
        if r == 0.0 || !r.is_finite() {
            return None;
        }
        Some(Self { c: a / r, s: b / r })
    }

    /// Applies the rotation to rows `top` and `top + 1` of `m`, columns
    /// `first_col..`. The matrix is column-major, so each column is a slice.
    fn apply_to_rows(self, m: &mut DMatrix<f64>, top: usize, first_col: usize) {
        let nrows = m.nrows();
        for col in m.as_mut_slice().chunks_exact_mut(nrows).skip(first_col) {
            if let [x, y] = &mut col[top..top + 2] {
                let (xv, yv) = (*x, *y);
                *x = self.c * xv + self.s * yv;
                *y = -self.s * xv + self.c * yv;
            }
        }
    }

    /// Applies the rotation to entries `top` and `top + 1` of `v`.
    fn apply_to_vector(self, v: &mut DVector<f64>, top: usize) {
        if let [x, y] = &mut v.as_mut_slice()[top..top + 2] {
            let (xv, yv) = (*x, *y);
            *x = self.c * xv + self.s * yv;
            *y = -self.s * xv + self.c * yv;
        }
    }
}

/// Givens QR of the feature Jacobian `h_f` (`m x k`), applying the same
/// orthogonal transform `Qᵀ` to the rows of `h_x` and `res`, and keeping all rows.
///
/// Column by column, the entries of `h_f` below the diagonal are zeroed from the
/// bottom up with rotations of adjacent rows. Afterwards:
/// * `h_f` holds `Qᵀ H_f = [R; 0]`, `R` upper-triangular in the top rows;
/// * the top rows of `h_x` and `res` are `Q₁ᵀ H_x`, `Q₁ᵀ r`: the part of the
///   system that involves the feature (usable for delayed feature
///   initialization, thesis Eqs. 2.41-2.45);
/// * the remaining rows are `Q₂ᵀ H_x`, `Q₂ᵀ r`, the projection onto the left
///   nullspace of `H_f`.
///
/// Returns the number of top rows, `min(m, k)`. `Q` is orthonormal, so
/// isotropic noise stays isotropic with the same variance.
///
/// # Panics
/// If `h_x` or `res` does not have as many rows as `h_f`.
pub fn givens_qr_split(
    h_f: &mut DMatrix<f64>,
    h_x: &mut DMatrix<f64>,
    res: &mut DVector<f64>,
) -> usize {
    let m = h_f.nrows();
    let k = h_f.ncols();
    assert_eq!(h_x.nrows(), m, "H_x must have as many rows as H_f");
    assert_eq!(res.len(), m, "the residual must have as many rows as H_f");
    let top = m.min(k);
    for n in 0..top {
        for row in (n + 1..m).rev() {
            let Some(g) = Givens::zeroing(h_f[(row - 1, n)], h_f[(row, n)]) else {
                continue;
            };
            g.apply_to_rows(h_f, row - 1, n);
            // Exact zero, rather than a rounding residue.
            h_f[(row, n)] = 0.0;
            g.apply_to_rows(h_x, row - 1, 0);
            g.apply_to_vector(res, row - 1);
        }
    }
    top
}

/// Projects the linearized system onto the left nullspace of the feature
/// Jacobian `h_f` (`m x k`, `m > k`), in place.
///
/// The rotations of [`givens_qr_split`] are applied to `h_f`, `h_x` and `res`,
/// then `h_x` and `res` are shrunk to their last `m - k` rows: `Q₂ᵀ H_x` and
/// `Q₂ᵀ r` with `Q₂ᵀ H_f = 0`. `h_f` keeps all `m` rows and holds `[R; 0]`
/// (upper-triangular `R` in its first `k` rows). If `m <= k` nothing is left
/// and `h_x` and `res` end with zero rows.
///
/// # Panics
/// If `h_x` or `res` does not have as many rows as `h_f`.
pub fn nullspace_project_in_place(
    h_f: &mut DMatrix<f64>,
    h_x: &mut DMatrix<f64>,
    res: &mut DVector<f64>,
) {
    let top = givens_qr_split(h_f, h_x, res);
    drop_leading_rows(h_x, res, top);
}

/// Compresses a tall measurement system in place: when `h_x` has more rows than
/// columns, a Givens QR zeroes it below the diagonal, the same rotations are
/// applied to `res`, and only the first `ncols` rows are kept. The information
/// `H_xᵀ H_x` and `H_xᵀ r` is unchanged (the dropped rows of `Qᵀ H_x` are zero;
/// the dropped residual rows carry no information about the state).
///
/// Does nothing when `h_x` has at most as many rows as columns. Rank-deficient
/// `h_x` is handled: its `R` then has zero rows, which are kept.
///
/// # Panics
/// If `res` does not have as many rows as `h_x`.
pub fn compress_in_place(h_x: &mut DMatrix<f64>, res: &mut DVector<f64>) {
    let m = h_x.nrows();
    let n_cols = h_x.ncols();
    assert_eq!(res.len(), m, "the residual must have as many rows as H_x");
    if m <= n_cols {
        return;
    }
    // Householder QR: the same R and Qᵀr as Givens rotations (up to signs), in
    // fewer passes over the tall matrix.
    let qr = nalgebra::linalg::QR::new(std::mem::replace(h_x, DMatrix::zeros(0, 0)));
    qr.q_tr_mul(res);
    *h_x = qr.r();
    let taken = std::mem::replace(res, DVector::zeros(0));
    *res = taken.resize_vertically(n_cols, 0.0);
}

/// Removes the first `count` rows of `h` and `v`, reusing their buffers.
fn drop_leading_rows(h: &mut DMatrix<f64>, v: &mut DVector<f64>, count: usize) {
    let count = count.min(h.nrows());
    let taken = std::mem::replace(h, DMatrix::zeros(0, 0));
    *h = taken.remove_rows(0, count);
    let taken = std::mem::replace(v, DVector::zeros(0));
    let count = count.min(taken.len());
    *v = taken.remove_rows(0, count);
}

#[cfg(test)]
mod tests {
    use super::*;
    use rand::{Rng, SeedableRng};
    use rand_chacha::ChaCha8Rng;

    fn random_matrix(rng: &mut ChaCha8Rng, rows: usize, cols: usize) -> DMatrix<f64> {
        DMatrix::from_fn(rows, cols, |_, _| rng.random_range(-1.0..1.0))
    }

    fn random_vector(rng: &mut ChaCha8Rng, rows: usize) -> DVector<f64> {
        DVector::from_fn(rows, |_, _| rng.random_range(-1.0..1.0))
    }

    /// `[H_x | I_m]`: after a row transform, the identity block holds `Qᵀ` rows.
    fn with_identity(h_x: &DMatrix<f64>) -> DMatrix<f64> {
        let m = h_x.nrows();
        let c = h_x.ncols();
        let mut out = DMatrix::zeros(m, c + m);
        out.view_mut((0, 0), (m, c)).copy_from(h_x);
        out.view_mut((0, c), (m, m)).fill_with_identity();
        out
    }

    #[test]
    fn projected_rows_annihilate_the_feature_jacobian_and_are_orthonormal() {
        let mut rng = ChaCha8Rng::seed_from_u64(10);
        for (m, k, c) in [(4, 3, 7), (10, 3, 15), (22, 3, 100), (9, 1, 4), (12, 5, 6)] {
            let h_f0 = random_matrix(&mut rng, m, k);
            let h_x0 = random_matrix(&mut rng, m, c);
            let r0 = random_vector(&mut rng, m);
            let mut h_f = h_f0.clone();
            let mut h_x = with_identity(&h_x0);
            let mut r = r0.clone();
            nullspace_project_in_place(&mut h_f, &mut h_x, &mut r);
            assert_eq!(h_x.nrows(), m - k);
            assert_eq!(r.len(), m - k);
            let q2t = h_x.columns(c, m).into_owned();
            assert!((&q2t * &h_f0).norm() < 1e-10, "Q2ᵀ H_f != 0");
            let gram = &q2t * q2t.transpose();
            assert!((gram - DMatrix::identity(m - k, m - k)).norm() < 1e-12);
            assert!((h_x.columns(0, c) - &q2t * &h_x0).norm() < 1e-12);
            assert!((&r - &q2t * &r0).norm() < 1e-12);
        }
    }

    #[test]
    fn feature_jacobian_becomes_upper_triangular_with_the_same_gram_matrix() {
        let mut rng = ChaCha8Rng::seed_from_u64(11);
        let (m, k) = (14, 3);
        let h_f0 = random_matrix(&mut rng, m, k);
        let mut h_f = h_f0.clone();
        let mut h_x = random_matrix(&mut rng, m, 5);
        let mut r = random_vector(&mut rng, m);
        nullspace_project_in_place(&mut h_f, &mut h_x, &mut r);
        for j in 0..k {
            for i in j + 1..m {
                assert_eq!(h_f[(i, j)], 0.0, "entry ({i}, {j}) not zeroed");
            }
        }
        let top = h_f.rows(0, k).into_owned();
        let err = (top.transpose() * &top - h_f0.transpose() * &h_f0).norm();
        assert!(err < 1e-12, "RᵀR != H_fᵀH_f: {err}");
    }

    #[test]
    fn projected_residual_norm_is_the_norm_of_the_residual_orthogonal_to_the_feature_columns() {
        let mut rng = ChaCha8Rng::seed_from_u64(12);
        for _ in 0..20 {
            let (m, k) = (rng.random_range(4..23), 3);
            let h_f0 = random_matrix(&mut rng, m, k);
            let r0 = random_vector(&mut rng, m);
            let normal = h_f0.transpose() * &h_f0;
            let coef = normal
                .lu()
                .solve(&(h_f0.transpose() * &r0))
                .unwrap_or_else(|| DVector::zeros(k));
            let orth = &r0 - &h_f0 * coef;
            let mut h_f = h_f0.clone();
            let mut h_x = random_matrix(&mut rng, m, 2);
            let mut r = r0.clone();
            nullspace_project_in_place(&mut h_f, &mut h_x, &mut r);
            assert!((r.norm() - orth.norm()).abs() < 1e-12);
        }
    }

    #[test]
    fn qr_split_keeps_all_rows_and_its_top_rows_carry_the_feature() {
        let mut rng = ChaCha8Rng::seed_from_u64(13);
        let (m, k, c) = (12, 3, 6);
        let h_f0 = random_matrix(&mut rng, m, k);
        let h_x0 = random_matrix(&mut rng, m, c);
        let r0 = random_vector(&mut rng, m);
        let mut h_f = h_f0.clone();
        let mut h_x = with_identity(&h_x0);
        let mut r = r0.clone();
        let top = givens_qr_split(&mut h_f, &mut h_x, &mut r);
        assert_eq!(top, k);
        assert_eq!(h_x.nrows(), m);
        let qt = h_x.columns(c, m).into_owned();
        assert!((&qt * qt.transpose() - DMatrix::identity(m, m)).norm() < 1e-12);
        // Qᵀ H_f = [R; 0] and the top rows reproduce R.
        let qt_hf = &qt * &h_f0;
        assert!((&qt_hf - &h_f).norm() < 1e-12);
        assert!(qt_hf.rows(k, m - k).norm() < 1e-12);
        assert!((&r - &qt * &r0).norm() < 1e-12);
        // The delayed-initialization system R δp_f = Q₁ᵀ r - Q₁ᵀ H_x δx is solvable.
        assert!(h_f.rows(0, k).determinant().abs() > 1e-9);
    }

    #[test]
    fn projection_of_a_system_without_redundancy_leaves_nothing() {
        let mut rng = ChaCha8Rng::seed_from_u64(14);
        let mut h_f = random_matrix(&mut rng, 3, 3);
        let mut h_x = random_matrix(&mut rng, 3, 8);
        let mut r = random_vector(&mut rng, 3);
        nullspace_project_in_place(&mut h_f, &mut h_x, &mut r);
        assert_eq!(h_x.shape(), (0, 8));
        assert_eq!(r.len(), 0);
    }

    #[test]
    fn compression_preserves_the_information_and_keeps_one_row_per_column() {
        let mut rng = ChaCha8Rng::seed_from_u64(15);
        for (m, c) in [(30, 10), (200, 100), (11, 10)] {
            let mut h0 = random_matrix(&mut rng, m, c);
            // Sparse columns, as in a real stacked MSCKF Jacobian.
            for i in 0..m / 2 {
                h0[(i, c - 1)] = 0.0;
            }
            let r0 = random_vector(&mut rng, m);
            let mut h = h0.clone();
            let mut r = r0.clone();
            compress_in_place(&mut h, &mut r);
            assert_eq!(h.shape(), (c, c));
            assert_eq!(r.len(), c);
            let info_err = (h.transpose() * &h - h0.transpose() * &h0).norm();
            let vec_err = (h.transpose() * &r - h0.transpose() * &r0).norm();
            let scale = 1.0 + (h0.transpose() * &h0).norm();
            assert!(info_err < 1e-9 * scale, "HᵀH changed by {info_err}");
            assert!(vec_err < 1e-9 * scale, "Hᵀr changed by {vec_err}");
            for j in 0..c {
                for i in j + 1..c {
                    assert_eq!(h[(i, j)], 0.0);
                }
            }
        }
    }

    #[test]
    fn compression_of_a_rank_deficient_jacobian_preserves_the_information() {
        let mut rng = ChaCha8Rng::seed_from_u64(16);
        let (m, c) = (25, 8);
        let mut h0 = random_matrix(&mut rng, m, c);
        h0.column_mut(2).fill(0.0);
        let dup = h0.column(0).into_owned();
        h0.column_mut(5).copy_from(&dup);
        let r0 = random_vector(&mut rng, m);
        let mut h = h0.clone();
        let mut r = r0.clone();
        compress_in_place(&mut h, &mut r);
        assert_eq!(h.shape(), (c, c));
        assert!((h.transpose() * &h - h0.transpose() * &h0).norm() < 1e-9);
        assert!((h.transpose() * &r - h0.transpose() * &r0).norm() < 1e-9);
    }

    #[test]
    fn compression_leaves_a_wide_system_unchanged() {
        let mut rng = ChaCha8Rng::seed_from_u64(17);
        let h0 = random_matrix(&mut rng, 5, 9);
        let r0 = random_vector(&mut rng, 5);
        let mut h = h0.clone();
        let mut r = r0.clone();
        compress_in_place(&mut h, &mut r);
        assert_eq!(h, h0);
        assert_eq!(r, r0);
    }
}
