//! Common SLAM features (thesis Section 5.3.4): our SLAM features that peers
//! also see, fused with the CI-EKF update.
//!
//! * **Measurement update** (case i, and case ii without the constraint): the
//!   peers' measurements of the feature, `z = π(R_CtoGᵀ (p_F − p_C)) + n`, with
//!   our feature in our state and the peer's camera poses as participants
//!   (Eq. 5.13). No nullspace projection: the feature is a state variable.
//! * **Constraint update** (case ii, Eqs. 5.22-5.24): our feature and the peer's
//!   SLAM feature are the same point, `p_Fa − p_Fb = 0`, with a synthetic noise
//!   (thesis: 2 cm) and the peer's landmark marginal as the participant. Only the
//!   two feature positions are involved, whatever the track lengths.

use super::chi2::Chi2Table;
use super::feature_system::Columns;
use super::options::EstimatorOptions;
use super::peer_window::{project_normalized, PeerLandmark, PeerWindow};
use super::slam_feature::global_position;
use super::state::{State, Var};
use super::updater_ci::{self, CiWeights, PeerTerm};
use super::updater_common::{CommonOutcome, CommonTrack};
use nalgebra::{DMatrix, DVector, Vector3};

/// Our SLAM feature `id` is the peer's SLAM landmark.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct SlamConstraint {
    /// Our SLAM feature (track id).
    pub id: u64,
    /// The peer's landmark estimate and marginal covariance.
    pub landmark: PeerLandmark,
}

/// One feature's rows over its own variables and its participants' poses.
struct Rows {
    vars: Vec<Var>,
    h_i: DMatrix<f64>,
    /// `(participant, poses, H)`; for constraints the "poses" are the landmark.
    peers: Vec<(usize, Vec<usize>, DMatrix<f64>)>,
    res: DVector<f64>,
}

/// Adds Jacobian blocks `(var, J)` times `a` into row block `r0` of `h` over
/// `cols` (summing blocks of the same variable).
fn add_blocks(
    h: &mut DMatrix<f64>,
    r0: usize,
    a: &DMatrix<f64>,
    jac: &[(Var, DMatrix<f64>)],
    cols: &Columns,
) {
    for (v, j) in jac {
        if let Some(c) = cols.col(*v) {
            let mut view = h.view_mut((r0, c), (a.nrows(), v.size()));
            view += a * j;
        }
    }
}

fn vars_of(jac: &[(Var, DMatrix<f64>)]) -> Vec<Var> {
    let mut vars: Vec<Var> = Vec::with_capacity(jac.len());
    for (v, _) in jac {
        if !vars.contains(v) {
            vars.push(*v);
        }
    }
    vars
}

/// The peers' measurements of our SLAM feature, whitened: `None` when a point
/// does not project.
fn measurement_rows(
    state: &State,
    track: &CommonTrack,
    participants: &[PeerWindow],
    opts: &EstimatorOptions,
) -> Option<Rows> {
    let f = state.features.get(&track.id)?;
    let (p_lin, jac) = global_position(state, track.id, f, opts.use_fej)?;
    let (p_cur, _) = global_position(state, track.id, f, false)?;
    let vars = vars_of(&jac);
    let cols = Columns::of(vars.clone());
    let m = 2 * track.peer_obs.len();
    let mut h_i = DMatrix::zeros(m, cols.dim);
    let mut res = DVector::zeros(m);
    let mut parts: Vec<(usize, Vec<usize>)> = Vec::new();
    for o in &track.peer_obs {
        match parts.iter_mut().find(|(p, _)| *p == o.participant) {
            Some((_, poses)) => poses.push(o.pose),
            None => parts.push((o.participant, vec![o.pose])),
        }
    }
    parts.sort_by_key(|(p, _)| *p);
    let mut peers: Vec<(usize, Vec<usize>, DMatrix<f64>)> = parts
        .into_iter()
        .map(|(p, mut poses)| {
            poses.sort_unstable();
            poses.dedup();
            let h = DMatrix::zeros(m, 6 * poses.len());
            (p, poses, h)
        })
        .collect();
    for (i, o) in track.peer_obs.iter().enumerate() {
        let w = participants.get(o.participant)?;
        let pose = w.poses.get(o.pose)?;
        let lin = project_normalized(pose, &p_lin)?;
        let cur = project_normalized(pose, &p_cur)?;
        let scale = w.focal_px / opts.pixel_sigma_px;
        let r = 2 * i;
        let e = (o.xy - cur.xy) * scale;
        res[r] = e.x;
        res[r + 1] = e.y;
        let h_f = DMatrix::from_iterator(2, 3, lin.h_feature.iter().map(|v| v * scale));
        add_blocks(&mut h_i, r, &h_f, &jac, &cols);
        let (_, poses, h) = peers.iter_mut().find(|(p, _, _)| *p == o.participant)?;
        let c = 6 * poses.binary_search(&o.pose).ok()?;
        h.fixed_view_mut::<2, 6>(r, c)
            .copy_from(&(lin.h_pose * scale));
    }
    Some(Rows {
        vars,
        h_i,
        peers,
        res,
    })
}

