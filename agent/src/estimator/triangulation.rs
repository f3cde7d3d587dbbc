//! Triangulation of one point feature from several posed camera observations.
//!
//! The method follows OpenVINS (thesis Section 2.3.3, "perform BA to triangulate
//! these features"):
//!
//! 1. [`triangulate_linear`]: every observation gives a bearing `b_i` (unit vector of
//!    `[u_n, v_n, 1]` rotated out of its camera). The point lies on the ray, so the
//!    component of `p_f - p_ci` orthogonal to the bearing vanishes:
//!    `N_i (p_f - p_ci) = 0` with `N_i = I - b_i b_iᵀ` (`N_i = [b_i]×ᵀ [b_i]×`).
//!    The normal equations `(Σ N_i) p_f = Σ N_i p_ci` are a 3x3 system whose
//!    condition number measures the parallax.
//! 2. [`refine_gauss_newton`]: Levenberg-Marquardt on the reprojection errors of
//!    all observations, measured where the camera's pixel noise is uniform
//!    ([`RayResidual`]: normalized coordinates for a pinhole lens, as OpenVINS
//!    does, angles for a fisheye), in anchored inverse-depth parameters
//!    `(α, β, ρ) = (x/z, y/z, 1/z)` of the point in the anchor camera.
//! 3. [`check_point`]: the point is in front of every camera, within the depth
//!    limits, seen with enough parallax (depth / baseline) and reprojects well.
//!
//! [`triangulate`] chains the three. The anchor camera is always the **last**
//! observation of the slice (the newest image when the slice is in time order).
//!
//! Everything runs on fixed-size nalgebra types: nothing is allocated.

use common::camera::{CameraModel, Distortion};
use common::estimator_options::TriangulationLimits;
use nalgebra::{Matrix2x3, Matrix3, SymmetricEigen, Vector2, Vector3};
use std::cmp::Ordering;

/// Levenberg-Marquardt damping of the first iteration (relative to `diag(H)`).
const LM_INITIAL_LAMBDA: f64 = 1e-3;
/// Factor by which the damping grows after a rejected step and shrinks after an
/// accepted one.
const LM_LAMBDA_FACTOR: f64 = 10.0;
/// Smallest damping kept after accepted steps.
const LM_MIN_LAMBDA: f64 = 1e-12;
/// Damping above which no step can lower the cost any more: the current point is
/// a minimum to numerical precision.
const LM_MAX_LAMBDA: f64 = 1e10;
/// An accepted step shorter than this (relative to the parameter norm) ends the
/// refinement as converged.
const STEP_TOLERANCE: f64 = 1e-12;
/// An accepted step lowering the cost by less than this fraction ends the
/// refinement as converged.
const COST_TOLERANCE: f64 = 1e-12;
/// A cost (sum of squared ray residuals) below this is zero for all purposes.
const COST_FLOOR: f64 = 1e-28;
/// When the iteration budget runs out, the refinement still counts as converged if
/// its last step was shorter than this (relative to the parameter norm).
const LOOSE_STEP_TOLERANCE: f64 = 1e-6;
/// Points with a camera-frame `z` (scaled by the inverse depth) at or below this are
/// treated as behind the camera during the refinement.
const MIN_SCALED_DEPTH: f64 = 1e-12;

/// One observation of the feature: the pose of the camera and the undistorted
/// normalized coordinates of the feature in that image.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct CameraObservation {
    /// Rotation from the camera frame `C` to the global frame `G` (`R_CtoG`).
    pub r_c_to_g: Matrix3<f64>,
    /// Position of the camera centre in `G` (`p_CinG`), metres.
    pub p_c_in_g: Vector3<f64>,
    /// Undistorted normalized image coordinates `[x/z, y/z]` of the feature.
    pub uvn: Vector2<f64>,
}

impl CameraObservation {
    /// Unit bearing of the observation, expressed in `G`.
    fn bearing_in_g(&self) -> Vector3<f64> {
        (self.r_c_to_g * Vector3::new(self.uvn.x, self.uvn.y, 1.0)).normalize()
    }

    /// The point `p_f_in_g` expressed in this camera frame.
    fn point_in_camera(&self, p_f_in_g: &Vector3<f64>) -> Vector3<f64> {
        self.r_c_to_g.tr_mul(&(p_f_in_g - self.p_c_in_g))
    }

    /// Two orthonormal directions (rows) perpendicular to the measured ray, in
    /// the camera frame.
    fn tangent_basis(&self) -> Matrix2x3<f64> {
        let m = Vector3::new(self.uvn.x, self.uvn.y, 1.0).normalize();
        // The camera's x axis is never along a ray in front of it (z > 0 for
        // every ray an undistorted pixel gives): Gram-Schmidt from it.
        let e1 = (Vector3::x() - m * m.x).normalize();
        let e2 = m.cross(&e1);
        Matrix2x3::from_rows(&[e1.transpose(), e2.transpose()])
    }

    /// The reprojection residual of the point at `p_c` (camera frame), as
    /// `kind` measures it.
    fn ray_residual(&self, p_c: &Vector3<f64>, kind: RayResidual) -> Vector2<f64> {
        match kind {
            RayResidual::Normalized => self.uvn - p_c.xy() / p_c.z,
            RayResidual::Angle => -(self.tangent_basis() * p_c.normalize()),
        }
    }
}

/// How the triangulation measures a ray's reprojection error: where the
/// camera's pixel noise is (about) uniform, so that every ray weighs by its
/// noise.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub enum RayResidual {
    /// Differences of normalized coordinates `[x/z, y/z]` (OpenVINS's): a
    /// pinhole lens spreads its pixels evenly over the normalized plane (up to
    /// its distortion's scale).
    #[default]
    Normalized,
    /// The measured ray's offset from the point's direction in the plane
    /// tangent to the ray (about the angle between them, radians): an
    /// equidistant fisheye spreads its pixels evenly over angles, and one of
    /// its pixels spans `sec² θ` of the normalized plane at `θ` off the axis.
    /// On TUM-VI's fisheye (190 px focal length) a pixel at the image's
    /// edges, 77 deg off the axis, spans 20 times the normalized plane a
    /// central one does: measured there, the refinement leaned on the
    /// noisiest rays, and the residual limit failed most tracks that reached
    /// the rim (README, "Other cameras and settings").
    Angle,
}

