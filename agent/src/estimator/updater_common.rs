//! Common VIO features (thesis Section 5.3.3): our tracks that peers also
//! measured, in their current windows or in stored historical windows, fused
//! with the CI-EKF update so that only our state and covariance change.
//!
//! For each feature, our measurements and each participant's (a participant is
//! one window of one peer) are linearized at the point triangulated from all of
//! them and whitened (ours are pixels, a peer's normalized coordinates; after
//! whitening every row has unit noise, so orthogonal projections keep it white).
//!
//! * **Two-stage** (Eqs. 5.18-5.19): each block is projected onto the left range
//!   and nullspace of its own feature Jacobian. A participant's nullspace rows
//!   involve only that peer and are dropped; our nullspace rows involve only us
//!   and go through a standard EKF update. The range rows (3 per block) are
//!   stacked and projected once more onto the nullspace of the stacked feature
//!   Jacobian: those rows relate our window to the peers' and go to the CI-EKF.
//! * **Combined**: every row of every block stacked and projected at once, all
//!   of them in the CI-EKF update (the larger system the thesis compares against).

use super::chi2::Chi2Table;
use super::ci_system::{self, correct_residuals, CiRows, Part, PeerRows};
use super::feature_db::FeatureDb;
use super::feature_system::{build_at, camera_observations, Columns};
use super::linalg::{compress_in_place, givens_qr_split, nullspace_project_in_place};
use super::options::EstimatorOptions;
use super::peer_window::{peer_measurement, PeerWindow};
use super::state::{State, Var};
use super::triangulation::{triangulate, CameraObservation, TriangulationOptions};
use common::estimator_options::CommonProjection;
use nalgebra::{DMatrix, DVector, Vector2};
#[cfg(test)]
use std::ops::AddAssign;

/// One measurement of a common feature by a peer.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct PeerObservation {
    /// Index of the participant (peer window) in the update's list.
    pub participant: usize,
    /// Index of the camera pose in that window.
    pub pose: usize,
    /// Undistorted normalized coordinates.
    pub xy: Vector2<f64>,
}

/// One of our tracks with the peers' measurements of the same feature.
#[derive(Clone, Debug, PartialEq)]
pub struct CommonTrack {
    /// Our track id.
    pub id: u64,
    /// The peers' measurements (none used before).
    pub peer_obs: Vec<PeerObservation>,
}

/// What one common-feature update did.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct CommonStats {
    /// Features used.
    pub used: usize,
    /// Features rejected by the chi-square gate (they fall back to the MSCKF).
    pub rejected_chi2: usize,
    /// Features that could not be triangulated or projected (fall back too).
    pub failed: usize,
    /// Rows of the CI-EKF update (before compression).
    pub ci_rows: usize,
    /// Rows of our own EKF update (two-stage only).
    pub own_rows: usize,
    /// Peer measurements used.
    pub peer_measurements: usize,
}

/// The outcome: statistics, and which tracks were used (the others should go
/// to the independent MSCKF update).
#[derive(Clone, Debug, Default, PartialEq)]
pub struct CommonOutcome {
    /// Statistics.
    pub stats: CommonStats,
    /// Our tracks whose measurements were used here.
    pub used: Vec<u64>,
    /// Our tracks not used (failed or gated out).
    pub fallback: Vec<u64>,
}

/// One participant's part of a feature's rows.
struct PeerPart {
    participant: usize,
    poses: Vec<usize>,
    h: DMatrix<f64>,
}

/// A feature's projected, whitened rows.
struct FeatureRows {
    our_vars: Vec<Var>,
    h_i: DMatrix<f64>,
    peers: Vec<PeerPart>,
    res: DVector<f64>,
    own: Option<(DMatrix<f64>, DVector<f64>)>,
    peer_measurements: usize,
}

/// A block of whitened rows `r = H_x δx + H_f δp_F + n`, `n ~ N(0, I)`.
struct Block {
    h_x: DMatrix<f64>,
    h_f: DMatrix<f64>,
    res: DVector<f64>,
}

