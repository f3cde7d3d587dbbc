//! The centralized estimator's common-feature updates: standard EKF updates of
//! the joint state with every robot's measurements of the feature, the
//! cross-covariances tracked (no CI needed). A measurement is used once: the
//! other robots' measurements used here are removed from their tracks.

use super::joint::JointVar;
use super::{CentralEstimator, TrackKey};
use crate::estimator::cooperative::CoopFrameStats;
use crate::estimator::feature_system::{build_at, camera_observations, Columns};
use crate::estimator::filter::FilterView;
use crate::estimator::linalg::{compress_in_place, nullspace_project_in_place};
use crate::estimator::projection::{predict, project};
use crate::estimator::slam_feature::global_position;
use crate::estimator::state::Var;
use crate::estimator::triangulation::triangulate;
use nalgebra::{DMatrix, DVector};

/// Rows over joint variables.
struct JointRows {
    vars: Vec<JointVar>,
    h: DMatrix<f64>,
    res: DVector<f64>,
}

/// The calibration variables and `keys`' clones of robot `q`, as estimated.
fn robot_vars(ce: &CentralEstimator, q: u16, keys: impl Iterator<Item = u64>) -> Vec<Var> {
    let Some(view) = ce.joint.view(q) else {
        return Vec::new();
    };
    let mut vars: Vec<Var> = [Var::Extrinsic, Var::Intrinsics]
        .into_iter()
        .filter(|v| view.has(*v))
        .collect();
    vars.extend(
        keys.filter(|k| view.means().clones.contains_key(k))
            .map(Var::Clone),
    );
    vars
}

/// One common VIO feature: every linked robot's track stacked, projected onto
/// the nullspace of the stacked feature Jacobian, gated against the joint
/// covariance. Returns the rows and the other robots' tracks used.
fn common_rows(ce: &CentralEstimator, r: u16, id: u64) -> Option<(JointRows, Vec<TrackKey>)> {
    let mut tracks: Vec<TrackKey> = vec![(r, id)];
    for &(q, u) in ce.links.get(&(r, id))? {
        let usable = ce
            .robots
            .get(usize::from(q))
            .and_then(|rb| rb.features.get(u));
        let is_slam = ce
            .joint
            .means(q)
            .is_some_and(|m| m.features.contains_key(&u));
        if usable.is_some_and(|f| !f.measurements.is_empty()) && !is_slam {
            tracks.push((q, u));
        }
    }
    if tracks.len() < 2 {
        return None;
    }
    let mut obs = Vec::new();
    for &(q, u) in &tracks {
        let f = ce.robots.get(usize::from(q))?.features.get(u)?;
        obs.extend(camera_observations(ce.joint.means(q)?, f));
    }
    let p_f = triangulate(&obs, &ce.tri).ok()?;
    let mut blocks = Vec::new();
    for &(q, u) in &tracks {
        let f = ce.robots.get(usize::from(q))?.features.get(u)?;
        let vars = robot_vars(ce, q, f.measurements.iter().map(|m| m.clone_key));
        let cols = Columns::of(vars);
        let mut sys = build_at(ce.joint.means(q)?, f, &cols, ce.opts.use_fej, &p_f)?;
        // Rows at the fleet's noise: robot q's scaled to its own.
        let (ratio, _) = ce.whitening_ratios(q);
        sys.h_x *= ratio;
        sys.h_f *= ratio;
        sys.res *= ratio;
        blocks.push((q, cols, sys));
    }
    let rows: usize = blocks.iter().map(|(_, _, s)| s.res.len()).sum();
    let dim: usize = blocks.iter().map(|(_, c, _)| c.dim).sum();
    let mut h_x = DMatrix::zeros(rows, dim);
    let mut h_f = DMatrix::zeros(rows, 3);
    let mut res = DVector::zeros(rows);
    let mut vars = Vec::new();
    let (mut r0, mut c0) = (0, 0);
    for (q, cols, sys) in &blocks {
        let m = sys.res.len();
        h_x.view_mut((r0, c0), (m, cols.dim)).copy_from(&sys.h_x);
        h_f.view_mut((r0, 0), (m, 3)).copy_from(&sys.h_f);
        res.rows_mut(r0, m).copy_from(&sys.res);
        vars.extend(cols.vars.iter().map(|v| JointVar { robot: *q, var: *v }));
        r0 += m;
        c0 += cols.dim;
    }
    nullspace_project_in_place(&mut h_f, &mut h_x, &mut res);
    if res.is_empty() {
        return None;
    }
    let sigma2 = ce.opts.pixel_sigma_px.powi(2);
    let noise = DMatrix::identity(res.len(), res.len()) * sigma2;
    let d2 = ce.joint.cov.mahalanobis(&vars, &h_x, &res, &noise).ok()?;
    if d2 > ce.opts.chi2_multiplier * ce.chi2.get(res.len()) {
        return None;
    }
    tracks.remove(0);
    Some((JointRows { vars, h: h_x, res }, tracks))
}

