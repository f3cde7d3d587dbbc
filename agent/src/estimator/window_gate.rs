//! The stacked gate of a peer window's rows (`cooperation.window_gate`).
//!
//! Each block of cooperative rows (one common feature, one peer measurement
//! of a SLAM feature, one constraint) passes its own chi-square gate with the
//! innovation covariance of uncorrelated robots. That covariance holds the
//! whole uncertainty of the peer window's pose relative to ours (both
//! robots' unobservable yaw and position priors), so alone a block can ask
//! for almost any relative pose: a wrong link passes with a distance far
//! under its dimension. Stacked, the window's other blocks pin the relative
//! pose down, and the wrong block's rows stand out against them.
//!
//! A window whose stacked distance fails the test loses its blocks one at a
//! time, each time the one whose removal leaves the smallest distance (as a
//! fraction of its limit), until it passes: a failure detection and
//! exclusion, as satellite navigation does with its pseudoranges. Rendered
//! three-robot flights showed it: windows at 30-170 over 8-24 rows fell to
//! 0.2-15 without one block that alone gave, in most, 0.0-1.4 over 3 rows.

use super::ci_system::{self, CiRows, Innovation};
use super::covariance::lower_triangular_inverse;
use super::peer_window::PeerWindow;
use super::state::State;
use nalgebra::{DMatrix, DVector};
use std::ops::Range;

/// The blocks of `rows` to leave out, in ascending order. `limit(m)` is the
/// gate of `m` stacked rows (the blocks' own). A window whose distance
/// cannot be computed is left as it is.
///
/// The window's rows are stacked once, with their innovation covariance
/// ([`ci_system::independent_innovation`]); every subset of its blocks has
/// a submatrix of it, and each block's removal is weighed from the kept
/// blocks' inverse ([`Kept::removals`]). Stacking and factoring every
/// candidate's `S` again took 1-9 s of one frame with 30-70 blocks over
/// up to 1000 rows (stop 90: an agent fell that far behind the wall clock).
pub fn rejected(
    state: &State,
    rows: &[CiRows],
    participants: &[PeerWindow],
    limit: impl Fn(usize) -> f64,
) -> Vec<usize> {
    let mut dropped = vec![false; rows.len()];
    for w in ci_system::windows(rows) {
        let of: Vec<usize> = (0..rows.len())
            .filter(|&i| !dropped[i] && rows[i].involves(w))
            .collect();
        // One block alone passed this very test at its own gate.
        if of.len() < 2 {
            continue;
        }
        let stacked: Vec<&CiRows> = of.iter().map(|&i| &rows[i]).collect();
        let Some((s, res)) = ci_system::independent_innovation(state, &stacked, participants)
        else {
            continue;
        };
        let spans = block_spans(&stacked);
        // Positions in `of` of the blocks still in.
        let mut kept: Vec<usize> = (0..of.len()).collect();
        while kept.len() >= 2 {
            let Some(k) = Kept::new(&s, &res, &spans, &kept) else {
                break;
            };
            let before = k.distance / limit(k.dim());
            if before.is_nan() || before <= 1.0 {
                break;
            }
            let worst = k
                .removals()
                .into_iter()
                .enumerate()
                .filter_map(|(j, r)| r.map(|(d, m)| (j, d / limit(m))))
                .min_by(|a, b| a.1.total_cmp(&b.1));
            let Some((j, after)) = worst else { break };
            let i = of[kept.remove(j)];
            tracing::debug!(
                t = state.means.t,
                window = w,
                block = i,
                rows = rows[i].res.len(),
                before,
                after,
                "window gate left a block out (distances as fractions of the limit)"
            );
            dropped[i] = true;
        }
    }
    (0..rows.len()).filter(|&i| dropped[i]).collect()
}

/// Each block's rows in `rows` stacked in their order.
fn block_spans(rows: &[&CiRows]) -> Vec<Range<usize>> {
    let mut spans = Vec::with_capacity(rows.len());
    let mut r0 = 0;
    for r in rows {
        spans.push(r0..r0 + r.res.len());
        r0 += r.res.len();
    }
    spans
}

