//! Split covariance intersection over the directions no peer observes
//! (`cooperation.split_unobservable`) and over each robot's own calibration
//! (`cooperation.split_calibration`).
//!
//! CI bounds the unknown correlation between our estimate and a peer's by
//! inflating our whole covariance, `P / ω`. A peer's window taken into our
//! frame through a peer frame held in our state is measured only relative to
//! our pose: a yaw and translation of our whole world frame moves our pose,
//! clones, global features and every held frame together and changes no such
//! measurement. Along those four directions (`N`,
//! [`unobservable_directions`](super::observability::unobservable_directions))
//! nothing but our own measurements ever informed our estimate, so the part of
//! our covariance there, conditioned on the rest, is treated as independent of
//! the peers and is not inflated (split CI, Julier and Uhlmann): with
//! `P = P_d + B Bᵀ`, `B Bᵀ = N (Nᵀ P⁻¹ N)⁻¹ Nᵀ`, the prior is
//! `P_d / ω + B Bᵀ`. `P_d` stays positive semidefinite, since `B Bᵀ` is the
//! covariance of the four directions' coordinates given every other
//! coordinate (a Schur complement).
//!
//! Without it, every cooperative update multiplies our frame-and-pose
//! uncertainty by `1/ω` and nothing shrinks it again: a frame held for a whole
//! flight ends with a covariance 25-100 times its error (README, "Robots in
//! their own frames").
//!
//! The calibration (time offset, extrinsics, intrinsics) is split the same
//! way: it describes one robot's own rig, which no peer estimates, and at
//! about ten updates a second the `1/ω` left a fleet's robots knowing their
//! calibration 2-5 times worse than alone by the end of a flight, one worse
//! than its prior. Ours, given the
//! rest of our state, stays out of `1/ω`; a peer window's intrinsics, given
//! its poses, out of the peer's `1/(1−ω)` (README, "Results: three robots").

use super::state::{State, Var};
use common::messages::INTRINSICS_DIM;
use nalgebra::DMatrix;

/// The relative increase of each variance before `P` is factored.
const REGULARIZATION: f64 = 1e-8;

/// The calibration's columns of the state (time offset, extrinsics,
/// intrinsics, those it holds) as unit directions, `n x k`; `None` without any.
pub fn calibration_directions(state: &State) -> Option<DMatrix<f64>> {
    let rows: Vec<usize> = [Var::TimeOffset, Var::Extrinsic, Var::Intrinsics]
        .into_iter()
        .filter_map(|v| state.offset(v).map(|o| o..o + v.size()))
        .flatten()
        .collect();
    if rows.is_empty() {
        return None;
    }
    let mut n = DMatrix::zeros(state.dim(), rows.len());
    for (j, i) in rows.into_iter().enumerate() {
        n[(i, j)] = 1.0;
    }
    Some(n)
}

/// `B` (`m x 8`) for a peer window's covariance `cov` (`m x m`) whose
/// intrinsics (8) start at column `at`: `B Bᵀ` is the intrinsics' covariance
/// given the window's poses, which split CI leaves out of the peer's
/// inflation (`cooperation.split_calibration`). `None` when `cov` has no such
/// columns or the conditioning fails (the caller then inflates it all).
pub fn peer_intrinsics_factor(cov: &DMatrix<f64>, at: usize) -> Option<DMatrix<f64>> {
    let m = cov.nrows();
    if at + INTRINSICS_DIM > m || cov.ncols() != m {
        return None;
    }
    let mut n = DMatrix::zeros(m, INTRINSICS_DIM);
    for j in 0..INTRINSICS_DIM {
        n[(at + j, j)] = 1.0;
    }
    factor_given_rest(cov.clone(), &n)
}

/// `B` over the directions `n` (`n x k`, columns side by side):
/// `B Bᵀ = N (Nᵀ P⁻¹ N)⁻¹ Nᵀ`, the covariance along them given the rest.
/// `None` when `P` or `Nᵀ P⁻¹ N` is not positive definite.
pub fn conditional_factor(state: &State, n: &DMatrix<f64>) -> Option<DMatrix<f64>> {
    factor_given_rest(state.cov().clone(), n)
}

