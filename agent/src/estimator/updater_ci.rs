//! The CI-EKF update (thesis Section 5.3.3.1, Eqs. 5.13-5.17): a measurement of
//! this robot's state and of `L` peers' states, fused without the unknown
//! cross-covariances. The joint prior is bounded by covariance intersection,
//! `Diag(P_i / ω_i, P_1 / ω_1, ..., P_L / ω_L) ≥ P` with `Σ ω = 1` (Eq. 5.14),
//! and only this robot's state and covariance are updated.
//!
//! The weights are fixed (configuration) or chosen to minimize the trace or the
//! determinant of the updated covariance, a one-dimensional search over `ω_i`
//! (`weight_search`) with the rest split evenly among the peers. Both
//! objectives only need `m x m` matrices (`m` measurement rows): the trace through
//! `tr(P Hᵀ S⁻¹ H P) = tr(S⁻¹ G)`, `G = (P Hᵀ)ᵀ (P Hᵀ) = Wᵀ W` with `W` at most
//! `m` rows (one Cholesky factor of `S` and a triangular solve per weight
//! tried), and the determinant through the determinant lemma,
//! `det P⁺ = det(P / ω) det R_o / det S`. The determinant of a block (our pose
//! and the SLAM features measured) needs that block's `k x k` prior too:
//! `ln det P⁺_BB = −k ln ω + ln det(P_BB − Zᵀ Z / ω)` with `Z = L⁻¹ Wᵀ`.

use super::state::{State, StateError, Var};
use super::weight_search::minimize_weight;
use nalgebra::{Cholesky, DMatrix, DVector, Dyn};

/// A peer's part of a measurement: its Jacobian (`m x n_o`) and the covariance
/// of the peer states it involves (`n_o x n_o`, from the peer's snapshot).
#[derive(Clone, Debug)]
pub struct PeerTerm {
    /// `H_o`.
    pub h: DMatrix<f64>,
    /// `P_oo`.
    pub cov: DMatrix<f64>,
    /// Its own fixed weight (with [`CiWeights::FixedPeer`]), or its share of the
    /// peers' weight (otherwise); `None`: the default (the `FixedPeer` value, an
    /// equal share).
    pub weight: Option<f64>,
}

/// Our smallest weight with [`CiWeights::FixedPeer`]. Each CI update divides
/// our covariance by our weight; one update per frame at a small weight would
/// throw away what we know faster than the peers can give it back (a fixed
/// peer weight of 0.2 with five participants would leave us none at all).
pub const MIN_OWN_WEIGHT: f64 = 0.5;

/// How the CI weights are chosen.
#[derive(Clone, Debug, PartialEq)]
pub enum CiWeights {
    /// Each participant's weight `ω_o` (thesis simulation: 0.001); this robot's
    /// is `ω_i = 1 − L ω_o`, but never below [`MIN_OWN_WEIGHT`]: with many
    /// participants the peers then share `1 − MIN_OWN_WEIGHT` in proportion.
    FixedPeer(f64),
    /// This robot's weight `ω_i` (thesis real data: 0.99); the participants
    /// share `1 − ω_i` evenly.
    FixedOwn(f64),
    /// Minimize the trace of the updated covariance.
    MinTrace,
    /// Minimize the trace of the updated covariance of our current pose
    /// (orientation and position of the IMU state), [`POSE_ROWS`].
    MinPoseTrace,
    /// Minimize the determinant of the updated covariance.
    MinDeterminant,
    /// Minimize the determinant of the updated covariance of our current pose
    /// ([`POSE_ROWS`]) together with the SLAM features the update measures. A
    /// determinant compares no units, where a trace would weigh a feature's cm²
    /// against the pose's mm².
    MinPoseFeaturesDeterminant,
}

/// The rows of the IMU block that [`CiWeights::MinPoseTrace`] weighs:
/// orientation then position (rad², m²: a degree and a few centimetres weigh
/// alike).
pub const POSE_ROWS: usize = 6;

/// What an update used.
#[derive(Clone, Debug, PartialEq)]
pub struct CiOutcome {
    /// This robot's weight.
    pub omega_own: f64,
    /// Each peer's weight.
    pub omega_peers: Vec<f64>,
    /// `rᵀ S⁻¹ r` with the CI innovation covariance.
    pub mahalanobis: f64,
}