impl RayResidual {
    /// The residual for `camera`'s lens.
    pub fn of(camera: &CameraModel) -> Self {
        match camera.model {
            Distortion::RadTan => Self::Normalized,
            Distortion::Equidistant => Self::Angle,
        }
    }
}

/// Thresholds of the triangulation.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct TriangulationOptions {
    /// Fewest observations to triangulate from (two are required whatever this says).
    pub min_observations: usize,
    /// Largest accepted ratio of the largest to the smallest singular value of the
    /// 3x3 linear system `Σ N_i`.
    pub max_condition_number: f64,
    /// Smallest accepted depth of the point in the anchor camera, metres.
    pub min_depth_m: f64,
    /// Largest accepted depth of the point in the anchor camera, metres.
    pub max_depth_m: f64,
    /// Largest accepted ratio of the anchor depth to the baseline (the largest
    /// distance between two camera centres): rejects features with tiny parallax.
    pub max_baseline_ratio: f64,
    /// Largest number of accepted Levenberg-Marquardt steps (0 disables the refinement).
    pub gn_iterations: usize,
    /// Largest accepted mean norm of the ray residuals after the refinement
    /// (normalized coordinates, or radians: alike near the optical axis).
    pub max_ray_residual: f64,
    /// How a ray's residual is measured (the camera's lens, [`RayResidual::of`]).
    pub residual: RayResidual,
    /// When a track's window views fail these limits and its retired rays are
    /// added ([`crate::estimator::feature_system::build`]), let the longer set's
    /// condition-number limit grow with its number of rays, so that it asks the
    /// depth precision the window's views would have had to reach (see
    /// [`TriangulationOptions::starved`]).
    pub retired_by_precision: bool,
}

impl Default for TriangulationOptions {
    /// OpenVINS's thresholds ([`TriangulationLimits::default`]: condition number
    /// 10⁴, depth in `[0.1, 60]` m, depth/baseline at most 40), 2 observations,
    /// 10 iterations, mean ray residual 0.02 (9 px at EuRoC's 458 px focal
    /// length near the optical axis) in normalized coordinates.
    fn default() -> Self {
        Self::with_limits(&TriangulationLimits::default())
    }
}

impl TriangulationOptions {
    /// The configurable limits, with the fixed refinement settings.
    ///
    /// On the condition number: 10⁵ let in rays 0.6-2 deg apart (5-7 m deep points
    /// seen over 0.2 m on V1_01's slow start), whose depth is too uncertain to
    /// linearize at; the first updates left roll 4-8 sigma off (V1_01, 40 seeds:
    /// 0.68 deg with 10⁵, 0.40 with 10⁴ once the candidates beyond the cap are
    /// kept; README).
    pub fn with_limits(l: &TriangulationLimits) -> Self {
        Self {
            min_observations: 2,
            max_condition_number: l.max_condition_number,
            min_depth_m: l.min_depth_m,
            max_depth_m: l.max_depth_m,
            max_baseline_ratio: l.max_baseline_ratio,
            gn_iterations: 10,
            max_ray_residual: 0.02,
            residual: RayResidual::Normalized,
            retired_by_precision: false,
        }
    }

    /// [`Self::with_limits`] with the residual of `camera`'s lens
    /// ([`RayResidual::of`]).
    pub fn for_camera(l: &TriangulationLimits, camera: &CameraModel) -> Self {
        Self {
            residual: RayResidual::of(camera),
            ..Self::with_limits(l)
        }
    }

    /// These limits for an update starved of features, where nearly every
    /// track fails them (see `updater_msckf::update_up_to`): a track whose
    /// window views fail may pass with its retired rays in front under a
    /// condition-number limit scaled by `rays / window views`. The depth's
    /// relative precision from `n` rays of angular noise `σ` is about
    /// `σ √(cond / n)` (the smallest eigenvalue of `Σ N_i` is the depth
    /// direction's information, the largest is about `n`), so this asks the
    /// longer set for the precision the window's views would have had to reach
    /// under the plain limit. On a slow flight (V1_01 at half speed: 0.2 m/s,
    /// points 5-7 m away) the plain limit passes almost nothing even with
    /// three seconds of rays (condition numbers 10⁴-10⁵), and the filter
    /// coasts on the IMU for seconds at a time.
    pub fn starved(&self) -> Self {
        Self {
            retired_by_precision: true,
            ..*self
        }
    }

    /// These limits with the two on ray geometry looser: for a first update
    /// none of whose candidates passed them, where the clones the rays come
    /// from are bent by the start's errors and the iterations triangulate the
    /// points again. The depth/baseline ratio is 100 times looser. The
    /// condition number is 100 times looser too, but never beyond
    /// [`noise_condition_number`] of `ray_noise_rad` (the angular pixel noise
    /// of one ray): past it the rays' spread is the pixel noise itself, and
    /// such a point has no depth to linearize at (V1_01 started from
    /// OpenVINS's prior, 20 seeds: position NEES 5.88 with 10⁶, 4.60 with
    /// this bound).
    pub fn relaxed(&self, ray_noise_rad: f64) -> Self {
        let loose = self.max_condition_number * 100.0;
        Self {
            max_condition_number: loose
                .min(noise_condition_number(ray_noise_rad))
                .max(self.max_condition_number),
            max_baseline_ratio: self.max_baseline_ratio * 100.0,
            ..*self
        }
    }
}

/// The condition number of `Σ N_i` for `n` rays from one camera centre that
/// differ only by pixel noise of `σ` radians per image axis: the largest
/// eigenvalue is near `n`, the smallest (along the mean ray) is
/// `Σ sin²(angle of ray i to the mean) ≈ 2 σ² (n - 1)`, so the ratio is
/// `n / (2 σ² (n - 1))`, which is `1 / (2 σ²)` for long tracks. A larger
/// condition number means rays whose spread the noise explains: no parallax.
/// Infinite when `σ` is not positive.
pub fn noise_condition_number(ray_noise_rad: f64) -> f64 {
    if ray_noise_rad > 0.0 {
        1.0 / (2.0 * ray_noise_rad * ray_noise_rad)
    } else {
        f64::INFINITY
    }
}