/// Stacks row blocks over the union of their variables, compresses, and applies
/// one joint EKF update with noise `sigma2`.
fn stacked_update(ce: &mut CentralEstimator, blocks: &[JointRows], sigma2: f64) -> bool {
    let mut vars: Vec<JointVar> = Vec::new();
    for b in blocks {
        for v in &b.vars {
            if !vars.contains(v) {
                vars.push(*v);
            }
        }
    }
    let mut offsets = Vec::with_capacity(vars.len());
    let mut dim = 0;
    for v in &vars {
        offsets.push(dim);
        dim += v.var.size();
    }
    let col = |v: &JointVar| vars.iter().position(|x| x == v).map(|i| offsets[i]);
    let m: usize = blocks.iter().map(|b| b.res.len()).sum();
    let mut h = DMatrix::zeros(m, dim);
    let mut res = DVector::zeros(m);
    let mut r0 = 0;
    for b in blocks {
        let k = b.res.len();
        let mut c_local = 0;
        for v in &b.vars {
            if let Some(c) = col(v) {
                let mut dst = h.view_mut((r0, c), (k, v.var.size()));
                dst += b.h.view((0, c_local), (k, v.var.size()));
            }
            c_local += v.var.size();
        }
        res.rows_mut(r0, k).copy_from(&b.res);
        r0 += k;
    }
    compress_in_place(&mut h, &mut res);
    let noise = DMatrix::identity(res.len(), res.len()) * sigma2;
    ce.joint.ekf_update(&vars, &h, &res, &noise).is_ok()
}

/// Common VIO features of robot `r`'s tracks `ids` (leaving its window): one
/// joint update with every linked robot's measurements. Returns the tracks used.
pub fn common_vio(
    ce: &mut CentralEstimator,
    r: usize,
    ids: &[u64],
    coop: &mut CoopFrameStats,
) -> Vec<u64> {
    let rid = r as u16;
    let mut blocks = Vec::new();
    let mut used = Vec::new();
    let mut consumed: Vec<TrackKey> = Vec::new();
    for &id in ids {
        match common_rows(ce, rid, id) {
            Some((rows, others)) if others.iter().all(|o| !consumed.contains(o)) => {
                coop.common_vio.peer_measurements += others.len();
                coop.common_vio.ci_rows += rows.res.len();
                blocks.push(rows);
                used.push(id);
                consumed.extend(others);
            }
            _ => coop.common_vio.rejected_chi2 += 1,
        }
    }
    let sigma2 = ce.opts.pixel_sigma_px.powi(2);
    if blocks.is_empty() || !stacked_update(ce, &blocks, sigma2) {
        return Vec::new();
    }
    for (q, u) in consumed {
        if let Some(f) = ce
            .robots
            .get_mut(usize::from(q))
            .and_then(|rb| rb.features.get_mut(u))
        {
            f.measurements.clear();
        }
    }
    coop.common_vio.used = used.len();
    used
}

