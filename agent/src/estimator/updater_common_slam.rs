//! Common SLAM features (thesis Section 5.3.4): our SLAM features that peers
//! also see, fused with the CI-EKF update.
//!
//! * **Measurement update** (case i, and case ii without the constraint): the
//!   peers' measurements of the feature, `z = π(R_CtoGᵀ (p_F − p_C)) + n`, with
//!   our feature in our state and the peer's camera poses (and intrinsics, when
//!   it estimates them) as participants (Eq. 5.13). No nullspace projection:
//!   the feature is a state variable.
//! * **Constraint update** (case ii, Eqs. 5.22-5.24): our feature and the peer's
//!   SLAM feature are the same point, `p_Fa − p_Fb = 0`, with a synthetic noise
//!   (thesis: 2 cm) and the peer's landmark marginal as the participant. Only the
//!   two feature positions are involved, whatever the track lengths.

use super::chi2::Chi2Table;
use super::ci_system::{self, CiRows, Part, PeerRows};
use super::feature_system::Columns;
use super::options::EstimatorOptions;
use super::peer_window::{peer_measurement, PeerWindow};
use super::slam_feature::global_position;
use super::state::{State, Var};
use super::updater_common::{self, CommonOutcome, CommonTrack};
use nalgebra::{DMatrix, DVector, Vector3};

/// Our SLAM feature `id` is landmark `landmark` of participant window
/// `participant`.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct SlamConstraint {
    /// Our SLAM feature (track id).
    pub id: u64,
    /// The peer window.
    pub participant: usize,
    /// Index of the landmark in that window's list.
    pub landmark: usize,
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
) -> Option<CiRows> {
    let f = state.features.get(&track.id)?;
    let (p_lin, jac) = global_position(state, track.id, f, opts.use_fej)?;
    let (p_cur, _) = global_position(state, track.id, f, false)?;
    let vars = vars_of(&jac);
    let cols = Columns::of(vars.clone());
    let m = 2 * track.peer_obs.len();
    let mut h_i = DMatrix::zeros(m, cols.dim);
    let mut res = DVector::zeros(m);
    let mut peers: Vec<PeerRows> = Vec::new();
    for o in &track.peer_obs {
        match peers
            .iter_mut()
            .find(|p| p.part == Part::Poses(o.participant))
        {
            Some(p) => p.items.push(o.pose),
            None => peers.push(PeerRows {
                part: Part::Poses(o.participant),
                items: vec![o.pose],
                h: DMatrix::zeros(0, 0),
            }),
        }
    }
    peers.sort_by_key(|p| p.part);
    for p in peers.iter_mut() {
        p.items.sort_unstable();
        p.items.dedup();
        let Part::Poses(w) = p.part else { continue };
        let w = participants.get(w)?;
        // The peer's intrinsics after its poses, when it estimates them: its
        // normalized coordinates carry its calibration error.
        p.items.extend(w.intrinsics_item());
        let cols: usize = p.items.iter().map(|i| w.item_size(*i)).sum();
        p.h = DMatrix::zeros(m, cols);
    }
    for (i, o) in track.peer_obs.iter().enumerate() {
        let w = participants.get(o.participant)?;
        // A peer's newest observation each frame, of a track that drifts as
        // ours do: the SLAM updates' noise (`up_slam_sigma_px`), scaled from
        // our pixel noise to the peer's.
        let sigma = opts.slam_sigma_px() * (w.pixel_sigma_px / opts.pixel_sigma_px);
        let pm = peer_measurement(w, o.pose, &o.xy, &p_lin, &p_cur, sigma)?;
        let r = 2 * i;
        res[r] = pm.res.x;
        res[r + 1] = pm.res.y;
        let h_f = DMatrix::from_iterator(2, 3, pm.h_feature.iter().copied());
        add_blocks(&mut h_i, r, &h_f, &jac, &cols);
        let p = peers
            .iter_mut()
            .find(|p| p.part == Part::Poses(o.participant))?;
        let c = 6 * p.items.binary_search(&o.pose).ok()?;
        p.h.fixed_view_mut::<2, 6>(r, c).copy_from(&pm.h_pose);
        if w.intrinsics_item().is_some() {
            // The intrinsics item is the last, after 6 columns per pose.
            let c = 6 * (p.items.len() - 1);
            p.h.fixed_view_mut::<2, 8>(r, c).copy_from(&pm.h_intrinsics);
        }
    }
    Some(CiRows {
        vars,
        h: h_i,
        res,
        peers,
    })
}

