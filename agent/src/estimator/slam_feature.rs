//! Where a SLAM feature is, in either representation, and how that position
//! depends on the state (thesis Section 2.3.2): global `p_FinG`, or anchored
//! `p_FinA` in the camera frame of an anchor clone `A`,
//! `p_FinG = R_A (R_CtoI p_FinA + p_CinI) + p_A`.

use super::filter::{Filter, FilterView};
use super::state::{Means, SlamFeature, Var};
pub use common::estimator_options::FeatureRepresentation;
use common::so3::skew;
use nalgebra::{DMatrix, Matrix3, Vector3};

/// Jacobian blocks by variable (each `3 x size`).
pub type SparseJacobian = Vec<(Var, DMatrix<f64>)>;

/// `p_FinG` of feature `id` and its Jacobians w.r.t. the state variables it
/// depends on (3 x size each), at the first estimates when `fej`.
pub fn global_position<F: FilterView + ?Sized>(
    filter: &F,
    id: u64,
    f: &SlamFeature,
    fej: bool,
) -> Option<(Vector3<f64>, SparseJacobian)> {
    let p = if fej { f.pos_fej } else { f.pos };
    let Some(a) = f.anchor else {
        return Some((p, vec![(Var::Feature(id), DMatrix::identity(3, 3))]));
    };
    let state = filter.means();
    let clone = state.clones.get(&a)?;
    let (r_a, p_a) = if fej {
        (clone.rot_fej, clone.pos_fej)
    } else {
        (clone.rot, clone.pos)
    };
    let c = &state.calib;
    let p_in_i = c.rot_c_to_i * p + c.p_c_in_i;
    let p_g = r_a * p_in_i + p_a;
    let dyn3 = |m: Matrix3<f64>| DMatrix::from_iterator(3, 3, m.iter().copied());
    let mut jac = vec![(Var::Feature(id), dyn3(r_a * c.rot_c_to_i))];
    let mut j_clone = DMatrix::zeros(3, 6);
    j_clone
        .view_mut((0, 0), (3, 3))
        .copy_from(&(-r_a * skew(&p_in_i)));
    j_clone.view_mut((0, 3), (3, 3)).fill_with_identity();
    jac.push((Var::Clone(a), j_clone));
    if filter.has(Var::Extrinsic) {
        let mut j_ext = DMatrix::zeros(3, 6);
        j_ext
            .view_mut((0, 0), (3, 3))
            .copy_from(&(-r_a * c.rot_c_to_i * skew(&p)));
        j_ext.view_mut((0, 3), (3, 3)).copy_from(&r_a);
        jac.push((Var::Extrinsic, j_ext));
    }
    Some((p_g, jac))
}

/// `p_FinA` of a global position in the camera of clone `a` (current values, or
/// first estimates when `fej`).
pub fn in_anchor(state: &Means, a: u64, p_g: &Vector3<f64>, fej: bool) -> Option<Vector3<f64>> {
    let clone = state.clones.get(&a)?;
    let (r_a, p_a) = if fej {
        (clone.rot_fej, clone.pos_fej)
    } else {
        (clone.rot, clone.pos)
    };
    let c = &state.calib;
    Some(c.rot_c_to_i.transpose() * (r_a.transpose() * (p_g - p_a) - c.p_c_in_i))
}