/// Our block of `feature`, linearized at `p_f`, whitened, over the calibration
/// and the clones that saw it.
fn our_block(
    state: &State,
    feature: &super::feature_db::Feature,
    p_f: &nalgebra::Vector3<f64>,
    opts: &EstimatorOptions,
) -> Option<(Vec<Var>, Block)> {
    let mut vars: Vec<Var> = [Var::Extrinsic, Var::Intrinsics]
        .into_iter()
        .filter(|v| state.has(*v))
        .collect();
    vars.extend(
        feature
            .measurements
            .iter()
            .filter(|m| state.clones.contains_key(&m.clone_key))
            .map(|m| Var::Clone(m.clone_key)),
    );
    let cols = Columns::of(vars);
    let sys = build_at(&state.means, feature, &cols, opts.use_fej, p_f)?;
    let w = 1.0 / opts.pixel_sigma_px;
    Some((
        cols.vars,
        Block {
            h_x: sys.h_x * w,
            h_f: sys.h_f * w,
            res: sys.res * w,
        },
    ))
}

/// Participant `j`'s block: its measurements of the feature at `p_f`, whitened,
/// over its items: the poses that saw it (sorted), then its intrinsics when its
/// covariance has them.
fn peer_block(
    w: &PeerWindow,
    obs: &[&PeerObservation],
    p_f: &nalgebra::Vector3<f64>,
    pixel_sigma: f64,
) -> Option<(Vec<usize>, Block)> {
    let mut items: Vec<usize> = obs.iter().map(|o| o.pose).collect();
    items.sort_unstable();
    items.dedup();
    let n_poses = items.len();
    let intrinsics = w.intrinsics_item();
    items.extend(intrinsics);
    let rows = 2 * obs.len();
    let cols = 6 * n_poses + if intrinsics.is_some() { 8 } else { 0 };
    let mut b = Block {
        h_x: DMatrix::zeros(rows, cols),
        h_f: DMatrix::zeros(rows, 3),
        res: DVector::zeros(rows),
    };
    for (i, o) in obs.iter().enumerate() {
        let m = peer_measurement(w, o.pose, &o.xy, p_f, p_f, pixel_sigma)?;
        let col = 6 * items[..n_poses].binary_search(&o.pose).ok()?;
        let r = 2 * i;
        b.h_x.fixed_view_mut::<2, 6>(r, col).copy_from(&m.h_pose);
        if intrinsics.is_some() {
            b.h_x
                .fixed_view_mut::<2, 8>(r, 6 * n_poses)
                .copy_from(&m.h_intrinsics);
        }
        b.h_f.fixed_view_mut::<2, 3>(r, 0).copy_from(&m.h_feature);
        b.res[r] = m.res.x;
        b.res[r + 1] = m.res.y;
    }
    Some((items, b))
}

/// Keeps the first `top` rows of a block (after [`givens_qr_split`]); returns the
/// rest as `(H_x, r)`.
fn split_rows(b: Block, top: usize) -> (Block, DMatrix<f64>, DVector<f64>) {
    let m = b.res.len();
    let rest_h = b.h_x.rows(top, m - top).into_owned();
    let rest_r = b.res.rows(top, m - top).into_owned();
    (
        Block {
            h_x: b.h_x.rows(0, top).into_owned(),
            h_f: b.h_f.rows(0, top).into_owned(),
            res: b.res.rows(0, top).into_owned(),
        },
        rest_h,
        rest_r,
    )
}

/// Stacks blocks with block-diagonal `H_x` columns (in the blocks' order) and
/// projects onto the left nullspace of the stacked `H_f`.
fn stack_and_project(blocks: &[Block]) -> Option<(DMatrix<f64>, DVector<f64>)> {
    let rows: usize = blocks.iter().map(|b| b.res.len()).sum();
    let cols: usize = blocks.iter().map(|b| b.h_x.ncols()).sum();
    if rows <= 3 {
        return None;
    }
    let mut h_x = DMatrix::zeros(rows, cols);
    let mut h_f = DMatrix::zeros(rows, 3);
    let mut res = DVector::zeros(rows);
    let (mut r0, mut c0) = (0, 0);
    for b in blocks {
        let (m, c) = b.h_x.shape();
        h_x.view_mut((r0, c0), (m, c)).copy_from(&b.h_x);
        h_f.view_mut((r0, 0), (m, 3)).copy_from(&b.h_f);
        res.rows_mut(r0, m).copy_from(&b.res);
        r0 += m;
        c0 += c;
    }
    nullspace_project_in_place(&mut h_f, &mut h_x, &mut res);
    (!res.is_empty()).then_some((h_x, res))
}

