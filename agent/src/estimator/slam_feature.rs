//! Where a SLAM feature is, in each representation, and how that position
//! depends on the state (thesis Section 2.3.2, Appendix A.6): global `p_FinG`, or
//! anchored `p_FinA` in the camera frame of an anchor clone `A`,
//! `p_FinG = R_A (R_CtoI p_FinA + p_CinI) + p_A`, kept either as `p_FinA` itself
//! or as its inverse depth `(α, β, ρ)`, `p_FinA = (α, β, 1) / ρ` (A.6.5).

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
    let params = if fej { f.pos_fej } else { f.pos };
    let Some(a) = f.anchor else {
        return Some((params, vec![(Var::Feature(id), DMatrix::identity(3, 3))]));
    };
    let (p, dp_dparams) = anchor_point(&params, f.inverse_depth)?;
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
    let mut jac = vec![(Var::Feature(id), dyn3(r_a * c.rot_c_to_i * dp_dparams))];
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

/// Smallest inverse depth kept, 1/m: a point 10 km away is at infinity for any
/// baseline a window spans, and `ρ <= 0` is behind the anchor.
const MIN_INVERSE_DEPTH: f64 = 1e-4;

/// `p_FinA` of an anchored feature's parameters and `∂p_FinA/∂params` (A.6.5's
/// `∂f/∂λ` without the rotation): the identity for `p_FinA` itself, and for
/// `(α, β, ρ)`, `[1/ρ 0 −α/ρ²; 0 1/ρ −β/ρ²; 0 0 −1/ρ²]`. `None` when `ρ` is
/// too small to stand for a point.
pub fn anchor_point(
    params: &Vector3<f64>,
    inverse_depth: bool,
) -> Option<(Vector3<f64>, Matrix3<f64>)> {
    if !inverse_depth {
        return Some((*params, Matrix3::identity()));
    }
    let (alpha, beta, rho) = (params.x, params.y, params.z);
    if !(rho.is_finite() && rho > MIN_INVERSE_DEPTH) {
        return None;
    }
    let z = 1.0 / rho;
    let z2 = z * z;
    Some((
        Vector3::new(alpha * z, beta * z, z),
        Matrix3::new(z, 0.0, -alpha * z2, 0.0, z, -beta * z2, 0.0, 0.0, -z2),
    ))
}

