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
    /// Our variables of the own rows.
    our_vars: Vec<Var>,
    /// Those and the peer frames of the CI rows, the columns of `h_i`.
    ci_vars: Vec<Var>,
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

/// Participant `j`'s block: its measurements of the feature at `p_f`, whitened
/// at its own pixel noise, over its items: the poses that saw it (sorted),
/// then its intrinsics when its covariance has them.
fn peer_block(
    w: &PeerWindow,
    obs: &[&PeerObservation],
    p_f: &nalgebra::Vector3<f64>,
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
        let m = peer_measurement(w, o.pose, &o.xy, p_f, p_f, w.pixel_sigma_px)?;
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
        let (poses, b) = peer_block(&participants[*p], list, &p_f).ok_or(false)?;
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
    // Peers taken into our frame through a frame our state holds depend on
    // it: its columns join ours (the own rows do not involve it).
    let mut ci_vars = our_vars.clone();
    let mut h_i = h_i;
    let mut res = res;
    ci_system::add_frame_columns(
        state,
        &mut ci_vars,
        &mut h_i,
        &mut res,
        peers
            .iter()
            .map(|p| (Part::Poses(p.participant), p.poses.as_slice(), &p.h)),
        participants,
    );
    // Gate with the innovation covariance the correlations would give if they
    // were zero (the CI one, inflated by 1/ω, would let wrong matches through).
    let mut s = state
        .covariance()
        .projected(&ci_vars, &h_i)
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
        ci_vars,
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
                    vars: r.ci_vars,
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
/// correction to first order (they were linearized before it). Returns whether
/// the update was applied: the tracks' own measurements are then spent, and
/// must not go to the MSCKF again should the CI-EKF update fail.
pub fn apply_own_rows(state: &mut State, rows: &mut CommonRows, others: &mut [CiRows]) -> bool {
    let Some((vars, h, res)) = rows.own.take() else {
        return false;
    };
    let eye = DMatrix::identity(res.len(), res.len());
    let Ok(dx) = state.ekf_update_dx(&vars, &h, &res, &eye) else {
        return false;
    };
    correct_residuals(&mut rows.ci, state, &dx);
    correct_residuals(others, state, &dx);
    true
}

/// After a failed CI-EKF update: the common tracks it would have used go to the
/// MSCKF, unless their own rows were already applied (the MSCKF would use those
/// measurements a second time; what they said of the peers is then lost).
pub fn fall_back(out: &mut CommonOutcome, own_applied: bool) {
    out.stats.used = 0;
    if own_applied {
        out.used.clear();
    } else {
        out.fallback.append(&mut out.used);
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
    let own_applied = apply_own_rows(state, &mut rows, &mut []);
    let mut out = rows.outcome;
    if ci_system::update(state, &rows.ci, participants, &opts.cooperation).is_err() {
        fall_back(&mut out, own_applied);
    }
    out
}

#[cfg(test)]
#[path = "updater_common_tests.rs"]
mod tests;
