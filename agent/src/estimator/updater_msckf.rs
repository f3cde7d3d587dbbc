//! MSCKF update (thesis Section 2.3.3.2): each feature's measurements over the
//! window are projected onto the left nullspace of its Jacobian (Givens, no dense
//! SVD), gated with a chi-square test, stacked, compressed when tall, and used in
//! one EKF update. The features themselves never enter the state.

use super::chi2::Chi2Table;
use super::feature_db::FeatureDb;
use super::feature_system::{build, Columns};
use super::filter::Filter;
use super::linalg::{compress_in_place, nullspace_project_in_place};
use super::observability;
use super::options::{EstimatorOptions, MsckfJacobians};
use super::state::Var;
use super::triangulation::TriangulationOptions;
use nalgebra::{DMatrix, DVector};

/// What one MSCKF update did.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct MsckfStats {
    /// Features used in the update.
    pub used: usize,
    /// Features rejected by the chi-square gate.
    pub rejected_chi2: usize,
    /// Features that could not be triangulated or projected.
    pub failed: usize,
    /// Whether this (first) update was rescued (see [`rescue`]).
    pub rescued: bool,
}

/// Updates `state` with the features `ids` of `db`, all of them.
pub fn update<F: Filter + ?Sized>(
    state: &mut F,
    db: &FeatureDb,
    ids: &[u64],
    opts: &EstimatorOptions,
    chi2: &Chi2Table,
    tri: &TriangulationOptions,
) -> MsckfStats {
    update_up_to(state, db, ids, usize::MAX, opts, chi2, tri, &mut Vec::new()).0
}

/// Updates `state` with the candidates `ids` of `db`, taken in order until `cap`
/// of them have a system (used or gated out): a candidate that cannot be
/// triangulated takes no place. Lists in `untriangulated` the candidates whose
/// system could not be built (nearly always too little parallax to triangulate
/// yet, at times a point that does not project): the caller may keep their tracks
/// for another try. Returns the stats and how many candidates were tried; the
/// caller keeps the rest for a later frame. An update starved of candidates
/// (nearly all fail, see [`RELAX_WHEN_FAILED_PER_PASSED`]) is rebuilt once
/// under [`TriangulationOptions::starved`].
#[allow(clippy::too_many_arguments)]
pub fn update_up_to<F: Filter + ?Sized>(
    state: &mut F,
    db: &FeatureDb,
    ids: &[u64],
    cap: usize,
    opts: &EstimatorOptions,
    chi2: &Chi2Table,
    tri: &TriangulationOptions,
    untriangulated: &mut Vec<u64>,
) -> (MsckfStats, usize) {
    // Starved (a slow flight's far points): the tracks with retired rays are
    // asked for the window's depth precision rather than its rays' spread.
    let (mut stats, tried, stacked, _) = stack_unless_starved(
        state,
        db,
        ids,
        cap,
        opts,
        chi2,
        [tri, &tri.starved()],
        untriangulated,
    );
    if let Some(st) = stacked {
        if state
            .ekf_update(&st.vars, &st.h, &st.res, &st.noise())
            .is_err()
        {
            stats.failed += stats.used;
            stats.used = 0;
        }
    }
    (stats, tried)
}

/// The first update relaxes the ray-geometry limits when more than this many
/// candidates fail them for each one that passes; a later update then asks
/// the tracks with retired rays for depth precision instead
/// ([`TriangulationOptions::starved`]).
pub const RELAX_WHEN_FAILED_PER_PASSED: usize = 10;

/// Whether an update's candidates nearly all failed to triangulate: more than
/// [`RELAX_WHEN_FAILED_PER_PASSED`] for each one that passed.
fn starved(stats: &MsckfStats) -> bool {
    starved_at(stats, RELAX_WHEN_FAILED_PER_PASSED)
}

