//! The covariance update's dense kernel, `P ← P − Wᵀ W` on the lower triangle,
//! with nalgebra (what the estimator uses: `covariance::subtract_gram_lower`,
//! matrixmultiply's gemm in column blocks) against faer's triangular matmul, on
//! the sizes the estimator meets (issue 3: "measure whether a faster dense kernel
//! pays off for the covariance update").
//!
//! `cargo bench -p agent --features faer-bench --bench covariance_kernel [--
//! ROUNDS]` (default 2000 products per case; the feature is what pulls faer in).
//!
//! Sizes, measured on V1_01 seed 1: with 50 SLAM features the state has n = 243
//! (p50) and an update m = 22 rows (p50; mean 48, p90 92), 2.75 updates per
//! frame; MSCKF only, n = 102 and m = 86 (p50), 0.9 per frame. Both kernels run
//! on the same matrices, alternately, single-threaded, and their results are
//! compared.
use agent::estimator::covariance::subtract_gram_lower;
use faer::linalg::matmul::triangular::{matmul, BlockStructure};
use faer::{Accum, MatMut, MatRef, Par};
use nalgebra::DMatrix;
use std::time::Instant;

/// `P ← P − Wᵀ W` on the lower triangle with faer, on views of nalgebra's
/// column-major storage (no copy).
fn faer_subtract_gram_lower(p: &mut DMatrix<f64>, w: &DMatrix<f64>) {
    let (m, n) = w.shape();
    let w = MatRef::from_column_major_slice(w.as_slice(), m, n);
    let p = MatMut::from_column_major_slice_mut(p.as_mut_slice(), n, n);
    matmul(
        p,
        BlockStructure::TriangularLower,
        Accum::Add,
        w.transpose(),
        BlockStructure::Rectangular,
        w,
        BlockStructure::Rectangular,
        -1.0,
        Par::Seq,
    );
}

/// A deterministic symmetric positive-definite `n x n` matrix and an `m x n` one.
fn case(n: usize, m: usize) -> (DMatrix<f64>, DMatrix<f64>) {
    let mut x = 0x9e37_79b9_7f4a_7c15_u64;
    let mut next = move || {
        x ^= x << 13;
        x ^= x >> 7;
        x ^= x << 17;
        (x >> 11) as f64 / (1u64 << 53) as f64 - 0.5
    };
    let a = DMatrix::from_fn(n, n, |_, _| next());
    let p = &a * a.transpose() + DMatrix::identity(n, n) * n as f64;
    let w = DMatrix::from_fn(m, n, |_, _| next() * 0.1);
    (p, w)
}

fn micros_per_call(rounds: usize, mut f: impl FnMut()) -> f64 {
    let t = Instant::now();
    for _ in 0..rounds {
        f();
    }
    t.elapsed().as_secs_f64() * 1e6 / rounds as f64
}

fn main() {
    let rounds: usize = std::env::args()
        .skip(1)
        .find_map(|a| a.parse().ok())
        .unwrap_or(2000);
    println!("P <- P - W^T W, lower triangle, one thread, {rounds} calls per case (us per call)");
    println!("    n     m   nalgebra     faer   faer/nalgebra   max |diff|");
    for (n, m) in [
        (102, 22),
        (102, 86),
        (243, 22),
        (243, 48),
        (243, 92),
        (252, 200),
    ] {
        let (p0, w) = case(n, m);
        // Same result first (lower triangles).
        let (mut pa, mut pb) = (p0.clone(), p0.clone());
        subtract_gram_lower(&mut pa, &w);
        faer_subtract_gram_lower(&mut pb, &w);
        let diff = (0..n)
            .flat_map(|j| (j..n).map(move |i| (i, j)))
            .map(|ij| (pa[ij] - pb[ij]).abs())
            .fold(0.0, f64::max);
        // Alternate the kernels in chunks, on fresh copies, so a noisy
        // machine hits both alike.
        let (mut t_na, mut t_fa) = (0.0, 0.0);
        let chunks = 10;
        for _ in 0..chunks {
            let mut p = p0.clone();
            t_na += micros_per_call(rounds / chunks, || subtract_gram_lower(&mut p, &w));
            let mut p = p0.clone();
            t_fa += micros_per_call(rounds / chunks, || faer_subtract_gram_lower(&mut p, &w));
        }
        let (t_na, t_fa) = (t_na / chunks as f64, t_fa / chunks as f64);
        println!(
            "{n:>5} {m:>5} {t_na:>10.1} {t_fa:>8.1} {:>15.2} {diff:>12.1e}",
            t_fa / t_na
        );
    }
}