/// The kept blocks' distance `rᵀ S⁻¹ r`, and what it becomes without each
/// of them, from one Cholesky factor `L Lᵀ` of either
/// - `S` (given, or `I + V Vᵀ` when `V` has at least as many columns as
///   rows), or
/// - `M = I + Vᵀ V`, with `S⁻¹ = I - V M⁻¹ Vᵀ` (Woodbury): everything is
///   then of `V`'s width, not of the rows'.
struct Kept {
    distance: f64,
    /// The kept rows of `V` in the Woodbury form (empty otherwise).
    v: DMatrix<f64>,
    res: DVector<f64>,
    l: DMatrix<f64>,
    woodbury: bool,
    /// Each kept block's rows, in the order of `kept`.
    spans: Vec<Range<usize>>,
}

impl Kept {
    /// From the window's innovation `s` and `res`, whose block `b` has rows
    /// `spans[b]`, the blocks `kept`. Only the distance: a window that
    /// passes needs nothing more.
    fn new(
        s: &Innovation,
        res: &DVector<f64>,
        spans: &[Range<usize>],
        kept: &[usize],
    ) -> Option<Self> {
        let mut idx = Vec::new();
        let mut local = Vec::with_capacity(kept.len());
        for &b in kept {
            let r0 = idx.len();
            idx.extend(spans[b].clone());
            local.push(r0..idx.len());
        }
        if idx.is_empty() {
            return None;
        }
        let res = res.select_rows(&idx);
        let m = idx.len();
        let (l, v, woodbury) = match s {
            Innovation::Covariance(s) => {
                let s = s.select_rows(&idx).select_columns(&idx);
                (s.cholesky()?.l(), DMatrix::zeros(0, 0), false)
            }
            Innovation::Factor(v) => {
                let v = v.select_rows(&idx);
                // Dense products (`tr_mul` is not).
                let vt = v.transpose();
                if m > v.ncols() {
                    let q = v.ncols();
                    let l = (DMatrix::identity(q, q) + &vt * &v).cholesky()?.l();
                    (l, v, true)
                } else {
                    let l = (DMatrix::identity(m, m) + &v * vt).cholesky()?.l();
                    (l, DMatrix::zeros(0, 0), false)
                }
            }
        };
        let distance = if woodbury {
            let t = l.solve_lower_triangular(&(v.transpose() * &res))?;
            res.dot(&res) - t.dot(&t)
        } else {
            let t = l.solve_lower_triangular(&res)?;
            t.dot(&t)
        };
        Some(Self {
            distance,
            v,
            res,
            l,
            woodbury,
            spans: local,
        })
    }

    fn dim(&self) -> usize {
        self.res.len()
    }