/// More than `failed_per_passed` candidates failed for each one that passed.
fn starved_at(stats: &MsckfStats, failed_per_passed: usize) -> bool {
    let passed = stats.used + stats.rejected_chi2;
    stats.failed > 0 && passed * failed_per_passed < stats.failed
}

/// Whether an update with the candidates `ids` would find fewer than one
/// candidate passing the ray limits `tri` for every `failed_per_passed` that
/// fail (built, not applied).
#[allow(clippy::too_many_arguments)]
pub fn would_starve<F: Filter + ?Sized>(
    state: &F,
    db: &FeatureDb,
    ids: &[u64],
    cap: usize,
    opts: &EstimatorOptions,
    chi2: &Chi2Table,
    tri: &TriangulationOptions,
    failed_per_passed: usize,
) -> bool {
    let (stats, _, _) = stack_up_to(state, db, ids, cap, opts, Some(chi2), tri, &mut Vec::new());
    starved_at(&stats, failed_per_passed)
}

/// [`stack_up_to`] under the first of `limits`; when that leaves the update
/// [`starved`], stacked again under the second (the candidates it lists in
/// `untriangulated` are those of the second try). The last value says whether
/// the second was taken.
#[allow(clippy::too_many_arguments)]
fn stack_unless_starved<F: Filter + ?Sized>(
    state: &F,
    db: &FeatureDb,
    ids: &[u64],
    cap: usize,
    opts: &EstimatorOptions,
    chi2: &Chi2Table,
    limits: [&TriangulationOptions; 2],
    untriangulated: &mut Vec<u64>,
) -> (MsckfStats, usize, Option<Stacked>, bool) {
    let stack = |tri: &TriangulationOptions, untriangulated: &mut Vec<u64>| {
        stack_up_to(state, db, ids, cap, opts, Some(chi2), tri, untriangulated)
    };
    let before = untriangulated.len();
    let (stats, tried, stacked) = stack(limits[0], untriangulated);
    if !starved(&stats) {
        return (stats, tried, stacked, false);
    }
    untriangulated.truncate(before);
    let (stats, tried, stacked) = stack(limits[1], untriangulated);
    (stats, tried, stacked, true)
}

/// [`update_up_to`] iterated (an iterated EKF, for the filter's first update):
/// after the update, the features it used are triangulated again at the
/// updated clones and the system rebuilt there, and the update is redone from
/// the prior with the residual moved to the prior's point,
/// `r' = r(x_i) + H_i (x_i ⊟ x_0)`, `iterations` times. The first update comes
/// after a whole window of flight on the start's errors alone: a tilt of a
/// degree has bent every clone, and one linearized step leaves a third of it
/// while the covariance claims it gone. When (nearly) none of the candidates
/// passes the ray-geometry limits, fewer than one for every
/// [`RELAX_WHEN_FAILED_PER_PASSED`] that fail, this update takes them looser
/// ([`TriangulationOptions::relaxed`]). When its first step leaves the rays
/// of most of its features apart, it is redone at the current estimate
/// ([`rescue`], `rescue_first_update`). With no iteration it is
/// [`update_up_to`] (no copy of the state).
#[allow(clippy::too_many_arguments)]
pub fn iterated_update_up_to<F: Filter + ?Sized>(
    state: &mut F,
    db: &FeatureDb,
    ids: &[u64],
    cap: usize,
    opts: &EstimatorOptions,
    chi2: &Chi2Table,
    tri: &TriangulationOptions,
    untriangulated: &mut Vec<u64>,
    iterations: usize,
) -> (MsckfStats, usize) {
    if iterations == 0 {
        return update_up_to(state, db, ids, cap, opts, chi2, tri, untriangulated);
    }
    // A tilted start bends the window's clones by the gravity it leaks
    // (½ g sin 3° t² ≈ 0.3 m after 1.1 s), and on a slow start no track may
    // then pass the ray-geometry limits, frame after frame, while the error
    // grows; or one track passes of a hundred, and the whole first update
    // rests on it (V1_01, seed 3 from a 3 deg tilt: 1 of 110, and the filter
    // diverged). Then this first update takes them looser, and its iterations
    // triangulate the points again at the corrected clones.
    let relaxed = tri.relaxed(ray_noise_rad(state, opts));
    let (mut stats, tried, stacked, relax) = stack_unless_starved(
        state,
        db,
        ids,
        cap,
        opts,
        chi2,
        [tri, &relaxed],
        untriangulated,
    );
    let tri = if relax { &relaxed } else { tri };
    tracing::debug!(
        used = stats.used,
        gated = stats.rejected_chi2,
        failed = stats.failed,
        relax,
        "first update: features used, gated out, not triangulated"
    );
    let Some(mut st) = stacked else {
        return (stats, tried);
    };
    // Saved only once there is something to update with (for the centralized
    // estimator this is the whole joint state).
    let prior = state.save();
    if state
        .ekf_update(&st.vars, &st.h, &st.res, &st.noise())
        .is_err()
    {
        state.restore(&prior);
        stats.failed += stats.used;
        stats.used = 0;
        return (stats, tried);
    }
    // Whether the step left the rays apart is checked only when a rescue may
    // follow; without it the iterations go on with the features that still
    // triangulate.
    let check_rays = opts.rescue_first_update;
    if relinearize(
        state, db, &mut st, &prior, opts, tri, iterations, check_rays,
    ) == Relinearized::RaysApart
    {
        stats.rescued = rescue(state, db, &st, &prior, opts, tri);
    }
    (stats, tried)
}