/// The innovation pieces that do not depend on the weights.
struct Pieces {
    /// `H P Hᵀ` of this robot.
    hph: DMatrix<f64>,
    /// `Wᵀ` (`m x k`, `k ≤ m`) with `Wᵀ W = (P Hᵀ)ᵀ (P Hᵀ)` over the rows whose
    /// trace is minimized, for the trace objectives only: those rows themselves
    /// when they are at most `m`, else the triangular factor of their QR.
    traced_factor: Option<DMatrix<f64>>,
    /// For [`CiWeights::MinPoseFeaturesDeterminant`]: the prior covariance of
    /// the weighed block (`k x k`) and `Wᵀ` (`m x k`), `W` its rows of `P Hᵀ`.
    block: Option<(DMatrix<f64>, DMatrix<f64>)>,
    /// `H_o P_o H_oᵀ` per peer.
    peers: Vec<DMatrix<f64>>,
    /// `Σ H_o P_o H_oᵀ / s_o` with `s_o` each peer's share of `1 − ω_i`: the
    /// peers' part of `R_o` is this over `1 − ω_i`, for the searches.
    peers_at_unit_share: DMatrix<f64>,
    /// Each peer's nominal weight: its weight with `FixedPeer`, its relative
    /// share of `1 − ω_i` otherwise.
    nominal: Vec<f64>,
    /// Measurement noise.
    r: DMatrix<f64>,
    /// State dimension.
    n: usize,
}

impl Pieces {
    /// The peers share `1 − ω_i` in proportion to their nominal weights.
    fn peer_weights(&self, omega: f64) -> Vec<f64> {
        let total: f64 = self.nominal.iter().sum();
        self.nominal
            .iter()
            .map(|w| (1.0 - omega) * w / total.max(f64::MIN_POSITIVE))
            .collect()
    }

    /// `R_o = Σ H_o P_o H_oᵀ / ω_o + R`.
    fn r_others(&self, omega: f64) -> DMatrix<f64> {
        let mut r = self.r.clone();
        for (t, w) in self.peers.iter().zip(self.peer_weights(omega)) {
            r += t / w;
        }
        r
    }

    /// The objective at weight `omega` (`None` where `S` is not positive).
    fn objective(&self, omega: f64, which: &CiWeights) -> Option<f64> {
        let r_o = &self.r + &self.peers_at_unit_share / (1.0 - omega);
        let s = &self.hph / omega + &r_o;
        let chol = s.cholesky()?;
        match which {
            CiWeights::MinTrace | CiWeights::MinPoseTrace => {
                // tr(P⁺) = tr(P)/ω − tr(S⁻¹ G)/ω², and tr(P) is a constant
                // factor of 1/ω: keep it through the caller's tr(P). With
                // S = L Lᵀ and G = Wᵀ W, tr(S⁻¹ G) = ‖L⁻¹ Wᵀ‖²: one triangular
                // solve with k right-hand sides instead of m.
                let y = chol
                    .l_dirty()
                    .solve_lower_triangular(self.traced_factor.as_ref()?)?;
                Some(-y.norm_squared() / (omega * omega))
            }
            CiWeights::MinDeterminant => {
                Some(-(self.n as f64) * omega.ln() + ln_det(&r_o.cholesky()?) - ln_det(&chol))
            }
            CiWeights::MinPoseFeaturesDeterminant => {
                // P⁺_BB = (P_BB − W S⁻¹ Wᵀ / ω) / ω over the block's k rows, so
                // ln det P⁺_BB = −k ln ω + ln det(P_BB − Zᵀ Z / ω), Z = L⁻¹ Wᵀ.
                let (p_bb, w_t) = self.block.as_ref()?;
                let z = chol.l_dirty().solve_lower_triangular(w_t)?;
                let reduced = p_bb - z.tr_mul(&z) / omega;
                Some(-(p_bb.nrows() as f64) * omega.ln() + ln_det(&reduced.cholesky()?))
            }
            CiWeights::FixedPeer(_) | CiWeights::FixedOwn(_) => Some(0.0),
        }
    }
}

