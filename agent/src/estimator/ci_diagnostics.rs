//! What a frame's CI-EKF update did, at debug level
//! (`RUST_LOG=agent::estimator::ci_diagnostics=debug`): how far it and our own
//! rows moved the pose, and whether the stacked rows agree with the
//! covariances. Each block of rows passes its own chi-square gate; stacked,
//! the rows that share a peer's window see that window's error whole, and a
//! window whose rows disagree far beyond their dimension is the first thing
//! to look for when a fleet is pulled off in one frame.

use super::ci_system::{self, CiRows};
use super::peer_window::PeerWindow;
use super::state::{ImuState, State};
use super::updater_ci::CiOutcome;
use nalgebra::Matrix3;

/// A window's stacked distance beyond this many times its rows is logged
/// block by block.
const SUSPECT_PER_ROW: f64 = 3.0;

/// Whether this module's debug events are wanted: the diagnostics cost a
/// stack of the frame's rows per peer window, and copies of the IMU state.
pub fn enabled() -> bool {
    tracing::enabled!(tracing::Level::DEBUG)
}

/// The rotation from `a` to `b` (`b aᵀ`, global frame) as a rotation vector, deg.
fn rotation_deg(a: &Matrix3<f64>, b: &Matrix3<f64>) -> [f64; 3] {
    let d = nalgebra::Rotation3::from_matrix_unchecked(b * a.transpose()).scaled_axis();
    [d.x.to_degrees(), d.y.to_degrees(), d.z.to_degrees()]
}

/// Logs how far our own rows (`before` to `after_own`) and then the CI
/// update (to the state's mean now) moved the pose.
pub fn log_moves(
    state: &State,
    rows: &[CiRows],
    o: &CiOutcome,
    before: &ImuState,
    after_own: &ImuState,
) {
    let now = &state.means.imu;
    tracing::debug!(
        t = state.means.t,
        rows = rows.iter().map(|r| r.res.len()).sum::<usize>(),
        mahalanobis = o.mahalanobis,
        omega_own = o.omega_own,
        own_rot_deg = ?rotation_deg(&before.rot, &after_own.rot),
        ci_rot_deg = ?rotation_deg(&after_own.rot, &now.rot),
        ci_pos_m = ?(now.pos - after_own.pos).as_slice(),
        "cooperative update"
    );
}

/// Logs the stacked rows' Mahalanobis distance with uncorrelated robots
/// (`ci_system::independent_mahalanobis`): all of them, the common VIO rows
/// (the first `n_vio`), the SLAM rows (measurements and constraints), and
/// each participant window's; the blocks of a suspect window one by one.
pub fn log_consistency(state: &State, rows: &[CiRows], n_vio: usize, p: &[PeerWindow]) {
    let d = |r: &[&CiRows]| ci_system::independent_mahalanobis(state, r, p);
    let of = |w: usize| -> Vec<&CiRows> { rows.iter().filter(|r| r.involves(w)).collect() };
    let per_window: Vec<(usize, Option<(f64, usize)>)> = ci_system::windows(rows)
        .into_iter()
        .map(|w| (w, d(&of(w))))
        .collect();
    for (w, dw) in &per_window {
        let Some((dist, m)) = dw else { continue };
        if *dist <= SUSPECT_PER_ROW * *m as f64 {
            continue;
        }
        let blocks: Vec<(usize, &CiRows)> = rows
            .iter()
            .enumerate()
            .filter(|(_, r)| r.involves(*w))
            .collect();
        for &(i, r) in &blocks {
            let without: Vec<&CiRows> = blocks
                .iter()
                .filter(|(j, _)| *j != i)
                .map(|(_, r)| *r)
                .collect();
            tracing::debug!(
                t = state.means.t,
                window = w,
                block = i,
                vio = i < n_vio,
                peers = ?r.peers.iter().map(|q| (q.part, q.items.clone())).collect::<Vec<_>>(),
                d = ?d(&[r]),
                window_without = ?d(&without),
                res = ?r.res.as_slice(),
                "suspect window block"
            );
        }
    }
    let all: Vec<&CiRows> = rows.iter().collect();
    tracing::debug!(
        t = state.means.t,
        all = ?d(&all),
        vio = ?d(&all[..n_vio]),
        slam = ?d(&all[n_vio..]),
        ?per_window,
        "independent mahalanobis"
    );
}
