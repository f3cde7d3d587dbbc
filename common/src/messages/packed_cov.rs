//! A symmetric covariance matrix packed as its row-major lower triangle in `f32`.
//!
//! See the [module documentation](super) for why `f32` is enough on the wire.

use nalgebra::{DMatrix, Dim, Matrix, StorageMut};
use serde::{Deserialize, Serialize};

use super::bounded_vec;
use super::validate::ValidationError;

/// A symmetric `dim x dim` covariance, row-major lower triangle in `f32`:
/// `lower = [P00, P10, P11, P20, P21, P22, …]`, so entry `(i, j)` with `j <= i`
/// is at `i (i + 1) / 2 + j` and `lower.len() == dim (dim + 1) / 2`.
///
/// In a [`super::StateSnapshot`] it is the joint covariance of all clone poses,
/// error order per clone `[δθ (3), δp (3)]` (see [`super::CameraPose`]), so
/// `dim == 6 · clones`.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize, Default)]
pub struct PackedCovariance {
    /// Side of the matrix.
    pub dim: u32,
    /// Row-major lower triangle, `dim (dim + 1) / 2` entries.
    #[serde(deserialize_with = "bounded_vec::deserialize")]
    pub lower: Vec<f32>,
}

impl PackedCovariance {
    /// Number of entries of the packed lower triangle of a `dim x dim` matrix
    /// (saturating, so absurd dimensions cannot overflow).
    pub fn packed_len(dim: usize) -> usize {
        dim.saturating_mul(dim.saturating_add(1)) / 2
    }

    /// Index in [`PackedCovariance::lower`] of entry `(row, col)` (either order).
    pub fn packed_index(row: usize, col: usize) -> usize {
        let (i, j) = if row >= col { (row, col) } else { (col, row) };
        Self::packed_len(i).saturating_add(j)
    }

    /// Packs a square matrix, symmetrizing it as `(P + Pᵀ) / 2` and rounding each
    /// entry to the nearest `f32` (values beyond the `f32` range become infinite
    /// and fail [`super::Envelope::validate`]).
    pub fn from_dmatrix(p: &DMatrix<f64>) -> Result<Self, ValidationError> {
        let (rows, cols) = p.shape();
        if rows != cols {
            return Err(ValidationError::CovarianceNotSquare { rows, cols });
        }
        let dim =
            u32::try_from(rows).map_err(|_| ValidationError::CovarianceNotSquare { rows, cols })?;
        let mut lower = Vec::with_capacity(Self::packed_len(rows));
        for i in 0..rows {
            for j in 0..=i {
                lower.push((0.5 * (p[(i, j)] + p[(j, i)])) as f32);
            }
        }
        Ok(Self { dim, lower })
    }

    /// The full symmetric matrix in `f64`.
    ///
    /// Never panics: for a malformed value (one that fails validation, which
    /// [`super::decode`] never returns) the matrix is the largest leading block
    /// that `lower` actually holds.
    pub fn to_dmatrix(&self) -> DMatrix<f64> {
        let n = self.complete_dim();
        DMatrix::from_fn(n, n, |i, j| {
            self.lower
                .get(Self::packed_index(i, j))
                .map_or(f64::NAN, |&v| f64::from(v))
        })
    }

    /// The full symmetric matrix in `f64`, each variance raised by what `f32`
    /// rounding can have taken from its row, so that the result is at least
    /// the sender's matrix (`P̃ + D ⪰ P`, see [`cover_f32_rounding`]) and
    /// positive definite whenever the sender's was. What a CI participant
    /// must be: covariance intersection is consistent only with covariances
    /// that are no smaller than the truth.
    pub fn to_dmatrix_at_least_sent(&self) -> DMatrix<f64> {
        let mut p = self.to_dmatrix();
        cover_f32_rounding(&mut p);
        p
    }

    /// Entry `(row, col)` (either order); `None` outside the matrix.
    pub fn get(&self, row: usize, col: usize) -> Option<f64> {
        let n = self.dim as usize;
        if row >= n || col >= n {
            return None;
        }
        self.lower
            .get(Self::packed_index(row, col))
            .map(|&v| f64::from(v))
    }

    /// The diagonal entries (variances), as far as `lower` holds them.
    pub fn diagonal(&self) -> impl Iterator<Item = f32> + '_ {
        (0..self.complete_dim()).filter_map(|i| self.lower.get(Self::packed_index(i, i)).copied())
    }

    /// The largest `n <= dim` whose packed triangle fits in `lower`.
    fn complete_dim(&self) -> usize {
        let mut n = self.dim as usize;
        // Only shrinks for malformed values; at most a few steps in practice,
        // and bounded by `dim` in any case.
        if Self::packed_len(n) > self.lower.len() {
            // Solve n (n + 1) / 2 <= len for the largest n, then adjust for rounding.
            let len = self.lower.len() as f64;
            n = n.min(((-1.0 + (1.0 + 8.0 * len).sqrt()) / 2.0) as usize);
            while n > 0 && Self::packed_len(n) > self.lower.len() {
                n -= 1;
            }
        }
        n
    }
}