/// Gates one feature with the innovation covariance of uncorrelated robots
/// (`cov_of` gives a participant's covariance of the listed poses).
fn passes_gate(
    state: &State,
    rows: &Rows,
    r: &DMatrix<f64>,
    cov_of: impl Fn(usize, &[usize]) -> DMatrix<f64>,
    opts: &EstimatorOptions,
    chi2: &Chi2Table,
) -> bool {
    let Ok(hph) = state.covariance().projected(&rows.vars, &rows.h_i) else {
        return false;
    };
    let mut s = hph + r;
    for (p, poses, h) in &rows.peers {
        s += h * cov_of(*p, poses) * h.transpose();
    }
    let Some(chol) = s.cholesky() else {
        return false;
    };
    rows.res.dot(&chol.solve(&rows.res)) <= opts.chi2_multiplier * chi2.get(rows.res.len())
}

/// Stacks the features' rows into one CI-EKF update over the union of their
/// variables; participant `p`'s columns are the union of its poses.
fn stacked_update(
    state: &mut State,
    rows: &[Rows],
    noise_var: f64,
    cov_of: impl Fn(usize, &[usize]) -> DMatrix<f64>,
    weights: &CiWeights,
) -> bool {
    let mut vars: Vec<Var> = Vec::new();
    // Per participant: its poses (or landmark) and the columns of each.
    let mut poses_of: Vec<(usize, Vec<usize>, usize)> = Vec::new();
    for r in rows {
        for v in &r.vars {
            if !vars.contains(v) {
                vars.push(*v);
            }
        }
        for (p, poses, hp) in &r.peers {
            let width = hp.ncols() / poses.len().max(1);
            match poses_of.iter_mut().find(|(q, _, _)| q == p) {
                Some((_, list, _)) => list.extend(poses),
                None => poses_of.push((*p, poses.clone(), width)),
            }
        }
    }
    poses_of.sort_by_key(|(p, _, _)| *p);
    for (_, list, _) in poses_of.iter_mut() {
        list.sort_unstable();
        list.dedup();
    }
    let cols = Columns::of(vars);
    let m: usize = rows.iter().map(|r| r.res.len()).sum();
    let mut h = DMatrix::zeros(m, cols.dim);
    let mut res = DVector::zeros(m);
    let mut h_peers: Vec<DMatrix<f64>> = poses_of
        .iter()
        .map(|(_, p, width)| DMatrix::zeros(m, width * p.len()))
        .collect();
    let mut r0 = 0;
    for r in rows {
        let k = r.res.len();
        let local = Columns::of(r.vars.clone());
        for v in &r.vars {
            if let (Some(s), Some(d)) = (local.col(*v), cols.col(*v)) {
                h.view_mut((r0, d), (k, v.size()))
                    .copy_from(&r.h_i.view((0, s), (k, v.size())));
            }
        }
        res.rows_mut(r0, k).copy_from(&r.res);
        for (p, poses, hp) in &r.peers {
            let Some(j) = poses_of.iter().position(|(q, _, _)| q == p) else {
                continue;
            };
            let width = poses_of[j].2;
            for (a, pose) in poses.iter().enumerate() {
                let Ok(g) = poses_of[j].1.binary_search(pose) else {
                    continue;
                };
                h_peers[j]
                    .view_mut((r0, width * g), (k, width))
                    .copy_from(&hp.view((0, width * a), (k, width)));
            }
        }
        r0 += k;
    }
    let terms: Vec<PeerTerm> = poses_of
        .iter()
        .zip(h_peers)
        .map(|((p, poses, _), h)| PeerTerm {
            h,
            cov: cov_of(*p, poses),
        })
        .collect();
    let r = DMatrix::identity(m, m) * noise_var;
    updater_ci::update(state, &cols.vars, &h, &res, &r, &terms, weights).is_ok()
}

