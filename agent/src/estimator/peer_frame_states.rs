//! Peers' frames held in our filter state for a while
//! (`cooperation.peer_frame_state_s`).
//!
//! A peer's frame measured from a loop closure depends on our camera pose of
//! that moment: `δa = D ξ + n` (`AlignmentMeasurement::our_pose_jacobian`).
//! Folding the alignment's covariance into every peer window, as the fixed
//! alignment does, forgets that dependence, and each window then claims our
//! own drift of the loop-closure time as the peer's uncertainty. Held as 4
//! states `[δψ, δt]` augmented with `D`'s cross-covariance to our clone, the
//! frame is corrected by every CI-EKF update that uses the peer's windows
//! (their Jacobians w.r.t. it go into our columns, `ci_system::add_frame_columns`),
//! and an update through it relates our pose now to our pose at the loop
//! closure.
//!
//! The noise `n` (pixels, the peer's triangulation and anchor pose) is taken
//! as independent of our state: before its frame is confirmed nothing of
//! that peer entered our state, but for what reached us through a third
//! robot that had fused it.
//!
//! The peers' windows constrain the frame relative to our pose only, so
//! frame and pose can move together, and a plain CI update inflates that
//! direction by `1/ω` (held for an hour so, the frames' NEES fell to
//! 0.01-0.04 and the robots drifted). `cooperation.split_unobservable` (the
//! default, `ci_split`) leaves it out of the inflation. After
//! `peer_frame_state_s` the frame leaves the state as a fixed alignment at
//! its marginal, which later loop closures refine.

use super::camera_window::camera_pose_jacobian;
use super::frame_alignment::{AlignmentMeasurement, FrameAlignment};
use super::state::{PeerFrameMean, State, StateError, Var};
use crate::cooperation::Cooperation;
use common::estimator_options::CooperationOptions;
use nalgebra::{DMatrix, Matrix4};
use std::collections::BTreeMap;

/// A peer frame confirmed by a loop closure in this frame, for the estimator
/// to take into its state.
#[derive(Clone, Debug, PartialEq)]
pub struct FrameSeed {
    /// The peer's robot id.
    pub peer: u32,
    /// Its frame (`StateSnapshot::frame_epoch`).
    pub epoch: u64,
    /// Our clone whose camera saw the loop closure.
    pub clone: u64,
    /// The alignment measured by that loop closure.
    pub measurement: AlignmentMeasurement,
}

/// The state variable of peer `peer`'s frame `epoch`.
pub fn frame_var(peer: u32, epoch: u64) -> Var {
    Var::PeerFrame { peer, epoch }
}

/// Augments the state with the seed's frame: `P_aa = D P_ξξ Dᵀ + Σ_n`,
/// `P_a· = D P_ξ·`, with `ξ = J [δclone, δextrinsic]` our camera's error.
/// A frame already held is left as it is.
pub fn augment(state: &mut State, seed: &FrameSeed) -> Result<(), StateError> {
    let var = frame_var(seed.peer, seed.epoch);
    if state.has(var) {
        return Ok(());
    }
    let Some(pieces) = camera_pose_jacobian(state, seed.clone) else {
        return Err(StateError::Missing(Var::Clone(seed.clone)));
    };
    let d = DMatrix::from_iterator(4, 6, seed.measurement.our_pose_jacobian.iter().copied());
    let jac: Vec<(Var, DMatrix<f64>)> = pieces.into_iter().map(|(v, j)| (v, &d * j)).collect();
    let noise = DMatrix::from_iterator(4, 4, seed.measurement.noise_cov.iter().copied());
    state.augment(var, &jac, &noise)?;
    let a = &seed.measurement.alignment;
    state.peer_frames.insert(
        (seed.peer, seed.epoch),
        PeerFrameMean {
            yaw_rad: a.yaw_rad,
            t_m: a.t_m,
            measurements: 0,
        },
    );
    Ok(())
}

/// After matching: the peer frames the cooperation confirmed join the state,
/// and those it dropped leave it. A frame that cannot join (our clone of its
/// loop closure is gone) is dropped by the cooperation too, to be measured
/// again, rather than confirmed forever and never used.
pub fn take_from(state: &mut State, coop: &mut Cooperation, opts: &CooperationOptions) {
    for seed in coop.take_frame_seeds() {
        match augment(state, &seed) {
            Ok(()) => tracing::debug!(
                peer = seed.peer,
                epoch = seed.epoch,
                "peer frame taken into the state"
            ),
            Err(e) => {
                tracing::warn!(
                    peer = seed.peer,
                    epoch = seed.epoch,
                    "peer frame not taken into the state, to be measured again: {e}"
                );
                coop.forget_frame(seed.peer, seed.epoch);
            }
        }
    }
    if !state.peer_frames.is_empty() {
        if let Err(e) = forget_unless(state, |p, e| coop.keeps_frame(p, e)) {
            tracing::warn!("a dropped peer frame stays in the state: {e}");
        }
    }
    // Held long enough, or one too many: a fixed alignment from now on, at
    // the state's estimate.
    let frames = held(state);
    let aligned: Vec<((u32, u64), f64)> = frames
        .keys()
        .map(|&(p, e)| ((p, e), coop.frame_aligned_at(p, e).unwrap_or(state.t)))
        .collect();
    for (p, e) in to_release(&aligned, state.t, opts) {
        let Some(a) = frames.get(&(p, e)) else {
            continue;
        };
        match state.marginalize(frame_var(p, e)) {
            Ok(()) => coop.freeze_frame(p, e, *a),
            Err(err) => tracing::warn!(
                peer = p,
                epoch = e,
                "a peer frame stays in the state: {err}"
            ),
        }
    }
}

