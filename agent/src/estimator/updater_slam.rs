//! SLAM features (thesis Sections 2.3.2, 2.3.3.3): EKF updates of the features kept
//! in the state, with First-Estimates Jacobians, and their delayed initialization
//! from a track that spans the window, with the QR split of Eqs. 2.41-2.45.

use super::chi2::Chi2Table;
use super::feature_db::FeatureDb;
use super::feature_system::{build, Columns};
use super::filter::Filter;
use super::linalg::givens_qr_split;
use super::observability;
use super::options::{EstimatorOptions, MsckfJacobians};
use super::projection::{predict, project, Projection};
use super::slam_feature::{anchor_params, global_position, in_anchor, FeatureRepresentation};
use super::state::{SlamFeature, Var};
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

/// One feature's measurement row: residual and Jacobian blocks by variable.
struct Row {
    res: [f64; 2],
    blocks: Vec<(Var, DMatrix<f64>)>,
}

impl Row {
    fn add(&mut self, var: Var, block: DMatrix<f64>) {
        match self.blocks.iter_mut().find(|(v, _)| *v == var) {
            Some((_, b)) => *b += block,
            None => self.blocks.push((var, block)),
        }
    }

    /// Writes the row's blocks into rows `r0..r0 + 2` of `h`, whose columns
    /// follow `cols`.
    fn write(&self, cols: &Columns, h: &mut DMatrix<f64>, r0: usize) {
        for (v, b) in &self.blocks {
            if let Some(o) = cols.col(*v) {
                h.view_mut((r0, o), (2, v.size())).copy_from(b);
            }
        }
    }
}

fn dyn_block<const C: usize>(m: &nalgebra::SMatrix<f64, 2, C>) -> DMatrix<f64> {
    DMatrix::from_iterator(2, C, m.iter().copied())
}

/// The measurement row of SLAM feature `id` seen from clone `clone_key`: the
/// Jacobians at the first estimates (FEJ) of the clone and of the feature (and of
/// its anchor), the residual at the current estimates.
fn measurement_row<F: Filter + ?Sized>(
    filter: &F,
    db: &FeatureDb,
    id: u64,
    clone_key: u64,
    use_fej: bool,
) -> Option<Row> {
    let state = filter.means();
    let clone = state.clones.get(&clone_key)?;
    let f = state.features.get(&id)?;
    let m = db
        .get(id)?
        .measurements
        .iter()
        .find(|m| m.clone_key == clone_key)?;
    let (p_lin, jac) = global_position(filter, id, f, use_fej)?;
    let (p_cur, _) = global_position(filter, id, f, false)?;
    let (lr, lp) = if use_fej {
        (&clone.rot_fej, &clone.pos_fej)
    } else {
        (&clone.rot, &clone.pos)
    };
    let proj: Projection = project(lr, lp, &p_lin, &state.calib)?;
    let e = m.uv - predict(&clone.rot, &clone.pos, &p_cur, &state.calib)?;
    let mut row = Row {
        res: [e.x, e.y],
        blocks: vec![(Var::Clone(clone_key), dyn_block(&proj.h_clone))],
    };
    if filter.has(Var::Extrinsic) {
        row.add(Var::Extrinsic, dyn_block(&proj.h_extrinsic));
    }
    if filter.has(Var::Intrinsics) {
        row.add(Var::Intrinsics, dyn_block(&proj.h_intrinsics));
    }
    let h_f = dyn_block(&proj.h_feature);
    for (v, j) in jac {
        row.add(v, &h_f * j);
    }
    Some(row)
}