/// Linearizes, projects and gates one common feature.
#[allow(clippy::too_many_arguments)]
fn feature_rows(
    state: &State,
    db: &FeatureDb,
    track: &CommonTrack,
    participants: &[PeerWindow],
    opts: &EstimatorOptions,
    projection: CommonProjection,
    chi2: &Chi2Table,
    tri: &TriangulationOptions,
) -> Result<FeatureRows, bool> {
    // Err(true): gated out; Err(false): failed.
    let feature = db.get(track.id).ok_or(false)?;
    let mut obs: Vec<CameraObservation> = camera_observations(&state.means, feature);
    if obs.is_empty() {
        return Err(false);
    }
    let mut by_participant: Vec<(usize, Vec<&PeerObservation>)> = Vec::new();
    for o in &track.peer_obs {
        let w = participants.get(o.participant).ok_or(false)?;
        let pose = w.poses.get(o.pose).ok_or(false)?;
        obs.push(CameraObservation {
            r_c_to_g: pose.rot,
            p_c_in_g: pose.pos,
            uvn: o.xy,
        });
        match by_participant.iter_mut().find(|(p, _)| *p == o.participant) {
            Some((_, list)) => list.push(o),
            None => by_participant.push((o.participant, vec![o])),
        }
    }
    by_participant.sort_by_key(|(p, _)| *p);
    if by_participant.is_empty() {
        return Err(false);
    }
    let p_f = triangulate(&obs, tri).map_err(|_| false)?;
    let (our_vars, ours) = our_block(state, feature, &p_f, opts).ok_or(false)?;
    let our_cols = ours.h_x.ncols();
    let mut metas = Vec::with_capacity(by_participant.len());
    let mut peer_blocks = Vec::with_capacity(by_participant.len());
    for (p, list) in &by_participant {
        let (poses, b) =
            peer_block(&participants[*p], list, &p_f, opts.pixel_sigma_px).ok_or(false)?;
        metas.push((*p, poses));
        peer_blocks.push(b);
    }
    let (mut own, stacked) = match projection {
        CommonProjection::TwoStage => {
            let mut ours = ours;
            let top = givens_qr_split(&mut ours.h_f, &mut ours.h_x, &mut ours.res);
            let (ours_top, own_h, own_r) = split_rows(ours, top);
            let mut blocks = vec![ours_top];
            for mut b in peer_blocks {
                let top = givens_qr_split(&mut b.h_f, &mut b.h_x, &mut b.res);
                // The peer's nullspace rows do not involve us: dropped.
                blocks.push(split_rows(b, top).0);
            }
            let own = (!own_r.is_empty()).then_some((own_h, own_r));
            (own, stack_and_project(&blocks))
        }
        CommonProjection::Combined => {
            let mut blocks = vec![ours];
            blocks.extend(peer_blocks);
            (None, stack_and_project(&blocks))
        }
    };
    let (h_all, res) = stacked.ok_or(false)?;
    let m = res.len();
    let h_i = h_all.columns(0, our_cols).into_owned();
    let mut peers = Vec::with_capacity(metas.len());
    let mut c0 = our_cols;
    for (p, poses) in metas {
        let c: usize = poses.iter().map(|i| participants[p].item_size(*i)).sum();
        peers.push(PeerPart {
            participant: p,
            h: h_all.columns(c0, c).into_owned(),
            poses,
        });
        c0 += c;
    }
    // Gate with the innovation covariance the correlations would give if they
    // were zero (the CI one, inflated by 1/ω, would let wrong matches through).
    let mut s = state
        .covariance()
        .projected(&our_vars, &h_i)
        .map_err(|_| false)?
        + DMatrix::identity(m, m);
    for part in &peers {
        let cov = participants[part.participant].sub_covariance(&part.poses);
        s += &part.h * cov * part.h.transpose();
    }
    let chol = s.cholesky().ok_or(false)?;
    let limit = |dof: usize| opts.chi2_multiplier * chi2.get(dof);
    if res.dot(&chol.solve(&res)) > limit(m) {
        return Err(true);
    }
    if let Some((h, r)) = &own {
        let eye = DMatrix::identity(r.len(), r.len());
        match state.mahalanobis(&our_vars, h, r, &eye) {
            Ok(d2) if d2 <= limit(r.len()) => {}
            Ok(_) => own = None,
            Err(_) => return Err(false),
        }
    }
    Ok(FeatureRows {
        our_vars,
        h_i,
        peers,
        res,
        own,
        peer_measurements: track.peer_obs.len(),
    })
}