/// Of the held frames (each with when it was confirmed, s), those to let go
/// at `now`: held `peer_frame_hold_s` or longer, and beyond the
/// `max_held_peer_frames` most recently confirmed (each adds 4 states to
/// every update, and a peer that starts again brings a new frame).
pub fn to_release(
    aligned: &[((u32, u64), f64)],
    now: f64,
    opts: &CooperationOptions,
) -> Vec<(u32, u64)> {
    let mut newest_first = aligned.to_vec();
    newest_first.sort_by(|x, y| y.1.total_cmp(&x.1).then(y.0.cmp(&x.0)));
    newest_first
        .into_iter()
        .enumerate()
        .filter(|(rank, (_, at))| {
            now - at >= opts.peer_frame_hold_s() || *rank >= opts.max_held_peer_frames
        })
        .map(|(_, (k, _))| k)
        .collect()
}

/// The frames the state holds, each with its marginal covariance.
pub fn held(state: &State) -> BTreeMap<(u32, u64), FrameAlignment> {
    state
        .peer_frames
        .iter()
        .filter_map(|(&(peer, epoch), m)| {
            let b = state.block(frame_var(peer, epoch), frame_var(peer, epoch))?;
            Some((
                (peer, epoch),
                FrameAlignment {
                    yaw_rad: m.yaw_rad,
                    t_m: m.t_m,
                    cov: Matrix4::from_fn(|r, c| b[(r, c)]),
                },
            ))
        })
        .collect()
}

/// Marginalizes the frames `keep` says no more (a peer frame the cooperation
/// forgot: at most `MAX_FRAMES_PER_PEER` are kept per peer).
pub fn forget_unless(state: &mut State, keep: impl Fn(u32, u64) -> bool) -> Result<(), StateError> {
    let gone: Vec<(u32, u64)> = state
        .peer_frames
        .keys()
        .copied()
        .filter(|(p, e)| !keep(*p, *e))
        .collect();
    for (p, e) in gone {
        state.marginalize(frame_var(p, e))?;
    }
    Ok(())
}

#[cfg(test)]
pub(crate) mod tests {
    use super::*;
    use crate::estimator::camera_window::camera_estimate;
    use crate::estimator::ci_system::{add_frame_columns, frame_columns, Part};
    use crate::estimator::frame_alignment::window_in_state_frame;
    use crate::estimator::peer_window::project_normalized;
    use crate::estimator::test_scene::scene;
    use nalgebra::{DVector, SMatrix, Vector3};

    /// A measurement of peer 3's frame 7 (yaw 0.4 rad) from our clone `clone`.
    pub(crate) fn seed(clone: u64) -> FrameSeed {
        let d = SMatrix::<f64, 4, 6>::from_fn(|r, c| 0.1 * (r as f64 + 1.0) - 0.07 * c as f64);
        FrameSeed {
            peer: 3,
            epoch: 7,
            clone,
            measurement: AlignmentMeasurement {
                alignment: FrameAlignment {
                    yaw_rad: 0.4,
                    t_m: Vector3::new(1.0, -2.0, 0.1),
                    cov: Matrix4::identity(),
                },
                inliers: vec![true; 12],
                rms_normalized: 0.0,
                our_pose_jacobian: d,
                noise_cov: Matrix4::from_diagonal(&nalgebra::Vector4::new(1e-5, 1e-4, 2e-4, 3e-4)),
                anchor_cov: Matrix4::from_diagonal(&nalgebra::Vector4::new(4e-6, 4e-5, 8e-5, 1e-4)),
            },
        }
    }

