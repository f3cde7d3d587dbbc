//! Chi-square quantiles for the Mahalanobis gating of updates.
//!
//! [`chi2_quantile`] inverts the chi-square CDF `P(ν/2, x/2)` (the regularized
//! lower incomplete gamma function) with a bracketed Newton iteration;
//! [`Chi2Table`] caches the quantiles of one probability for the degrees of
//! freedom an update usually has.

/// Lanczos coefficients for `g = 7`, `n = 9` (about 15 significant digits).
const LANCZOS_G: f64 = 7.0;
/// Lanczos series coefficients.
const LANCZOS_COEF: [f64; 9] = [
    0.999_999_999_999_809_9,
    676.520_368_121_885_1,
    -1_259.139_216_722_402_8,
    771.323_428_777_653_1,
    -176.615_029_162_140_6,
    12.507_343_278_686_905,
    -0.138_571_095_265_720_12,
    9.984_369_578_019_572e-6,
    1.505_632_735_149_311_6e-7,
];

/// Relative accuracy of the incomplete gamma series and continued fraction.
const GAMMA_EPS: f64 = 1e-16;
/// Iteration cap of the series and the continued fraction (they need about
/// `10 + 3√a` terms, so this covers `a` up to about 10⁷).
const GAMMA_MAX_ITER: usize = 10_000;
/// Smallest magnitude the modified Lentz algorithm lets a denominator reach.
const TINY: f64 = 1e-300;
/// Relative width at which the quantile search stops.
const QUANTILE_RTOL: f64 = 1e-13;
/// Iteration cap of the quantile search (bisection alone needs about 60-1100).
const QUANTILE_MAX_ITER: usize = 2_000;

/// Natural logarithm of the gamma function for `x > 0` (Lanczos approximation,
/// relative error about 1e-15).
pub fn ln_gamma(x: f64) -> f64 {
    if x < 0.5 {
        // Reflection: Γ(x) Γ(1 - x) = π / sin(πx).
        let pi = std::f64::consts::PI;
        return (pi / (pi * x).sin()).ln() - ln_gamma(1.0 - x);
    }
    let x = x - 1.0;
    let mut sum = LANCZOS_COEF[0];
    for (i, c) in LANCZOS_COEF.iter().enumerate().skip(1) {
        sum += c / (x + i as f64);
    }
    let t = x + LANCZOS_G + 0.5;
    0.5 * (2.0 * std::f64::consts::PI).ln() + (x + 0.5) * t.ln() - t + sum.ln()
}

/// The regularized lower incomplete gamma function `P(a, x)` for `a > 0`,
/// `x >= 0`: the series for `x < a + 1`, else `1 - Q` with `Q` from a continued
/// fraction. Returns NaN for invalid arguments.
pub fn gamma_p(a: f64, x: f64) -> f64 {
    if a.is_nan() || x.is_nan() || a <= 0.0 || x < 0.0 {
        return f64::NAN;
    }
    if x == 0.0 {
        return 0.0;
    }
    if x == f64::INFINITY {
        return 1.0;
    }
    if x < a + 1.0 {
        gamma_p_series(a, x)
    } else {
        1.0 - gamma_q_continued_fraction(a, x)
    }
}

/// `exp(-x + a ln x - ln Γ(a))`, the common prefactor of the two expansions.
fn gamma_prefactor(a: f64, x: f64) -> f64 {
    (-x + a * x.ln() - ln_gamma(a)).exp()
}

/// `P(a, x)` by its power series (converges fast for `x < a + 1`).
fn gamma_p_series(a: f64, x: f64) -> f64 {
    let mut denom = a;
    let mut term = 1.0 / a;
    let mut sum = term;
    for _ in 0..GAMMA_MAX_ITER {
        denom += 1.0;
        term *= x / denom;
        sum += term;
        if term.abs() < sum.abs() * GAMMA_EPS {
            break;
        }
    }
    sum * gamma_prefactor(a, x)
}