/// Why a feature could not be triangulated.
#[derive(Clone, Copy, Debug, PartialEq, thiserror::Error)]
pub enum TriangulationError {
    /// Fewer observations than [`TriangulationOptions::min_observations`] (or than 2).
    #[error("too few observations to triangulate the feature")]
    TooFewObservations,
    /// The linear system is (nearly) singular: too little parallax between the rays.
    #[error("ill-conditioned triangulation: condition number {cond:e}")]
    IllConditioned {
        /// Ratio of the largest to the smallest singular value of `Σ N_i`
        /// (infinite when singular, NaN when the input is not finite).
        cond: f64,
    },
    /// The point is behind a camera, or closer to the anchor camera than
    /// [`TriangulationOptions::min_depth_m`].
    #[error("the triangulated point is behind a camera or closer than the minimum depth")]
    BehindCamera,
    /// The point is farther from the anchor camera than
    /// [`TriangulationOptions::max_depth_m`].
    #[error("the triangulated point is farther than the maximum depth")]
    TooFar,
    /// Depth / baseline exceeds [`TriangulationOptions::max_baseline_ratio`].
    #[error("the baseline is too small for the depth of the point")]
    SmallBaseline,
    /// The refinement did not converge or produced non-finite values.
    #[error("the triangulation refinement did not converge")]
    NotConverged,
    /// The mean reprojection residual after refinement exceeds
    /// [`TriangulationOptions::max_ray_residual`].
    #[error("the triangulated point reprojects with a large residual")]
    LargeResidual,
}

/// Whether `a > b` (false when either is NaN).
fn above(a: f64, b: f64) -> bool {
    a.partial_cmp(&b) == Some(Ordering::Greater)
}

/// Whether `a <= b` (false when either is NaN).
fn at_most(a: f64, b: f64) -> bool {
    matches!(a.partial_cmp(&b), Some(Ordering::Less | Ordering::Equal))
}

/// The anchor observation (the last one), after checking there are enough.
fn anchor_of<'a>(
    obs: &'a [CameraObservation],
    opts: &TriangulationOptions,
) -> Result<&'a CameraObservation, TriangulationError> {
    if obs.len() < opts.min_observations.max(2) {
        return Err(TriangulationError::TooFewObservations);
    }
    obs.last().ok_or(TriangulationError::TooFewObservations)
}

/// Checks the depth of the point in the anchor camera against the limits.
fn check_anchor_depth(depth: f64, opts: &TriangulationOptions) -> Result<(), TriangulationError> {
    if depth.is_nan() {
        return Err(TriangulationError::NotConverged);
    }
    if depth < opts.min_depth_m {
        return Err(TriangulationError::BehindCamera);
    }
    if depth > opts.max_depth_m {
        return Err(TriangulationError::TooFar);
    }
    Ok(())
}

/// The largest distance between two camera centres of the observations, metres.
pub fn max_baseline(obs: &[CameraObservation]) -> f64 {
    let mut best_sq = 0.0_f64;
    for (i, a) in obs.iter().enumerate() {
        for b in &obs[i + 1..] {
            best_sq = best_sq.max((a.p_c_in_g - b.p_c_in_g).norm_squared());
        }
    }
    best_sq.sqrt()
}

/// Linear triangulation of the point `p_FinG` from the observations.
///
/// Solves `(Σ N_i) (p_f - p_a) = Σ N_i (p_ci - p_a)` with `N_i = I - b_i b_iᵀ`,
/// relative to the anchor (last) camera centre `p_a` to keep the numbers small. The
/// bearings are expressed in axes parallel to `G` rather than rotated into the
/// anchor camera: the system is the anchor-frame system rotated by `R_AtoG`, with
/// the same singular values and solution. Rejects a condition number of `Σ N_i`
/// at or above [`TriangulationOptions::max_condition_number`] and an anchor depth
/// outside `[min_depth_m, max_depth_m]`.
pub fn triangulate_linear(
    obs: &[CameraObservation],
    opts: &TriangulationOptions,
) -> Result<Vector3<f64>, TriangulationError> {
    let anchor = anchor_of(obs, opts)?;
    let mut a = Matrix3::<f64>::zeros();
    let mut rhs = Vector3::<f64>::zeros();
    for o in obs {
        let b = o.bearing_in_g();
        let n = Matrix3::identity() - b * b.transpose();
        a += n;
        rhs += n * (o.p_c_in_g - anchor.p_c_in_g);
    }
    // Σ N_i is symmetric positive semi-definite: its singular values are its
    // eigenvalues, and the eigen-decomposition also solves the system.
    let eig = SymmetricEigen::new(a);
    let (mut lo, mut hi) = (f64::INFINITY, 0.0_f64);
    for &v in eig.eigenvalues.iter() {
        lo = lo.min(v.abs());
        hi = hi.max(v.abs());
    }
    let cond = if eig.eigenvalues.iter().any(|v| v.is_nan()) {
        f64::NAN
    } else if lo > 0.0 {
        hi / lo
    } else {
        f64::INFINITY
    };
    if cond.is_nan() || cond >= opts.max_condition_number {
        return Err(TriangulationError::IllConditioned { cond });
    }
    let mut coeffs = eig.eigenvectors.tr_mul(&rhs);
    for (c, &v) in coeffs.iter_mut().zip(eig.eigenvalues.iter()) {
        *c /= v;
    }
    let p_rel_g = eig.eigenvectors * coeffs;
    if !p_rel_g.iter().all(|v| v.is_finite()) {
        return Err(TriangulationError::IllConditioned { cond });
    }
    let p_in_anchor = anchor.r_c_to_g.tr_mul(&p_rel_g);
    check_anchor_depth(p_in_anchor.z, opts)?;
    Ok(p_rel_g + anchor.p_c_in_g)
}