    #[test]
    fn a_frame_joins_the_state_with_the_covariance_of_its_measurement() {
        let mut s = scene(4, 10, 1e-3, 1e-4).state;
        let sd = seed(2);
        augment(&mut s, &sd).expect("augmented");
        let var = frame_var(3, 7);
        let cam = camera_estimate(&s, 2).expect("clone 2");
        let d = sd.measurement.our_pose_jacobian;
        let expected = d * cam.cov * d.transpose() + sd.measurement.noise_cov;
        let p_aa = s.block(var, var).expect("held");
        assert!(
            (Matrix4::from_fn(|r, c| p_aa[(r, c)]) - expected)
                .abs()
                .max()
                < 1e-12
        );
        // Its cross-covariance with our clone is D's share of the clone's.
        let p_ac = s.block(var, Var::Clone(2)).expect("cross");
        let (jac_c, jac_e) = {
            let pieces = camera_pose_jacobian(&s, 2).expect("pieces");
            (pieces[0].1.clone(), pieces[1].1.clone())
        };
        let dd = DMatrix::from_iterator(4, 6, d.iter().copied());
        let p_cc = s.block(Var::Clone(2), Var::Clone(2)).expect("clone");
        let p_ec = s.block(Var::Extrinsic, Var::Clone(2)).expect("ext");
        let want = &dd * (&jac_c * p_cc + &jac_e * p_ec);
        assert!((p_ac - want).abs().max() < 1e-12);
        let held = held(&s);
        assert_eq!(held[&(3, 7)].yaw_rad, 0.4);
        // Held once: a second seed of the same frame changes nothing.
        let before = s.cov().clone();
        augment(&mut s, &sd).expect("no-op");
        assert_eq!(s.cov(), &before);
        // A clone we do not have is an error, not a panic.
        assert!(augment(
            &mut s,
            &FrameSeed {
                epoch: 8,
                ..seed(99)
            }
        )
        .is_err());
        forget_unless(&mut s, |_, _| false).expect("forgotten");
        assert!(!s.has(var) && s.peer_frames.is_empty());
    }

    /// The columns a peer measurement gives the frame are the derivative of
    /// that measurement w.r.t. the frame (numerically), and a window built at
    /// an older mean has its residual moved to the state's.
    #[test]
    fn the_frame_columns_are_the_derivative_of_a_peer_measurement() {
        let sc = scene(3, 4, 1e-3, 1e-4);
        let mut s = sc.state;
        augment(&mut s, &seed(1)).expect("augmented");
        let at = s.peer_frames[&(3, 7)];
        let var = frame_var(3, 7);
        let p_g = Vector3::new(0.3, 5.0, 0.2);
        let window_at = |a: &PeerFrameMean| window_in_state_frame(&sc.peer, a, var);
        let xy = |a: &PeerFrameMean| {
            let w = window_at(a);
            project_normalized(&w.poses[1], &p_g).expect("in view").xy
        };
        let w = window_at(&at);
        let h_pose = project_normalized(&w.poses[1], &p_g)
            .expect("in view")
            .h_pose;
        let h_p = DMatrix::from_iterator(2, 6, h_pose.iter().copied());
        let (link, cols) = frame_columns(Part::Poses(0), &[1], &h_p, std::slice::from_ref(&w))
            .expect("a frame window");
        assert_eq!(link.var, var);
        let h = 1e-6;
        for k in 0..4 {
            let moved = |sign: f64| {
                let mut a = at;
                if k == 0 {
                    a.yaw_rad += sign * h;
                } else {
                    a.t_m[k - 1] += sign * h;
                }
                xy(&a)
            };
            let num = (moved(1.0) - moved(-1.0)) / (2.0 * h);
            assert!(
                (num - cols.column(k)).abs().max() < 1e-6,
                "column {k}: {num} vs {}",
                cols.column(k)
            );
        }
        // The state's mean moved on after the window was built: r −= H_a δa.
        let delta = [0.002, 0.01, -0.02, 0.005];
        if let Some(m) = s.peer_frames.get_mut(&(3, 7)) {
            m.yaw_rad += delta[0];
            m.t_m += Vector3::new(delta[1], delta[2], delta[3]);
        }
        let mut vars = vec![Var::Clone(1)];
        let mut h_ours = DMatrix::zeros(2, 6);
        let mut res = DVector::from_column_slice(&[0.1, -0.2]);
        add_frame_columns(
            &s,
            &mut vars,
            &mut h_ours,
            &mut res,
            [(Part::Poses(0), &[1usize][..], &h_p)],
            std::slice::from_ref(&w),
        );
        assert_eq!(vars, vec![Var::Clone(1), var]);
        assert_eq!(h_ours.columns(6, 4), cols);
        let want =
            DVector::from_column_slice(&[0.1, -0.2]) - &cols * DVector::from_column_slice(&delta);
        assert!((res - want).abs().max() < 1e-12);
    }

    #[test]
    fn frames_are_let_go_when_held_long_enough_or_one_too_many() {
        let aligned = [
            ((1, 1), 10.0),
            ((2, 1), 50.0),
            ((2, 2), 80.0),
            ((3, 1), 90.0),
        ];
        let mut opts = CooperationOptions {
            peer_frame_state_s: Some(60.0),
            ..CooperationOptions::default()
        };
        assert_eq!(to_release(&aligned, 100.0, &opts), vec![(1, 1)]);
        assert_eq!(to_release(&aligned, 110.0, &opts), vec![(2, 1), (1, 1)]);
        // The whole flight: only a cap lets go, the longest held first.
        opts.peer_frame_state_s = Some(f64::INFINITY);
        assert!(to_release(&aligned, 1e6, &opts).is_empty());
        opts.max_held_peer_frames = 2;
        assert_eq!(to_release(&aligned, 100.0, &opts), vec![(2, 1), (1, 1)]);
    }
}