/// `B` with `B Bᵀ = N (Nᵀ P⁻¹ N)⁻¹ Nᵀ` for the covariance `p`.
fn factor_given_rest(mut p: DMatrix<f64>, n: &DMatrix<f64>) -> Option<DMatrix<f64>> {
    // The newest clone is a copy of the IMU pose until the next propagation,
    // so a state's `P` is singular: condition on a `P` whose every variance is
    // larger by a part in 10⁸ (the copy's difference is then known to that
    // part, and N, which moves both alike, does not see it).
    for i in 0..p.nrows() {
        p[(i, i)] *= 1.0 + REGULARIZATION;
    }
    let chol = p.cholesky()?;
    // Nᵀ P⁻¹ N = Yᵀ Y with Y = L⁻¹ N.
    let y = chol.l_dirty().solve_lower_triangular(n)?;
    let information = y.tr_mul(&y);
    let sigma = information.cholesky()?.inverse();
    let root = sigma.cholesky()?;
    Some(n * root.l())
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::estimator::feature_system::Columns;
    use crate::estimator::observability::unobservable_directions;
    use crate::estimator::state::{PeerFrameMean, SlamFeature, Var};
    use crate::estimator::test_scene::scene;
    use nalgebra::Vector3;
    use rand::{Rng, SeedableRng};
    use rand_chacha::ChaCha8Rng;

    /// A scene's state with a peer frame, and a random full covariance.
    fn state() -> State {
        let mut s = scene(5, 3, 1e-4, 1e-4).state;
        let var = Var::PeerFrame { peer: 2, epoch: 1 };
        s.means.peer_frames.insert(
            (2, 1),
            PeerFrameMean {
                yaw_rad: 0.4,
                t_m: Vector3::new(3.0, -1.0, 0.5),
                measurements: 0,
            },
        );
        let mut rng = ChaCha8Rng::seed_from_u64(7);
        s.augment(var, &[], &(DMatrix::identity(4, 4) * 0.01))
            .unwrap();
        // A global SLAM feature.
        let p_f = Vector3::new(1.0, 4.0, -0.5);
        s.means.features.insert(
            99,
            SlamFeature {
                pos: p_f,
                pos_fej: p_f,
                anchor: None,
                inverse_depth: false,
            },
        );
        s.augment(Var::Feature(99), &[], &(DMatrix::identity(3, 3) * 0.01))
            .unwrap();
        let n = s.dim();
        let a = DMatrix::from_fn(n, n, |_, _| rng.random_range(-0.1..0.1));
        s.set_cov(&a * a.transpose() + DMatrix::identity(n, n) * 1e-3)
            .unwrap();
        s
    }

    /// The four directions are what a turn `ψ` about our world's z axis and a
    /// shift `t` of it do to every variable's error state (numerically, with
    /// the means' own boxminus), peer frames included: the conventions of
    /// `unobservable_directions` are the state's.
    #[test]
    fn the_directions_are_a_turn_and_shift_of_our_whole_world() {
        let mut s = state();
        s.means.imu.vel = Vector3::new(0.4, -0.3, 0.1);
        s.means.reset_first_estimates();
        let vars: Vec<Var> = s.vars().collect();
        let cols = Columns::of(vars.clone());
        let n = unobservable_directions(&cols, &s.means);
        let moved = |g: [f64; 4]| {
            let rz = nalgebra::Rotation3::from_axis_angle(&Vector3::z_axis(), g[3]).into_inner();
            let t = Vector3::new(g[0], g[1], g[2]);
            let mut m = s.means.clone();
            m.imu.rot = rz * m.imu.rot;
            m.imu.pos = rz * m.imu.pos + t;
            m.imu.vel = rz * m.imu.vel;
            for c in m.clones.values_mut() {
                c.rot = rz * c.rot;
                c.pos = rz * c.pos + t;
            }
            for f in m.features.values_mut().filter(|f| f.anchor.is_none()) {
                f.pos = rz * f.pos + t;
            }
            for a in m.peer_frames.values_mut() {
                a.yaw_rad += g[3];
                a.t_m = rz * a.t_m + t;
            }
            m.boxminus(&s.means, &vars)
        };
        let h = 1e-6;
        for k in 0..4 {
            let mut plus = [0.0; 4];
            plus[k] = h;
            let mut minus = [0.0; 4];
            minus[k] = -h;
            let num = (moved(plus) - moved(minus)) / (2.0 * h);
            let err = (&num - n.column(k)).abs().max();
            assert!(err < 1e-6, "direction {k}: off by {err}");
        }
        assert!(s.means.features.values().any(|f| f.anchor.is_none()));
    }

    #[test]
    fn the_unobserved_part_is_the_conditional_covariance_along_the_directions() {
        let s = state();
        let cols = Columns::of(s.vars().collect());
        let n = unobservable_directions(&cols, &s.means);
        let b = conditional_factor(&s, &n).expect("factor");
        let p = s.cov();
        // (P − B Bᵀ) P⁻¹ N = N − N = 0: the inflated part loses exactly the
        // four directions' rank and stays positive semidefinite.
        let pd = p - &b * b.transpose();
        let eig = pd.clone().symmetric_eigen();
        let mut ev: Vec<f64> = eig.eigenvalues.iter().copied().collect();
        ev.sort_by(f64::total_cmp);
        let scale = ev[ev.len() - 1];
        for e in &ev[..4] {
            // Zero but for the factorization's regularization.
            assert!(e.abs() < 1e-7 * scale, "{ev:?}");
        }
        assert!(ev[4] > 1e-4 * scale, "{ev:?}");
        // Along N: B Bᵀ = N Σ Nᵀ with Σ⁻¹ = Nᵀ P⁻¹ N.
        let info = n.transpose() * p.clone().try_inverse().unwrap() * &n;
        let sigma = info.try_inverse().unwrap();
        let expect = &n * sigma * n.transpose();
        assert!((&b * b.transpose() - &expect).norm() < 1e-6 * expect.norm());
    }

    /// The smallest eigenvalue of `a` relative to its largest.
    fn relative_min_eigenvalue(a: &DMatrix<f64>) -> f64 {
        let ev = a.clone().symmetric_eigen().eigenvalues;
        ev.min() / ev.max()
    }

    /// Our calibration's split part lives on the calibration's rows alone, is
    /// its covariance given the rest of the state, and leaves the inflated
    /// rest positive semidefinite.
    #[test]
    fn the_calibration_part_is_its_covariance_given_the_rest() {
        let s = state();
        let n = calibration_directions(&s).expect("the scene estimates its extrinsics");
        assert_eq!(n.ncols(), 6);
        let b = conditional_factor(&s, &n).expect("factor");
        let o = s.offset(Var::Extrinsic).unwrap();
        for i in (0..s.dim()).filter(|i| !(o..o + 6).contains(i)) {
            assert_eq!(b.row(i).norm(), 0.0, "row {i} is not the calibration's");
        }
        let p = s.cov();
        let info = p
            .clone()
            .try_inverse()
            .unwrap()
            .view((o, o), (6, 6))
            .into_owned();
        let given_rest = info.try_inverse().unwrap();
        let bbt = &b * b.transpose();
        let got = bbt.view((o, o), (6, 6)).into_owned();
        assert!((&got - &given_rest).norm() < 1e-6 * given_rest.norm());
        assert!(relative_min_eigenvalue(&(p - &bbt)) > -1e-7);
        // Less than the calibration's marginal: the part the rest explains
        // stays inflated.
        let marginal = p.view((o, o), (6, 6)).into_owned();
        assert!(relative_min_eigenvalue(&(marginal - got)) > -1e-7);
    }

    /// A state without calibration variables has nothing to split.
    #[test]
    fn without_calibration_states_there_is_no_calibration_part() {
        let s = State::new(
            0.0,
            crate::estimator::state::ImuState::default(),
            DMatrix::identity(15, 15),
            common::calibration::CameraCalibration::euroc_cam0(),
            &[],
        );
        assert!(calibration_directions(&s).is_none());
    }

    /// A peer window's intrinsics part (two poses, then the intrinsics): its
    /// intrinsics' covariance given the poses, on the intrinsics' rows only.
    #[test]
    fn a_peer_window_intrinsics_part_is_their_covariance_given_the_poses() {
        let mut rng = ChaCha8Rng::seed_from_u64(11);
        let m = 12 + INTRINSICS_DIM;
        let a = DMatrix::from_fn(m, m, |_, _| rng.random_range(-0.1..0.1));
        let cov = &a * a.transpose() + DMatrix::identity(m, m) * 1e-3;
        let b = peer_intrinsics_factor(&cov, 12).expect("factor");
        let bbt = &b * b.transpose();
        assert_eq!(bbt.view((0, 0), (12, m)).norm(), 0.0);
        let info = cov.clone().try_inverse().unwrap();
        let given_poses = info
            .view((12, 12), (INTRINSICS_DIM, INTRINSICS_DIM))
            .into_owned()
            .try_inverse()
            .unwrap();
        let got = bbt
            .view((12, 12), (INTRINSICS_DIM, INTRINSICS_DIM))
            .into_owned();
        assert!((&got - &given_poses).norm() < 1e-6 * given_poses.norm());
        assert!(relative_min_eigenvalue(&(&cov - &bbt)) > -1e-7);
        assert!(peer_intrinsics_factor(&cov, 13).is_none());
    }
}