/// Cost and normal equations of the reprojection problem at one parameter vector.
struct Linearization {
    /// Sum of the squared ray residuals.
    cost: f64,
    /// `Σ Jᵢᵀ Jᵢ` with `Jᵢ` the Jacobian of the predicted ray (its normalized
    /// coordinates, or its components across the measured ray).
    hessian: Matrix3<f64>,
    /// `Σ Jᵢᵀ rᵢ` with `rᵢ = measured - predicted`.
    gradient: Vector3<f64>,
}

/// Evaluates the reprojection cost and its normal equations at the anchored
/// inverse-depth parameters `x = [α, β, ρ]`; `None` when `ρ <= 0` or the point is
/// behind (or on the plane of) any camera.
///
/// With `p_FinA = [α, β, 1] / ρ`, the point in camera `i` scaled by `ρ` is
/// `h_i = R_Ciᵀ (R_A [α, β, 1] + ρ (p_A - p_Ci))`, whose projection `h_xy / h_z`
/// does not depend on the scale.
fn linearize(
    obs: &[CameraObservation],
    anchor: &CameraObservation,
    x: &Vector3<f64>,
    kind: RayResidual,
) -> Option<Linearization> {
    if !above(x.z, 0.0) || !x.iter().all(|v| v.is_finite()) {
        return None;
    }
    let r_a = &anchor.r_c_to_g;
    let mut out = Linearization {
        cost: 0.0,
        hessian: Matrix3::zeros(),
        gradient: Vector3::zeros(),
    };
    for o in obs {
        let d = anchor.p_c_in_g - o.p_c_in_g;
        // Columns: ∂h/∂α, ∂h/∂β, ∂h/∂ρ (all in the camera frame).
        let dh_dx = o.r_c_to_g.tr_mul(&Matrix3::from_columns(&[
            r_a.column(0).into(),
            r_a.column(1).into(),
            d,
        ]));
        let h = dh_dx * x + o.r_c_to_g.tr_mul(&r_a.column(2).into_owned());
        if !above(h.z, MIN_SCALED_DEPTH) {
            return None;
        }
        let (r, j) = match kind {
            RayResidual::Normalized => {
                let inv_z = 1.0 / h.z;
                let predicted = Vector2::new(h.x * inv_z, h.y * inv_z);
                let dz_dh = Matrix2x3::new(
                    inv_z,
                    0.0,
                    -predicted.x * inv_z,
                    0.0,
                    inv_z,
                    -predicted.y * inv_z,
                );
                (o.uvn - predicted, dz_dh * dh_dx)
            }
            RayResidual::Angle => {
                // The predicted direction's components across the measured
                // ray, and their derivative through the normalization.
                let norm = h.norm();
                let u = h / norm;
                let tangent = o.tangent_basis();
                let du_dh = (Matrix3::identity() - u * u.transpose()) / norm;
                (-(tangent * u), tangent * du_dh * dh_dx)
            }
        };
        out.cost += r.norm_squared();
        out.hessian += j.tr_mul(&j);
        out.gradient += j.tr_mul(&r);
    }
    Some(out)
}

/// Refines `initial` (`p_FinG`) by Levenberg-Marquardt on the ray residuals
/// ([`TriangulationOptions::residual`]) of all observations, in inverse-depth parameters
/// `[x/z, y/z, 1/z]` of the anchor (last) camera.
///
/// Runs at most [`TriangulationOptions::gn_iterations`] accepted steps. Fails with
/// [`TriangulationError::BehindCamera`] when the initial or final point is behind a
/// camera, and with [`TriangulationError::NotConverged`] when the budget runs out
/// while the steps are still large or the values become non-finite. Depth,
/// baseline and residual limits are left to [`check_point`].
pub fn refine_gauss_newton(
    obs: &[CameraObservation],
    initial: Vector3<f64>,
    opts: &TriangulationOptions,
) -> Result<Vector3<f64>, TriangulationError> {
    let anchor = anchor_of(obs, opts)?;
    let p_in_anchor = anchor.point_in_camera(&initial);
    if !p_in_anchor.iter().all(|v| v.is_finite()) {
        return Err(TriangulationError::NotConverged);
    }
    if !above(p_in_anchor.z, 0.0) {
        return Err(TriangulationError::BehindCamera);
    }
    let inv_z = 1.0 / p_in_anchor.z;
    let mut x = Vector3::new(p_in_anchor.x * inv_z, p_in_anchor.y * inv_z, inv_z);
    let mut lin =
        linearize(obs, anchor, &x, opts.residual).ok_or(TriangulationError::BehindCamera)?;
    if !lin.cost.is_finite() {
        // Non-finite observations: no step can be judged.
        return Err(TriangulationError::NotConverged);
    }

    let mut lambda = LM_INITIAL_LAMBDA;
    let mut converged = opts.gn_iterations == 0 || lin.cost < COST_FLOOR;
    let mut last_relative_step = 0.0;
    let mut accepted = 0;
    while !converged && accepted < opts.gn_iterations {
        if lambda > LM_MAX_LAMBDA {
            // No damped step lowers the cost: a minimum to numerical precision.
            converged = true;
            break;
        }
        let mut damped = lin.hessian;
        let scale = lin.hessian.trace().abs() * 1e-12 + f64::MIN_POSITIVE;
        for i in 0..3 {
            damped[(i, i)] += lambda * (lin.hessian[(i, i)] + scale);
        }
        let Some(chol) = damped.cholesky() else {
            lambda *= LM_LAMBDA_FACTOR;
            continue;
        };
        let dx = chol.solve(&lin.gradient);
        let x_new = x + dx;
        match linearize(obs, anchor, &x_new, opts.residual) {
            Some(new_lin) if new_lin.cost <= lin.cost => {
                let relative_decrease = (lin.cost - new_lin.cost) / lin.cost;
                x = x_new;
                lin = new_lin;
                accepted += 1;
                lambda = (lambda / LM_LAMBDA_FACTOR).max(LM_MIN_LAMBDA);
                last_relative_step = dx.norm() / x.norm();
                converged = last_relative_step < STEP_TOLERANCE
                    || relative_decrease < COST_TOLERANCE
                    || lin.cost < COST_FLOOR;
            }
            _ => lambda *= LM_LAMBDA_FACTOR,
        }
    }
    if !converged && !above(LOOSE_STEP_TOLERANCE, last_relative_step) {
        return Err(TriangulationError::NotConverged);
    }
    let z = 1.0 / x.z;
    let p_f_in_g = anchor.r_c_to_g * Vector3::new(x.x * z, x.y * z, z) + anchor.p_c_in_g;
    if !p_f_in_g.iter().all(|v| v.is_finite()) {
        return Err(TriangulationError::NotConverged);
    }
    if obs
        .iter()
        .any(|o| !above(o.point_in_camera(&p_f_in_g).z, 0.0))
    {
        return Err(TriangulationError::BehindCamera);
    }
    Ok(p_f_in_g)
}