/// Updates our SLAM features `tracks` with the peers' measurements of them.
pub fn measurement_update(
    state: &mut State,
    tracks: &[CommonTrack],
    participants: &[PeerWindow],
    opts: &EstimatorOptions,
    weights: &CiWeights,
    chi2: &Chi2Table,
) -> CommonOutcome {
    let mut out = CommonOutcome::default();
    let cov_of = |p: usize, poses: &[usize]| participants[p].sub_covariance(poses);
    let mut rows = Vec::with_capacity(tracks.len());
    for t in tracks {
        match measurement_rows(state, t, participants, opts) {
            Some(r) => {
                let eye = DMatrix::identity(r.res.len(), r.res.len());
                if passes_gate(state, &r, &eye, cov_of, opts, chi2) {
                    out.used.push(t.id);
                    out.stats.peer_measurements += t.peer_obs.len();
                    rows.push(r);
                } else {
                    out.stats.rejected_chi2 += 1;
                    out.fallback.push(t.id);
                }
            }
            None => {
                out.stats.failed += 1;
                out.fallback.push(t.id);
            }
        }
    }
    out.stats.used = rows.len();
    out.stats.ci_rows = rows.iter().map(|r| r.res.len()).sum();
    if !rows.is_empty() && !stacked_update(state, &rows, 1.0, cov_of, weights) {
        out.stats.used = 0;
        out.fallback.append(&mut out.used);
    }
    out
}