/// Moves every feature anchored at clone `old` to clone `new` (before `old` is
/// marginalized): the covariance by a change of variables linearized at the first
/// estimates, the mean and first estimate re-expressed in the new anchor.
pub fn reanchor<F: Filter + ?Sized>(filter: &mut F, old: u64, new: u64) {
    let ids: Vec<u64> = filter
        .means()
        .features
        .iter()
        .filter(|(_, f)| f.anchor == Some(old))
        .map(|(id, _)| *id)
        .collect();
    for id in ids {
        let Some(f) = filter.means().features.get(&id).cloned() else {
            continue;
        };
        let (Some((pg, _)), Some((pg_fej, jac_old))) = (
            global_position(filter, id, &f, false),
            global_position(filter, id, &f, true),
        ) else {
            continue;
        };
        let has_extrinsic = filter.has(Var::Extrinsic);
        let state = filter.means();
        let (Some(p_new), Some(p_new_fej), Some(clone_b)) = (
            in_anchor(state, new, &pg, false),
            in_anchor(state, new, &pg_fej, true),
            state.clones.get(&new),
        ) else {
            continue;
        };
        let c = &state.calib;
        let (r_b, p_b) = (clone_b.rot_fej, clone_b.pos_fej);
        // p_FinB = R_CtoIᵀ (R_Bᵀ (p_FinG − p_B) − p_CinI)
        let m = c.rot_c_to_i.transpose() * r_b.transpose();
        let q = r_b.transpose() * (pg_fej - p_b);
        let mut jac: Vec<(Var, DMatrix<f64>)> = jac_old
            .into_iter()
            .map(|(v, j)| (v, DMatrix::from_iterator(3, 3, m.iter().copied()) * j))
            .collect();
        let mut j_b = DMatrix::zeros(3, 6);
        j_b.view_mut((0, 0), (3, 3))
            .copy_from(&(c.rot_c_to_i.transpose() * skew(&q)));
        j_b.view_mut((0, 3), (3, 3)).copy_from(&(-m));
        jac.push((Var::Clone(new), j_b));
        if has_extrinsic {
            let mut j_e = DMatrix::zeros(3, 6);
            j_e.view_mut((0, 0), (3, 3)).copy_from(&skew(&p_new_fej));
            j_e.view_mut((0, 3), (3, 3))
                .copy_from(&(-c.rot_c_to_i.transpose()));
            jac.push((Var::Extrinsic, j_e));
        }
        // The same variable may appear twice (e.g. the extrinsic): sum them.
        let mut merged: Vec<(Var, DMatrix<f64>)> = Vec::new();
        for (v, j) in jac {
            match merged.iter_mut().find(|(mv, _)| *mv == v) {
                Some((_, mj)) => *mj += j,
                None => merged.push((v, j)),
            }
        }
        if filter.transform(Var::Feature(id), &merged).is_ok() {
            if let Some(f) = filter.means_mut().features.get_mut(&id) {
                f.pos = p_new;
                f.pos_fej = p_new_fej;
                f.anchor = Some(new);
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::estimator::state::{ClonePose, ImuState, State};
    use common::calibration::CameraCalibration;
    use common::so3::exp_so3;

    fn state_with_two_clones() -> State {
        let imu = ImuState::default();
        let mut s = State::new(
            0.0,
            imu,
            DMatrix::identity(15, 15) * 1e-2,
            CameraCalibration::euroc_cam0(),
            &[(Var::Extrinsic, DMatrix::identity(6, 6) * 1e-4)],
        );
        for (k, (w, p)) in [
            (Vector3::new(0.1, -0.2, 0.3), Vector3::new(1.0, 0.5, 1.2)),
            (Vector3::new(0.2, -0.1, 0.5), Vector3::new(1.4, 0.7, 1.1)),
        ]
        .into_iter()
        .enumerate()
        {
            let mut j = DMatrix::zeros(6, 15);
            j.view_mut((0, 0), (6, 6)).fill_with_identity();
            s.augment(
                Var::Clone(k as u64),
                &[(Var::Imu, j)],
                &(DMatrix::identity(6, 6) * 1e-3),
            )
            .unwrap();
            let rot = exp_so3(&w);
            s.clones.insert(
                k as u64,
                ClonePose {
                    t: k as f64,
                    t_cam: k as f64,
                    rot,
                    pos: p,
                    rot_fej: rot,
                    pos_fej: p,
                },
            );
        }
        s
    }

    /// Two clones and feature 7 anchored at clone 0, 4 m in front of its camera.
    fn state_with_anchored_feature() -> (State, SlamFeature) {
        let mut s = state_with_two_clones();
        let p = Vector3::new(0.3, -0.2, 4.0);
        let f = SlamFeature {
            pos: p,
            pos_fej: p,
            anchor: Some(0),
        };
        s.features.insert(7, f.clone());
        s.augment(Var::Feature(7), &[], &(DMatrix::identity(3, 3) * 0.01))
            .unwrap();
        (s, f)
    }

    #[test]
    fn anchored_position_jacobians_match_numerical_differentiation() {
        let (s, f) = state_with_anchored_feature();
        let (p0, jac) = global_position(&s, 7, &f, false).unwrap();
        let n = s.dim();
        let h = 1e-6;
        for (v, j) in jac {
            let o = s.offset(v).unwrap();
            for c in 0..v.size() {
                let mut dx = nalgebra::DVector::zeros(n);
                dx[o + c] = h;
                let mut sp = s.clone();
                sp.apply_correction(&dx);
                let fp = sp.features[&7].clone();
                let (pp, _) = global_position(&sp, 7, &fp, false).unwrap();
                let num = (pp - p0) / h;
                assert!((num - j.column(c)).norm() < 1e-4, "{v:?} column {c}");
            }
        }
    }

    #[test]
    fn reanchoring_keeps_the_global_position_and_its_covariance() {
        let (mut s, f) = state_with_anchored_feature();
        let (pg, jac) = global_position(&s, 7, &f, false).unwrap();
        // Covariance of p_FinG before: Σ J_i P_ij J_jᵀ.
        let cov_g = |s: &State, jac: &[(Var, DMatrix<f64>)]| {
            let mut c = DMatrix::zeros(3, 3);
            for (a, ja) in jac {
                for (b, jb) in jac {
                    c += ja * s.block(*a, *b).unwrap() * jb.transpose();
                }
            }
            c
        };
        let before = cov_g(&s, &jac);
        reanchor(&mut s, 0, 1);
        let f2 = s.features[&7].clone();
        assert_eq!(f2.anchor, Some(1));
        let (pg2, jac2) = global_position(&s, 7, &f2, false).unwrap();
        assert!((pg2 - pg).norm() < 1e-12);
        assert!((cov_g(&s, &jac2) - before).norm() < 1e-12);
    }
}
