//! The one-dimensional search behind the CI weights chosen per update
//! (`updater_ci`): the weight `ω ∈ [ω_min, 1 − ω_min]` that minimizes a
//! unimodal objective.
//!
//! The search runs over `u = ln(ω / (1 − ω))`: a step in `u` is a relative
//! change of `ω` near 0 and of the peers' share `1 − ω` near 1, so a share of
//! 1e-4 is resolved as well as one of 0.5 (an absolute tolerance on `ω` either
//! wastes evaluations in the middle or cannot tell 1e-4 from 2e-4 at the end).
//!
//! Each evaluation costs a Cholesky factor of the `m x m` innovation
//! covariance. Many updates of a long mission end at the upper bound (rows
//! that tell our pose little give the peers the least share): two evaluations
//! settle those. The rest go to Brent's method, parabolic steps through the
//! three best points with a golden-section step whenever a parabola is not to
//! be trusted. Over the 5 443 CI updates of two seeds of the EuRoC fleet
//! (stop 49) that took 8.4 evaluations on average (2 at the bound, 11-26
//! inside), against about 31 for the golden-section search to 1e-6 on `ω` it
//! replaced.

/// Tolerance on `u`: `ω` and `1 − ω` to 0.1 %.
const TOL_U: f64 = 1e-3;

/// `(3 − √5) / 2`, the golden-section fraction.
const GOLDEN: f64 = 0.381_966_011_250_105_1;

fn logit(w: f64) -> f64 {
    (w / (1.0 - w)).ln()
}

fn logistic(u: f64) -> f64 {
    1.0 / (1.0 + (-u).exp())
}

/// The weight in `[w_min, 1 − w_min]` that minimizes `f`, assumed unimodal
/// there (non-finite values count as +∞).
pub(super) fn minimize_weight(w_min: f64, f: impl Fn(f64) -> f64) -> f64 {
    let g = |u: f64| {
        let v = f(logistic(u));
        if v.is_nan() {
            f64::INFINITY
        } else {
            v
        }
    };
    let (lo, hi) = (logit(w_min), logit(1.0 - w_min));
    // Unimodal and no lower one step inside: the minimum is within one
    // tolerance of the bound.
    let at_hi = g(hi);
    if at_hi.is_finite() && at_hi <= g(hi - TOL_U) {
        return logistic(hi);
    }
    logistic(brent(lo, hi, TOL_U, g))
}

