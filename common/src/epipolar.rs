//! Two-view geometry for verifying feature matches: the fundamental matrix from
//! eight or more correspondences (Hartley-normalized eight-point algorithm with the
//! rank-2 constraint), its Sampson error, and a seeded RANSAC around them (thesis
//! Section 4.4.1: a loop-closure candidate is accepted only when enough of its
//! descriptor matches agree on one epipolar geometry).
//!
//! Points are undistorted normalized image coordinates `[x/z, y/z]`, so the
//! matrix is in fact an essential matrix up to scale; the eight-point solver does
//! not rely on that, which keeps it usable on pixel coordinates too. The
//! convention is `x₂ᵀ F x₁ = 0` for a point seen at `x₁` in the first view and
//! `x₂` in the second.

use nalgebra::{Matrix3, SMatrix, SVector, Vector2, Vector3};
use rand::seq::index::sample;
use rand::SeedableRng;
use rand_chacha::ChaCha8Rng;
use thiserror::Error;

/// Fewest correspondences the eight-point solver accepts.
pub const MIN_POINTS: usize = 8;

/// Why no fundamental matrix was found.
#[derive(Debug, Error, Clone, PartialEq)]
pub enum EpipolarError {
    /// Fewer correspondences than the solver needs.
    #[error("{got} correspondences, at least {MIN_POINTS} needed")]
    TooFewPoints {
        /// Correspondences given.
        got: usize,
    },
    /// The two point lists differ in length.
    #[error("{first} points in the first view, {second} in the second")]
    LengthMismatch {
        /// First view.
        first: usize,
        /// Second view.
        second: usize,
    },
    /// A coordinate is NaN or infinite.
    #[error("correspondence {index} has a non-finite coordinate")]
    NonFinite {
        /// Its index.
        index: usize,
    },
    /// The points are degenerate (e.g. all identical): no unique solution.
    #[error("degenerate point configuration")]
    Degenerate,
}

/// Settings of [`ransac_fundamental`].
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct RansacParams {
    /// Inlier threshold on the Sampson distance, in the points' units (for
    /// normalized coordinates: pixels divided by the focal length).
    pub threshold: f64,
    /// Most hypotheses tried.
    pub max_iterations: usize,
    /// Wanted probability of drawing at least one all-inlier sample (adapts the
    /// number of iterations to the inlier ratio found so far).
    pub confidence: f64,
    /// Seed of the sampler (the same inputs and seed give the same result).
    pub seed: u64,
}

impl Default for RansacParams {
    /// 1.5 px at a 460 px focal length, 200 hypotheses, 99 % confidence, seed 0.
    fn default() -> Self {
        Self {
            threshold: 1.5 / 460.0,
            max_iterations: 200,
            confidence: 0.99,
            seed: 0,
        }
    }
}

/// A fundamental matrix and the correspondences that agree with it.
#[derive(Clone, Debug, PartialEq)]
pub struct FundamentalFit {
    /// `F`, with `x₂ᵀ F x₁ = 0`, unit Frobenius norm, rank 2.
    pub f: Matrix3<f64>,
    /// Per correspondence: within the threshold.
    pub inliers: Vec<bool>,
    /// Number of inliers.
    pub inlier_count: usize,
}

fn check(x1: &[Vector2<f64>], x2: &[Vector2<f64>]) -> Result<(), EpipolarError> {
    if x1.len() != x2.len() {
        return Err(EpipolarError::LengthMismatch {
            first: x1.len(),
            second: x2.len(),
        });
    }
    if x1.len() < MIN_POINTS {
        return Err(EpipolarError::TooFewPoints { got: x1.len() });
    }
    if let Some(index) = x1
        .iter()
        .zip(x2)
        .position(|(a, b)| !(a.iter().chain(b.iter()).all(|v| v.is_finite())))
    {
        return Err(EpipolarError::NonFinite { index });
    }
    Ok(())
}