/// The constraint `p_Fa − p_Fb = 0` (Eqs. 5.22-5.24) whitened by the synthetic
/// noise: `h(x) = p_Fa − p_Fb`, `z = 0`, so `r = p̂_Fb − p̂_Fa`, `H_b = −I`.
fn constraint_rows(
    state: &State,
    c: &SlamConstraint,
    participants: &[PeerWindow],
    opts: &EstimatorOptions,
) -> Option<CiRows> {
    let lm = participants.get(c.participant)?.landmarks.get(c.landmark)?;
    let f = state.features.get(&c.id)?;
    let (_, jac) = global_position(state, c.id, f, opts.use_fej)?;
    let (p_cur, _) = global_position(state, c.id, f, false)?;
    let w = 1.0 / opts.cooperation.constraint_sigma_m;
    let vars = vars_of(&jac);
    let cols = Columns::of(vars.clone());
    let mut h = DMatrix::zeros(3, cols.dim);
    add_blocks(&mut h, 0, &(DMatrix::identity(3, 3) * w), &jac, &cols);
    let res: Vector3<f64> = (lm.pos - p_cur) * w;
    Some(CiRows {
        vars,
        h,
        res: DVector::from_column_slice(res.as_slice()),
        peers: vec![PeerRows {
            part: Part::Landmarks(c.participant),
            items: vec![c.landmark],
            h: DMatrix::identity(3, 3) * -w,
        }],
    })
}

/// Gates one block with the innovation covariance of uncorrelated robots (unit
/// noise: the rows are whitened).
fn passes_gate(
    state: &State,
    rows: &CiRows,
    participants: &[PeerWindow],
    opts: &EstimatorOptions,
    chi2: &Chi2Table,
) -> bool {
    let Ok(hph) = state.covariance().projected(&rows.vars, &rows.h) else {
        return false;
    };
    let m = rows.res.len();
    let mut s = hph + DMatrix::identity(m, m);
    for p in &rows.peers {
        let cov = match p.part {
            Part::Poses(w) => participants[w].sub_covariance(&p.items),
            Part::Landmarks(w) => {
                let Some(lm) = p
                    .items
                    .first()
                    .and_then(|j| participants[w].landmarks.get(*j))
                else {
                    return false;
                };
                DMatrix::from_iterator(3, 3, lm.cov.iter().copied())
            }
        };
        s += &p.h * cov * p.h.transpose();
    }
    let Some(chol) = s.cholesky() else {
        return false;
    };
    rows.res.dot(&chol.solve(&rows.res)) <= opts.chi2_multiplier * chi2.get(m)
}

/// Builds and gates one block per item; `build` gives the item's rows.
fn gated<T>(
    state: &State,
    items: &[T],
    id_of: impl Fn(&T) -> u64,
    build: impl Fn(&T) -> Option<CiRows>,
    participants: &[PeerWindow],
    opts: &EstimatorOptions,
    chi2: &Chi2Table,
) -> (Vec<CiRows>, CommonOutcome) {
    let mut out = CommonOutcome::default();
    let mut rows = Vec::with_capacity(items.len());
    for item in items {
        let built = build(item).map(|mut r| {
            ci_system::add_block_frame_columns(state, &mut r, participants);
            r
        });
        match built {
            Some(r) if passes_gate(state, &r, participants, opts, chi2) => {
                out.used.push(id_of(item));
                out.stats.ci_rows += r.res.len();
                rows.push(r);
            }
            Some(_) => {
                out.stats.rejected_chi2 += 1;
                out.fallback.push(id_of(item));
            }
            None => {
                out.stats.failed += 1;
                out.fallback.push(id_of(item));
            }
        }
    }
    out.stats.used = rows.len();
    (rows, out)
}

/// The peers' measurements of our SLAM features `tracks`, gated.
pub fn measurement_blocks(
    state: &State,
    tracks: &[CommonTrack],
    participants: &[PeerWindow],
    opts: &EstimatorOptions,
    chi2: &Chi2Table,
) -> (Vec<CiRows>, CommonOutcome) {
    let (rows, mut out) = gated(
        state,
        tracks,
        |t| t.id,
        |t| measurement_rows(state, t, participants, opts),
        participants,
        opts,
        chi2,
    );
    out.stats.peer_measurements = tracks
        .iter()
        .filter(|t| out.used.contains(&t.id))
        .map(|t| t.peer_obs.len())
        .sum();
    (rows, out)
}

/// The SLAM constraints, gated.
pub fn constraint_blocks(
    state: &State,
    constraints: &[SlamConstraint],
    participants: &[PeerWindow],
    opts: &EstimatorOptions,
    chi2: &Chi2Table,
) -> (Vec<CiRows>, CommonOutcome) {
    gated(
        state,
        constraints,
        |c| c.id,
        |c| constraint_rows(state, c, participants, opts),
        participants,
        opts,
        chi2,
    )
}

/// Updates our SLAM features with the peers' measurements alone (one CI-EKF
/// update).
pub fn measurement_update(
    state: &mut State,
    tracks: &[CommonTrack],
    participants: &[PeerWindow],
    opts: &EstimatorOptions,
    chi2: &Chi2Table,
) -> CommonOutcome {
    let (rows, mut out) = measurement_blocks(state, tracks, participants, opts, chi2);
    if ci_system::update(state, &rows, participants, &opts.cooperation).is_err() {
        updater_common::fall_back(&mut out, false);
    }
    out
}