/// Brent's minimization of `f` on `[a, b]` to an absolute tolerance `tol`.
fn brent(mut a: f64, mut b: f64, tol: f64, f: impl Fn(f64) -> f64) -> f64 {
    let mut x = a + GOLDEN * (b - a);
    let (mut w, mut v) = (x, x);
    let mut fx = f(x);
    let (mut fw, mut fv) = (fx, fx);
    // `d`: the last step; `e`: the one before, which a parabolic step must
    // halve to be taken (else the search could crawl).
    let (mut d, mut e) = (0.0f64, 0.0f64);
    for _ in 0..200 {
        let mid = 0.5 * (a + b);
        if (x - mid).abs() <= 2.0 * tol - 0.5 * (b - a) {
            break;
        }
        let mut parabolic = false;
        if e.abs() > tol && fx.is_finite() && fw.is_finite() && fv.is_finite() {
            // The vertex of the parabola through (v, fv), (w, fw), (x, fx) is
            // at x + p / q.
            let r = (x - w) * (fx - fv);
            let mut q = (x - v) * (fx - fw);
            let mut p = (x - v) * q - (x - w) * r;
            q = 2.0 * (q - r);
            if q > 0.0 {
                p = -p;
            } else {
                q = -q;
            }
            let before_last = e;
            e = d;
            if p.abs() < (0.5 * q * before_last).abs() && p > q * (a - x) && p < q * (b - x) {
                d = p / q;
                let u = x + d;
                if u - a < 2.0 * tol || b - u < 2.0 * tol {
                    d = tol.copysign(mid - x);
                }
                parabolic = true;
            }
        }
        if !parabolic {
            e = if x >= mid { a - x } else { b - x };
            d = GOLDEN * e;
        }
        let u = if d.abs() >= tol {
            x + d
        } else {
            x + tol.copysign(d)
        };
        let fu = f(u);
        if fu <= fx {
            if u >= x {
                a = x;
            } else {
                b = x;
            }
            (v, fv) = (w, fw);
            (w, fw) = (x, fx);
            (x, fx) = (u, fu);
        } else {
            if u < x {
                a = u;
            } else {
                b = u;
            }
            if fu <= fw || w == x {
                (v, fv) = (w, fw);
                (w, fw) = (u, fu);
            } else if fu <= fv || v == x || v == w {
                (v, fv) = (u, fu);
            }
        }
    }
    x
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::cell::Cell;

    const W_MIN: f64 = 1e-4;

    /// The minimizer of `f` on a fine grid of `u`.
    fn grid_min(f: impl Fn(f64) -> f64) -> f64 {
        let (lo, hi) = (logit(W_MIN), logit(1.0 - W_MIN));
        let n = 200_000;
        (0..=n)
            .map(|i| logistic(lo + (hi - lo) * i as f64 / n as f64))
            .min_by(|a, b| f(*a).total_cmp(&f(*b)))
            .unwrap()
    }

    /// Two weights agree to the search's tolerance in `u`.
    fn close(a: f64, b: f64) -> bool {
        (logit(a) - logit(b)).abs() < 5.0 * TOL_U
    }

    #[test]
    fn it_finds_the_minima_of_the_ci_objectives_shape() {
        // Two states, one measuring row: tr(P⁺) = (u + p)/ω − p² / (ω² s)
        // with s = p / ω + c / (1 − ω) + r, the trace objective's shape (u:
        // the variance of the state the row does not see, which each CI
        // update inflates for nothing; c: the peers' part at unit share; r:
        // the noise). The minimum is inside for the first five, at the upper
        // bound for the last.
        let cases = [
            (1.0, 1.0, 0.2, 0.1),
            (0.1, 1.0, 0.01, 0.01),
            (0.5, 2.0, 1.0, 0.3),
            (0.01, 1.0, 1e-3, 1e-3),
            (1e-5, 1e-4, 1e-5, 1e-6),
            (3.0, 1.0, 0.5, 0.1),
        ];
        for (i, (u, p, c, r)) in cases.into_iter().enumerate() {
            let f = |w: f64| (u + p) / w - p * p / (w * w * (p / w + c / (1.0 - w) + r));
            let best = minimize_weight(W_MIN, f);
            let grid = grid_min(f);
            assert_eq!(i < 5, grid < 0.99, "case {i}: {grid}");
            assert!(close(best, grid), "{best} against the grid's {grid}");
            let gap = (f(best) - f(grid)) / f(grid).abs();
            assert!(gap <= 1e-6, "objective {gap:e} above the grid's");
        }
    }

    #[test]
    fn a_minimum_at_either_bound_is_found() {
        let upper = minimize_weight(W_MIN, |w| -w);
        assert!((upper - (1.0 - W_MIN)).abs() < 1e-12);
        let lower = minimize_weight(W_MIN, |w| w);
        assert!(close(lower, W_MIN), "{lower}");
    }

    #[test]
    fn it_needs_far_fewer_evaluations_than_a_golden_section_search() {
        let calls = Cell::new(0);
        let at_bound = minimize_weight(W_MIN, |w| {
            calls.set(calls.get() + 1);
            1.0 / w
        });
        assert!((at_bound - (1.0 - W_MIN)).abs() < 1e-12);
        assert_eq!(calls.get(), 2, "a minimum at the bound");
        calls.set(0);
        let inside = minimize_weight(W_MIN, |w| {
            calls.set(calls.get() + 1);
            (w.ln() - 0.3f64.ln()).powi(2) + 0.1 * (1.0 - w).ln().powi(2)
        });
        assert!(inside > 0.0 && inside < 1.0);
        // Golden-section search to the same tolerance: ln(18.4 / 1e-3) /
        // ln(1.618) ≈ 21 steps.
        assert!(calls.get() <= 14, "{} evaluations", calls.get());
    }

    #[test]
    fn non_finite_values_are_avoided() {
        // An objective undefined (NaN) or infinite above ω = 0.5.
        let f = |w: f64| {
            if w > 0.5 {
                f64::NAN
            } else {
                (w - 0.2).powi(2)
            }
        };
        let best = minimize_weight(W_MIN, f);
        assert!(close(best, 0.2), "{best}");
        let best = minimize_weight(W_MIN, |w| if w > 0.5 { f64::INFINITY } else { -w });
        assert!(best <= 0.5 && best > 0.49, "{best}");
    }
}