/// Hartley's normalization: the similarity moving the centroid to the origin and
/// scaling the mean distance to √2.
fn normalizer(pts: &[Vector2<f64>]) -> Option<Matrix3<f64>> {
    let n = pts.len() as f64;
    let c = pts.iter().fold(Vector2::zeros(), |a, p| a + p) / n;
    let mean_dist = pts.iter().map(|p| (p - c).norm()).sum::<f64>() / n;
    if mean_dist <= f64::EPSILON {
        return None;
    }
    let s = std::f64::consts::SQRT_2 / mean_dist;
    Some(Matrix3::new(
        s,
        0.0,
        -s * c.x,
        0.0,
        s,
        -s * c.y,
        0.0,
        0.0,
        1.0,
    ))
}

/// The eight-point solution from all given correspondences (least squares; for
/// exactly eight, the exact solve of a RANSAC hypothesis), with the rank-2
/// constraint enforced.
pub fn fundamental_eight_point(
    x1: &[Vector2<f64>],
    x2: &[Vector2<f64>],
) -> Result<Matrix3<f64>, EpipolarError> {
    check(x1, x2)?;
    let (t1, t2) = match (normalizer(x1), normalizer(x2)) {
        (Some(a), Some(b)) => (a, b),
        _ => return Err(EpipolarError::Degenerate),
    };
    let row = |a: &Vector2<f64>, b: &Vector2<f64>| design_row(&t1, &t2, a, b);
    let f = if x1.len() == MIN_POINTS {
        minimal_null_vector(x1, x2, row)
    } else {
        least_squares_null_vector(x1, x2, row)
    }
    .ok_or(EpipolarError::Degenerate)?;
    let f_hat = Matrix3::new(f[0], f[1], f[2], f[3], f[4], f[5], f[6], f[7], f[8]);
    // Rank 2: zero the smallest singular value.
    let svd = f_hat.svd(true, true);
    let (Some(u), Some(v_t)) = (svd.u, svd.v_t) else {
        return Err(EpipolarError::Degenerate);
    };
    let mut s = svd.singular_values;
    let (imin, _) = s
        .iter()
        .enumerate()
        .min_by(|a, b| a.1.total_cmp(b.1))
        .ok_or(EpipolarError::Degenerate)?;
    s[imin] = 0.0;
    let f_rank2 = u * Matrix3::from_diagonal(&s) * v_t;
    let f = t2.transpose() * f_rank2 * t1;
    let norm = f.norm();
    if !(norm > 0.0 && norm.is_finite()) {
        return Err(EpipolarError::Degenerate);
    }
    Ok(f / norm)
}

/// One correspondence's row of the eight-point system `A f = 0` (`x₂ᵀ F x₁ = 0`
/// with `f` the rows of `F`), in the Hartley-normalized coordinates `t1`, `t2`.
fn design_row(
    t1: &Matrix3<f64>,
    t2: &Matrix3<f64>,
    a: &Vector2<f64>,
    b: &Vector2<f64>,
) -> SVector<f64, 9> {
    let p = t1 * Vector3::new(a.x, a.y, 1.0);
    let q = t2 * Vector3::new(b.x, b.y, 1.0);
    SVector::<f64, 9>::from_column_slice(&[
        q.x * p.x,
        q.x * p.y,
        q.x,
        q.y * p.x,
        q.y * p.y,
        q.y,
        p.x,
        p.y,
        1.0,
    ])
}