/// `Q(a, x) = 1 - P(a, x)` by its continued fraction (modified Lentz), for
/// `x >= a + 1`.
fn gamma_q_continued_fraction(a: f64, x: f64) -> f64 {
    let mut b = x + 1.0 - a;
    let mut c = 1.0 / TINY;
    let mut d = 1.0 / b;
    let mut h = d;
    for i in 1..=GAMMA_MAX_ITER {
        let an = -(i as f64) * (i as f64 - a);
        b += 2.0;
        d = an * d + b;
        if d.abs() < TINY {
            d = TINY;
        }
        c = b + an / c;
        if c.abs() < TINY {
            c = TINY;
        }
        d = 1.0 / d;
        let delta = d * c;
        h *= delta;
        if (delta - 1.0).abs() < GAMMA_EPS {
            break;
        }
    }
    gamma_prefactor(a, x) * h
}

/// The chi-square CDF with `dof` degrees of freedom at `x`.
pub fn chi2_cdf(dof: usize, x: f64) -> f64 {
    if x <= 0.0 {
        return 0.0;
    }
    gamma_p(0.5 * dof as f64, 0.5 * x)
}

/// The chi-square density with `dof` degrees of freedom at `x > 0`.
fn chi2_pdf(dof: usize, x: f64) -> f64 {
    let a = 0.5 * dof as f64;
    let half = 0.5 * x;
    ((a - 1.0) * half.ln() - half - ln_gamma(a)).exp() * 0.5
}

/// The `p`-quantile of the chi-square distribution with `dof` degrees of
/// freedom: the `x` with `P(dof/2, x/2) = p`, to about 1e-12 relative.
///
/// Edge cases: `dof == 0` or `p <= 0` gives `0`, `p >= 1` gives `+∞`, and a NaN
/// `p` gives NaN.
pub fn chi2_quantile(dof: usize, p: f64) -> f64 {
    if p.is_nan() {
        return f64::NAN;
    }
    if dof == 0 || p <= 0.0 {
        return 0.0;
    }
    if p >= 1.0 {
        return f64::INFINITY;
    }
    let f = |x: f64| chi2_cdf(dof, x) - p;
    // Bracket [lo, hi] with f(lo) < 0 <= f(hi).
    let mut lo = 0.0;
    let mut hi = (dof as f64).max(1.0);
    while f(hi) < 0.0 {
        lo = hi;
        hi *= 2.0;
        if !hi.is_finite() {
            return f64::INFINITY;
        }
    }
    // Newton from the mean, falling back to bisection when a step leaves the
    // bracket or does not shrink it fast enough.
    let mut x = (dof as f64).clamp(lo, hi);
    if x <= lo || x >= hi {
        x = 0.5 * (lo + hi);
    }
    for _ in 0..QUANTILE_MAX_ITER {
        let fx = f(x);
        if fx == 0.0 {
            return x;
        }
        if fx < 0.0 {
            lo = x;
        } else {
            hi = x;
        }
        if hi - lo <= QUANTILE_RTOL * hi {
            break;
        }
        let slope = chi2_pdf(dof, x);
        let newton = x - fx / slope;
        let step_ok = slope > 0.0 && newton.is_finite() && newton > lo && newton < hi;
        let next = if step_ok { newton } else { 0.5 * (lo + hi) };
        if (next - x).abs() <= QUANTILE_RTOL * x {
            return next;
        }
        x = next;
    }
    0.5 * (lo + hi)
}

/// Cached chi-square quantiles of one probability for `1..=max_dof` degrees of
/// freedom; larger degrees of freedom are computed on demand.
#[derive(Clone, Debug, PartialEq)]
pub struct Chi2Table {
    /// The probability of every quantile.
    p: f64,
    /// `quantiles[d]` is the quantile for `d` degrees of freedom (`[0] = 0`).
    quantiles: Vec<f64>,
}

impl Chi2Table {
    /// Precomputes the `p`-quantiles for `1..=max_dof` degrees of freedom
    /// (about 10 µs per entry).
    pub fn new(p: f64, max_dof: usize) -> Self {
        let quantiles = (0..=max_dof).map(|d| chi2_quantile(d, p)).collect();
        Self { p, quantiles }
    }

    /// The probability of the table.
    pub fn probability(&self) -> f64 {
        self.p
    }

    /// The largest cached degrees of freedom.
    pub fn max_dof(&self) -> usize {
        self.quantiles.len().saturating_sub(1)
    }