/// Checks a triangulated point `p_f_in_g` against the observations: in front of
/// every camera, anchor (last camera) depth within `[min_depth_m, max_depth_m]`,
/// anchor depth / [`max_baseline`] at most `max_baseline_ratio`, and mean norm of
/// the ray residuals at most `max_ray_residual`.
pub fn check_point(
    obs: &[CameraObservation],
    p_f_in_g: &Vector3<f64>,
    opts: &TriangulationOptions,
) -> Result<(), TriangulationError> {
    let anchor = anchor_of(obs, opts)?;
    if !p_f_in_g.iter().all(|v| v.is_finite()) {
        return Err(TriangulationError::NotConverged);
    }
    let mut residual_sum = 0.0;
    for o in obs {
        let p_c = o.point_in_camera(p_f_in_g);
        if !above(p_c.z, 0.0) {
            return Err(TriangulationError::BehindCamera);
        }
        residual_sum += o.ray_residual(&p_c, opts.residual).norm();
    }
    let depth = anchor.point_in_camera(p_f_in_g).z;
    check_anchor_depth(depth, opts)?;
    if !at_most(depth, opts.max_baseline_ratio * max_baseline(obs)) {
        return Err(TriangulationError::SmallBaseline);
    }
    // The observation count is at least 2 (checked by `anchor_of`).
    let mean_residual = residual_sum / obs.len() as f64;
    if !at_most(mean_residual, opts.max_ray_residual) {
        return Err(TriangulationError::LargeResidual);
    }
    Ok(())
}

/// Triangulates `p_FinG`: [`triangulate_linear`], then [`refine_gauss_newton`],
/// then [`check_point`].
///
/// Observations whose baseline is too short for any admissible depth
/// (`max_baseline · max_baseline_ratio < min_depth_m`, e.g. a purely rotating
/// camera) are rejected up front as [`TriangulationError::SmallBaseline`].
pub fn triangulate(
    obs: &[CameraObservation],
    opts: &TriangulationOptions,
) -> Result<Vector3<f64>, TriangulationError> {
    anchor_of(obs, opts)?;
    if !at_most(
        opts.min_depth_m,
        max_baseline(obs) * opts.max_baseline_ratio,
    ) {
        return Err(TriangulationError::SmallBaseline);
    }
    let linear = triangulate_linear(obs, opts)?;
    let refined = refine_gauss_newton(obs, linear, opts)?;
    check_point(obs, &refined, opts)?;
    Ok(refined)
}

#[cfg(test)]
mod tests {
    use super::*;
    use common::so3::exp_so3;
    use rand::{Rng, SeedableRng};
    use rand_chacha::ChaCha8Rng;

    /// A standard normal sample (Box-Muller).
    fn normal(rng: &mut ChaCha8Rng) -> f64 {
        let u1: f64 = rng.random_range(f64::EPSILON..1.0);
        let u2: f64 = rng.random();
        (-2.0 * u1.ln()).sqrt() * (std::f64::consts::TAU * u2).cos()
    }

    /// `R_CtoG` of a camera at `from` whose optical axis points at `to`.
    fn look_at(from: &Vector3<f64>, to: &Vector3<f64>) -> Matrix3<f64> {
        let z = (to - from).normalize();
        let helper = if z.z.abs() < 0.9 {
            Vector3::z()
        } else {
            Vector3::x()
        };
        let x = helper.cross(&z).normalize();
        let y = z.cross(&x);
        Matrix3::from_columns(&[x, y, z])
    }

    /// An observation of `p_f` from a camera at `p_c` looking roughly at the point
    /// (rotated by up to ~0.1 rad), with normalized noise of std `sigma`.
    fn observe(
        rng: &mut ChaCha8Rng,
        p_c: Vector3<f64>,
        p_f: &Vector3<f64>,
        sigma: f64,
    ) -> CameraObservation {
        let jitter = Vector3::new(normal(rng), normal(rng), normal(rng)) * 0.05;
        let r_c_to_g = look_at(&p_c, p_f) * exp_so3(&jitter);
        let p_in_c = r_c_to_g.transpose() * (p_f - p_c);
        let noise = Vector2::new(normal(rng), normal(rng)) * sigma;
        CameraObservation {
            r_c_to_g,
            p_c_in_g: p_c,
            uvn: p_in_c.xy() / p_in_c.z + noise,
        }
    }

    /// `n` cameras spread over a segment of length `baseline` (plus small vertical
    /// wiggle), all observing `p_f`.
    fn scene(
        rng: &mut ChaCha8Rng,
        n: usize,
        baseline: f64,
        p_f: &Vector3<f64>,
        sigma: f64,
    ) -> Vec<CameraObservation> {
        (0..n)
            .map(|i| {
                let s = i as f64 / (n - 1) as f64 - 0.5;
                let p_c = Vector3::new(s * baseline, 0.05 * normal(rng), 1.0 + 0.05 * normal(rng));
                observe(rng, p_c, p_f, sigma)
            })
            .collect()
    }