/// The null vector of the 8 x 9 system of a minimal sample (a RANSAC
/// hypothesis): from the thin QR of Aᵀ, whose 8 columns of Q span A's row space,
/// the basis vector least inside that span, minus its projection onto it. No
/// 9 x 9 eigen-decomposition of AᵀA (it squares the condition number, and it
/// cost a quarter of a cooperative frame in RANSAC).
fn minimal_null_vector(
    x1: &[Vector2<f64>],
    x2: &[Vector2<f64>],
    row: impl Fn(&Vector2<f64>, &Vector2<f64>) -> SVector<f64, 9>,
) -> Option<SVector<f64, 9>> {
    let mut at = SMatrix::<f64, 9, 8>::zeros();
    for (j, (a, b)) in x1.iter().zip(x2).enumerate() {
        at.set_column(j, &row(a, b));
    }
    let q = at.qr().q();
    // The rows' squared norms sum to 8, so the smallest is at most 8/9 and the
    // residual's squared norm at least 1/9: no cancellation.
    let (k, _) = (0..9)
        .map(|k| (k, q.row(k).norm_squared()))
        .min_by(|a, b| a.1.total_cmp(&b.1))?;
    let mut v = -(q * q.row(k).transpose());
    v[k] += 1.0;
    let norm = v.norm();
    (norm.is_finite() && norm > 0.0).then(|| v / norm)
}

/// The least-squares null vector of the n x 9 system (n > 8): the eigenvector of
/// AᵀA (accumulated row by row, so no n x 9 matrix is formed) with the smallest
/// eigenvalue.
fn least_squares_null_vector(
    x1: &[Vector2<f64>],
    x2: &[Vector2<f64>],
    row: impl Fn(&Vector2<f64>, &Vector2<f64>) -> SVector<f64, 9>,
) -> Option<SVector<f64, 9>> {
    let mut ata = SMatrix::<f64, 9, 9>::zeros();
    for (a, b) in x1.iter().zip(x2) {
        let r = row(a, b);
        ata += r * r.transpose();
    }
    let eig = ata.symmetric_eigen();
    let (imin, _) = eig
        .eigenvalues
        .iter()
        .enumerate()
        .min_by(|a, b| a.1.total_cmp(b.1))?;
    Some(eig.eigenvectors.column(imin).into_owned())
}

/// The Sampson distance of one correspondence (first-order geometric error),
/// in the points' units: `(x₂ᵀFx₁)² / ((Fx₁)₁² + (Fx₁)₂² + (Fᵀx₂)₁² + (Fᵀx₂)₂²)`,
/// square-rooted.
pub fn sampson_distance(f: &Matrix3<f64>, x1: &Vector2<f64>, x2: &Vector2<f64>) -> f64 {
    let p = Vector3::new(x1.x, x1.y, 1.0);
    let q = Vector3::new(x2.x, x2.y, 1.0);
    let fp = f * p;
    let ftq = f.transpose() * q;
    let num = q.dot(&fp);
    let den = fp.x * fp.x + fp.y * fp.y + ftq.x * ftq.x + ftq.y * ftq.y;
    if den <= 0.0 {
        return f64::INFINITY;
    }
    (num * num / den).sqrt()
}

fn inliers_of(
    f: &Matrix3<f64>,
    x1: &[Vector2<f64>],
    x2: &[Vector2<f64>],
    threshold: f64,
) -> (Vec<bool>, usize) {
    let inl: Vec<bool> = x1
        .iter()
        .zip(x2)
        .map(|(a, b)| sampson_distance(f, a, b) <= threshold)
        .collect();
    let n = inl.iter().filter(|v| **v).count();
    (inl, n)
}