    /// The `p`-quantile for `dof` degrees of freedom (cached up to
    /// [`Chi2Table::max_dof`], computed above it).
    pub fn get(&self, dof: usize) -> f64 {
        match self.quantiles.get(dof) {
            Some(&q) => q,
            None => chi2_quantile(dof, self.p),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn assert_rel(actual: f64, expected: f64, rtol: f64) {
        let rel = ((actual - expected) / expected).abs();
        assert!(rel < rtol, "{actual} vs {expected}: relative error {rel}");
    }

    #[test]
    fn quantiles_match_published_table_values() {
        let cases = [
            (1, 0.95, 3.841_459),
            (2, 0.95, 5.991_465),
            (3, 0.95, 7.814_728),
            (10, 0.95, 18.307_038),
            (100, 0.95, 124.342_113),
            (3, 0.025, 0.215_795),
            (3, 0.975, 9.348_404),
        ];
        for (dof, p, expected) in cases {
            let q = chi2_quantile(dof, p);
            // The references are rounded to 6 decimals.
            assert!(
                (q - expected).abs() <= 5e-7 + 1e-6 * expected,
                "{q} vs {expected}"
            );
        }
    }

    #[test]
    fn two_degrees_of_freedom_have_a_closed_form_quantile() {
        // P(1, x/2) = 1 - exp(-x/2), so the quantile is -2 ln(1 - p).
        for p in [1e-6, 0.01, 0.3, 0.5, 0.9, 0.95, 0.99, 0.999_999] {
            assert_rel(chi2_quantile(2, p), -2.0 * (-p).ln_1p(), 1e-11);
        }
    }

    #[test]
    fn ln_gamma_matches_factorials_and_the_half_integer_value() {
        let mut fact: f64 = 1.0;
        for n in 1..30 {
            // Γ(n) = (n-1)!
            assert_rel(ln_gamma(n as f64).exp(), fact, 1e-13);
            fact *= n as f64;
        }
        assert_rel(ln_gamma(0.5), std::f64::consts::PI.sqrt().ln(), 1e-14);
        assert_rel(ln_gamma(0.1).exp(), 9.513_507_698_668_732, 1e-13);
    }

    #[test]
    fn cdf_of_the_quantile_returns_the_probability_for_many_degrees_of_freedom() {
        for dof in [1, 2, 3, 5, 7, 15, 40, 99, 250, 600, 1000, 5000] {
            for p in [0.001, 0.025, 0.5, 0.95, 0.99, 0.999] {
                let x = chi2_quantile(dof, p);
                assert!((chi2_cdf(dof, x) - p).abs() < 1e-12, "dof {dof} p {p}");
            }
        }
    }

    #[test]
    fn large_degrees_of_freedom_agree_with_the_wilson_hilferty_approximation() {
        // z(0.95) = 1.644854; the approximation is accurate to ~1e-4 here.
        let z = 1.644_853_626_951_472_2;
        for dof in [500usize, 1000, 3000] {
            let k = dof as f64;
            let w = k * (1.0 - 2.0 / (9.0 * k) + z * (2.0 / (9.0 * k)).sqrt()).powi(3);
            assert_rel(chi2_quantile(dof, 0.95), w, 1e-4);
        }
    }

    #[test]
    fn edge_cases_give_zero_infinity_or_nan() {
        assert_eq!(chi2_quantile(0, 0.95), 0.0);
        assert_eq!(chi2_quantile(3, 0.0), 0.0);
        assert_eq!(chi2_quantile(3, 1.0), f64::INFINITY);
        assert!(chi2_quantile(3, f64::NAN).is_nan());
        assert!(gamma_p(-1.0, 1.0).is_nan());
    }

    #[test]
    fn table_caches_the_quantiles_and_computes_beyond_its_range() {
        let table = Chi2Table::new(0.95, 1000);
        assert_eq!(table.max_dof(), 1000);
        assert_eq!(table.probability(), 0.95);
        assert!((table.get(3) - 7.814_728).abs() < 1e-6);
        assert!((table.get(100) - 124.342_113).abs() < 1e-6);
        assert_eq!(table.get(1000), chi2_quantile(1000, 0.95));
        assert_eq!(table.get(1500), chi2_quantile(1500, 0.95));
        assert_eq!(table.get(0), 0.0);
        let mut last = 0.0;
        for d in 1..=1000 {
            assert!(table.get(d) > last, "quantiles must increase with dof");
            last = table.get(d);
        }
    }
}