/// Common SLAM features of robot `r` (`ce-cmsckf-cslam`): each SLAM feature
/// linked to another robot's (non-SLAM) track is updated jointly with that
/// robot's newest measurement of it, which is then consumed.
pub fn common_slam(ce: &mut CentralEstimator, r: usize, coop: &mut CoopFrameStats) {
    let rid = r as u16;
    let Some(view) = ce.joint.view(rid) else {
        return;
    };
    // A SLAM feature's update, whoever observed it (`updater_slam`).
    let sigma2 = ce.opts.slam_sigma_px().powi(2);
    let mut blocks = Vec::new();
    let mut consumed: Vec<(u16, u64, u64)> = Vec::new();
    for (&id, f) in &view.means().features {
        let Some(links) = ce.links.get(&(rid, id)) else {
            continue;
        };
        let Some((p_lin, jac)) = global_position(&view, id, f, ce.opts.use_fej) else {
            continue;
        };
        let Some((p_cur, _)) = global_position(&view, id, f, false) else {
            continue;
        };
        for &(q, u) in links {
            let (Some(qm), Some(rb)) = (ce.joint.means(q), ce.robots.get(usize::from(q))) else {
                continue;
            };
            if qm.features.contains_key(&u) {
                continue;
            }
            let Some(newest) = qm.clones.keys().next_back().copied() else {
                continue;
            };
            let Some(m) = rb.features.get(u).and_then(|t| t.measurement_at(newest)) else {
                continue;
            };
            let Some(clone) = qm.clones.get(&newest) else {
                continue;
            };
            let (lr, lp) = if ce.opts.use_fej {
                (&clone.rot_fej, &clone.pos_fej)
            } else {
                (&clone.rot, &clone.pos)
            };
            let (Some(proj), Some(z_hat)) = (
                project(lr, lp, &p_lin, &qm.calib),
                predict(&clone.rot, &clone.pos, &p_cur, &qm.calib),
            ) else {
                continue;
            };
            let mut vars = vec![JointVar {
                robot: q,
                var: Var::Clone(newest),
            }];
            let mut parts: Vec<DMatrix<f64>> =
                vec![DMatrix::from_iterator(2, 6, proj.h_clone.iter().copied())];
            let q_view = ce.joint.view(q);
            if q_view.is_some_and(|v| v.has(Var::Extrinsic)) {
                vars.push(JointVar {
                    robot: q,
                    var: Var::Extrinsic,
                });
                parts.push(DMatrix::from_iterator(
                    2,
                    6,
                    proj.h_extrinsic.iter().copied(),
                ));
            }
            if q_view.is_some_and(|v| v.has(Var::Intrinsics)) {
                vars.push(JointVar {
                    robot: q,
                    var: Var::Intrinsics,
                });
                parts.push(DMatrix::from_iterator(
                    2,
                    8,
                    proj.h_intrinsics.iter().copied(),
                ));
            }
            let h_f = DMatrix::from_iterator(2, 3, proj.h_feature.iter().copied());
            for (v, j) in &jac {
                let jv = JointVar {
                    robot: rid,
                    var: *v,
                };
                match vars.iter().position(|x| *x == jv) {
                    Some(i) => parts[i] += &h_f * j,
                    None => {
                        vars.push(jv);
                        parts.push(&h_f * j);
                    }
                }
            }
            let dim: usize = vars.iter().map(|v| v.var.size()).sum();
            let mut h = DMatrix::zeros(2, dim);
            let mut c = 0;
            for p in &parts {
                h.view_mut((0, c), (2, p.ncols())).copy_from(p);
                c += p.ncols();
            }
            // At the fleet's SLAM noise: robot q's view scaled to its own.
            let (_, ratio) = ce.whitening_ratios(q);
            h *= ratio;
            let e = (m.uv - z_hat) * ratio;
            let res = DVector::from_vec(vec![e.x, e.y]);
            let noise = DMatrix::identity(2, 2) * sigma2;
            match ce.joint.cov.mahalanobis(&vars, &h, &res, &noise) {
                Ok(d2) if d2 <= ce.opts.chi2_multiplier * ce.chi2.get(2) => {
                    blocks.push(JointRows { vars, h, res });
                    consumed.push((q, u, newest));
                }
                _ => coop.common_slam.rejected_chi2 += 1,
            }
        }
    }
    if blocks.is_empty() || !stacked_update(ce, &blocks, sigma2) {
        return;
    }
    coop.common_slam.used = blocks.len();
    for (q, u, key) in consumed {
        if let Some(f) = ce
            .robots
            .get_mut(usize::from(q))
            .and_then(|rb| rb.features.get_mut(u))
        {
            f.measurements.retain(|m| m.clone_key != key);
        }
    }
}