    fn random_point(rng: &mut ChaCha8Rng, depth: f64) -> Vector3<f64> {
        Vector3::new(
            rng.random_range(-1.0..1.0),
            depth,
            rng.random_range(0.0..2.0),
        )
    }

    #[test]
    fn rays_from_one_place_reach_the_noise_condition_number() {
        // Eleven images from one camera centre (no parallax at all), with
        // 1 px noise at a 458 px focal length: the median condition number of
        // Σ N_i is the noise bound times n / (n - 1).
        let mut rng = ChaCha8Rng::seed_from_u64(11);
        let sigma = 1.0 / 458.0;
        let n = 11;
        let opts = TriangulationOptions {
            max_condition_number: 1.0,
            ..TriangulationOptions::default()
        };
        let p_f = Vector3::new(0.3, 5.0, 1.2);
        let mut conds: Vec<f64> = (0..201)
            .map(|_| {
                let obs: Vec<_> = (0..n)
                    .map(|_| observe(&mut rng, Vector3::new(0.0, 0.0, 1.0), &p_f, sigma))
                    .collect();
                match triangulate_linear(&obs, &opts) {
                    Err(TriangulationError::IllConditioned { cond }) => cond,
                    other => panic!("expected an ill-conditioned system, got {other:?}"),
                }
            })
            .collect();
        conds.sort_by(f64::total_cmp);
        let expected = noise_condition_number(sigma) * n as f64 / (n - 1) as f64;
        let ratio = conds[100] / expected;
        assert!(
            (0.8..1.25).contains(&ratio),
            "median {} vs {expected}",
            conds[100]
        );
    }

    #[test]
    fn the_relaxed_condition_number_stops_at_the_noise_bound_and_never_tightens() {
        let strict = TriangulationOptions::default();
        assert_eq!(strict.max_condition_number, 1e4);
        // 1 px at 458 px: the bound, 1.05e5, is tighter than 100 x 1e4.
        let sigma = 1.0 / 458.0;
        let r = strict.relaxed(sigma);
        assert!((r.max_condition_number - 0.5 * 458.0 * 458.0).abs() < 1e-6);
        assert_eq!(r.max_baseline_ratio, 100.0 * strict.max_baseline_ratio);
        // No noise figure: 100 times looser.
        assert_eq!(strict.relaxed(0.0).max_condition_number, 1e6);
        // A noise bound below the strict limit leaves the strict limit.
        assert_eq!(strict.relaxed(0.1).max_condition_number, 1e4);
        assert!(noise_condition_number(-1.0).is_infinite());
    }

    #[test]
    fn noiseless_observations_from_five_to_eleven_poses_recover_the_point_to_1e_9() {
        let mut rng = ChaCha8Rng::seed_from_u64(1);
        let opts = TriangulationOptions::default();
        for n in 5..=11 {
            for _ in 0..20 {
                let depth = rng.random_range(1.0..20.0);
                let p_f = random_point(&mut rng, depth);
                let obs = scene(&mut rng, n, 1.0, &p_f, 0.0);
                let p = triangulate(&obs, &opts).unwrap();
                assert!((p - p_f).norm() < 1e-9, "n = {n}: {p} vs {p_f}");
            }
        }
    }

    #[test]
    fn linear_triangulation_alone_is_exact_without_noise() {
        let mut rng = ChaCha8Rng::seed_from_u64(2);
        let p_f = Vector3::new(0.3, 5.0, 1.2);
        let obs = scene(&mut rng, 6, 1.0, &p_f, 0.0);
        let p = triangulate_linear(&obs, &TriangulationOptions::default()).unwrap();
        assert!((p - p_f).norm() < 1e-9);
    }

    #[test]
    fn with_1e_3_normalized_noise_a_point_at_5_m_with_1_m_baseline_is_within_centimetres() {
        let mut rng = ChaCha8Rng::seed_from_u64(3);
        let opts = TriangulationOptions::default();
        let trials = 200;
        let mut sum_sq = 0.0;
        let mut worst = 0.0_f64;
        for _ in 0..trials {
            let p_f = random_point(&mut rng, 5.0);
            let obs = scene(&mut rng, 8, 1.0, &p_f, 1e-3);
            let p = triangulate(&obs, &opts).unwrap();
            let e = (p - p_f).norm();
            sum_sq += e * e;
            worst = worst.max(e);
        }
        let rms = (sum_sq / trials as f64).sqrt();
        // First-order depth std: z σ / (angular spread · √n) ≈ 5 · 1e-3 / (0.058 · √8) ≈ 3 cm.
        assert!(rms < 0.05, "rms error {rms} m");
        assert!(worst < 0.15, "worst error {worst} m");
    }

    #[test]
    fn refinement_improves_on_the_linear_solution_under_noise() {
        let mut rng = ChaCha8Rng::seed_from_u64(4);
        let opts = TriangulationOptions::default();
        let (mut cost_linear, mut cost_refined) = (0.0, 0.0);
        for _ in 0..50 {
            let p_f = random_point(&mut rng, 5.0);
            let obs = scene(&mut rng, 8, 1.0, &p_f, 1e-3);
            let linear = triangulate_linear(&obs, &opts).unwrap();
            let refined = refine_gauss_newton(&obs, linear, &opts).unwrap();
            let cost = |p: &Vector3<f64>| {
                obs.iter()
                    .map(|o| {
                        let c = o.point_in_camera(p);
                        (o.uvn - c.xy() / c.z).norm_squared()
                    })
                    .sum::<f64>()
            };
            assert!(cost(&refined) <= cost(&linear) * (1.0 + 1e-12));
            cost_linear += cost(&linear);
            cost_refined += cost(&refined);
        }
        assert!(cost_refined < cost_linear);
    }

