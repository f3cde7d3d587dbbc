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

use super::ci_system::{self, CiRows};
use super::peer_window::PeerWindow;
use super::state::State;

/// The blocks of `rows` to leave out, in ascending order. `limit(m)` is the
/// gate of `m` stacked rows (the blocks' own). A window whose distance
/// cannot be computed is left as it is.
pub fn rejected(
    state: &State,
    rows: &[CiRows],
    participants: &[PeerWindow],
    limit: impl Fn(usize) -> f64,
) -> Vec<usize> {
    let mut dropped = vec![false; rows.len()];
    for w in ci_system::windows(rows) {
        loop {
            let of: Vec<usize> = (0..rows.len())
                .filter(|&i| !dropped[i] && rows[i].involves(w))
                .collect();
            // One block alone passed this very test at its own gate.
            if of.len() < 2 {
                break;
            }
            let fraction = |skip: Option<usize>| {
                let kept: Vec<&CiRows> = of
                    .iter()
                    .filter(|&&i| Some(i) != skip)
                    .map(|&i| &rows[i])
                    .collect();
                ci_system::independent_mahalanobis(state, &kept, participants)
                    .map(|(d, m)| d / limit(m))
            };
            let Some(before) = fraction(None).filter(|f| *f > 1.0) else {
                break;
            };
            let worst = of
                .iter()
                .filter_map(|&i| fraction(Some(i)).map(|f| (i, f)))
                .min_by(|a, b| a.1.total_cmp(&b.1));
            let Some((i, after)) = worst else { break };
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

#[cfg(test)]
mod tests {
    use super::*;
    use crate::estimator::chi2::Chi2Table;
    use crate::estimator::options::EstimatorOptions;
    use crate::estimator::test_scene::scene;
    use crate::estimator::updater_common::CommonTrack;
    use crate::estimator::updater_common_slam::measurement_blocks;
    use nalgebra::Vector2;

    /// Six SLAM features known to 1 cm, each measured from every pose of the peer's
    /// window, whose poses are known to `sigma` (rad, m) per axis; the views
    /// behind feature `bad` (when given) are 0.03 (14 px) off, all the same
    /// way, as a wrong link to a nearby point would be.
    fn blocks(bad: Option<usize>, sigma: f64) -> (Vec<CiRows>, Vec<usize>) {
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
        let out = rejected(&sc.state, &rows, p, |m| chi2.get(m));
        (rows, out)
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