/// The constraint updates alone (one CI-EKF update).
pub fn constraint_update(
    state: &mut State,
    constraints: &[SlamConstraint],
    participants: &[PeerWindow],
    opts: &EstimatorOptions,
    chi2: &Chi2Table,
) -> CommonOutcome {
    let (rows, mut out) = constraint_blocks(state, constraints, participants, opts, chi2);
    if ci_system::update(state, &rows, participants, &opts.cooperation).is_err() {
        updater_common::fall_back(&mut out, false);
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::estimator::peer_window::PeerLandmark;
    use crate::estimator::test_scene::{scene, Scene};
    use crate::estimator::updater_common::CommonTrack;

    fn chi2() -> Chi2Table {
        Chi2Table::new(0.95, 500)
    }

    /// A scene with SLAM features 0-3, and our track `l` given the peer's
    /// views of landmark `view_of(l)`.
    fn four_slam_tracks(view_of: impl Fn(usize) -> usize) -> (Scene, Vec<CommonTrack>) {
        let mut sc = scene(6, 8, 1e-4, 1e-5);
        sc.add_slam_features(&[0, 1, 2, 3], 1e-2);
        let tracks = (0..4)
            .map(|l| CommonTrack {
                id: l as u64,
                peer_obs: sc.peer_obs(view_of(l)),
            })
            .collect();
        (sc, tracks)
    }

    #[test]
    fn peer_measurements_of_our_slam_features_keep_the_truth_and_shrink_them() {
        let (mut sc, tracks) = four_slam_tracks(|l| if l == 2 { 6 } else { l });
        let before = sc.state.block(Var::Feature(0), Var::Feature(0)).unwrap();
        let out = measurement_update(
            &mut sc.state,
            &tracks,
            std::slice::from_ref(&sc.peer),
            &EstimatorOptions::default(),
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
    fn the_stacked_distance_is_zero_for_true_views_and_at_least_each_blocks() {
        let (sc, tracks) = four_slam_tracks(|l| l);
        let p = std::slice::from_ref(&sc.peer);
        let opts = EstimatorOptions::default();
        let (mut rows, _) = measurement_blocks(&sc.state, &tracks, p, &opts, &chi2());
        assert_eq!(rows.len(), 4);
        let d = |r: &[CiRows]| {
            let refs: Vec<&CiRows> = r.iter().collect();
            ci_system::independent_mahalanobis(&sc.state, &refs, p).unwrap()
        };
        let (zero, m) = d(&rows);
        assert!(zero < 1e-9, "{zero}");
        assert_eq!(m, rows.iter().map(|r| r.res.len()).sum::<usize>());
        // Every view one pixel off the same way: a marginal's distance is never
        // more than the whole stack's, whatever the correlations.
        for r in rows.iter_mut() {
            r.res.add_scalar_mut(1.0);
        }
        let (all, _) = d(&rows);
        for r in &rows {
            let (one, k) = d(std::slice::from_ref(r));
            assert_eq!(k, r.res.len());
            assert!(one > 0.0 && one <= all + 1e-9, "{one} > {all}");
        }
    }

    #[test]
    fn the_constraint_pulls_our_feature_to_the_peers_and_rejects_a_wrong_one() {
        // The thesis' fixed weights (the peer's landmark at 0.005) and the
        // determinant over our pose and the measured features: both move our
        // feature to within 6 mm. `min_pose_trace` weighs the update by what
        // it tells our pose alone, which in this scene is little: it leaves our
        // feature 5.1 cm off.
        use common::estimator_options::CiWeighting;
        for w in [
            CiWeighting::FixedPeer,
            CiWeighting::MinPoseFeaturesDeterminant,
        ] {
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
            sc.peer.landmarks = vec![
                lm(40, truth),
                lm(41, sc.landmarks[1] + Vector3::new(1.5, 0.0, 0.0)),
            ];
            let constraints = [
                SlamConstraint {
                    id: 0,
                    participant: 0,
                    landmark: 0,
                },
                SlamConstraint {
                    id: 1,
                    participant: 0,
                    landmark: 1,
                },
            ];
            let before = (sc.state.features[&0].pos - truth).norm();
            let mut opts = EstimatorOptions::default();
            opts.cooperation.ci_weighting = w;
            let out = constraint_update(
                &mut sc.state,
                &constraints,
                std::slice::from_ref(&sc.peer),
                &opts,
                &chi2(),
            );
            let after = (sc.state.features[&0].pos - truth).norm();
            assert_eq!(out.used, vec![0], "{w:?}");
            assert_eq!(out.fallback, vec![1], "{w:?}");
            assert!(after < 0.1 * before, "{w:?}: {before} -> {after}");
        }
    }
}