/// The parameters of an anchor-frame point `p_FinA` and their Jacobian w.r.t. it
/// (the inverse of [`anchor_point`]); `None` when an inverse depth cannot hold it
/// (at or behind the anchor camera, or beyond `1 / MIN_INVERSE_DEPTH`).
pub fn anchor_params(
    p: &Vector3<f64>,
    inverse_depth: bool,
) -> Option<(Vector3<f64>, Matrix3<f64>)> {
    if !inverse_depth {
        return Some((*p, Matrix3::identity()));
    }
    let rho = 1.0 / p.z;
    if !(rho.is_finite() && rho > MIN_INVERSE_DEPTH) {
        return None;
    }
    let r2 = rho * rho;
    Some((
        Vector3::new(p.x * rho, p.y * rho, rho),
        Matrix3::new(rho, 0.0, -p.x * r2, 0.0, rho, -p.y * r2, 0.0, 0.0, -r2),
    ))
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
/// estimates, the mean and first estimate re-expressed in the new anchor. A
/// feature the new anchor cannot hold (an inverse depth behind its camera) is
/// marginalized: left anchored at a clone that leaves, it would dangle.
pub fn reanchor<F: Filter + ?Sized>(filter: &mut F, old: u64, new: u64) {
    let ids: Vec<u64> = filter
        .means()
        .features
        .iter()
        .filter(|(_, f)| f.anchor == Some(old))
        .map(|(id, _)| *id)
        .collect();
    for id in ids {
        if !reanchor_one(filter, id, new) {
            let _ = filter.marginalize(Var::Feature(id));
        }
    }
}

/// Moves feature `id` to anchor `new`; whether it could.
fn reanchor_one<F: Filter + ?Sized>(filter: &mut F, id: u64, new: u64) -> bool {
    let Some(f) = filter.means().features.get(&id).cloned() else {
        return false;
    };
    let (Some((pg, _)), Some((pg_fej, jac_old))) = (
        global_position(filter, id, &f, false),
        global_position(filter, id, &f, true),
    ) else {
        return false;
    };
    let has_extrinsic = filter.has(Var::Extrinsic);
    let state = filter.means();
    let (Some(p_new), Some(p_new_fej), Some(clone_b)) = (
        in_anchor(state, new, &pg, false),
        in_anchor(state, new, &pg_fej, true),
        state.clones.get(&new),
    ) else {
        return false;
    };
    let (Some((params, _)), Some((params_fej, dparams_dp))) = (
        anchor_params(&p_new, f.inverse_depth),
        anchor_params(&p_new_fej, f.inverse_depth),
    ) else {
        return false;
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
    // The same variable may appear twice (e.g. the extrinsic): sum them; then
    // chain p_FinB to the new parameters.
    let mut merged: Vec<(Var, DMatrix<f64>)> = Vec::new();
    for (v, j) in jac {
        match merged.iter_mut().find(|(mv, _)| *mv == v) {
            Some((_, mj)) => *mj += j,
            None => merged.push((v, j)),
        }
    }
    if f.inverse_depth {
        let g = DMatrix::from_iterator(3, 3, dparams_dp.iter().copied());
        for (_, j) in merged.iter_mut() {
            *j = &g * &*j;
        }
    }
    if filter.transform(Var::Feature(id), &merged).is_err() {
        return false;
    }
    if let Some(f) = filter.means_mut().features.get_mut(&id) {
        f.pos = params;
        f.pos_fej = params_fej;
        f.anchor = Some(new);
    }
    true
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

    /// Two clones and feature 7 anchored at clone 0, 4 m in front of its camera,
    /// as `p_FinA` or as its inverse depth.
    fn state_with_anchored_feature(inverse_depth: bool) -> (State, SlamFeature) {
        let mut s = state_with_two_clones();
        let (p, _) = anchor_params(&Vector3::new(0.3, -0.2, 4.0), inverse_depth).unwrap();
        let f = SlamFeature {
            pos: p,
            pos_fej: p,
            anchor: Some(0),
            inverse_depth,
        };
        s.features.insert(7, f.clone());
        s.augment(Var::Feature(7), &[], &(DMatrix::identity(3, 3) * 0.01))
            .unwrap();
        (s, f)
    }

    #[test]
    fn anchored_position_jacobians_match_numerical_differentiation() {
        for inverse_depth in [false, true] {
            let (s, f) = state_with_anchored_feature(inverse_depth);
            let (_, jac) = global_position(&s, 7, &f, false).unwrap();
            let n = s.dim();
            let h = 1e-6;
            let moved = |step: f64, i: usize| {
                let mut dx = nalgebra::DVector::zeros(n);
                dx[i] = step;
                let mut sp = s.clone();
                sp.apply_correction(&dx);
                let fp = sp.features[&7].clone();
                global_position(&sp, 7, &fp, false).unwrap().0
            };
            for (v, j) in jac {
                let o = s.offset(v).unwrap();
                for c in 0..v.size() {
                    // Central differences: 1/ρ curves too much for a forward one.
                    let num = (moved(h, o + c) - moved(-h, o + c)) / (2.0 * h);
                    assert!(
                        (num - j.column(c)).norm() < 1e-6,
                        "inverse depth {inverse_depth}: {v:?} column {c}"
                    );
                }
            }
        }
    }

    #[test]
    fn inverse_depth_parameters_round_trip_and_refuse_points_behind() {
        let p = Vector3::new(0.3, -0.2, 4.0);
        let (params, dparams) = anchor_params(&p, true).unwrap();
        let (back, dp) = anchor_point(&params, true).unwrap();
        assert!((back - p).norm() < 1e-12);
        assert!((dp * dparams - Matrix3::identity()).norm() < 1e-12);
        assert!(anchor_params(&Vector3::new(0.3, -0.2, -4.0), true).is_none());
        assert!(anchor_point(&Vector3::new(0.1, 0.1, -0.25), true).is_none());
        assert!(anchor_point(&Vector3::new(0.1, 0.1, f64::NAN), true).is_none());
    }

    #[test]
    fn reanchoring_keeps_the_global_position_and_its_covariance() {
        for inverse_depth in [false, true] {
            let (mut s, f) = state_with_anchored_feature(inverse_depth);
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
            assert_eq!(f2.inverse_depth, inverse_depth);
            let (pg2, jac2) = global_position(&s, 7, &f2, false).unwrap();
            assert!((pg2 - pg).norm() < 1e-12);
            assert!(
                (cov_g(&s, &jac2) - before).norm() < 1e-12,
                "inverse depth {inverse_depth}"
            );
        }
    }

    #[test]
    fn a_feature_the_new_anchor_cannot_hold_is_marginalized() {
        let (mut s, _) = state_with_anchored_feature(true);
        // Turn clone 1's camera to look back along clone 0's: the feature, 4 m in
        // front of clone 0's camera, is behind it, where no inverse depth holds it.
        let r_c_to_i = s.calib.rot_c_to_i;
        let flip = exp_so3(&Vector3::new(std::f64::consts::PI, 0.0, 0.0));
        let r1 = s.clones[&0].rot * r_c_to_i * flip * r_c_to_i.transpose();
        let c1 = s.clones.get_mut(&1).unwrap();
        c1.rot = r1;
        c1.rot_fej = r1;
        let dim = s.dim();
        reanchor(&mut s, 0, 1);
        assert!(!s.features.contains_key(&7));
        assert_eq!(s.dim(), dim - 3);
    }
}