/// The constraint update (Eqs. 5.22-5.24): each landmark is its own CI
/// participant (its correlation with the peer's other landmarks is unknown too).
pub fn constraint_update(
    state: &mut State,
    constraints: &[SlamConstraint],
    opts: &EstimatorOptions,
    weights: &CiWeights,
    chi2: &Chi2Table,
) -> CommonOutcome {
    let mut out = CommonOutcome::default();
    let sigma2 = opts.cooperation.constraint_sigma_m.powi(2);
    let noise = DMatrix::identity(3, 3) * sigma2;
    let cov_of = |p: usize, _: &[usize]| -> DMatrix<f64> {
        constraints.get(p).map_or_else(
            || DMatrix::identity(3, 3),
            |c| DMatrix::from_iterator(3, 3, c.landmark.cov.iter().copied()),
        )
    };
    let mut rows = Vec::with_capacity(constraints.len());
    for (p, c) in constraints.iter().enumerate() {
        let built = state.features.get(&c.id).and_then(|f| {
            let (_, jac) = global_position(state, c.id, f, opts.use_fej)?;
            let (p_cur, _) = global_position(state, c.id, f, false)?;
            Some((jac, p_cur))
        });
        let Some((jac, p_cur)) = built else {
            out.stats.failed += 1;
            out.fallback.push(c.id);
            continue;
        };
        let vars = vars_of(&jac);
        let cols = Columns::of(vars.clone());
        let mut h_i = DMatrix::zeros(3, cols.dim);
        add_blocks(&mut h_i, 0, &DMatrix::identity(3, 3), &jac, &cols);
        // h(x) = p_Fa − p_Fb, z = 0: r = p̂_Fb − p̂_Fa, H_b = −I.
        let res: Vector3<f64> = c.landmark.pos - p_cur;
        let r = Rows {
            vars,
            h_i,
            peers: vec![(p, vec![0], -DMatrix::identity(3, 3))],
            res: DVector::from_column_slice(res.as_slice()),
        };
        if passes_gate(state, &r, &noise, cov_of, opts, chi2) {
            out.used.push(c.id);
            rows.push(r);
        } else {
            out.stats.rejected_chi2 += 1;
            out.fallback.push(c.id);
        }
    }
    out.stats.used = rows.len();
    out.stats.ci_rows = 3 * rows.len();
    if !rows.is_empty() && !stacked_update(state, &rows, sigma2, cov_of, weights) {
        out.stats.used = 0;
        out.fallback.append(&mut out.used);
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::estimator::test_scene::scene;
    use crate::estimator::updater_common::CommonTrack;

    fn chi2() -> Chi2Table {
        Chi2Table::new(0.95, 500)
    }

    #[test]
    fn peer_measurements_of_our_slam_features_keep_the_truth_and_shrink_them() {
        let mut sc = scene(6, 8, 1e-4, 1e-5);
        sc.add_slam_features(&[0, 1, 2, 3], 1e-2);
        let tracks: Vec<CommonTrack> = (0..4)
            .map(|l| CommonTrack {
                id: l as u64,
                peer_obs: sc.peer_obs(if l == 2 { 6 } else { l }),
            })
            .collect();
        let before = sc.state.block(Var::Feature(0), Var::Feature(0)).unwrap();
        let out = measurement_update(
            &mut sc.state,
            &tracks,
            std::slice::from_ref(&sc.peer),
            &EstimatorOptions::default(),
            &CiWeights::FixedPeer(0.001),
            &chi2(),
        );
        // Track 2 was given the peer's view of landmark 6: gated out.
        assert_eq!(out.used, vec![0, 1, 3]);
        assert_eq!(out.fallback, vec![2]);
        let after = sc.state.block(Var::Feature(0), Var::Feature(0)).unwrap();
        assert!(
            after.trace() < 0.7 * before.trace(),
            "{} -> {}",
            before.trace(),
            after.trace()
        );
        for l in [0u64, 1, 3] {
            let p = sc.state.features[&l].pos;
            assert!((p - sc.landmarks[l as usize]).norm() < 1e-6);
        }
    }

    #[test]
    fn the_constraint_pulls_our_feature_to_the_peers_and_rejects_a_wrong_one() {
        let mut sc = scene(6, 8, 1e-4, 1e-5);
        sc.add_slam_features(&[0, 1], 1e-2);
        let truth = sc.landmarks[0];
        // Our estimate of feature 0 is 10 cm off; the peer's is right.
        sc.state.features.get_mut(&0).unwrap().pos += Vector3::new(0.1, 0.0, 0.0);
        let lm = |id: u64, pos: Vector3<f64>| PeerLandmark {
            id,
            pos,
            cov: nalgebra::Matrix3::identity() * 1e-6,
        };
        let constraints = [
            SlamConstraint {
                id: 0,
                landmark: lm(40, truth),
            },
            SlamConstraint {
                id: 1,
                landmark: lm(41, sc.landmarks[1] + Vector3::new(1.5, 0.0, 0.0)),
            },
        ];
        let before = (sc.state.features[&0].pos - truth).norm();
        let out = constraint_update(
            &mut sc.state,
            &constraints,
            &EstimatorOptions::default(),
            &CiWeights::FixedPeer(0.005),
            &chi2(),
        );
        assert_eq!(out.used, vec![0]);
        assert_eq!(out.fallback, vec![1]);
        let after = (sc.state.features[&0].pos - truth).norm();
        assert!(after < 0.5 * before, "{before} -> {after}");
    }
}