/// Copies a feature's rows over its own variables into the window layout.
fn place(dst: &mut DMatrix<f64>, r0: usize, src: &DMatrix<f64>, vars: &[Var], cols: &Columns) {
    let local = Columns::of(vars.to_vec());
    for v in vars {
        if let (Some(s), Some(d)) = (local.col(*v), cols.col(*v)) {
            dst.view_mut((r0, d), (src.nrows(), v.size()))
                .copy_from(&src.view((0, s), (src.nrows(), v.size())));
        }
    }
}

/// The common tracks' rows, ready for the updates.
#[derive(Clone, Debug, Default)]
pub struct CommonRows {
    /// What was built, gated and used.
    pub outcome: CommonOutcome,
    /// Rows relating us to peers, one block per feature (for the CI-EKF).
    pub ci: Vec<CiRows>,
    /// Our own rows over the window (two-stage only), for a standard EKF
    /// update: variables, `H`, `r` (whitened).
    pub own: Option<(Vec<Var>, DMatrix<f64>, DVector<f64>)>,
}

/// Linearizes, projects and gates the common tracks at the current estimate.
#[allow(clippy::too_many_arguments)]
pub fn rows(
    state: &State,
    db: &FeatureDb,
    tracks: &[CommonTrack],
    participants: &[PeerWindow],
    opts: &EstimatorOptions,
    chi2: &Chi2Table,
    tri: &TriangulationOptions,
) -> CommonRows {
    let projection = opts.cooperation.projection;
    let mut out = CommonRows::default();
    let mut own_blocks = Vec::new();
    for t in tracks {
        match feature_rows(state, db, t, participants, opts, projection, chi2, tri) {
            Ok(r) => {
                out.outcome.used.push(t.id);
                out.outcome.stats.peer_measurements += r.peer_measurements;
                out.outcome.stats.ci_rows += r.res.len();
                if let Some((h, v)) = r.own {
                    out.outcome.stats.own_rows += v.len();
                    own_blocks.push((r.our_vars.clone(), h, v));
                }
                out.ci.push(CiRows {
                    vars: r.our_vars,
                    h: r.h_i,
                    res: r.res,
                    peers: r
                        .peers
                        .into_iter()
                        .map(|p| PeerRows {
                            part: Part::Poses(p.participant),
                            items: p.poses,
                            h: p.h,
                        })
                        .collect(),
                });
            }
            Err(gated) => {
                if gated {
                    out.outcome.stats.rejected_chi2 += 1;
                } else {
                    out.outcome.stats.failed += 1;
                }
                out.outcome.fallback.push(t.id);
            }
        }
    }
    out.outcome.stats.used = out.ci.len();
    let m_own: usize = own_blocks.iter().map(|(_, _, v)| v.len()).sum();
    if m_own > 0 {
        let cols = Columns::window(state);
        let mut h = DMatrix::zeros(m_own, cols.dim);
        let mut res = DVector::zeros(m_own);
        let mut r0 = 0;
        for (vars, hb, vb) in &own_blocks {
            place(&mut h, r0, hb, vars, &cols);
            res.rows_mut(r0, vb.len()).copy_from(vb);
            r0 += vb.len();
        }
        compress_in_place(&mut h, &mut res);
        out.own = Some((cols.vars, h, res));
    }
    out
}

/// Our own rows by a standard EKF update; the CI rows' residuals then follow its
/// correction to first order (they were linearized before it).
pub fn apply_own_rows(state: &mut State, rows: &mut CommonRows, others: &mut [CiRows]) {
    let Some((vars, h, res)) = rows.own.take() else {
        return;
    };
    let eye = DMatrix::identity(res.len(), res.len());
    if let Ok(dx) = state.ekf_update_dx(&vars, &h, &res, &eye) {
        correct_residuals(&mut rows.ci, state, &dx);
        correct_residuals(others, state, &dx);
    }
}