/// `ln det A` from the Cholesky factor of `A`.
fn ln_det(c: &Cholesky<f64, Dyn>) -> f64 {
    2.0 * c.l_dirty().diagonal().iter().map(|d| d.ln()).sum::<f64>()
}

/// Updates `state` with residual `res` (`m`), this robot's Jacobian `h` over
/// `vars`, the peers' terms and noise `r`, with CI weights chosen by `weights`.
/// With no peer the update is the standard EKF (`ω_i = 1`).
///
/// `unobserved`: `B` (`n x k`) of a part `B Bᵀ` of our covariance that is
/// independent of every participant (split CI: the prior is
/// `(P − B Bᵀ) / ω + B Bᵀ`, see [`super::ci_split`]); the weight search
/// weighs the inflated part.
#[allow(clippy::too_many_arguments)]
pub fn update(
    state: &mut State,
    vars: &[Var],
    h: &DMatrix<f64>,
    res: &DVector<f64>,
    r: &DMatrix<f64>,
    peers: &[PeerTerm],
    weights: &CiWeights,
    unobserved: Option<&DMatrix<f64>>,
) -> Result<CiOutcome, StateError> {
    let m = h.nrows();
    if res.len() != m || r.shape() != (m, m) || peers.iter().any(|p| p.h.nrows() != m) {
        return Err(StateError::Dimension("CI update sizes".into()));
    }
    if unobserved.is_some_and(|b| b.nrows() != state.dim()) {
        return Err(StateError::Dimension("CI split factor rows".into()));
    }
    let zero = DMatrix::zeros(m, m);
    let (hph, pht) = state.innovation(vars, h, &zero)?;
    // Split CI: `H P Hᵀ` and `P Hᵀ` of the inflated part `P − B Bᵀ`, and the
    // part that is not inflated, `H B (H B)ᵀ` (with the noise) and `B (H B)ᵀ`.
    let split = unobserved.map(|b| {
        let hb = jacobian_times(state, vars, h, b);
        let pht_i = b * hb.transpose();
        let hph_i = &hb * hb.transpose();
        (hph_i, pht_i)
    });
    let (hph, pht, r_split) = match &split {
        Some((hph_i, pht_i)) => (hph - hph_i, pht - pht_i, r + hph_i),
        None => (hph, pht, r.clone()),
    };
    // The rows whose trace `MinPoseTrace` minimizes (all with `MinTrace`).
    let traced = match weights {
        CiWeights::MinPoseTrace => state.offset(Var::Imu).map(|o| (o, POSE_ROWS)),
        _ => None,
    }
    .unwrap_or((0, state.dim()));
    let traced_objective = matches!(weights, CiWeights::MinTrace | CiWeights::MinPoseTrace);
    let searched = !peers.is_empty()
        && (traced_objective
            || matches!(
                weights,
                CiWeights::MinDeterminant | CiWeights::MinPoseFeaturesDeterminant
            ));
    // The rows `MinPoseFeaturesDeterminant` weighs: our pose, then each SLAM
    // feature the update measures.
    let block_rows: Vec<usize> = match (weights, state.offset(Var::Imu)) {
        (CiWeights::MinPoseFeaturesDeterminant, Some(imu)) if searched => (imu..imu + POSE_ROWS)
            .chain(
                vars.iter()
                    .filter_map(|v| match v {
                        Var::Feature(_) => state.offset(*v).map(|o| o..o + v.size()),
                        _ => None,
                    })
                    .flatten(),
            )
            .collect(),
        _ => Vec::new(),
    };
    let peer_terms: Vec<DMatrix<f64>> = peers
        .iter()
        .map(|p| &p.h * &p.cov * p.h.transpose())
        .collect();
    let nominal: Vec<f64> = peers
        .iter()
        .map(|p| {
            let default = match weights {
                CiWeights::FixedPeer(w) => *w,
                _ => 1.0,
            };
            p.weight.unwrap_or(default).max(1e-9)
        })
        .collect();
    // The peers share 1 − ω_i in proportion to their nominal weights.
    let total = nominal.iter().sum::<f64>().max(f64::MIN_POSITIVE);
    let peers_at_unit_share = if searched {
        let zero = DMatrix::zeros(m, m);
        peer_terms
            .iter()
            .zip(&nominal)
            .fold(zero, |sum, (t, w)| sum + t * (total / w))
    } else {
        DMatrix::zeros(0, 0)
    };
    let pieces = Pieces {
        traced_factor: (searched && traced_objective).then(|| {
            let rows = pht.rows(traced.0, traced.1);
            if traced.1 <= m {
                rows.transpose()
            } else {
                rows.into_owned().qr().r().transpose()
            }
        }),
        block: (!block_rows.is_empty()).then(|| {
            let p_bb = state
                .cov()
                .select_rows(&block_rows)
                .select_columns(&block_rows);
            (p_bb, pht.select_rows(&block_rows).transpose())
        }),
        hph,
        peers: peer_terms,
        peers_at_unit_share,
        nominal,
        r: r_split,
        n: state.dim(),
    };
    // The inflated part's trace over the traced rows.
    let trace_p: f64 = (traced.0..traced.0 + traced.1)
        .map(|i| state.cov()[(i, i)] - unobserved.map_or(0.0, |b| b.row(i).norm_squared()))
        .sum();
    let omega = if peers.is_empty() {
        1.0
    } else {
        match weights {
            CiWeights::FixedOwn(w) => w.clamp(1e-6, 1.0 - 1e-6),
            CiWeights::FixedPeer(_) => {
                (1.0 - pieces.nominal.iter().sum::<f64>()).clamp(MIN_OWN_WEIGHT, 1.0 - 1e-6)
            }
            CiWeights::MinTrace | CiWeights::MinPoseTrace => minimize_weight(1e-4, |w| {
                pieces
                    .objective(w, weights)
                    .map_or(f64::INFINITY, |v| trace_p / w + v)
            }),
            CiWeights::MinDeterminant | CiWeights::MinPoseFeaturesDeterminant => {
                minimize_weight(1e-4, |w| {
                    pieces.objective(w, weights).unwrap_or(f64::INFINITY)
                })
            }
        }
    };
    let r_others = pieces.r_others(omega);
    let s = &pieces.hph / omega + &r_others;
    let chol = s
        .clone()
        .cholesky()
        .ok_or(StateError::NotPositiveDefinite)?;
    let mahalanobis = res.dot(&chol.solve(res));
    match (&split, unobserved) {
        (Some((_, pht_i)), Some(b)) => {
            let pht = pht / omega + pht_i;
            state.ci_apply(s, &pht, res, omega, Some(&b.transpose()))?
        }
        _ => state.ci_apply(s, &(pht / omega), res, omega, None)?,
    }
    Ok(CiOutcome {
        omega_own: omega,
        omega_peers: pieces.peer_weights(omega),
        mahalanobis,
    })
}

