//! Which of a peer's keyframe windows goes when its history is over its memory
//! bound (`history.max_mib_per_peer`).
//!
//! [`Retention::Oldest`] drops the oldest windows first, a ring buffer: what is
//! kept is the peer's last minutes.
//!
//! A historical window helps us through CI, where its covariance is divided by
//! the peer's weight: the more certain the peer was of that window, the more it
//! can tell us (the evidence step already prefers the most certain window of a
//! track, `cooperation::evidence`). The oldest windows are often a peer's most
//! certain ones (global position and yaw are unobservable, so a robot's
//! uncertainty about them only grows between cooperative updates), and a ring
//! buffer keeps many windows of a place the peer flew through again and again.
//! [`Retention::Informed`] (the default) drops instead, while the history is
//! over its bound:
//! 1. among places seen from more than one window, the least certain window of
//!    such a place (largest summed position variance), so every place keeps its
//!    best view;
//! 2. once every place has a single window, the least certain window overall.
//!
//! A place is the newest camera's position on a [`PLACE_CELL_M`] grid and its
//! viewing direction in [`AZIMUTH_BINS`] azimuth and 3 elevation bins (a loop
//! closure needs the same scene, not only the same position).
//!
//! Measured (README, "Results: an hour of flight"): over an hour of the
//! three-robot EuRoC fleet with 8 MiB per peer (about an eighth of a peer-hour),
//! `oldest` keeps the peers' last 7 minutes and the fleet drifts as a whole
//! (their windows carry the peers' drift): in its last 10 minutes the error is
//! 2-4x that of its first. `informed` keeps the peers' first, most certain
//! views of each place and the error stays near that of an unbounded history.
//! In a 2-minute flight (0.25 MiB per peer, about 12 windows) it gives 13 %
//! less orientation error than `oldest` and the same position error.

use crate::peer_history::KeyframeWindow;
use common::messages::StateSnapshot;
use serde::{Deserialize, Serialize};
use std::collections::{BTreeMap, HashMap};

/// Side of a place cell, m.
pub const PLACE_CELL_M: f64 = 1.0;
/// Azimuth bins of the viewing direction (45 deg each).
pub const AZIMUTH_BINS: f64 = 8.0;
/// Elevation of the viewing direction beyond which a camera looks up or down
/// (its own bin), rad (30 deg).
const STEEP_RAD: f64 = std::f64::consts::FRAC_PI_6;

/// How a peer's history makes room.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum Retention {
    /// Drop the oldest windows first (a ring buffer).
    Oldest,
    /// Keep each place's most certain window, then the most certain places.
    #[default]
    Informed,
}

impl std::str::FromStr for Retention {
    type Err = String;
    fn from_str(s: &str) -> Result<Self, String> {
        match s {
            "informed" => Ok(Self::Informed),
            "oldest" => Ok(Self::Oldest),
            other => Err(format!(
                "unknown history retention {other:?} (informed, oldest)"
            )),
        }
    }
}

/// Where a window's newest camera was and where it looked.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
pub struct Place {
    cell: [i64; 3],
    azimuth: u8,
    elevation: u8,
}

/// The place of `snap`'s newest camera (`None` without a finite pose).
pub fn place_of(snap: &StateSnapshot) -> Option<Place> {
    let c = snap.clones.last()?;
    let axis = c.rot_c_to_g() * nalgebra::Vector3::z();
    if !(axis.iter().chain(c.p_m.iter()).all(|v| v.is_finite())) {
        return None;
    }
    // Positions beyond ±9e15 m saturate into the outermost cells.
    let cell = c.p_m.map(|p| (p / PLACE_CELL_M).floor() as i64);
    let turn = axis.y.atan2(axis.x).rem_euclid(std::f64::consts::TAU);
    let azimuth = ((turn / std::f64::consts::TAU * AZIMUTH_BINS) as u8).min(AZIMUTH_BINS as u8 - 1);
    let pitch = axis.z.clamp(-1.0, 1.0).asin();
    let elevation = if pitch < -STEEP_RAD {
        0
    } else if pitch > STEEP_RAD {
        2
    } else {
        1
    };
    Some(Place {
        cell,
        azimuth,
        elevation,
    })
}

/// Sum of the position variances of a window's camera poses, m² (infinite when
/// the covariance lacks them, so such a window goes first).
pub fn position_variance_m2(snap: &StateSnapshot) -> f64 {
    if snap.clones.is_empty() {
        return f64::INFINITY;
    }
    let mut sum = 0.0;
    for d in (0..snap.clones.len()).flat_map(|i| (3..6).map(move |j| 6 * i + j)) {
        match snap.covariance.get(d, d) {
            Some(v) if v.is_finite() => sum += v,
            _ => return f64::INFINITY,
        }
    }
    sum
}

/// The key of the window to drop next from `windows` (`None` when empty).
pub fn victim(windows: &BTreeMap<u64, KeyframeWindow>, retention: Retention) -> Option<u64> {
    match retention {
        Retention::Oldest => windows.keys().next().copied(),
        Retention::Informed => informed_victim(windows),
    }
}

/// Whether `a` (variance, key) should go before `b`: the less certain first,
/// then the older.
fn worse(a: (f64, u64), b: (f64, u64)) -> bool {
    a.0 > b.0 || (a.0 == b.0 && a.1 < b.1)
}