/// RANSAC over eight-point hypotheses, then a least-squares refit on the inliers
/// of the best one. Deterministic for a given `params.seed`.
pub fn ransac_fundamental(
    x1: &[Vector2<f64>],
    x2: &[Vector2<f64>],
    params: &RansacParams,
) -> Result<FundamentalFit, EpipolarError> {
    check(x1, x2)?;
    let n = x1.len();
    let mut rng = ChaCha8Rng::seed_from_u64(params.seed);
    let mut best: Option<(Matrix3<f64>, usize)> = None;
    let mut needed = params.max_iterations;
    let mut it = 0;
    let (mut s1, mut s2) = (
        Vec::with_capacity(MIN_POINTS),
        Vec::with_capacity(MIN_POINTS),
    );
    while it < needed.min(params.max_iterations) {
        it += 1;
        s1.clear();
        s2.clear();
        for i in sample(&mut rng, n, MIN_POINTS) {
            s1.push(x1[i]);
            s2.push(x2[i]);
        }
        let Ok(f) = fundamental_eight_point(&s1, &s2) else {
            continue;
        };
        let count = x1
            .iter()
            .zip(x2)
            .filter(|(a, b)| sampson_distance(&f, a, b) <= params.threshold)
            .count();
        if best.as_ref().is_none_or(|(_, c)| count > *c) {
            best = Some((f, count));
            // Iterations for `confidence` at this inlier ratio.
            let w = count as f64 / n as f64;
            let p_all = w.powi(MIN_POINTS as i32);
            if p_all >= 1.0 - 1e-12 {
                needed = it;
            } else if p_all > 0.0 {
                let k = (1.0 - params.confidence).ln() / (1.0 - p_all).ln();
                needed = (k.ceil() as usize).max(1);
            }
        }
    }
    let Some((f_best, _)) = best else {
        return Err(EpipolarError::Degenerate);
    };
    let (inl, count) = inliers_of(&f_best, x1, x2, params.threshold);
    // Refit on the inliers when there are enough, and keep it if it is no worse.
    let mut fit = FundamentalFit {
        f: f_best,
        inliers: inl,
        inlier_count: count,
    };
    if count >= MIN_POINTS {
        let (a, b): (Vec<_>, Vec<_>) = x1
            .iter()
            .zip(x2)
            .zip(&fit.inliers)
            .filter(|(_, keep)| **keep)
            .map(|((a, b), _)| (*a, *b))
            .unzip();
        if let Ok(f) = fundamental_eight_point(&a, &b) {
            let (inl, c) = inliers_of(&f, x1, x2, params.threshold);
            if c >= count {
                fit = FundamentalFit {
                    f,
                    inliers: inl,
                    inlier_count: c,
                };
            }
        }
    }
    Ok(fit)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::so3::exp_so3;
    use rand::Rng;

    /// Random points 4-8 m in front of camera 1 seen from camera 2 at
    /// `x_2 = R x_1 + t`, with Gaussian-ish noise (uniform ±noise), normalized.
    fn two_views(
        n: usize,
        noise: f64,
        rng: &mut ChaCha8Rng,
    ) -> (Vec<Vector2<f64>>, Vec<Vector2<f64>>, Matrix3<f64>) {
        let r = exp_so3(&Vector3::new(0.05, -0.2, 0.1));
        let t = Vector3::new(0.8, 0.1, -0.2);
        let (mut a, mut b) = (Vec::new(), Vec::new());
        while a.len() < n {
            let p = Vector3::new(
                rng.random_range(-3.0..3.0),
                rng.random_range(-2.0..2.0),
                rng.random_range(4.0..8.0),
            );
            let q = r * p + t;
            if q.z < 0.5 {
                continue;
            }
            let jitter = |rng: &mut ChaCha8Rng| {
                Vector2::new(
                    rng.random_range(-noise..=noise),
                    rng.random_range(-noise..=noise),
                )
            };
            a.push(Vector2::new(p.x / p.z, p.y / p.z) + jitter(rng));
            b.push(Vector2::new(q.x / q.z, q.y / q.z) + jitter(rng));
        }
        // Essential matrix [t]x R: x₂ᵀ E x₁ = 0.
        let e = crate::so3::skew(&t) * r;
        (a, b, e / e.norm())
    }

    #[test]
    fn eight_point_recovers_the_essential_matrix_from_exact_points() {
        let mut rng = ChaCha8Rng::seed_from_u64(1);
        let (a, b, e) = two_views(20, 0.0, &mut rng);
        let f = fundamental_eight_point(&a, &b).unwrap();
        // Same matrix up to sign.
        let d = (f - e).norm().min((f + e).norm());
        assert!(d < 1e-8, "distance {d}");
        for (p, q) in a.iter().zip(&b) {
            assert!(sampson_distance(&f, p, q) < 1e-10);
        }
    }

    #[test]
    fn the_minimal_solve_agrees_with_least_squares_on_eight_points() {
        let mut rng = ChaCha8Rng::seed_from_u64(5);
        for noise in [0.0, 1.0 / 460.0] {
            let (a, b, _) = two_views(8, noise, &mut rng);
            let f = fundamental_eight_point(&a, &b).unwrap();
            let (t1, t2) = (normalizer(&a).unwrap(), normalizer(&b).unwrap());
            let row = |p: &Vector2<f64>, q: &Vector2<f64>| design_row(&t1, &t2, p, q);
            let exact = minimal_null_vector(&a, &b, row).unwrap();
            let ls = least_squares_null_vector(&a, &b, row).unwrap();
            let d = (exact - ls).norm().min((exact + ls).norm());
            assert!(d < 1e-7, "noise {noise}: null vectors {d} apart");
            // Eight points fit their own hypothesis exactly (before rank 2).
            for (p, q) in a.iter().zip(&b) {
                let r = row(p, q);
                assert!(r.dot(&exact).abs() < 1e-12);
            }
            assert!(f.norm() > 0.99);
        }
    }

    #[test]
    fn ransac_separates_inliers_from_thirty_percent_outliers() {
        let mut rng = ChaCha8Rng::seed_from_u64(2);
        let (mut a, mut b, _) = two_views(70, 0.5 / 460.0, &mut rng);
        let outliers = 30;
        for _ in 0..outliers {
            a.push(Vector2::new(
                rng.random_range(-0.6..0.6),
                rng.random_range(-0.4..0.4),
            ));
            b.push(Vector2::new(
                rng.random_range(-0.6..0.6),
                rng.random_range(-0.4..0.4),
            ));
        }
        let fit = ransac_fundamental(&a, &b, &RansacParams::default()).unwrap();
        let true_in = fit.inliers[..70].iter().filter(|v| **v).count();
        let false_in = fit.inliers[70..].iter().filter(|v| **v).count();
        assert!(true_in >= 68, "{true_in} of 70 inliers kept");
        assert!(false_in <= 2, "{false_in} of 30 outliers accepted");
        // Deterministic for a seed.
        let again = ransac_fundamental(&a, &b, &RansacParams::default()).unwrap();
        assert_eq!(fit, again);
    }

    #[test]
    fn random_correspondences_find_little_support() {
        let mut rng = ChaCha8Rng::seed_from_u64(3);
        let pts = |rng: &mut ChaCha8Rng| -> Vec<Vector2<f64>> {
            (0..60)
                .map(|_| Vector2::new(rng.random_range(-0.6..0.6), rng.random_range(-0.4..0.4)))
                .collect()
        };
        let (a, b) = (pts(&mut rng), pts(&mut rng));
        let fit = ransac_fundamental(&a, &b, &RansacParams::default()).unwrap();
        assert!(fit.inlier_count < 20, "{} inliers", fit.inlier_count);
    }

    #[test]
    fn bad_inputs_are_errors() {
        let p = vec![Vector2::new(0.1, 0.2); 8];
        assert_eq!(
            fundamental_eight_point(&p[..5], &p[..5]),
            Err(EpipolarError::TooFewPoints { got: 5 })
        );
        assert!(matches!(
            fundamental_eight_point(&p, &p[..7]),
            Err(EpipolarError::LengthMismatch { .. })
        ));
        assert_eq!(
            fundamental_eight_point(&p, &p),
            Err(EpipolarError::Degenerate)
        );
        let mut q = p.clone();
        q[3].x = f64::NAN;
        assert_eq!(
            ransac_fundamental(&q, &p, &RansacParams::default()),
            Err(EpipolarError::NonFinite { index: 3 })
        );
    }
}