/// Updates `state` with the common tracks alone: our own rows by the EKF, the
/// rows relating us to peers by one CI-EKF update (Eqs. 5.15-5.17).
#[allow(clippy::too_many_arguments)]
pub fn update(
    state: &mut State,
    db: &FeatureDb,
    tracks: &[CommonTrack],
    participants: &[PeerWindow],
    opts: &EstimatorOptions,
    chi2: &Chi2Table,
    tri: &TriangulationOptions,
) -> CommonOutcome {
    let mut rows = rows(state, db, tracks, participants, opts, chi2, tri);
    apply_own_rows(state, &mut rows, &mut []);
    let mut out = rows.outcome;
    if ci_system::update(state, &rows.ci, participants, &opts.cooperation).is_err() {
        out.stats.used = 0;
        out.fallback.append(&mut out.used);
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::estimator::chi2::Chi2Table;
    use crate::estimator::test_scene::scene;
    use rand::{Rng, SeedableRng};
    use rand_chacha::ChaCha8Rng;

    fn random_block(rows: usize, cols: usize, rng: &mut ChaCha8Rng) -> Block {
        let mut r = || rng.random_range(-1.0..1.0);
        Block {
            h_x: DMatrix::from_fn(rows, cols, |_, _| r()),
            h_f: DMatrix::from_fn(rows, 3, |_, _| r()),
            res: DVector::from_fn(rows, |_, _| r()),
        }
    }

    /// Eq. 5.19's claim: our nullspace rows, the second-stage rows and the
    /// peer's (dropped) nullspace rows carry exactly the information of one
    /// projection of the whole stack.
    #[test]
    fn two_stage_rows_carry_the_combined_information() {
        let mut rng = ChaCha8Rng::seed_from_u64(5);
        let (ci, cp) = (8, 12);
        let ours = random_block(10, ci, &mut rng);
        let peer = random_block(14, cp, &mut rng);
        let copy = |b: &Block| Block {
            h_x: b.h_x.clone(),
            h_f: b.h_f.clone(),
            res: b.res.clone(),
        };
        let (hc, rc) = stack_and_project(&[copy(&ours), copy(&peer)]).unwrap();
        let info_c = hc.transpose() * &hc;
        let vec_c = hc.transpose() * &rc;

        let mut o = copy(&ours);
        let top = givens_qr_split(&mut o.h_f, &mut o.h_x, &mut o.res);
        let (o_top, o_h, o_r) = split_rows(o, top);
        let mut p = copy(&peer);
        let top = givens_qr_split(&mut p.h_f, &mut p.h_x, &mut p.res);
        let (p_top, p_h, p_r) = split_rows(p, top);
        let (h2, r2) = stack_and_project(&[o_top, p_top]).unwrap();
        let mut info = h2.transpose() * &h2;
        let mut vec = h2.transpose() * &r2;
        info.view_mut((0, 0), (ci, ci))
            .add_assign(&(o_h.transpose() * &o_h));
        vec.rows_mut(0, ci).add_assign(&(o_h.transpose() * &o_r));
        info.view_mut((ci, ci), (cp, cp))
            .add_assign(&(p_h.transpose() * &p_h));
        vec.rows_mut(ci, cp).add_assign(&(p_h.transpose() * &p_r));
        assert!((info - info_c).abs().max() < 1e-10);
        assert!((vec - vec_c).abs().max() < 1e-10);
        // And the CI system is smaller: 3 + 3 - 3 rows instead of 10 + 14 - 3.
        assert_eq!(h2.nrows(), 3);
        assert_eq!(hc.nrows(), 21);
    }

    fn run(
        projection: CommonProjection,
        wrong: bool,
    ) -> (CommonOutcome, crate::estimator::test_scene::Scene, f64) {
        let mut sc = scene(6, 12, 1e-4, 1e-5);
        let tracks: Vec<CommonTrack> = (0..12)
            .map(|l| CommonTrack {
                id: l as u64,
                // With `wrong`, track 3 gets the peer's view of landmark 9.
                peer_obs: sc.peer_obs(if wrong && l == 3 { 9 } else { l }),
            })
            .collect();
        let mut opts = EstimatorOptions::default();
        opts.cooperation.projection = projection;
        let trace_before = sc.state.cov().trace();
        let out = update(
            &mut sc.state,
            &sc.db,
            &tracks,
            std::slice::from_ref(&sc.peer),
            &opts,
            &Chi2Table::new(0.95, 500),
            &TriangulationOptions::default(),
        );
        (out, sc, trace_before)
    }

    #[test]
    fn exact_common_measurements_keep_the_truth_and_shrink_the_covariance() {
        for projection in [CommonProjection::TwoStage, CommonProjection::Combined] {
            let truth = scene(6, 12, 1e-4, 1e-5);
            let (out, sc, trace_before) = run(projection, false);
            assert_eq!(out.stats.used, 12, "{projection:?}: {:?}", out.stats);
            assert!(out.fallback.is_empty());
            for (k, c) in &sc.state.clones {
                let t = &truth.state.clones[k];
                assert!((c.pos - t.pos).norm() < 1e-6, "{projection:?} clone {k}");
            }
            assert!(sc.state.cov().trace() < trace_before);
            if projection == CommonProjection::TwoStage {
                assert_eq!(out.stats.ci_rows, 12 * 3);
                assert!(out.stats.own_rows > 0);
            } else {
                assert_eq!(out.stats.own_rows, 0);
                assert!(out.stats.ci_rows > 12 * 3);
            }
        }
    }

    /// A wrong loop closure: the peer's window saw a rigid copy of our scene
    /// 2 m away (perceptual aliasing), so every match is consistent with one
    /// epipolar geometry but not with the two robots' poses: all are rejected.
    #[test]
    fn a_whole_wrong_loop_closure_is_rejected() {
        let mut sc = scene(6, 12, 1e-4, 1e-5);
        let offset = nalgebra::Vector3::new(2.0, 0.0, 0.3);
        let tracks: Vec<CommonTrack> = (0..12)
            .map(|l| {
                let seen_at = sc.landmarks[l] + offset;
                let peer_obs = sc
                    .peer
                    .poses
                    .iter()
                    .enumerate()
                    .filter_map(|(j, pose)| {
                        let p = crate::estimator::peer_window::project_normalized(pose, &seen_at)?;
                        Some(PeerObservation {
                            participant: 0,
                            pose: j,
                            xy: p.xy,
                        })
                    })
                    .collect();
                CommonTrack {
                    id: l as u64,
                    peer_obs,
                }
            })
            .collect();
        let before = sc.state.clone();
        let out = update(
            &mut sc.state,
            &sc.db,
            &tracks,
            std::slice::from_ref(&sc.peer),
            &EstimatorOptions::default(),
            &Chi2Table::new(0.95, 500),
            &TriangulationOptions::default(),
        );
        assert_eq!(out.stats.used, 0, "{:?}", out.stats);
        assert_eq!(out.fallback.len(), 12);
        assert_eq!(sc.state.cov(), before.cov());
    }

    #[test]
    fn a_wrong_association_is_gated_out_and_falls_back() {
        let (out, _, _) = run(CommonProjection::TwoStage, true);
        assert_eq!(out.fallback, vec![3]);
        assert_eq!(out.stats.rejected_chi2 + out.stats.failed, 1);
        assert_eq!(out.stats.used, 11);
    }
}

#[cfg(test)]
mod consistency {
    use super::*;
    use crate::estimator::chi2::Chi2Table;
    use crate::estimator::peer_window::project_normalized;
    use crate::estimator::projection::predict;
    use crate::estimator::test_scene::scene;
    use common::so3::exp_so3;
    use nalgebra::{Vector2, Vector3};
    use rand::{Rng, SeedableRng};
    use rand_chacha::ChaCha8Rng;
    /// A standard normal sample (Box-Muller).
    fn gauss(rng: &mut ChaCha8Rng) -> f64 {
        let u1: f64 = rng.random_range(f64::EPSILON..1.0);
        let u2: f64 = rng.random();
        (-2.0 * u1.ln()).sqrt() * (std::f64::consts::TAU * u2).cos()
    }

    /// Monte-Carlo NEES of our clone poses after a common-VIO update: truth
    /// drawn around the estimate from our covariance and the peer's, noisy
    /// measurements of the true scene. CI must not be overconfident.
    #[test]
    fn the_common_update_is_not_overconfident() {
        let mut rng = ChaCha8Rng::seed_from_u64(21);
        let (mut nees, mut trials) = (0.0, 0);
        for _ in 0..200 {
            let mut sc = scene(6, 12, 4e-4, 1e-4);
            // True clone poses: the estimate moved by a draw of our covariance
            // (diagonal in the scene).
            let calib = sc.state.calib.clone();
            let mut true_clones = std::collections::BTreeMap::new();
            for (k, c) in &sc.state.clones {
                let dth = Vector3::from_fn(|_, _| gauss(&mut rng) * 4e-4f64.sqrt());
                let dp = Vector3::from_fn(|_, _| gauss(&mut rng) * 4e-4f64.sqrt());
                true_clones.insert(*k, (c.rot * exp_so3(&dth), c.pos + dp));
            }
            // True peer poses likewise.
            let true_peer: Vec<_> = sc
                .peer
                .poses
                .iter()
                .map(|p| {
                    let dth = Vector3::from_fn(|_, _| gauss(&mut rng) * 1e-4f64.sqrt());
                    let dp = Vector3::from_fn(|_, _| gauss(&mut rng) * 1e-4f64.sqrt());
                    let mut q = *p;
                    q.rot = p.rot * exp_so3(&dth);
                    q.pos = p.pos + dp;
                    q
                })
                .collect();
            // Measurements of the true scene, 1 px noise.
            let mut db = crate::estimator::feature_db::FeatureDb::new();
            let mut tracks = Vec::new();
            for (l, p_f) in sc.landmarks.iter().enumerate() {
                for (k, (rot, pos)) in &true_clones {
                    let Some(uv) = predict(rot, pos, p_f, &calib) else {
                        continue;
                    };
                    let uv = uv + Vector2::new(gauss(&mut rng), gauss(&mut rng));
                    let Ok(uvn) = calib.camera.undistort(&uv) else {
                        continue;
                    };
                    let m = crate::estimator::feature_db::FeatureMeasurement {
                        clone_key: *k,
                        t: *k as f64,
                        uv,
                        uvn,
                    };
                    db.insert(l as u64, m).ok();
                }
                let peer_obs = true_peer
                    .iter()
                    .enumerate()
                    .filter_map(|(j, pose)| {
                        let p = project_normalized(pose, p_f)?;
                        let noise = Vector2::new(gauss(&mut rng), gauss(&mut rng)) / 458.0;
                        Some(PeerObservation {
                            participant: 0,
                            pose: j,
                            xy: p.xy + noise,
                        })
                    })
                    .collect();
                tracks.push(CommonTrack {
                    id: l as u64,
                    peer_obs,
                });
            }
            sc.db = db;
            let out = update(
                &mut sc.state,
                &sc.db,
                &tracks,
                std::slice::from_ref(&sc.peer),
                &EstimatorOptions::default(),
                &Chi2Table::new(0.95, 500),
                &TriangulationOptions::default(),
            );
            if out.stats.used == 0 {
                continue;
            }
            // NEES of the newest clone's pose.
            let key = *sc.state.clones.keys().next_back().unwrap();
            let c = &sc.state.clones[&key];
            let (tr, tp) = true_clones[&key];
            let mut e = nalgebra::DVector::zeros(6);
            e.rows_mut(0, 3)
                .copy_from(&common::so3::log_so3(&(c.rot.transpose() * tr)));
            e.rows_mut(3, 3).copy_from(&(tp - c.pos));
            let p = sc.state.block(Var::Clone(key), Var::Clone(key)).unwrap();
            nees += e.dot(&p.cholesky().unwrap().solve(&e));
            trials += 1;
        }
        let mean = nees / trials as f64;
        assert!(trials > 150, "{trials} trials used the update");
        assert!(
            mean < 6.0 * 1.15,
            "mean NEES {mean} over {trials} trials (6 dof)"
        );
    }
}
