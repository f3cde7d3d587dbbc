//! SLAM features (thesis Sections 2.3.2, 2.3.3.3): EKF updates of the features kept
//! in the state, with First-Estimates Jacobians, and their delayed initialization
//! from a track that spans the window, with the QR split of Eqs. 2.41-2.45.

use super::chi2::Chi2Table;
use super::feature_db::FeatureDb;
use super::feature_system::{build, Columns};
use super::linalg::givens_qr_split;
use super::options::EstimatorOptions;
use super::projection::{predict, project, Projection};
use super::state::{SlamFeature, State, Var};
use super::triangulation::TriangulationOptions;
use nalgebra::{DMatrix, DVector, Vector3};

/// What the SLAM step did in one frame.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct SlamStats {
    /// Features updated.
    pub updated: usize,
    /// Updates rejected by the chi-square gate.
    pub rejected_chi2: usize,
    /// Features initialized into the state.
    pub initialized: usize,
    /// Initializations refused (triangulation or gate).
    pub init_failed: usize,
}

/// Updates the SLAM features `ids` with their observation in clone `clone_key`.
pub fn update(
    state: &mut State,
    db: &FeatureDb,
    ids: &[u64],
    clone_key: u64,
    opts: &EstimatorOptions,
    chi2: &Chi2Table,
    stats: &mut SlamStats,
) {
    let Some(clone) = state.clones.get(&clone_key).cloned() else {
        return;
    };
    let calib = state.calib.clone();
    let sigma2 = opts.pixel_sigma_px.powi(2);
    let mut vars: Vec<Var> = [Var::Extrinsic, Var::Intrinsics]
        .into_iter()
        .filter(|v| state.has(*v))
        .collect();
    vars.push(Var::Clone(clone_key));
    let mut used: Vec<(u64, [f64; 2], Projection)> = Vec::new();
    for id in ids {
        let (Some(feat), Some(f)) = (db.get(*id), state.features.get(id)) else {
            continue;
        };
        let Some(m) = feat.measurements.iter().find(|m| m.clone_key == clone_key) else {
            continue;
        };
        let (lr, lp, lf) = if opts.use_fej {
            (&clone.rot_fej, &clone.pos_fej, &f.pos_fej)
        } else {
            (&clone.rot, &clone.pos, &f.pos)
        };
        let (Some(proj), Some(z_hat)) = (
            project(lr, lp, lf, &calib),
            predict(&clone.rot, &clone.pos, &f.pos, &calib),
        ) else {
            continue;
        };
        let e = m.uv - z_hat;
        // Gate this feature alone.
        let mut one_vars = vars.clone();
        one_vars.push(Var::Feature(*id));
        let one_cols = Columns::of(one_vars.clone());
        let h = jacobian_row(&one_cols, clone_key, *id, &proj);
        let res = DVector::from_vec(vec![e.x, e.y]);
        let r = DMatrix::identity(2, 2) * sigma2;
        match state.mahalanobis(&one_cols.vars, &h, &res, &r) {
            Ok(d2) if d2 <= opts.chi2_multiplier * chi2.get(2) => {
                used.push((*id, [e.x, e.y], proj));
            }
            _ => stats.rejected_chi2 += 1,
        }
    }
    if used.is_empty() {
        return;
    }
    vars.extend(used.iter().map(|u| Var::Feature(u.0)));
    let cols = Columns::of(vars);
    let mut h = DMatrix::zeros(2 * used.len(), cols.dim);
    let mut res = DVector::zeros(2 * used.len());
    for (i, (id, e, proj)) in used.iter().enumerate() {
        let row = jacobian_row(&cols, clone_key, *id, proj);
        h.view_mut((2 * i, 0), (2, cols.dim)).copy_from(&row);
        res[2 * i] = e[0];
        res[2 * i + 1] = e[1];
    }
    let r = DMatrix::identity(res.len(), res.len()) * sigma2;
    if state.ekf_update(&cols.vars, &h, &res, &r).is_ok() {
        stats.updated += used.len();
    }
}

fn jacobian_row(cols: &Columns, clone_key: u64, id: u64, proj: &Projection) -> DMatrix<f64> {
    let mut h = DMatrix::zeros(2, cols.dim);
    if let Some(o) = cols.col(Var::Clone(clone_key)) {
        h.fixed_view_mut::<2, 6>(0, o).copy_from(&proj.h_clone);
    }
    if let Some(o) = cols.col(Var::Feature(id)) {
        h.fixed_view_mut::<2, 3>(0, o).copy_from(&proj.h_feature);
    }
    if let Some(o) = cols.col(Var::Extrinsic) {
        h.fixed_view_mut::<2, 6>(0, o).copy_from(&proj.h_extrinsic);
    }
    if let Some(o) = cols.col(Var::Intrinsics) {
        h.fixed_view_mut::<2, 8>(0, o).copy_from(&proj.h_intrinsics);
    }
    h
}

/// Delayed initialization of feature `id` into the state from its whole track.
/// Returns whether it entered the state.
pub fn initialize(
    state: &mut State,
    db: &FeatureDb,
    id: u64,
    opts: &EstimatorOptions,
    chi2: &Chi2Table,
    tri: &TriangulationOptions,
) -> bool {
    let Some(feature) = db.get(id) else {
        return false;
    };
    let cols = Columns::window(state);
    let Some(mut sys) = build(state, feature, &cols, opts.use_fej, tri) else {
        return false;
    };
    // Eq. 2.41-2.43: rotate so H_f = [R_f; 0]; the top 3 rows initialize the
    // feature, the rest update the state.
    let top = givens_qr_split(&mut sys.h_f, &mut sys.h_x, &mut sys.res);
    if top != 3 || sys.res.len() <= 3 {
        return false;
    }
    let sigma2 = opts.pixel_sigma_px.powi(2);
    let m = sys.res.len();
    let h_x2 = sys.h_x.rows(3, m - 3).into_owned();
    let r2 = sys.res.rows(3, m - 3).into_owned();
    let noise2 = DMatrix::identity(m - 3, m - 3) * sigma2;
    match state.mahalanobis(&cols.vars, &h_x2, &r2, &noise2) {
        Ok(d2) if d2 <= opts.chi2_multiplier * chi2.get(m - 3) => {}
        _ => return false,
    }
    let h_x1 = sys.h_x.rows(0, 3).into_owned();
    let h_f1 = sys.h_f.rows(0, 3).into_owned();
    let r1 = sys.res.rows(0, 3).into_owned();
    let Ok(dx) =
        state.initialize_invertible(Var::Feature(id), &cols.vars, &h_x1, &h_f1, &r1, sigma2)
    else {
        return false;
    };
    let pos = sys.p_f + Vector3::new(dx[0], dx[1], dx[2]);
    // The first estimate is the point the initialization was linearized at, so
    // every later Jacobian shares its unobservable directions (FEJ).
    state.features.insert(
        id,
        SlamFeature {
            pos,
            pos_fej: sys.p_f,
        },
    );
    // Eq. 2.45: the remaining rows update the whole state (the new feature through
    // its correlations).
    let _ = state.ekf_update(&cols.vars, &h_x2, &r2, &noise2);
    true
}