    #[test]
    fn a_point_behind_the_cameras_is_rejected() {
        let mut rng = ChaCha8Rng::seed_from_u64(5);
        let p_f = Vector3::new(0.2, 5.0, 1.0);
        let mut obs = scene(&mut rng, 6, 1.0, &p_f, 0.0);
        // Turn every camera around (180° about its y axis) and re-observe the same
        // point, which now lies behind all of them.
        for o in &mut obs {
            o.r_c_to_g *= exp_so3(&Vector3::new(0.0, std::f64::consts::PI, 0.0));
            let p_in_c = o.point_in_camera(&p_f);
            assert!(p_in_c.z < 0.0);
            o.uvn = p_in_c.xy() / p_in_c.z;
        }
        let opts = TriangulationOptions::default();
        assert_eq!(
            triangulate(&obs, &opts),
            Err(TriangulationError::BehindCamera)
        );
        assert_eq!(
            triangulate_linear(&obs, &opts),
            Err(TriangulationError::BehindCamera)
        );
        assert_eq!(
            refine_gauss_newton(&obs, p_f, &opts),
            Err(TriangulationError::BehindCamera)
        );
    }

    #[test]
    fn pure_rotation_is_rejected_as_ill_conditioned_or_small_baseline() {
        let mut rng = ChaCha8Rng::seed_from_u64(6);
        let opts = TriangulationOptions::default();
        let p_c = Vector3::new(0.0, 0.0, 1.0);
        for sigma in [0.0, 1e-3] {
            let p_f = Vector3::new(0.5, 6.0, 1.5);
            let obs: Vec<_> = (0..8)
                .map(|_| observe(&mut rng, p_c, &p_f, sigma))
                .collect();
            let err = triangulate(&obs, &opts).unwrap_err();
            assert!(
                matches!(
                    err,
                    TriangulationError::IllConditioned { .. } | TriangulationError::SmallBaseline
                ),
                "{err:?}"
            );
            let err = triangulate_linear(&obs, &opts).unwrap_err();
            assert!(
                matches!(err, TriangulationError::IllConditioned { .. }),
                "{err:?}"
            );
        }
    }

    #[test]
    fn levenberg_marquardt_converges_from_a_twenty_percent_depth_error() {
        let mut rng = ChaCha8Rng::seed_from_u64(7);
        let opts = TriangulationOptions::default();
        for factor in [0.8, 1.2] {
            for _ in 0..20 {
                let depth = rng.random_range(2.0..15.0);
                let p_f = random_point(&mut rng, depth);
                let obs = scene(&mut rng, 7, 1.0, &p_f, 0.0);
                let anchor = obs[obs.len() - 1].p_c_in_g;
                let initial = anchor + (p_f - anchor) * factor;
                let p = refine_gauss_newton(&obs, initial, &opts).unwrap();
                assert!((p - p_f).norm() < 1e-9, "{factor}: {p} vs {p_f}");
            }
        }
    }

    #[test]
    fn levenberg_marquardt_converges_from_a_lateral_and_depth_error_under_noise() {
        let mut rng = ChaCha8Rng::seed_from_u64(8);
        let opts = TriangulationOptions::default();
        for _ in 0..20 {
            let p_f = random_point(&mut rng, 5.0);
            let obs = scene(&mut rng, 9, 1.0, &p_f, 1e-3);
            let best = triangulate(&obs, &opts).unwrap();
            let initial = p_f + Vector3::new(0.3, 1.0, -0.2);
            let p = refine_gauss_newton(&obs, initial, &opts).unwrap();
            assert!((p - best).norm() < 1e-6, "{p} vs {best}");
        }
    }

    #[test]
    fn fewer_observations_than_required_are_rejected() {
        let mut rng = ChaCha8Rng::seed_from_u64(9);
        let p_f = Vector3::new(0.0, 5.0, 1.0);
        let obs = scene(&mut rng, 4, 1.0, &p_f, 0.0);
        let opts = TriangulationOptions {
            min_observations: 5,
            ..Default::default()
        };
        assert_eq!(
            triangulate(&obs, &opts),
            Err(TriangulationError::TooFewObservations)
        );
        let one = TriangulationOptions {
            min_observations: 1,
            ..Default::default()
        };
        assert_eq!(
            triangulate(&obs[..1], &one),
            Err(TriangulationError::TooFewObservations)
        );
        assert_eq!(
            triangulate(&[], &one),
            Err(TriangulationError::TooFewObservations)
        );
    }

    #[test]
    fn a_point_beyond_the_maximum_depth_is_rejected_as_too_far() {
        let mut rng = ChaCha8Rng::seed_from_u64(10);
        let p_f = Vector3::new(0.0, 100.0, 1.0);
        let obs = scene(&mut rng, 6, 10.0, &p_f, 0.0);
        let opts = TriangulationOptions::default();
        assert_eq!(triangulate(&obs, &opts), Err(TriangulationError::TooFar));
    }

    #[test]
    fn a_point_far_away_for_its_baseline_is_rejected_as_small_baseline() {
        let mut rng = ChaCha8Rng::seed_from_u64(11);
        let p_f = Vector3::new(0.0, 10.0, 1.0);
        let obs = scene(&mut rng, 6, 0.2, &p_f, 0.0);
        let opts = TriangulationOptions {
            max_condition_number: 1e12,
            ..Default::default()
        };
        assert_eq!(
            triangulate(&obs, &opts),
            Err(TriangulationError::SmallBaseline)
        );
        // The same geometry passes with a longer baseline.
        let obs = scene(&mut rng, 6, 0.5, &p_f, 0.0);
        assert!(triangulate(&obs, &opts).is_ok());
    }

    #[test]
    fn an_outlier_observation_is_rejected_as_large_residual() {
        let mut rng = ChaCha8Rng::seed_from_u64(12);
        let p_f = Vector3::new(0.0, 5.0, 1.0);
        let mut obs = scene(&mut rng, 5, 1.0, &p_f, 0.0);
        obs[2].uvn.x += 0.15;
        let opts = TriangulationOptions::default();
        assert_eq!(
            triangulate(&obs, &opts),
            Err(TriangulationError::LargeResidual)
        );
    }