/// Updates the SLAM features `ids` with their observation in clone `clone_key`,
/// each gated alone, all in one EKF update. The gate of a feature is its own
/// 2x2 block of the stack's innovation covariance (see
/// [`Filter::gated_ekf_update`]), so gating costs no pass over the covariance
/// of its own.
pub fn update<F: Filter + ?Sized>(
    state: &mut F,
    db: &FeatureDb,
    ids: &[u64],
    clone_key: u64,
    opts: &EstimatorOptions,
    chi2: &Chi2Table,
    stats: &mut SlamStats,
) {
    let Some((cols, h, res)) = stacked_rows(state, db, ids, clone_key, opts) else {
        return;
    };
    let m = res.len();
    let r = DMatrix::identity(m, m) * opts.slam_sigma_px().powi(2);
    let threshold = opts.chi2_multiplier * chi2.get(2);
    match state.gated_ekf_update(&cols.vars, &h, &res, &r, 2, threshold) {
        Ok(accepted) => {
            let used = accepted.iter().filter(|a| **a).count();
            stats.updated += used;
            stats.rejected_chi2 += accepted.len() - used;
        }
        Err(_) => stats.rejected_chi2 += m / 2,
    }
}

/// The stacked rows of SLAM features `ids` seen by clone `clone_key`: their
/// columns, Jacobian and residual (`None` when no feature gives a row).
fn stacked_rows<F: Filter + ?Sized>(
    state: &F,
    db: &FeatureDb,
    ids: &[u64],
    clone_key: u64,
    opts: &EstimatorOptions,
) -> Option<(Columns, DMatrix<f64>, DVector<f64>)> {
    let oc = constrained(opts);
    let rows: Vec<Row> = ids
        .iter()
        .filter_map(|&id| measurement_row(state, db, id, clone_key, opts.use_fej && !oc))
        .collect();
    if rows.is_empty() {
        return None;
    }
    let mut vars: Vec<Var> = Vec::new();
    for row in &rows {
        for (v, _) in &row.blocks {
            if !vars.contains(v) {
                vars.push(*v);
            }
        }
    }
    let cols = Columns::of(vars);
    let m = 2 * rows.len();
    let mut h = DMatrix::zeros(m, cols.dim);
    let mut res = DVector::zeros(m);
    for (i, row) in rows.iter().enumerate() {
        row.write(&cols, &mut h, 2 * i);
        res[2 * i] = row.res[0];
        res[2 * i + 1] = row.res[1];
    }
    if oc {
        // No information along the first estimates' unobservable directions.
        let n = observability::unobservable_directions(&cols, state.means());
        observability::project_out(&mut h, &n);
    }
    Some((cols, h, res))
}

/// Whether the SLAM Jacobians are taken at the current estimates and then
/// constrained (`EstimatorOptions::slam_jacobians`).
fn constrained(opts: &EstimatorOptions) -> bool {
    opts.use_fej && opts.slam_jacobians == MsckfJacobians::ObservabilityConstrained
}

/// Delayed initialization of each of `candidates`, counted in `stats`. A
/// candidate that does not enter the state still has measurements worth using
/// once: they go through the MSCKF, unless `used_elsewhere` says another update
/// of this frame already took them. The candidates that could not be
/// triangulated at all are listed in `untriangulated` (their measurements went
/// to no update: the caller may keep the tracks for another try).
#[allow(clippy::too_many_arguments)]
pub fn initialize_candidates<F: Filter + ?Sized>(
    state: &mut F,
    db: &FeatureDb,
    candidates: &[u64],
    used_elsewhere: impl Fn(u64) -> bool,
    opts: &EstimatorOptions,
    chi2: &Chi2Table,
    tri: &TriangulationOptions,
    stats: &mut SlamStats,
    untriangulated: &mut Vec<u64>,
) {
    for &id in candidates {
        if initialize(state, db, id, opts, chi2, tri) {
            stats.initialized += 1;
        } else {
            stats.init_failed += 1;
            if !used_elsewhere(id) {
                let _ = super::updater_msckf::update_up_to(
                    state,
                    db,
                    &[id],
                    usize::MAX,
                    opts,
                    chi2,
                    tri,
                    untriangulated,
                );
            }
        }
    }
}