    /// The distance and row count without each kept block, in their order
    /// (`None` for one that cannot be weighed):
    /// `rᵀ S⁻¹ r - y_bᵀ ((S⁻¹)_bb)⁻¹ y_b` with `y = S⁻¹ r` (the inverse of
    /// a principal submatrix by the Schur complement). `(S⁻¹)_bb` is
    /// `Z_bᵀ Z_b` with `Z = L⁻¹`, or `I - Z_bᵀ Z_b` with `Z = L⁻¹ Vᵀ` in the
    /// Woodbury form.
    fn removals(&self) -> Vec<Option<(f64, usize)>> {
        let l_inv = lower_triangular_inverse(&self.l);
        let (z, y) = if self.woodbury {
            let z = l_inv * self.v.transpose();
            let y = &self.res - z.transpose() * (&z * &self.res);
            (z, y)
        } else {
            let y = l_inv.transpose() * (&l_inv * &self.res);
            (l_inv, y)
        };
        let m = self.dim();
        self.spans
            .iter()
            .map(|span| {
                let (r0, k) = (span.start, span.len());
                if k == 0 {
                    return Some((self.distance, m));
                }
                if k == m {
                    return None;
                }
                let z_b = z.columns(r0, k);
                let gram = z_b.transpose() * z_b;
                let s_inv_bb = if self.woodbury {
                    DMatrix::identity(k, k) - gram
                } else {
                    gram
                };
                let y_b = y.rows(r0, k).into_owned();
                let chol = s_inv_bb.cholesky()?;
                Some((self.distance - y_b.dot(&chol.solve(&y_b)), m - k))
            })
            .collect()
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::estimator::chi2::Chi2Table;
    use crate::estimator::options::EstimatorOptions;
    use crate::estimator::test_scene::{scene, Scene};
    use crate::estimator::updater_common::CommonTrack;
    use crate::estimator::updater_common_slam::measurement_blocks;
    use nalgebra::Vector2;

    /// Six SLAM features known to 1 cm, each measured from every pose of the peer's
    /// window, whose poses are known to `sigma` (rad, m) per axis; the views
    /// behind feature `bad` (when given) are 0.03 (14 px) off, all the same
    /// way, as a wrong link to a nearby point would be.
    fn blocks(bad: Option<usize>, sigma: f64) -> (Vec<CiRows>, Vec<usize>) {
        let (sc, rows) = scene_rows(bad, sigma);
        let chi2 = Chi2Table::new(0.95, 500);
        let p = std::slice::from_ref(&sc.peer);
        let out = rejected(&sc.state, &rows, p, |m| chi2.get(m));
        (rows, out)
    }

    /// The scene of [`blocks`] and its rows.
    fn scene_rows(bad: Option<usize>, sigma: f64) -> (Scene, Vec<CiRows>) {
        let mut sc = scene(6, 8, 1e-4, sigma * sigma);
        sc.add_slam_features(&[0, 1, 2, 3, 4, 5], 1e-4);
        let tracks: Vec<CommonTrack> = (0..6)
            .map(|l| {
                let mut peer_obs = sc.peer_obs(l);
                if Some(l) == bad {
                    for o in &mut peer_obs {
                        o.xy += Vector2::new(0.03, 0.0);
                    }
                }
                CommonTrack {
                    id: l as u64,
                    peer_obs,
                }
            })
            .collect();
        let p = std::slice::from_ref(&sc.peer);
        let opts = EstimatorOptions::default();
        let chi2 = Chi2Table::new(0.95, 500);
        let (rows, _) = measurement_blocks(&sc.state, &tracks, p, &opts, &chi2);
        (sc, rows)
    }

    /// Every form of [`Kept`] gives the distance of the blocks stacked, and
    /// of every block left out, as stacking and factoring them anew does.
    #[test]
    fn each_removal_is_weighed_as_the_blocks_stacked_anew() {
        let (sc, rows) = scene_rows(Some(2), 0.05);
        let p = std::slice::from_ref(&sc.peer);
        let all: Vec<&CiRows> = rows.iter().collect();
        let spans = block_spans(&all);
        let direct = |kept: &[usize]| {
            let kept: Vec<&CiRows> = kept.iter().map(|&i| &rows[i]).collect();
            ci_system::independent_mahalanobis(&sc.state, &kept, p).unwrap()
        };
        let close = |a: f64, b: f64| (a - b).abs() <= 1e-9 * b.abs().max(1.0);
        // All six blocks (more rows than V has columns: the factor is used
        // in the Woodbury form), and two (fewer: as I + V Vᵀ).
        for kept in [vec![0, 1, 2, 3, 4, 5], vec![1, 4]] {
            for factor in [false, true] {
                let (s, res) =
                    ci_system::independent_innovation_as(&sc.state, &all, p, |_, _| factor)
                        .unwrap();
                let k = Kept::new(&s, &res, &spans, &kept).unwrap();
                let (d, m) = direct(&kept);
                assert_eq!(k.dim(), m);
                assert_eq!(k.woodbury, factor && kept.len() == 6, "{kept:?}");
                assert!(close(k.distance, d), "{factor}: {} against {d}", k.distance);
                for (j, r) in k.removals().into_iter().enumerate() {
                    let rest: Vec<usize> = kept.iter().copied().filter(|&b| b != kept[j]).collect();
                    let (d_j, m_j) = direct(&rest);
                    let (got, m_got) = r.unwrap();
                    assert_eq!(m_got, m_j);
                    assert!(
                        close(got, d_j),
                        "{factor}, {kept:?} without {j}: {got} against {d_j}"
                    );
                }
            }
        }
        // The wrong block is the one whose removal leaves the least.
        let (s, res) = ci_system::independent_innovation(&sc.state, &all, p).unwrap();
        let k = Kept::new(&s, &res, &spans, &[0, 1, 2, 3, 4, 5]).unwrap();
        let left: Vec<f64> = k.removals().into_iter().map(|r| r.unwrap().0).collect();
        let least = (0..6).min_by(|&a, &b| left[a].total_cmp(&left[b])).unwrap();
        assert_eq!(least, 2, "{left:?}");
    }

    #[test]
    fn a_window_that_agrees_loses_nothing() {
        let (rows, out) = blocks(None, 0.05);
        assert_eq!(rows.len(), 6);
        assert!(out.is_empty(), "{out:?}");
    }

    #[test]
    fn the_block_that_disagrees_with_its_window_is_left_out() {
        let (rows, out) = blocks(Some(2), 0.05);
        // It passed its own gate: the window's pose is loose enough alone.
        assert_eq!(rows.len(), 6);
        assert_eq!(out, vec![2]);
    }
}