/// Adds to each diagonal entry of `p`, a matrix whose entries were each
/// rounded to the nearest `f32` from a symmetric `P`, the bound on what that
/// rounding took from its row: `D_ii = ε Σ_j |p_ij| + n δ` with `ε` = `f32`'s
/// epsilon (twice the unit round-off, which also covers `|P_ij| ≤ |p_ij| /
/// (1 − u)`) and `δ` its smallest subnormal. Then `p + D − P = D − E` with
/// `|E_ij| ≤ ε |p_ij|` is diagonally dominant with a non-negative diagonal, so
/// positive semi-definite (Gershgorin): `p + D ⪰ P`.
///
/// Why it matters: a window's clones are correlated to within 1e-7 of 1, so its
/// smallest eigenvalues (the relative poses, the best known directions) are
/// below what rounding moves. Measured on the EuRoC fleet (stop 47), the f64
/// windows' smallest eigenvalue was about 9e-11 and 15 % of the windows came
/// out of `f32` with a negative one (down to −3.8e-10, the largest about 2 px²
/// of the intrinsics). The raise is `ε` (1.2e-7) times the row's absolute sum.
pub fn cover_f32_rounding<R: Dim, C: Dim, S: StorageMut<f64, R, C>>(p: &mut Matrix<f64, R, C, S>) {
    let n = p.nrows().min(p.ncols());
    let eps = f64::from(f32::EPSILON);
    let tiny = n as f64 * f64::from(f32::from_bits(1));
    for i in 0..n {
        let row: f64 = p.row(i).iter().map(|v| v.abs()).sum();
        p[(i, i)] += eps * row + tiny;
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use rand::{Rng, SeedableRng};
    use rand_chacha::ChaCha8Rng;

    /// A window-like covariance: 11 poses that share one large, uncertain
    /// offset and differ by little, in fewer directions than they have (the
    /// smallest eigenvalues 1e-18, far below what rounding moves).
    fn nearly_singular(rng: &mut ChaCha8Rng) -> DMatrix<f64> {
        let n = 66;
        let common = DMatrix::from_fn(n, 6, |i, j| if i % 6 == j { 1e-3 } else { 0.0 });
        let small = DMatrix::from_fn(n, 40, |_, _| rng.random_range(-1.0..1.0)) * 1e-6;
        &common * common.transpose() + &small * small.transpose() + DMatrix::identity(n, n) * 1e-18
    }

    #[test]
    fn covering_the_rounding_gives_at_least_the_sent_matrix() {
        let mut rng = ChaCha8Rng::seed_from_u64(7);
        let mut plain_failed = 0;
        for _ in 0..20 {
            let p = nearly_singular(&mut rng);
            let packed = PackedCovariance::from_dmatrix(&p).unwrap();
            plain_failed += usize::from(packed.to_dmatrix().cholesky().is_none());
            let covered = packed.to_dmatrix_at_least_sent();
            let gap = (&covered - &p).symmetric_eigenvalues().min();
            assert!(gap >= -1e-24, "covered - sent has eigenvalue {gap:e}");
            assert!(covered.cholesky().is_some());
        }
        // The case it is for: rounding alone breaks positive definiteness.
        assert!(plain_failed > 0, "no rounded matrix failed Cholesky");
    }

    #[test]
    fn packs_symmetrizes_and_unpacks() {
        let p = DMatrix::from_row_slice(3, 3, &[4.0, 1.0, 0.5, 1.2, 9.0, -2.0, 0.5, -2.0, 16.0]);
        let packed = PackedCovariance::from_dmatrix(&p).unwrap();
        assert_eq!(packed.dim, 3);
        assert_eq!(packed.lower, vec![4.0, 1.1, 9.0, 0.5, -2.0, 16.0]);
        let back = packed.to_dmatrix();
        assert_eq!(back, back.transpose());
        assert!((back[(0, 1)] - 1.1).abs() < 1e-6);
        assert_eq!(packed.get(2, 1), Some(-2.0));
        assert_eq!(packed.get(1, 2), Some(-2.0));
        assert_eq!(packed.get(3, 0), None);
        assert_eq!(packed.diagonal().collect::<Vec<_>>(), vec![4.0, 9.0, 16.0]);
    }

    #[test]
    fn rejects_non_square() {
        let p = DMatrix::<f64>::zeros(2, 3);
        assert!(matches!(
            PackedCovariance::from_dmatrix(&p),
            Err(ValidationError::CovarianceNotSquare { rows: 2, cols: 3 })
        ));
    }

    #[test]
    fn malformed_values_do_not_panic() {
        let huge = PackedCovariance {
            dim: u32::MAX,
            lower: vec![1.0; 7],
        };
        assert_eq!(huge.to_dmatrix().nrows(), 3);
        let empty = PackedCovariance {
            dim: 5,
            lower: vec![],
        };
        assert_eq!(empty.to_dmatrix().nrows(), 0);
        assert_eq!(empty.get(4, 4), None);
    }

    #[test]
    fn f32_keeps_seven_significant_digits() {
        let v = 1.234_567_891e-9_f64;
        let p = DMatrix::from_element(1, 1, v);
        let back = PackedCovariance::from_dmatrix(&p).unwrap().to_dmatrix()[(0, 0)];
        assert!(((back - v) / v).abs() < 6e-8);
    }
}