/// Projects an initialization system `[H_x, H_f]` (Eq. 2.41) so that it gives
/// no information along the unobservable directions `n_x` of its columns and
/// of the new feature: a global point at `global` moves with the world as the
/// clones do; an anchored one (`None`) moves with its anchor clone.
fn constrain_initialization(
    h_x: &mut DMatrix<f64>,
    h_f: &mut DMatrix<f64>,
    n_x: &DMatrix<f64>,
    global: Option<&Vector3<f64>>,
) {
    let (rows, dim) = h_x.shape();
    let mut n = DMatrix::zeros(dim + 3, 4);
    n.view_mut((0, 0), (dim, 4)).copy_from(n_x);
    if let Some(p) = global {
        let yaw = Vector3::z().cross(p);
        for a in 0..3 {
            n[(dim + a, a)] = 1.0;
            n[(dim + a, 3)] = yaw[a];
        }
    }
    let mut h = DMatrix::zeros(rows, dim + 3);
    h.columns_mut(0, dim).copy_from(h_x);
    h.columns_mut(dim, 3).copy_from(h_f);
    observability::project_out(&mut h, &n);
    *h_x = h.columns(0, dim).into_owned();
    *h_f = h.columns(dim, 3).into_owned();
}

/// Delayed initialization of feature `id` into the state from its whole track.
/// Returns whether it entered the state.
pub fn initialize<F: Filter + ?Sized>(
    state: &mut F,
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
    let oc = constrained(opts);
    let Some(mut sys) = build(state.means(), feature, &cols, opts.use_fej && !oc, tri) else {
        return false;
    };
    // Anchored: the new variable is p_FinA in the newest clone's camera (or its
    // inverse depth); H_f and H_x follow p_FinG = R_A (R_CtoI p_FinA + p_CinI) +
    // p_A (at first estimates).
    let newest = state.means().clones.keys().next_back().copied();
    let (anchor, inverse_depth) = match opts.feature_representation {
        FeatureRepresentation::Global => (None, false),
        FeatureRepresentation::Anchored => (newest, false),
        FeatureRepresentation::AnchoredInverseDepth => (newest, true),
    };
    let (mut p_init, mut p_init_fej) = (sys.p_f, sys.p_f);
    if let Some(a) = anchor {
        // The parameters of the triangulated point in the anchor (current and
        // first-estimate anchor pose).
        let params_in = |fej: bool| {
            in_anchor(state.means(), a, &sys.p_f, fej)
                .and_then(|p| anchor_params(&p, inverse_depth))
                .map(|(params, _)| params)
        };
        let (Some(p_a), Some(p_a_fej)) = (params_in(false), params_in(opts.use_fej)) else {
            return false;
        };
        let probe = SlamFeature {
            pos: p_a,
            pos_fej: p_a_fej,
            anchor: Some(a),
            inverse_depth,
        };
        let Some((_, jac)) = global_position(state, id, &probe, !oc) else {
            return false;
        };
        let h_fg = sys.h_f.clone();
        for (v, j) in jac {
            let block = &h_fg * j;
            if v == Var::Feature(id) {
                sys.h_f = block;
            } else if let Some(o) = cols.col(v) {
                let mut view = sys.h_x.view_mut((0, o), (h_fg.nrows(), v.size()));
                view += block;
            }
        }
        (p_init, p_init_fej) = (p_a, p_a_fej);
    }
    if oc {
        let n_x = observability::unobservable_directions(&cols, state.means());
        let global = anchor.is_none().then_some(&p_init_fej);
        constrain_initialization(&mut sys.h_x, &mut sys.h_f, &n_x, global);
    }
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
    let pos = p_init + Vector3::new(dx[0], dx[1], dx[2]);
    // The first estimate is the point the initialization was linearized at, so
    // every later Jacobian shares its unobservable directions (FEJ).
    state.means_mut().features.insert(
        id,
        SlamFeature {
            pos,
            pos_fej: p_init_fej,
            anchor,
            inverse_depth,
        },
    );
    // Eq. 2.45: the remaining rows update the whole state (the new feature through
    // its correlations).
    let _ = state.ekf_update(&cols.vars, &h_x2, &r2, &noise2);
    true
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::estimator::test_scene::scene;
    use common::so3::exp_so3;

    /// A scene of 6 clones whose first estimates are off their current poses
    /// (cloned before corrections of 1-6 cm and 0.5 deg), with landmark 0 a
    /// global SLAM feature whose first estimate is 19 cm off.
    fn stale_scene() -> crate::estimator::test_scene::Scene {
        let mut s = scene(6, 4, 1e-4, 1e-4);
        for (k, c) in s.state.means.clones.values_mut().enumerate() {
            let d = 0.01 * (k as f64 + 1.0);
            c.pos_fej = c.pos + Vector3::new(d, -0.5 * d, 0.3 * d);
            c.rot_fej = c.rot * exp_so3(&Vector3::new(0.0, 0.009, 0.004 * k as f64));
        }
        let p = s.landmarks[0];
        s.state
            .augment(Var::Feature(0), &[], &(DMatrix::identity(3, 3) * 0.01))
            .expect("new feature");
        s.state.means.features.insert(
            0,
            SlamFeature {
                pos: p,
                pos_fej: p + Vector3::new(0.1, 0.15, -0.05),
                anchor: None,
                inverse_depth: false,
            },
        );
        s
    }

    fn leak(cols: &Columns, h: &DMatrix<f64>, means: &crate::estimator::state::Means) -> f64 {
        let n = observability::unobservable_directions(cols, means);
        (h * &n).norm() / h.norm()
    }

    #[test]
    fn constrained_slam_rows_give_no_information_along_the_unobservable_directions() {
        let s = stale_scene();
        let opts = |j| EstimatorOptions {
            slam_jacobians: j,
            ..EstimatorOptions::default()
        };
        let first = opts(MsckfJacobians::FirstEstimates);
        let (cols, h, _) = stacked_rows(&s.state, &s.db, &[0], 6, &first).expect("rows");
        // At the first estimates the rows annihilate the directions by construction.
        assert!(leak(&cols, &h, &s.state.means) < 1e-12);
        // At the current estimates they would not; constrained, they do.
        let current = EstimatorOptions {
            use_fej: false,
            ..first.clone()
        };
        let (cols, h_cur, _) = stacked_rows(&s.state, &s.db, &[0], 6, &current).expect("rows");
        assert!(leak(&cols, &h_cur, &s.state.means) > 1e-4);
        let oc = opts(MsckfJacobians::ObservabilityConstrained);
        let (cols, h_oc, res) = stacked_rows(&s.state, &s.db, &[0], 6, &oc).expect("rows");
        assert!(leak(&cols, &h_oc, &s.state.means) < 1e-12);
        assert!((&h_oc - &h_cur).norm() < 0.1 * h_cur.norm());
        // The residual is the current estimate's either way (exact here).
        assert!(res.norm() < 1e-9, "{res}");
    }

    #[test]
    fn a_constrained_initialization_gives_no_information_along_them() {
        let s = stale_scene();
        let cols = Columns::window(&s.state);
        let feature = s.db.get(1).expect("track");
        let tri = TriangulationOptions::default();
        let sys = build(&s.state.means, feature, &cols, false, &tri).expect("system");
        let n_x = observability::unobservable_directions(&cols, &s.state.means);
        let joint_leak = |h_x: &DMatrix<f64>, h_f: &DMatrix<f64>, p: Option<&Vector3<f64>>| {
            let mut n = DMatrix::zeros(cols.dim + 3, 4);
            n.view_mut((0, 0), (cols.dim, 4)).copy_from(&n_x);
            if let Some(p) = p {
                let yaw = Vector3::z().cross(p);
                for a in 0..3 {
                    n[(cols.dim + a, a)] = 1.0;
                    n[(cols.dim + a, 3)] = yaw[a];
                }
            }
            let mut h = DMatrix::zeros(h_x.nrows(), cols.dim + 3);
            h.columns_mut(0, cols.dim).copy_from(h_x);
            h.columns_mut(cols.dim, 3).copy_from(h_f);
            (&h * &n).norm() / h.norm()
        };
        for global in [Some(sys.p_f), None] {
            let (mut h_x, mut h_f) = (sys.h_x.clone(), sys.h_f.clone());
            assert!(joint_leak(&h_x, &h_f, global.as_ref()) > 1e-4);
            constrain_initialization(&mut h_x, &mut h_f, &n_x, global.as_ref());
            assert!(joint_leak(&h_x, &h_f, global.as_ref()) < 1e-12);
        }
    }
}