    #[test]
    fn the_ray_residual_is_the_angle_between_the_ray_and_the_point() {
        // Rays from the optical axis to 80 deg off it, the point turned away
        // from each by 0.01 rad in some direction: the residual's norm is the
        // sine of that angle wherever the ray is, while the normalized
        // coordinates' difference grows as sec² of the ray's angle.
        for (i, off_axis) in [0.0_f64, 0.5, 1.0, 1.4].iter().enumerate() {
            let ray = Vector3::new(off_axis.sin(), 0.0, off_axis.cos());
            let o = CameraObservation {
                r_c_to_g: Matrix3::identity(),
                p_c_in_g: Vector3::zeros(),
                uvn: ray.xy() / ray.z,
            };
            let axis = ray
                .cross(&Vector3::new(0.3, 1.0, 0.2 * i as f64))
                .normalize();
            let p_c = exp_so3(&(axis * 0.01)) * ray * 4.0;
            let r = o.ray_residual(&p_c, RayResidual::Angle);
            assert!((r.norm() - 0.01_f64.sin()).abs() < 1e-9, "{off_axis}: {r}");
        }
    }

    #[test]
    fn rim_rays_of_a_fisheye_triangulate_like_central_ones_as_angles() {
        // A point 70 deg off the optical axes of eleven cameras spread over
        // 1 m, seen through TUM-VI's equidistant fisheye (190 px focal length):
        // 1 px of noise is about 1/190 rad in every direction of the image.
        // In normalized coordinates that noise is sec²(70 deg) = 8.5 times
        // larger at the rim than at the centre, and the mean residual alone
        // exceeds the limit; as angles, rim rays give the point as well as
        // central ones.
        let sigma_rad = 1.0 / 190.0;
        let p_f = Vector3::new(0.2, 4.0, 1.0);
        // (triangulations that passed, worst error of those, m) of 50 draws.
        let draws = |off_axis_deg: f64, residual: RayResidual| {
            let mut rng = ChaCha8Rng::seed_from_u64(21);
            let opts = TriangulationOptions {
                residual,
                ..TriangulationOptions::default()
            };
            let (mut passed, mut worst) = (0, 0.0_f64);
            for _ in 0..50 {
                let obs: Vec<CameraObservation> = (0..11)
                    .map(|k| {
                        let p_c = Vector3::new(k as f64 / 10.0 - 0.5, 0.0, 1.0);
                        // The camera looks away from the point by the angle,
                        // about a random axis across the ray.
                        let to_point = (p_f - p_c).normalize();
                        let random =
                            Vector3::new(normal(&mut rng), normal(&mut rng), normal(&mut rng));
                        let across = to_point.cross(&random).normalize();
                        let r_c_to_g =
                            exp_so3(&(across * off_axis_deg.to_radians())) * look_at(&p_c, &p_f);
                        // The ray turned by the angular noise, in the camera.
                        let noise =
                            Vector3::new(normal(&mut rng), normal(&mut rng), normal(&mut rng))
                                * sigma_rad;
                        let ray = r_c_to_g.tr_mul(&(exp_so3(&noise) * to_point));
                        CameraObservation {
                            r_c_to_g,
                            p_c_in_g: p_c,
                            uvn: ray.xy() / ray.z,
                        }
                    })
                    .collect();
                if let Ok(p) = triangulate(&obs, &opts) {
                    passed += 1;
                    worst = worst.max((p - p_f).norm());
                }
            }
            (passed, worst)
        };
        let (central_passed, central) = draws(0.0, RayResidual::Angle);
        let (rim_passed, rim) = draws(70.0, RayResidual::Angle);
        assert_eq!((central_passed, rim_passed), (50, 50));
        assert!(rim < 1.5 * central, "rim {rim} m, centre {central} m");
        let (normalized_passed, _) = draws(70.0, RayResidual::Normalized);
        assert!(normalized_passed < 10, "{normalized_passed} of 50");
    }

    #[test]
    fn a_radtan_lens_keeps_normalized_residuals_and_a_fisheye_takes_angles() {
        let mut fisheye = CameraModel::euroc_cam0();
        assert_eq!(RayResidual::of(&fisheye), RayResidual::Normalized);
        fisheye.model = Distortion::Equidistant;
        assert_eq!(RayResidual::of(&fisheye), RayResidual::Angle);
        let limits = TriangulationLimits::default();
        assert_eq!(
            TriangulationOptions::for_camera(&limits, &CameraModel::euroc_cam0()),
            TriangulationOptions::with_limits(&limits)
        );
    }

    #[test]
    fn a_point_closer_than_the_minimum_depth_is_rejected() {
        let mut rng = ChaCha8Rng::seed_from_u64(13);
        let p_f = Vector3::new(0.0, 1.0, 1.0);
        let obs = scene(&mut rng, 5, 0.5, &p_f, 0.0);
        let opts = TriangulationOptions {
            min_depth_m: 2.0,
            ..Default::default()
        };
        assert_eq!(
            triangulate(&obs, &opts),
            Err(TriangulationError::BehindCamera)
        );
    }

    #[test]
    fn non_finite_input_is_rejected() {
        let mut rng = ChaCha8Rng::seed_from_u64(14);
        let p_f = Vector3::new(0.0, 5.0, 1.0);
        let mut obs = scene(&mut rng, 5, 1.0, &p_f, 0.0);
        obs[1].uvn.y = f64::NAN;
        let opts = TriangulationOptions::default();
        assert!(triangulate(&obs, &opts).is_err());
        assert!(triangulate_linear(&obs, &opts).is_err());
        assert!(refine_gauss_newton(&obs, p_f, &opts).is_err());
        let mut obs = scene(&mut rng, 5, 1.0, &p_f, 0.0);
        obs[0].p_c_in_g.x = f64::INFINITY;
        assert!(triangulate(&obs, &opts).is_err());
    }

    #[test]
    fn triangulation_is_deterministic_bit_for_bit() {
        let mut rng = ChaCha8Rng::seed_from_u64(15);
        let p_f = Vector3::new(0.4, 7.0, 0.5);
        let obs = scene(&mut rng, 9, 1.0, &p_f, 1e-3);
        let opts = TriangulationOptions::default();
        let a = triangulate(&obs, &opts).unwrap();
        let b = triangulate(&obs, &opts).unwrap();
        assert_eq!(a.map(f64::to_bits), b.map(f64::to_bits));
    }
}