fn informed_victim(windows: &BTreeMap<u64, KeyframeWindow>) -> Option<u64> {
    // Per place: how many windows, and its least certain one. A window without a
    // place is a place of its own.
    let mut places: HashMap<Option<Place>, (usize, (f64, u64))> = HashMap::new();
    let mut overall: Option<(f64, u64)> = None;
    for (&key, w) in windows {
        let candidate = (w.position_variance_m2, key);
        if overall.is_none_or(|o| worse(candidate, o)) {
            overall = Some(candidate);
        }
        let Some(place) = w.place else {
            continue;
        };
        places
            .entry(Some(place))
            .and_modify(|(n, worst)| {
                *n += 1;
                if worse(candidate, *worst) {
                    *worst = candidate;
                }
            })
            .or_insert((1, candidate));
    }
    let redundant = places
        .values()
        .filter(|(n, _)| *n > 1)
        .map(|(_, worst)| *worst)
        .reduce(|a, b| if worse(a, b) { a } else { b });
    redundant.or(overall).map(|(_, key)| key)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::peer_history::test_support::snapshot;
    use common::messages::{CameraPose, PackedCovariance};
    use nalgebra::{DMatrix, Matrix3, Vector3};

    /// A one-clone window at `pos` looking along `dir` (camera z) with position
    /// variance `var` per axis.
    fn window(pos: [f64; 3], dir: Vector3<f64>, var: f64) -> KeyframeWindow {
        // Camera z along `dir`; any up that is not parallel to it.
        let up = if dir.normalize().z.abs() < 0.9 {
            Vector3::z()
        } else {
            Vector3::x()
        };
        let rot: Matrix3<f64> = nalgebra::Rotation3::face_towards(&dir, &up).into_inner();
        let mut cov = DMatrix::identity(6, 6) * 1e-4;
        for j in 3..6 {
            cov[(j, j)] = var;
        }
        let snapshot = snapshot(
            0.0,
            true,
            vec![CameraPose::new(0.0, &rot, &Vector3::from(pos))],
            &cov,
        );
        KeyframeWindow::new(snapshot, Vec::new(), Vec::new())
    }

    fn history(ws: Vec<KeyframeWindow>) -> BTreeMap<u64, KeyframeWindow> {
        ws.into_iter()
            .enumerate()
            .map(|(k, w)| (k as u64, w))
            .collect()
    }

    #[test]
    fn places_tell_position_cells_and_viewing_directions_apart() {
        let east = Vector3::x();
        let a = window([0.2, 0.3, 1.0], east, 1e-4);
        let b = window([0.8, 0.9, 1.4], east, 1e-4);
        let c = window([1.2, 0.3, 1.0], east, 1e-4);
        let d = window([0.2, 0.3, 1.0], -east, 1e-4);
        let e = window([0.2, 0.3, 1.0], Vector3::new(1.0, 0.0, -1.0), 1e-4);
        let p = |w: &KeyframeWindow| place_of(&w.snapshot).unwrap();
        assert_eq!(p(&a), p(&b), "same cell, same direction");
        assert_ne!(p(&a), p(&c), "next cell");
        assert_ne!(p(&a), p(&d), "looking the other way");
        assert_ne!(p(&a), p(&e), "looking down");
    }

    #[test]
    fn position_variance_sums_every_clone_and_refuses_what_is_missing() {
        let w = window([0.0; 3], Vector3::x(), 2e-4);
        assert!((position_variance_m2(&w.snapshot) - 6e-4).abs() < 1e-9);
        let mut s = w.snapshot.clone();
        s.covariance = PackedCovariance::from_dmatrix(&DMatrix::identity(3, 3)).unwrap();
        assert_eq!(position_variance_m2(&s), f64::INFINITY);
        s.clones.clear();
        assert_eq!(position_variance_m2(&s), f64::INFINITY);
    }

    #[test]
    fn a_revisited_place_loses_its_least_certain_window_first() {
        let east = Vector3::x();
        // Key 0: the most certain window of all, alone at its place. Keys 1-3:
        // one place seen three times; key 2 is its least certain view. Key 4: a
        // place of its own, less certain than key 2.
        let h = history(vec![
            window([0.5, 0.5, 1.0], east, 1e-6),
            window([5.5, 0.5, 1.0], east, 1e-4),
            window([5.6, 0.4, 1.2], east, 4e-4),
            window([5.4, 0.6, 1.1], east, 2e-4),
            window([9.5, 0.5, 1.0], east, 9e-4),
        ]);
        assert_eq!(victim(&h, Retention::Informed), Some(2));
        assert_eq!(victim(&h, Retention::Oldest), Some(0));
    }

    #[test]
    fn with_one_window_per_place_the_least_certain_goes() {
        let east = Vector3::x();
        let h = history(vec![
            window([0.5, 0.5, 1.0], east, 1e-6),
            window([5.5, 0.5, 1.0], east, 3e-4),
            window([9.5, 0.5, 1.0], east, 3e-4),
            window([2.5, 0.5, 1.0], east, 1e-4),
        ]);
        // Keys 1 and 2 tie: the older goes.
        assert_eq!(victim(&h, Retention::Informed), Some(1));
        assert_eq!(victim(&BTreeMap::new(), Retention::Informed), None);
    }

    #[test]
    fn a_window_without_a_usable_pose_goes_first() {
        let east = Vector3::x();
        let mut broken = window([0.5, 0.5, 1.0], east, 1e-6);
        broken.snapshot.clones.clear();
        let broken = KeyframeWindow::new(broken.snapshot, Vec::new(), Vec::new());
        let h = history(vec![window([5.5, 0.5, 1.0], east, 3e-4), broken]);
        assert_eq!(victim(&h, Retention::Informed), Some(1));
    }
}
