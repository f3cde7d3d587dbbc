//! The four directions a visual-inertial system cannot observe (global
//! translation and yaw about gravity, thesis Section 2.2.2), and the
//! observability-constrained measurement Jacobian: one evaluated at the
//! current estimate and then changed as little as possible (in the Frobenius
//! norm, as Hesch et al.'s OC-EKF does) so that it gives no information along
//! those directions as the first estimates define them.
//!
//! Why: with First-Estimates Jacobians the MSCKF linearizes every clone at the
//! pose it had when cloned. On a platform that moves slowly, few tracks
//! triangulate per frame and the clones are corrected long after they were
//! cloned; the Jacobians at those stale poses then misplace the scale, and
//! the filter claims it (a circle started at 0.34 m/s: MSCKF-only position
//! NEES 14.3 with first estimates, 1.46 with these Jacobians). Evaluated at
//! the current estimate without the projection they leak yaw information
//! (V1_02 with every measurement Jacobian there: orientation NEES 17.6); the
//! projection keeps FEJ's nullspace.

use super::feature_system::Columns;
use super::state::{Means, Var};
use nalgebra::{DMatrix, Vector3};

/// The unobservable directions over the columns `cols` (one per column of the
/// result: x, y, z translation, then yaw), at the first estimates of the IMU
/// state, the clones and global SLAM features, and at the mean of peer frames
/// held in the state. Orientation errors are local
/// (`R_ItoG ← R_ItoG Exp(δθ)`): a yaw `ψ` about the world z axis is
/// `δθ = R_ItoGᵀ e_z ψ`, `δp = ψ e_z × p`, `δv = ψ e_z × v`. A peer frame
/// (`p_G = R_z(ψ_a) p_H + t_a`) turns with the world: `δψ_a = ψ`,
/// `δt_a = ψ e_z × t_a` plus the translation. Calibration, biases, anchored
/// features and the time offset do not move.
pub fn unobservable_directions(cols: &Columns, means: &Means) -> DMatrix<f64> {
    let ez = Vector3::z();
    let mut n = DMatrix::zeros(cols.dim, 4);
    let put_point = |n: &mut DMatrix<f64>, o: usize, p: &Vector3<f64>| {
        let yaw = ez.cross(p);
        for a in 0..3 {
            n[(o + a, a)] = 1.0;
            n[(o + a, 3)] = yaw[a];
        }
    };
    for v in &cols.vars {
        let Some(o) = cols.col(*v) else {
            continue;
        };
        match v {
            Var::Clone(k) => {
                let Some(c) = means.clones.get(k) else {
                    continue;
                };
                let th = c.rot_fej.transpose() * ez;
                for a in 0..3 {
                    n[(o + a, 3)] = th[a];
                }
                put_point(&mut n, o + 3, &c.pos_fej);
            }
            Var::Feature(id) => {
                if let Some(f) = means.features.get(id).filter(|f| f.anchor.is_none()) {
                    put_point(&mut n, o, &f.pos_fej);
                }
            }
            Var::Imu => {
                let fej = &means.imu_fej;
                let th = fej.rot.transpose() * ez;
                let dv = ez.cross(&fej.vel);
                for a in 0..3 {
                    n[(o + a, 3)] = th[a];
                    n[(o + 6 + a, 3)] = dv[a];
                }
                put_point(&mut n, o + 3, &fej.pos);
            }
            Var::PeerFrame { peer, epoch } => {
                if let Some(f) = means.peer_frames.get(&(*peer, *epoch)) {
                    n[(o, 3)] = 1.0;
                    put_point(&mut n, o + 1, &f.t_m);
                }
            }
            _ => {}
        }
    }
    n
}

/// `H ← H − H N (NᵀN)⁻¹ Nᵀ`: the nearest Jacobian (row by row, Frobenius)
/// with `H N = 0`. `N` without full column rank (no clone among the columns)
/// leaves `H` as it is.
pub fn project_out(h: &mut DMatrix<f64>, n: &DMatrix<f64>) {
    let Some(inv) = (n.transpose() * n).try_inverse() else {
        return;
    };
    let hn = &*h * n;
    *h -= hn * inv * n.transpose();
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::estimator::feature_system::build;
    use crate::estimator::linalg::nullspace_project_in_place;
    use crate::estimator::test_scene::scene;
    use crate::estimator::triangulation::TriangulationOptions;
    use common::so3::exp_so3;

    /// The MSCKF system of track `id` of `s`, Jacobians at the current
    /// estimate, the feature projected out.
    fn msckf_jacobian(s: &crate::estimator::test_scene::Scene, id: u64) -> (Columns, DMatrix<f64>) {
        let cols = Columns::window(&s.state);
        let feature = s.db.get(id).expect("track");
        let mut sys = build(
            &s.state.means,
            feature,
            &cols,
            false,
            &TriangulationOptions::default(),
        )
        .expect("system");
        nullspace_project_in_place(&mut sys.h_f, &mut sys.h_x, &mut sys.res);
        (cols, sys.h_x)
    }

    #[test]
    fn a_jacobian_at_one_point_gives_no_information_along_that_points_directions() {
        // First estimates equal to the current estimate: the MSCKF Jacobian
        // already annihilates them (this checks the directions' convention),
        // and the projection changes nothing.
        let s = scene(6, 4, 1e-4, 1e-4);
        for id in 0..4 {
            let (cols, h) = msckf_jacobian(&s, id);
            let n = unobservable_directions(&cols, &s.state.means);
            let leak = (&h * &n).norm() / h.norm();
            assert!(leak < 1e-12, "track {id}: |H N| / |H| = {leak:e}");
            let mut p = h.clone();
            project_out(&mut p, &n);
            assert!((&p - &h).norm() < 1e-12 * h.norm());
        }
    }

    #[test]
    fn the_projection_annihilates_the_first_estimates_directions_and_changes_little() {
        // First estimates off the current estimate (cloned before corrections
        // of 5 cm and 0.5 deg): the Jacobian at the current estimate leaks
        // along the first estimates' directions; projected, it does not, and
        // it stays close to what it was.
        let mut s = scene(6, 4, 1e-4, 1e-4);
        for (k, c) in s.state.means.clones.values_mut().enumerate() {
            let d = 0.01 * (k as f64 + 1.0);
            c.pos_fej = c.pos + Vector3::new(d, -0.5 * d, 0.3 * d);
            c.rot_fej = c.rot * exp_so3(&Vector3::new(0.0, 0.009, 0.004 * k as f64));
        }
        for id in 0..4 {
            let (cols, h) = msckf_jacobian(&s, id);
            let n = unobservable_directions(&cols, &s.state.means);
            let before = (&h * &n).norm() / h.norm();
            assert!(before > 1e-4, "track {id}: no leak to remove ({before:e})");
            let mut p = h.clone();
            project_out(&mut p, &n);
            let after = (&p * &n).norm() / p.norm();
            assert!(after < 1e-12, "track {id}: |H N| / |H| = {after:e} after");
            let change = (&p - &h).norm() / h.norm();
            assert!(change < 0.05, "track {id}: changed by {change:.3}");
        }
    }
}