/// Iterations of a rescued first update (see [`rescue`]).
pub const RESCUE_ITERATIONS: usize = 8;

/// What [`relinearize`] found.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
enum Relinearized {
    /// It iterated (or stopped where an iteration could not be made).
    Done,
    /// After the first step fewer than half of the features' rays still met.
    RaysApart,
}

/// The iterations of [`iterated_update_up_to`]: the features of `st` triangulated
/// again at the current estimate, the system rebuilt there with its residual
/// moved to the prior's point, `r' = r(x_i) + H_i (x_i ⊟ x_0)`, and the update
/// redone from `prior`, `iterations` times. With `check_rays`, the first
/// rebuild is a test of the step the update took: when fewer than half of its
/// features can be triangulated at the updated clones, it returns
/// [`Relinearized::RaysApart`] and leaves the state as the step left it.
#[allow(clippy::too_many_arguments)]
fn relinearize<F: Filter + ?Sized>(
    state: &mut F,
    db: &FeatureDb,
    st: &mut Stacked,
    prior: &F::Saved,
    opts: &EstimatorOptions,
    tri: &TriangulationOptions,
    iterations: usize,
    mut check_rays: bool,
) -> Relinearized {
    for _ in 0..iterations {
        let (again, _, next) = stack_up_to(
            state,
            db,
            &st.used,
            usize::MAX,
            opts,
            None,
            tri,
            &mut Vec::new(),
        );
        if check_rays && again.used * 2 < st.used.len() {
            return Relinearized::RaysApart;
        }
        check_rays = false;
        let Some(next) = next else {
            break;
        };
        let Some(prior_means) = state.saved_means(prior) else {
            break;
        };
        let delta = state.means().boxminus(prior_means, &next.vars);
        *st = Stacked {
            res: &next.res + &next.h * delta,
            ..next
        };
        // Redone from the prior; an iteration that fails keeps the last one.
        let last = state.save();
        state.restore(prior);
        if state
            .ekf_update(&st.vars, &st.h, &st.res, &st.noise())
            .is_err()
        {
            state.restore(&last);
            break;
        }
    }
    Relinearized::Done
}