/// `H B` for `H` over `vars` and `B` over the whole state (`n x k`).
fn jacobian_times(state: &State, vars: &[Var], h: &DMatrix<f64>, b: &DMatrix<f64>) -> DMatrix<f64> {
    let mut hb = DMatrix::zeros(h.nrows(), b.ncols());
    let mut c = 0;
    for v in vars {
        let k = v.size();
        if let Some(o) = state.offset(*v) {
            hb.gemm(1.0, &h.columns(c, k), &b.rows(o, k), 1.0);
        }
        c += k;
    }
    hb
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::estimator::state::ImuState;
    use common::calibration::CameraCalibration;
    use rand::{Rng, SeedableRng};
    use rand_chacha::ChaCha8Rng;

    fn random_spd(n: usize, rng: &mut ChaCha8Rng) -> DMatrix<f64> {
        let a = DMatrix::from_fn(n, n, |_, _| rng.random_range(-1.0..1.0));
        &a * a.transpose() + DMatrix::identity(n, n) * 0.1
    }

    /// A state whose only variable is the 15-dim IMU block, with covariance `p`.
    fn state_with(p: &DMatrix<f64>) -> State {
        let mut s = State::new(
            0.0,
            ImuState::default(),
            DMatrix::identity(15, 15),
            CameraCalibration::euroc_cam0(),
            &[],
        );
        s.set_cov(p.clone()).unwrap();
        s
    }

    #[test]
    fn without_peers_it_is_the_standard_ekf() {
        let mut rng = ChaCha8Rng::seed_from_u64(1);
        let p = random_spd(15, &mut rng);
        let h = DMatrix::from_fn(4, 15, |_, _| rng.random_range(-1.0..1.0));
        let res = DVector::from_fn(4, |_, _| rng.random_range(-0.1..0.1));
        let r = DMatrix::identity(4, 4) * 0.5;
        let mut a = state_with(&p);
        let mut b = state_with(&p);
        let out = update(
            &mut a,
            &[Var::Imu],
            &h,
            &res,
            &r,
            &[],
            &CiWeights::MinTrace,
            None,
        )
        .unwrap();
        b.ekf_update(&[Var::Imu], &h, &res, &r).unwrap();
        assert_eq!(out.omega_own, 1.0);
        assert!((a.cov() - b.cov()).abs().max() < 1e-12);
        assert!((a.imu.pos - b.imu.pos).norm() < 1e-12);
    }

    /// Split CI: with `B` the prior is `(P − B Bᵀ) / ω + B Bᵀ`, and the update
    /// is the Kalman update from that prior (checked against the dense
    /// formulas).
    #[test]
    fn a_split_update_inflates_only_the_rest() {
        let mut rng = ChaCha8Rng::seed_from_u64(5);
        let p = random_spd(15, &mut rng);
        // B Bᵀ ≤ P: a part of P's own square root.
        let root = p.clone().cholesky().unwrap().l();
        let b = root.columns(0, 4).into_owned() * 0.7;
        let h = DMatrix::from_fn(4, 15, |_, _| rng.random_range(-1.0..1.0));
        let res = DVector::from_fn(4, |_, _| rng.random_range(-0.1..0.1));
        let r = DMatrix::identity(4, 4) * 0.5;
        let peer = [PeerTerm {
            h: DMatrix::from_fn(4, 6, |_, _| rng.random_range(-1.0..1.0)),
            cov: random_spd(6, &mut rng),
            weight: None,
        }];
        let omega = 0.7;
        let mut s = state_with(&p);
        let w = CiWeights::FixedOwn(omega);
        let out = update(&mut s, &[Var::Imu], &h, &res, &r, &peer, &w, Some(&b)).unwrap();
        assert_eq!(out.omega_own, omega);
        let bbt = &b * b.transpose();
        let prior = (&p - &bbt) / omega + &bbt;
        let r_o = &r + &peer[0].h * &peer[0].cov * peer[0].h.transpose() / (1.0 - omega);
        let s_mat = &h * &prior * h.transpose() + r_o;
        let k = &prior * h.transpose() * s_mat.clone().try_inverse().unwrap();
        let want = &prior - &k * s_mat * k.transpose();
        assert!((s.cov() - &want).abs().max() < 1e-10 * want.abs().max());
        let dx = &k * &res;
        let moved = s.imu.pos - ImuState::default().pos;
        assert!((moved - dx.fixed_rows::<3>(3)).norm() < 1e-12);
        // Without B the same weight inflates everything.
        let mut plain = state_with(&p);
        update(&mut plain, &[Var::Imu], &h, &res, &r, &peer, &w, None).unwrap();
        assert!(plain.cov().trace() > s.cov().trace());
    }

    /// Covariance of the actual error after an update of robot i alone with gain
    /// `k`, under the true joint prior: `e⁺ = (I − K H_i) e_i − K H_o e_o − K n`.
    fn actual_error_cov(
        k: &DMatrix<f64>,
        h_i: &DMatrix<f64>,
        h_o: &DMatrix<f64>,
        p_i: &DMatrix<f64>,
        p_o: &DMatrix<f64>,
        p_io: &DMatrix<f64>,
        r: &DMatrix<f64>,
    ) -> DMatrix<f64> {
        let a = DMatrix::identity(p_i.nrows(), p_i.nrows()) - k * h_i;
        let b = -(k * h_o);
        &a * p_i * a.transpose()
            + &b * p_o * b.transpose()
            + &a * p_io * b.transpose()
            + &b * p_io.transpose() * a.transpose()
            + k * r * k.transpose()
    }

    /// A random update of robot i with one peer (15 and 6 variables, 5 rows)
    /// under a true joint prior with strong random cross-correlation.
    struct Correlated {
        p_i: DMatrix<f64>,
        p_o: DMatrix<f64>,
        p_io: DMatrix<f64>,
        h_i: DMatrix<f64>,
        h_o: DMatrix<f64>,
        r: DMatrix<f64>,
    }

    impl Correlated {
        fn draw(rng: &mut ChaCha8Rng) -> Self {
            let (ni, no, m) = (15, 6, 5);
            let joint = random_spd(ni + no, rng);
            Self {
                p_i: joint.view((0, 0), (ni, ni)).into_owned(),
                p_o: joint.view((ni, ni), (no, no)).into_owned(),
                p_io: joint.view((0, ni), (ni, no)).into_owned(),
                h_i: DMatrix::from_fn(m, ni, |_, _| rng.random_range(-1.0..1.0)),
                h_o: DMatrix::from_fn(m, no, |_, _| rng.random_range(-1.0..1.0)),
                r: DMatrix::identity(m, m) * 0.2,
            }
        }

        /// Robot i after a CI update with `weights` (a zero residual), and what
        /// the update used.
        fn update(&self, weights: &CiWeights) -> (State, CiOutcome) {
            let mut s = state_with(&self.p_i);
            let peer = [PeerTerm {
                h: self.h_o.clone(),
                cov: self.p_o.clone(),
                weight: None,
            }];
            let zero = DVector::zeros(self.r.nrows());
            let out = update(
                &mut s,
                &[Var::Imu],
                &self.h_i,
                &zero,
                &self.r,
                &peer,
                weights,
                None,
            )
            .unwrap();
            (s, out)
        }

        /// The smallest eigenvalue of `reported − actual`, the actual error
        /// covariance after the update with gain `k`: at least 0 when the
        /// reported covariance bounds the error.
        fn bound_gap(&self, reported: &DMatrix<f64>, k: &DMatrix<f64>) -> f64 {
            let (h_i, h_o) = (&self.h_i, &self.h_o);
            let actual = actual_error_cov(k, h_i, h_o, &self.p_i, &self.p_o, &self.p_io, &self.r);
            let gap = reported - actual;
            let gap = (&gap + gap.transpose()) * 0.5;
            gap.symmetric_eigen().eigenvalues.min()
        }

        /// The gain the CI update used: `K = (P_i/ω_i) H_iᵀ S⁻¹`.
        fn ci_gain(&self, out: &CiOutcome) -> DMatrix<f64> {
            let (wi, wo) = (out.omega_own, out.omega_peers[0]);
            let (h_i, h_o) = (&self.h_i, &self.h_o);
            let s_ci = h_i * &self.p_i * h_i.transpose() / wi
                + h_o * &self.p_o * h_o.transpose() / wo
                + &self.r;
            &self.p_i / wi * h_i.transpose() * s_ci.try_inverse().unwrap()
        }
    }

    /// The CI bound holds whatever the true cross-covariance: the covariance
    /// this robot reports after the update is at least the actual covariance of
    /// its error, computed with the true correlated joint prior.
    #[test]
    fn updated_covariance_bounds_the_actual_error_for_any_correlation() {
        let mut rng = ChaCha8Rng::seed_from_u64(7);
        let mut naive_violations = 0;
        for trial in 0..50 {
            let c = Correlated::draw(&mut rng);
            let weights = match trial % 3 {
                0 => CiWeights::FixedOwn(rng.random_range(0.05..0.95)),
                1 => CiWeights::MinTrace,
                _ => CiWeights::MinDeterminant,
            };
            let (s, out) = c.update(&weights);
            let (wi, wo) = (out.omega_own, out.omega_peers[0]);
            assert!((wi + wo - 1.0).abs() < 1e-12);
            let min_eig = c.bound_gap(s.cov(), &c.ci_gain(&out));
            assert!(
                min_eig > -1e-9,
                "trial {trial} ({weights:?}): min eigenvalue {min_eig}"
            );

            // Control: ignoring the correlation (no inflation) is overconfident in
            // some trials, so the bound above is not vacuous.
            let (h_i, h_o, p_i) = (&c.h_i, &c.h_o, &c.p_i);
            let s_naive = h_i * p_i * h_i.transpose() + h_o * &c.p_o * h_o.transpose() + &c.r;
            let k = p_i * h_i.transpose() * s_naive.try_inverse().unwrap();
            let reported = (DMatrix::identity(p_i.nrows(), p_i.nrows()) - &k * h_i) * p_i;
            if c.bound_gap(&reported, &k) < -1e-6 {
                naive_violations += 1;
            }
        }
        assert!(
            naive_violations > 5,
            "naive update violated the bound only {naive_violations} times"
        );
    }

    #[test]
    fn optimized_weights_beat_fixed_ones_on_their_objective() {
        let mut rng = ChaCha8Rng::seed_from_u64(3);
        let p_i = random_spd(15, &mut rng);
        let p_o = random_spd(6, &mut rng);
        let pose_trace = |c: &DMatrix<f64>| (0..POSE_ROWS).map(|i| c[(i, i)]).sum::<f64>();
        // Fewer rows than traced variables (the search works from the QR factor
        // of the traced rows of P Hᵀ) and more (from the rows themselves).
        for m in [4, 20] {
            let h_i = DMatrix::from_fn(m, 15, |_, _| rng.random_range(-1.0..1.0));
            let h_o = DMatrix::from_fn(m, 6, |_, _| rng.random_range(-1.0..1.0));
            let r = DMatrix::identity(m, m) * 0.3;
            let peer = [PeerTerm {
                h: h_o,
                cov: p_o.clone(),
                weight: None,
            }];
            let run = |w: &CiWeights| {
                let mut s = state_with(&p_i);
                update(
                    &mut s,
                    &[Var::Imu],
                    &h_i,
                    &DVector::zeros(m),
                    &r,
                    &peer,
                    w,
                    None,
                )
                .unwrap();
                s.cov().clone()
            };
            let best_trace = run(&CiWeights::MinTrace).trace();
            let best_pose = pose_trace(&run(&CiWeights::MinPoseTrace));
            let best_det = run(&CiWeights::MinDeterminant).determinant();
            for w in [0.1, 0.3, 0.5, 0.7, 0.9, 0.99] {
                let c = run(&CiWeights::FixedOwn(w));
                let (t, d) = (c.trace(), c.determinant());
                assert!(
                    best_trace <= t * (1.0 + 1e-9),
                    "m {m}, ω {w}: {best_trace} > {t}"
                );
                assert!(
                    best_pose <= pose_trace(&c) * (1.0 + 1e-9),
                    "m {m}, ω {w}: pose"
                );
                assert!(
                    best_det <= d * (1.0 + 1e-6),
                    "m {m}, ω {w}: {best_det} > {d}"
                );
            }
        }
    }

    /// `MinPoseTrace` minimizes the pose block's trace, not the whole state's: it
    /// beats every fixed weight there, and its covariance still bounds the
    /// actual error whatever the true correlation with the peer.
    #[test]
    fn pose_trace_weights_minimize_the_pose_block_and_stay_conservative() {
        let mut rng = ChaCha8Rng::seed_from_u64(11);
        let pose_trace = |s: &State| (0..POSE_ROWS).map(|i| s.cov()[(i, i)]).sum::<f64>();
        for trial in 0..10 {
            let c = Correlated::draw(&mut rng);
            let (best, out) = c.update(&CiWeights::MinPoseTrace);
            for w in [0.1, 0.3, 0.5, 0.7, 0.9, 0.99] {
                let (fixed, _) = c.update(&CiWeights::FixedOwn(w));
                assert!(
                    pose_trace(&best) <= pose_trace(&fixed) * (1.0 + 1e-9),
                    "trial {trial}, ω {w}"
                );
            }
            // The bound of Eq. (5.14) holds at the chosen weights.
            let min_eig = c.bound_gap(best.cov(), &c.ci_gain(&out));
            assert!(min_eig > -1e-9, "trial {trial}: min eigenvalue {min_eig}");
        }
    }

    /// `MinPoseFeaturesDeterminant` minimizes the determinant of the block of
    /// our pose and the SLAM features the update measures (not of a feature it
    /// does not measure): it beats every fixed weight there, and the CI bound
    /// holds at its weights.
    #[test]
    fn pose_feature_determinant_weights_minimize_their_block_and_stay_conservative() {
        let mut rng = ChaCha8Rng::seed_from_u64(5);
        let feature_cov = DMatrix::identity(3, 3);
        // IMU (15), feature 0 (measured), feature 1 (not measured).
        let (ni, no, m) = (21, 6, 7);
        let measured = [Var::Imu, Var::Feature(0)];
        for trial in 0..10 {
            let joint = random_spd(ni + no, &mut rng);
            let p_i = joint.view((0, 0), (ni, ni)).into_owned();
            let p_o = joint.view((ni, ni), (no, no)).into_owned();
            let p_io = joint.view((0, ni), (ni, no)).into_owned();
            // Jacobian over the measured variables (IMU and feature 0, 18
            // columns), and the same embedded in the whole state.
            let h_meas = DMatrix::from_fn(m, 18, |_, _| rng.random_range(-1.0..1.0));
            let mut h_full = DMatrix::zeros(m, ni);
            h_full.columns_mut(0, 18).copy_from(&h_meas);
            let h_o = DMatrix::from_fn(m, no, |_, _| rng.random_range(-1.0..1.0));
            let r = DMatrix::identity(m, m) * 0.2;
            let peer = [PeerTerm {
                h: h_o.clone(),
                cov: p_o.clone(),
                weight: None,
            }];
            let run = |w: &CiWeights| {
                let mut s = State::new(
                    0.0,
                    ImuState::default(),
                    DMatrix::identity(15, 15),
                    CameraCalibration::euroc_cam0(),
                    &[
                        (Var::Feature(0), feature_cov.clone()),
                        (Var::Feature(1), feature_cov.clone()),
                    ],
                );
                s.set_cov(p_i.clone()).unwrap();
                let out = update(
                    &mut s,
                    &measured,
                    &h_meas,
                    &DVector::zeros(m),
                    &r,
                    &peer,
                    w,
                    None,
                )
                .unwrap();
                (s, out)
            };
            // The block: orientation and position (rows 0-5), feature 0 (15-17).
            let rows: Vec<usize> = (0..POSE_ROWS).chain(15..18).collect();
            let block_det = |s: &State| {
                s.cov()
                    .select_rows(&rows)
                    .select_columns(&rows)
                    .determinant()
            };
            let (best, out) = run(&CiWeights::MinPoseFeaturesDeterminant);
            for w in [0.1, 0.3, 0.5, 0.7, 0.9, 0.99] {
                let (fixed, _) = run(&CiWeights::FixedOwn(w));
                assert!(
                    block_det(&best) <= block_det(&fixed) * (1.0 + 1e-6),
                    "trial {trial}, ω {w}"
                );
            }
            let c = Correlated {
                p_i,
                p_o,
                p_io,
                h_i: h_full,
                h_o,
                r,
            };
            let min_eig = c.bound_gap(best.cov(), &c.ci_gain(&out));
            assert!(min_eig > -1e-9, "trial {trial}: min eigenvalue {min_eig}");
        }
    }

    #[test]
    fn many_fixed_peer_weights_never_push_our_weight_below_the_floor() {
        let mut rng = ChaCha8Rng::seed_from_u64(4);
        let p_i = random_spd(15, &mut rng);
        let h_i = DMatrix::from_fn(4, 15, |_, _| rng.random_range(-1.0..1.0));
        let peers: Vec<PeerTerm> = (0..10)
            .map(|_| PeerTerm {
                h: DMatrix::from_fn(4, 6, |_, _| rng.random_range(-1.0..1.0)),
                cov: random_spd(6, &mut rng),
                weight: None,
            })
            .collect();
        let r = DMatrix::identity(4, 4) * 0.3;
        let mut s = state_with(&p_i);
        let out = update(
            &mut s,
            &[Var::Imu],
            &h_i,
            &DVector::zeros(4),
            &r,
            &peers,
            &CiWeights::FixedPeer(0.2),
            None,
        )
        .unwrap();
        // Ten peers at 0.2 would ask for 2.0: we keep the floor, and the peers
        // share the rest equally (the weights still sum to one).
        assert_eq!(out.omega_own, MIN_OWN_WEIGHT);
        let total: f64 = out.omega_peers.iter().sum();
        assert!((out.omega_own + total - 1.0).abs() < 1e-12);
        assert!(out.omega_peers.iter().all(|w| (w - 0.05).abs() < 1e-12));
    }
}