/// The angular noise of one camera ray, radians: the pixel noise over the
/// geometric mean of the current focal lengths. It bounds how far the first
/// update loosens the rays' condition number
/// ([`TriangulationOptions::relaxed`]). Zero (no bound) when the focal lengths
/// are not positive.
pub(crate) fn ray_noise_rad<F: Filter + ?Sized>(state: &F, opts: &EstimatorOptions) -> f64 {
    let camera = &state.means().calib.camera;
    let focal = (camera.fx() * camera.fy()).sqrt();
    if focal > 0.0 {
        opts.pixel_sigma_px / focal
    } else {
        0.0
    }
}

/// A first update whose step left its features' rays apart (see
/// [`relinearize`]): a start a few degrees off and a gyro bias of 0.02 rad/s have
/// bent the window's clones so far that the Jacobians at their first estimates
/// point the step the wrong way (V1_01 from OpenVINS's prior, seed 3: the first
/// update turned a 3.5 deg tilt into 2.7 deg of yaw, no track triangulated
/// afterwards, and the filter diverged). It is redone from the prior as a
/// Gauss-Newton iteration should be: Jacobians at the current estimate, not at
/// the first estimates, rays triangulated under the looser limits (the clones
/// are still far off), [`RESCUE_ITERATIONS`] times. The clones' and the IMU
/// state's first estimates are then reset to the result: the start's errors
/// were a window's worth of propagation on a wrong state, and linearizing the
/// rest of the flight there would keep them. Taken when this happens only, so
/// a first update whose step stays near its prior is unchanged. Returns
/// whether the update was redone (else the step stands).
fn rescue<F: Filter + ?Sized>(
    state: &mut F,
    db: &FeatureDb,
    st: &Stacked,
    prior: &F::Saved,
    opts: &EstimatorOptions,
    tri: &TriangulationOptions,
) -> bool {
    let current = EstimatorOptions {
        use_fej: false,
        ..opts.clone()
    };
    let relaxed = tri.relaxed(ray_noise_rad(state, opts));
    let last = state.save();
    state.restore(prior);
    let rebuilt = stack_up_to(
        state,
        db,
        &st.used,
        usize::MAX,
        &current,
        None,
        &relaxed,
        &mut Vec::new(),
    )
    .2;
    let Some(mut again) = rebuilt else {
        state.restore(&last);
        return false;
    };
    if state
        .ekf_update(&again.vars, &again.h, &again.res, &again.noise())
        .is_err()
    {
        state.restore(&last);
        return false;
    }
    relinearize(
        state,
        db,
        &mut again,
        prior,
        &current,
        &relaxed,
        RESCUE_ITERATIONS,
        false,
    );
    tracing::info!(
        features = again.used.len(),
        "first update rescued: its step left the rays apart, redone at the current estimate"
    );
    state.means_mut().reset_first_estimates();
    true
}

/// The stacked, compressed MSCKF system of some features (what
/// [`update_up_to`] updates with).
#[derive(Clone, Debug)]
pub struct Stacked {
    /// Our variables, the columns of `h`.
    pub vars: Vec<Var>,
    /// The Jacobian.
    pub h: DMatrix<f64>,
    /// The residual.
    pub res: DVector<f64>,
    /// The pixel variance of every row.
    pub sigma2: f64,
    /// The features in it.
    pub used: Vec<u64>,
}

impl Stacked {
    /// The rows' noise covariance.
    pub fn noise(&self) -> DMatrix<f64> {
        DMatrix::identity(self.res.len(), self.res.len()) * self.sigma2
    }
}

/// [`update_up_to`] without the update: the system of the candidates, gated
/// when `chi2` is given. `None` when no feature has rows.
#[allow(clippy::too_many_arguments)]
pub fn stack_up_to<F: Filter + ?Sized>(
    state: &F,
    db: &FeatureDb,
    ids: &[u64],
    cap: usize,
    opts: &EstimatorOptions,
    chi2: Option<&Chi2Table>,
    tri: &TriangulationOptions,
    untriangulated: &mut Vec<u64>,
) -> (MsckfStats, usize, Option<Stacked>) {
    let mut stats = MsckfStats::default();
    let mut tried = 0;
    let cols = Columns::window(state);
    let calib_vars: Vec<Var> = cols
        .vars
        .iter()
        .copied()
        .filter(|v| !matches!(v, Var::Clone(_)))
        .collect();
    let sigma2 = opts.pixel_sigma_px * opts.pixel_sigma_px;
    // Each feature's system over the variables it involves (calibration and the
    // clones that saw it): gating touches only that block of the covariance.
    let mut blocks: Vec<(Columns, DMatrix<f64>, DVector<f64>)> = Vec::with_capacity(ids.len());
    let mut used = Vec::new();
    let mut rows = 0;
    for id in ids {
        if stats.used + stats.rejected_chi2 >= cap {
            break;
        }
        tried += 1;
        let Some(feature) = db.get(*id) else { continue };
        let mut vars = calib_vars.clone();
        vars.extend(
            feature
                .measurements
                .iter()
                .filter(|m| state.means().clones.contains_key(&m.clone_key))
                .map(|m| Var::Clone(m.clone_key)),
        );
        let fcols = Columns::of(vars);
        let constrained =
            opts.use_fej && opts.msckf_jacobians == MsckfJacobians::ObservabilityConstrained;
        let at_fej = opts.use_fej && !constrained;
        let Some(mut sys) = build(state.means(), feature, &fcols, at_fej, tri) else {
            untriangulated.push(*id);
            stats.failed += 1;
            continue;
        };
        nullspace_project_in_place(&mut sys.h_f, &mut sys.h_x, &mut sys.res);
        if constrained {
            let n = observability::unobservable_directions(&fcols, state.means());
            observability::project_out(&mut sys.h_x, &n);
        }
        if sys.res.is_empty() {
            stats.failed += 1;
            continue;
        }
        if let Some(chi2) = chi2 {
            let r = DMatrix::identity(sys.res.len(), sys.res.len()) * sigma2;
            let Ok(d2) = state.mahalanobis(&fcols.vars, &sys.h_x, &sys.res, &r) else {
                stats.failed += 1;
                continue;
            };
            if d2 > opts.chi2_multiplier * chi2.get(sys.res.len()) {
                stats.rejected_chi2 += 1;
                continue;
            }
        }
        rows += sys.res.len();
        blocks.push((fcols, sys.h_x, sys.res));
        used.push(*id);
        stats.used += 1;
    }
    if rows == 0 {
        return (stats, tried, None);
    }
    let mut h = DMatrix::zeros(rows, cols.dim);
    let mut res = DVector::zeros(rows);
    let mut r0 = 0;
    for (fcols, hx, rs) in &blocks {
        let m = rs.len();
        for v in &fcols.vars {
            let (Some(src), Some(dst)) = (fcols.col(*v), cols.col(*v)) else {
                continue;
            };
            h.view_mut((r0, dst), (m, v.size()))
                .copy_from(&hx.view((0, src), (m, v.size())));
        }
        res.rows_mut(r0, m).copy_from(rs);
        r0 += m;
    }
    compress_in_place(&mut h, &mut res);
    let stacked = Stacked {
        vars: cols.vars,
        h,
        res,
        sigma2,
        used,
    };
    (stats, tried, Some(stacked))
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::estimator::test_scene::scene;

    #[test]
    fn a_candidate_that_cannot_be_triangulated_takes_no_place_in_the_cap() {
        let mut s = scene(8, 6, 1e-4, 1e-4);
        // Tracks 0 and 1 keep one view each: nothing to triangulate.
        for id in [0, 1] {
            if let Some(f) = s.db.get_mut(id) {
                f.measurements.truncate(1);
            }
        }
        let opts = EstimatorOptions::default();
        let (chi2, tri) = (Chi2Table::new(0.95, 500), TriangulationOptions::default());
        let ids: Vec<u64> = (0..6).collect();
        let mut failed = Vec::new();
        let (stats, tried) = update_up_to(
            &mut s.state,
            &s.db,
            &ids,
            2,
            &opts,
            &chi2,
            &tri,
            &mut failed,
        );
        // 0 and 1 fail, 2 and 3 fill the cap, 4 and 5 are left for a later frame.
        assert_eq!(failed, vec![0, 1]);
        assert_eq!(stats.used + stats.rejected_chi2, 2, "{stats:?}");
        assert_eq!(stats.failed, 2);
        assert_eq!(tried, 4);
        // Without a cap every candidate is tried.
        let mut s = scene(8, 6, 1e-4, 1e-4);
        let (stats, tried) = update_scene(&mut s, &ids, &tri, &mut Vec::new());
        assert_eq!((stats.used, tried), (6, 6), "{stats:?}");
    }

    /// The update of `scene(8, n, ..)`'s tracks `0..n` under a depth/baseline
    /// limit: with `iterations` > 0 it is the filter's first update. Returns
    /// its stats and the tracks it could not triangulate.
    fn update_under_baseline_limit(
        n: usize,
        limit: f64,
        iterations: usize,
    ) -> (MsckfStats, Vec<u64>) {
        let tri = TriangulationOptions {
            max_baseline_ratio: limit,
            ..TriangulationOptions::default()
        };
        let ids: Vec<u64> = (0..n as u64).collect();
        let mut s = scene(8, n, 1e-4, 1e-4);
        let mut failed = Vec::new();
        let (stats, _) = iterated_update_up_to(
            &mut s.state,
            &s.db,
            &ids,
            usize::MAX,
            &EstimatorOptions::default(),
            &Chi2Table::new(0.95, 500),
            &tri,
            &mut failed,
            iterations,
        );
        (stats, failed)
    }

    /// A first update none of whose candidates passes the ray-geometry limits
    /// takes them 100 times looser; a later update does not.
    #[test]
    fn a_first_update_with_no_triangulable_candidate_relaxes_the_ray_limits() {
        // A depth/baseline limit of 0.1 rejects every track of this scene; the
        // relaxed 10 none.
        let (stats, failed) = update_under_baseline_limit(6, 0.1, 0);
        assert_eq!((stats.used, stats.failed), (0, 6), "{stats:?}");
        assert_eq!(failed, (0..6).collect::<Vec<u64>>());
        let (stats, failed) = update_under_baseline_limit(6, 0.1, 2);
        assert_eq!((stats.used, stats.failed), (6, 0), "{stats:?}");
        assert!(failed.is_empty(), "{failed:?}");
    }

    /// A first update that only a few of its candidates pass (under a tenth of
    /// those tried) takes the looser limits too: one feature would have to
    /// carry the whole first update (seed 3 of V1_01 from a 3 deg tilt: 1 of
    /// 110 passed, and the filter diverged).
    #[test]
    fn a_first_update_that_few_candidates_pass_relaxes_the_ray_limits() {
        // At a depth/baseline limit of 2.92 only the nearest of these 12
        // landmarks passes: a later update takes it alone, the first all 12.
        let (stats, _) = update_under_baseline_limit(12, 2.92, 0);
        assert_eq!((stats.used, stats.failed), (1, 11), "{stats:?}");
        let (stats, _) = update_under_baseline_limit(12, 2.92, 2);
        assert_eq!((stats.used, stats.failed), (12, 0), "{stats:?}");
        // At 3.0 two pass, a sixth of those tried: the limits stay.
        let (stats, _) = update_under_baseline_limit(12, 3.0, 2);
        assert_eq!((stats.used, stats.failed), (2, 10), "{stats:?}");
    }

    /// [`update_up_to`] of `s`'s tracks `ids` with no cap and the default
    /// options.
    fn update_scene(
        s: &mut crate::estimator::test_scene::Scene,
        ids: &[u64],
        tri: &TriangulationOptions,
        failed: &mut Vec<u64>,
    ) -> (MsckfStats, usize) {
        let (opts, chi2) = (EstimatorOptions::default(), Chi2Table::new(0.95, 500));
        update_up_to(
            &mut s.state,
            &s.db,
            ids,
            usize::MAX,
            &opts,
            &chi2,
            tri,
            failed,
        )
    }

    /// The condition number of track `id`'s window views in `s`.
    fn window_condition(s: &crate::estimator::test_scene::Scene, id: u64) -> f64 {
        use crate::estimator::feature_system::camera_observations;
        use crate::estimator::triangulation::{triangulate, TriangulationError};
        let f = s.db.get(id).expect("track");
        let obs = camera_observations(&s.state.means, f);
        let any = TriangulationOptions {
            max_condition_number: 1.0,
            ..TriangulationOptions::default()
        };
        match triangulate(&obs, &any) {
            Err(TriangulationError::IllConditioned { cond }) => cond,
            other => panic!("{other:?}"),
        }
    }

    /// Track `id`'s window views in `s`, as rays retired a second time.
    fn retired_again(
        s: &crate::estimator::test_scene::Scene,
        id: u64,
    ) -> Vec<crate::estimator::feature_db::RetiredRay> {
        use crate::estimator::feature_system::camera_observations;
        let f = s.db.get(id).expect("track");
        camera_observations(&s.state.means, f)
            .into_iter()
            .zip(&f.measurements)
            .map(|(view, m)| crate::estimator::feature_db::RetiredRay { view, uv: m.uv })
            .collect()
    }

    /// A starved update (nearly every candidate fails) asks a track with
    /// retired rays for the window's depth precision: the same spread from
    /// twice the rays passes under twice the condition number. A later update
    /// with candidates that pass keeps the plain limit.
    #[test]
    fn a_starved_update_takes_retired_rays_by_their_depth_precision() {
        let mut s = scene(8, 1, 1e-4, 1e-4);
        let cond = window_condition(&s, 0);
        let tri = TriangulationOptions {
            max_condition_number: cond / 1.5,
            ..TriangulationOptions::default()
        };
        // The window's own views, retired a second time: the rays' spread,
        // hence the condition number, is the same; the depth is √2 as precise.
        s.db.get_mut(0).expect("track").retired = retired_again(&s, 0);
        let cols = Columns::window(&s.state);
        let f = s.db.get(0).expect("track");
        assert!(build(&s.state.means, f, &cols, true, &tri).is_none());
        assert!(build(&s.state.means, f, &cols, true, &tri.starved()).is_some());
        let (stats, _) = update_scene(&mut s, &[0], &tri, &mut Vec::new());
        assert_eq!((stats.used, stats.failed), (1, 0), "{stats:?}");

        // Eleven tracks pass the plain limit beside the retired one: not
        // starved, and that one is left for a later frame.
        let mut s = scene(8, 12, 1e-4, 1e-4);
        let conds: Vec<f64> = (0..12).map(|id| window_condition(&s, id)).collect();
        let worst = (0..12)
            .max_by(|a, b| conds[*a].total_cmp(&conds[*b]))
            .expect("tracks");
        let second = conds
            .iter()
            .copied()
            .filter(|c| *c < conds[worst])
            .fold(0.0, f64::max);
        let tri = TriangulationOptions {
            max_condition_number: (second + conds[worst]) / 2.0,
            ..TriangulationOptions::default()
        };
        s.db.get_mut(worst as u64).expect("track").retired = retired_again(&s, worst as u64);
        let ids: Vec<u64> = (0..12).collect();
        let mut failed = Vec::new();
        let (stats, _) = update_scene(&mut s, &ids, &tri, &mut failed);
        assert_eq!((stats.used, stats.failed), (11, 1), "{stats:?}");
        assert_eq!(failed, vec![worst as u64]);
    }
}
