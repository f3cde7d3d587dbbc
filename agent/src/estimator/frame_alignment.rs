//! The transform between a peer's world frame and ours, for robots that were
//! not given their start poses in one fleet frame.
//!
//! Every robot's world frame is gravity aligned (the static initializer or the
//! start pose fixes roll and pitch), so two of them differ by a yaw and a
//! translation, four degrees of freedom: `p_G = R_z(ψ) p_H + t`, with `G` our
//! frame and `H` the peer's. Errors are `ψ = ψ̂ + δψ`, `t = t̂ + δt`, ordered
//! `[δψ, δt]`.
//!
//! * [`estimate_alignment`] measures it from one verified loop closure: points
//!   the peer triangulated in its keyframe window, seen now by our camera.
//!   A two-point minimal solver in RANSAC, then Gauss-Newton on the
//!   reprojection errors. Its covariance carries the pixel noise, the points'
//!   triangulation error, and the pose errors of our camera and of the peer's
//!   anchor camera, which move every point together and do not average out.
//! * [`FrameAlignment::fuse`] combines two measurements by covariance
//!   intersection: they share our state and the peer's, with a correlation
//!   nobody tracks (the same reason the CI-EKF fuses the peers' windows).
//! * [`window_in_frame`] expresses a peer's window in our frame, its
//!   covariance grown by the alignment's, so the CI-EKF uses it unchanged. The
//!   alignment holds our own pose estimate; CI is consistent whatever the
//!   correlation between a participant and our state, this one included.

use super::peer_window::{project_normalized, FrameLink, PeerLandmark, PeerPose, PeerWindow};
use super::state::wrap_yaw as wrap;
use super::state::{PeerFrameMean, Var};
use common::so3::skew;
use nalgebra::{
    DMatrix, Matrix2, Matrix2x3, Matrix3, Matrix4, SMatrix, Vector2, Vector3, Vector4, Vector5,
};
use std::sync::Arc;

/// `p_G = R_z(ψ) p_H + t`: where a peer's world frame `H` is in ours, `G`.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct FrameAlignment {
    /// `ψ`, rad.
    pub yaw_rad: f64,
    /// `t`, m.
    pub t_m: Vector3<f64>,
    /// Covariance of `[δψ, δt]` (rad², m²).
    pub cov: Matrix4<f64>,
}

/// The rotation about `z` by `yaw`.
pub fn rot_z(yaw: f64) -> Matrix3<f64> {
    let (s, c) = yaw.sin_cos();
    Matrix3::new(c, -s, 0.0, s, c, 0.0, 0.0, 0.0, 1.0)
}

/// `∂(R_z(ψ) p)/∂ψ = e_z × R_z(ψ) p`.
fn d_yaw(rotated: &Vector3<f64>) -> Vector3<f64> {
    Vector3::new(-rotated.y, rotated.x, 0.0)
}

impl FrameAlignment {
    /// The same frame, known exactly (a peer given its start in the fleet frame).
    pub fn identity() -> Self {
        Self {
            yaw_rad: 0.0,
            t_m: Vector3::zeros(),
            cov: Matrix4::zeros(),
        }
    }

    /// `R_z(ψ)`.
    pub fn rot(&self) -> Matrix3<f64> {
        rot_z(self.yaw_rad)
    }

    /// A point of the peer's frame in ours.
    pub fn point(&self, p_h: &Vector3<f64>) -> Vector3<f64> {
        self.rot() * p_h + self.t_m
    }

    /// `∂p_G/∂[δψ, δt]` of the point `p_h` of the peer's frame (3x4).
    pub fn point_jacobian(&self, p_h: &Vector3<f64>) -> SMatrix<f64, 3, 4> {
        let mut g = SMatrix::<f64, 3, 4>::zeros();
        g.fixed_view_mut::<3, 1>(0, 0)
            .copy_from(&d_yaw(&(self.rot() * p_h)));
        g.fixed_view_mut::<3, 3>(0, 1)
            .copy_from(&Matrix3::identity());
        g
    }

    /// Standard deviation of the yaw, rad.
    pub fn yaw_sigma_rad(&self) -> f64 {
        self.cov[(0, 0)].max(0.0).sqrt()
    }

    /// Root of the summed translation variances, m.
    pub fn translation_sigma_m(&self) -> f64 {
        (self.cov[(1, 1)] + self.cov[(2, 2)] + self.cov[(3, 3)])
            .max(0.0)
            .sqrt()
    }

    /// `[ψ_other − ψ, t_other − t]` (the yaw difference wrapped).
    pub fn difference(&self, other: &Self) -> Vector4<f64> {
        let d = other.t_m - self.t_m;
        Vector4::new(wrap(other.yaw_rad - self.yaw_rad), d.x, d.y, d.z)
    }

    /// The squared Mahalanobis distance between two estimates of one
    /// alignment, each with its own covariance (their sum: when they are
    /// correlated the gate is looser than it need be, never tighter).
    pub fn mahalanobis_sq(&self, other: &Self) -> Option<f64> {
        let d = self.difference(other);
        let s = (self.cov + other.cov).cholesky()?;
        Some(d.dot(&s.solve(&d)))
    }

    /// Covariance intersection of two estimates of one alignment whose
    /// correlation is unknown: `P⁻¹ = ω P_a⁻¹ + (1 − ω) P_b⁻¹` with `ω` on a
    /// grid minimizing `det P`. `None` when either covariance is singular.
    pub fn fuse(&self, other: &Self) -> Option<Self> {
        let ia = self.cov.try_inverse()?;
        let ib = other.cov.try_inverse()?;
        let d = self.difference(other);
        let mut best: Option<(f64, Matrix4<f64>, Vector4<f64>)> = None;
        // det of a 4x4 is cheap: a fine grid is simpler than a search and
        // good to 0.5 % of ω.
        for k in 0..=200 {
            let w = f64::from(k) / 200.0;
            let info = ia * w + ib * (1.0 - w);
            let Some(p) = info.try_inverse() else {
                continue;
            };
            let det = p.determinant();
            if det.is_finite() && det > 0.0 && best.as_ref().is_none_or(|b| det < b.0) {
                // Mean relative to `self`: x = P (ω P_a⁻¹ 0 + (1 − ω) P_b⁻¹ d).
                let step = p * (ib * d) * (1.0 - w);
                best = Some((det, p, step));
            }
        }
        let (_, p, step) = best?;
        Some(Self {
            yaw_rad: wrap(self.yaw_rad + step[0]),
            t_m: self.t_m + Vector3::new(step[1], step[2], step[3]),
            cov: (p + p.transpose()) * 0.5,
        })
    }
}

/// A peer's window expressed in our frame through `a`: poses `R_CtoG =
/// R_z R_CtoH`, `p_CinG = R_z p_CinH + t`, and its covariance `J P Jᵀ + G Σ_a
/// Gᵀ`. With the right-local pose error, `δθ_G = δθ_H + R_CtoGᵀ e_z δψ`; the
/// position error is `R_z δp_H + (e_z × R_z p_H) δψ + δt`. Every pose shares
/// the alignment's error, so they become correlated through it. The
/// intrinsics (when sent) are unchanged. Landmarks keep marginal covariances.
pub fn window_in_frame(w: &PeerWindow, a: &FrameAlignment) -> PeerWindow {
    let (mut out, g, gl) = transformed(w, a);
    let cov = out.cov.as_ref() + &g * a.cov * g.transpose();
    // (`transformed` leaves `J P Jᵀ` unsymmetrized: one rounding, as before
    // the in-state frames were written.)
    out.cov = Arc::new((&cov + cov.transpose()) * 0.5);
    for (l, g) in out.landmarks.iter_mut().zip(&gl) {
        l.cov += g * a.cov * g.transpose();
    }
    out
}

/// A peer's window expressed in our frame through the peer frame `var` our
/// state holds, at its mean `a`: the window's covariance only rotated, and
/// its Jacobians w.r.t. the frame's error kept beside it (`PeerWindow::frame`)
/// for the updates to put in our columns of `var`.
pub fn window_in_state_frame(w: &PeerWindow, a: &PeerFrameMean, var: Var) -> PeerWindow {
    let alignment = FrameAlignment {
        yaw_rad: a.yaw_rad,
        t_m: a.t_m,
        cov: Matrix4::zeros(),
    };
    let (mut out, poses, landmarks) = transformed(w, &alignment);
    out.cov = Arc::new(out.cov.as_ref() * 0.5 + out.cov.transpose() * 0.5);
    out.frame = Some(Arc::new(FrameLink {
        var,
        at: *a,
        poses,
        landmarks,
    }));
    out
}

/// The window through `a` with its own covariance moved into our frame
/// (`J P Jᵀ`, not yet symmetrized), its Jacobian w.r.t. the alignment's error (dim x 4) and each
/// landmark's (3 x 4).
fn transformed(
    w: &PeerWindow,
    a: &FrameAlignment,
) -> (PeerWindow, DMatrix<f64>, Vec<SMatrix<f64, 3, 4>>) {
    let rz = a.rot();
    let n = w.poses.len();
    let dim = w.cov.nrows();
    let mut j = DMatrix::<f64>::identity(dim, dim);
    let mut g = DMatrix::<f64>::zeros(dim, 4);
    let mut poses = Vec::with_capacity(n);
    for (i, p) in w.poses.iter().enumerate() {
        let rot = rz * p.rot;
        j.view_mut((6 * i + 3, 6 * i + 3), (3, 3)).copy_from(&rz);
        g.view_mut((6 * i, 0), (3, 1))
            .copy_from(&(rot.transpose() * Vector3::z()));
        g.view_mut((6 * i + 3, 0), (3, 4))
            .copy_from(&a.point_jacobian(&p.pos));
        poses.push(PeerPose {
            t_s: p.t_s,
            rot,
            pos: a.point(&p.pos),
        });
    }
    let cov = &j * w.cov.as_ref() * j.transpose();
    let mut gl = Vec::with_capacity(w.landmarks.len());
    let landmarks = w
        .landmarks
        .iter()
        .map(|l| {
            gl.push(a.point_jacobian(&l.pos));
            PeerLandmark {
                id: l.id,
                pos: a.point(&l.pos),
                cov: rz * l.cov * rz.transpose(),
            }
        })
        .collect();
    let out = PeerWindow {
        peer: w.peer,
        key: w.key,
        poses,
        cov: Arc::new(cov),
        camera: w.camera.clone(),
        pixel_sigma_px: w.pixel_sigma_px,
        landmarks,
        frame: None,
    };
    (out, g, gl)
}

/// A camera pose estimate: `(R_CtoX, p_CinX)` in some world frame `X`, and the
/// covariance of its right-local error `[δθ, δp]`.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct CameraEstimate {
    /// `R_CtoX`.
    pub rot: Matrix3<f64>,
    /// `p_CinX`, m.
    pub pos: Vector3<f64>,
    /// Covariance of `[δθ, δp]` (rad², m²).
    pub cov: SMatrix<f64, 6, 6>,
}

impl CameraEstimate {
    fn as_peer_pose(&self) -> PeerPose {
        PeerPose {
            t_s: 0.0,
            rot: self.rot,
            pos: self.pos,
        }
    }
}

/// One point of a loop closure: triangulated by the peer, seen by us now.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct AlignmentPoint {
    /// The point in the peer's anchor camera, m.
    pub in_anchor: Vector3<f64>,
    /// Its covariance from the peer's pixel noise, m².
    pub cov_in_anchor: Matrix3<f64>,
    /// Our undistorted normalized measurement of it.
    pub xy: Vector2<f64>,
}

/// Settings of [`estimate_alignment`].
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct AlignmentOptions {
    /// Our pixel noise over the focal length (normalized units).
    pub sigma_normalized: f64,
    /// Fewest points that must agree with the alignment.
    pub min_inliers: usize,
    /// Largest accepted yaw standard deviation, rad.
    pub max_yaw_sigma_rad: f64,
    /// Largest accepted root summed translation variance, m.
    pub max_translation_sigma_m: f64,
    /// Minimal samples tried.
    pub ransac_samples: usize,
}

impl Default for AlignmentOptions {
    fn default() -> Self {
        Self {
            sigma_normalized: 1.0 / 458.0,
            min_inliers: 10,
            max_yaw_sigma_rad: 2f64.to_radians(),
            max_translation_sigma_m: 0.5,
            ransac_samples: 200,
        }
    }
}

/// Why a loop closure gave no alignment.
#[derive(Clone, Copy, Debug, PartialEq, thiserror::Error)]
pub enum AlignmentError {
    /// Fewer points than the options ask for, before or after RANSAC.
    #[error("{found} points agree on an alignment, {needed} are needed")]
    TooFewInliers {
        /// Points that agreed.
        found: usize,
        /// Points needed.
        needed: usize,
    },
    /// The points do not fix the yaw and translation (all in a line, say).
    #[error("the points do not determine the alignment")]
    Degenerate,
    /// The alignment is less certain than the options accept.
    #[error("alignment too uncertain: yaw σ {yaw_sigma_deg:.2} deg, translation σ {translation_sigma_m:.3} m")]
    TooUncertain {
        /// Yaw standard deviation, deg.
        yaw_sigma_deg: f64,
        /// Root summed translation variance, m.
        translation_sigma_m: f64,
    },
}

/// A measured alignment and the points that agreed with it.
#[derive(Clone, Debug, PartialEq)]
pub struct AlignmentMeasurement {
    /// The alignment with its covariance.
    pub alignment: FrameAlignment,
    /// Which of the points agreed.
    pub inliers: Vec<bool>,
    /// Root mean square reprojection error of the inliers, normalized units.
    pub rms_normalized: f64,
    /// `∂[ψ̂, t̂]/∂ξ`: how the fitted alignment moves with an error `ξ` of our
    /// camera pose estimate `[δθ, δp]` (4x6), so that `δa = D ξ + n` with `ξ`
    /// the error of our camera: an alignment held in the filter state is
    /// augmented with this cross-covariance to our pose.
    pub our_pose_jacobian: SMatrix<f64, 4, 6>,
    /// Covariance of `n`: the pixel noise and the triangulation and anchor
    /// errors (the covariance without our camera's share), rad², m².
    pub noise_cov: Matrix4<f64>,
    /// The peer's anchor pose's share of `noise_cov`, `B_a P_a B_aᵀ`: the
    /// part of the noise that the peer's other windows share (its anchor
    /// poses drift together), rad², m².
    pub anchor_cov: Matrix4<f64>,
}

/// Gate on a point's whitened squared residual: χ²(2) at 99 %.
const POINT_GATE: f64 = 9.21;

/// The point's projection in our camera for alignment `(yaw, t)` and its
/// Jacobians: w.r.t. `[δψ, δt]`, our camera pose, the peer's anchor pose
/// `[δθ, δp]`, and the point in the anchor frame.
struct Projected {
    xy: Vector2<f64>,
    h_align: SMatrix<f64, 2, 4>,
    h_ours: SMatrix<f64, 2, 6>,
    h_anchor: SMatrix<f64, 2, 6>,
    h_point: Matrix2x3<f64>,
}

fn project(
    yaw: f64,
    t: &Vector3<f64>,
    ours: &CameraEstimate,
    anchor: &CameraEstimate,
    y: &Vector3<f64>,
) -> Option<Projected> {
    let rz = rot_z(yaw);
    let p_h = anchor.rot * y + anchor.pos;
    let rotated = rz * p_h;
    let p_g = rotated + t;
    let proj = project_normalized(&ours.as_peer_pose(), &p_g)?;
    let mut h_align = SMatrix::<f64, 2, 4>::zeros();
    h_align
        .fixed_view_mut::<2, 1>(0, 0)
        .copy_from(&(proj.h_feature * d_yaw(&rotated)));
    h_align
        .fixed_view_mut::<2, 3>(0, 1)
        .copy_from(&proj.h_feature);
    let d_h = proj.h_feature * rz;
    // `p_H = R_a Exp(δθ) y + p_a + δp`.
    let mut h_anchor = SMatrix::<f64, 2, 6>::zeros();
    h_anchor
        .fixed_view_mut::<2, 3>(0, 0)
        .copy_from(&(-d_h * anchor.rot * skew(y)));
    h_anchor.fixed_view_mut::<2, 3>(0, 3).copy_from(&d_h);
    Some(Projected {
        xy: proj.xy,
        h_align,
        h_ours: proj.h_pose,
        h_anchor,
        h_point: d_h * anchor.rot,
    })
}

/// The alignments that make our camera see points `a` and `b` of the peer's
/// frame exactly where we measured them: each point gives two equations
/// linear in `(cos ψ, sin ψ, t)`, so two points leave a line of solutions,
/// cut by `cos² ψ + sin² ψ = 1` in at most two places.
fn minimal_solutions(
    ours: &CameraEstimate,
    pts: [(&Vector3<f64>, &Vector2<f64>); 2],
) -> Vec<(f64, Vector3<f64>)> {
    // Rows `n · (R_z p + t − p_C) = 0` with `n = R_CtoG (xy_k e_z − e_k)`.
    let mut a = SMatrix::<f64, 4, 5>::zeros();
    let mut b = Vector4::zeros();
    for (i, (p, xy)) in pts.iter().enumerate() {
        for k in 0..2 {
            let mut e = Vector3::new(0.0, 0.0, xy[k]);
            e[k] -= 1.0;
            let n = ours.rot * e;
            let r = 2 * i + k;
            a[(r, 0)] = n.x * p.x + n.y * p.y;
            a[(r, 1)] = n.y * p.x - n.x * p.y;
            a[(r, 2)] = n.x;
            a[(r, 3)] = n.y;
            a[(r, 4)] = n.z;
            b[r] = n.dot(&ours.pos) - n.z * p.z;
        }
    }
    let aat = a * a.transpose();
    let Some(x0) = aat.try_inverse().map(|m| a.transpose() * (m * b)) else {
        return Vec::new();
    };
    let eig = (a.transpose() * a).symmetric_eigen();
    let Some((k, _)) = eig
        .eigenvalues
        .iter()
        .enumerate()
        .min_by(|x, y| x.1.total_cmp(y.1))
    else {
        return Vec::new();
    };
    let v: Vector5<f64> = eig.eigenvectors.column(k).into();
    // (c0 + λ vc)² + (s0 + λ vs)² = 1.
    let qa = v[0] * v[0] + v[1] * v[1];
    let qb = 2.0 * (x0[0] * v[0] + x0[1] * v[1]);
    let qc = x0[0] * x0[0] + x0[1] * x0[1] - 1.0;
    let disc = qb * qb - 4.0 * qa * qc;
    if qa < 1e-12 || disc < 0.0 {
        return Vec::new();
    }
    let root = disc.sqrt();
    [(-qb + root) / (2.0 * qa), (-qb - root) / (2.0 * qa)]
        .iter()
        .map(|l| {
            let x = x0 + v * *l;
            (x[1].atan2(x[0]), Vector3::new(x[2], x[3], x[4]))
        })
        .collect()
}

/// Per point: the whitening weight `(σ² I + H_y Σ_y H_yᵀ)⁻¹` and the
/// whitened squared residual, `None` when the point is behind our camera.
fn point_fit(
    yaw: f64,
    t: &Vector3<f64>,
    ours: &CameraEstimate,
    anchor: &CameraEstimate,
    pt: &AlignmentPoint,
    sigma: f64,
) -> Option<(Projected, Matrix2<f64>, f64)> {
    let pr = project(yaw, t, ours, anchor, &pt.in_anchor)?;
    let r = Matrix2::identity() * (sigma * sigma)
        + pr.h_point * pt.cov_in_anchor * pr.h_point.transpose();
    let w = r.try_inverse()?;
    let res = pt.xy - pr.xy;
    let chi = res.dot(&(w * res));
    Some((pr, w, chi))
}

fn inliers_of(
    yaw: f64,
    t: &Vector3<f64>,
    ours: &CameraEstimate,
    anchor: &CameraEstimate,
    points: &[AlignmentPoint],
    sigma: f64,
    gate: f64,
) -> Vec<bool> {
    points
        .iter()
        .map(|pt| point_fit(yaw, t, ours, anchor, pt, sigma).is_some_and(|(_, _, c)| c <= gate))
        .collect()
}

/// Gauss-Newton on the whitened reprojection errors of the inliers, from
/// `(yaw, t)`.
fn refine(
    mut yaw: f64,
    mut t: Vector3<f64>,
    ours: &CameraEstimate,
    anchor: &CameraEstimate,
    points: &[AlignmentPoint],
    inliers: &[bool],
    sigma: f64,
) -> Option<(f64, Vector3<f64>)> {
    for _ in 0..10 {
        let mut n = Matrix4::<f64>::zeros();
        let mut g = Vector4::<f64>::zeros();
        for (pt, _) in points.iter().zip(inliers).filter(|(_, k)| **k) {
            let (pr, w, _) = point_fit(yaw, &t, ours, anchor, pt, sigma)?;
            let res = pt.xy - pr.xy;
            n += pr.h_align.transpose() * w * pr.h_align;
            g += pr.h_align.transpose() * w * res;
        }
        let step = n.cholesky()?.solve(&g);
        yaw = wrap(yaw + step[0]);
        t += Vector3::new(step[1], step[2], step[3]);
        if step.norm() < 1e-10 {
            break;
        }
    }
    Some((yaw, t))
}

/// The alignment of the peer's frame to ours from one loop closure: `points`
/// the peer triangulated relative to its `anchor` camera (a pose in its
/// frame), each measured by `ours` (our camera now, in our frame).
///
/// The covariance is `N⁻¹ + B_o P_o B_oᵀ + B_a P_a B_aᵀ` with `N = Σ H_kᵀ W_k
/// H_k` over the inliers, and `B = N⁻¹ Σ H_kᵀ W_k ∂r_k/∂ξ` mapping an error
/// `ξ` of our camera (`o`) or the anchor (`a`) to the fitted alignment: those
/// errors move all the points at once.
pub fn estimate_alignment(
    ours: &CameraEstimate,
    anchor: &CameraEstimate,
    points: &[AlignmentPoint],
    opts: &AlignmentOptions,
) -> Result<AlignmentMeasurement, AlignmentError> {
    let n = points.len();
    let needed = opts.min_inliers.max(3);
    if n < needed {
        return Err(AlignmentError::TooFewInliers { found: n, needed });
    }
    let sigma = opts.sigma_normalized;
    let in_h: Vec<Vector3<f64>> = points
        .iter()
        .map(|p| anchor.rot * p.in_anchor + anchor.pos)
        .collect();
    // Deterministic pairs spread over the points: all of them when few.
    let pairs: Vec<(usize, usize)> = if n * (n - 1) / 2 <= opts.ransac_samples {
        (0..n)
            .flat_map(|i| (i + 1..n).map(move |j| (i, j)))
            .collect()
    } else {
        (0..opts.ransac_samples)
            .map(|k| {
                let i = (k * 7919) % n;
                let j = (i + 1 + (k * 104_729) % (n - 1)) % n;
                (i, j)
            })
            .collect()
    };
    // Two noisy points fix the hypothesis only roughly: a looser gate to count.
    let coarse_gate = 4.0 * POINT_GATE;
    let mut best: Option<(usize, f64, Vector3<f64>)> = None;
    for (i, j) in pairs {
        for (yaw, t) in
            minimal_solutions(ours, [(&in_h[i], &points[i].xy), (&in_h[j], &points[j].xy)])
        {
            let count = inliers_of(yaw, &t, ours, anchor, points, sigma, coarse_gate)
                .iter()
                .filter(|k| **k)
                .count();
            if best.as_ref().is_none_or(|b| count > b.0) {
                best = Some((count, yaw, t));
            }
        }
    }
    let Some((_, mut yaw, mut t)) = best else {
        return Err(AlignmentError::Degenerate);
    };
    let mut inliers = inliers_of(yaw, &t, ours, anchor, points, sigma, coarse_gate);
    for _ in 0..3 {
        let found = inliers.iter().filter(|k| **k).count();
        if found < needed {
            return Err(AlignmentError::TooFewInliers { found, needed });
        }
        (yaw, t) = refine(yaw, t, ours, anchor, points, &inliers, sigma)
            .ok_or(AlignmentError::Degenerate)?;
        let next = inliers_of(yaw, &t, ours, anchor, points, sigma, POINT_GATE);
        if next == inliers {
            break;
        }
        inliers = next;
    }
    let found = inliers.iter().filter(|k| **k).count();
    if found < needed {
        return Err(AlignmentError::TooFewInliers { found, needed });
    }
    // Covariance at the solution.
    let mut info = Matrix4::<f64>::zeros();
    let mut to_ours = SMatrix::<f64, 4, 6>::zeros();
    let mut to_anchor = SMatrix::<f64, 4, 6>::zeros();
    let mut sq = 0.0;
    for (pt, _) in points.iter().zip(&inliers).filter(|(_, k)| **k) {
        let (pr, w, _) =
            point_fit(yaw, &t, ours, anchor, pt, sigma).ok_or(AlignmentError::Degenerate)?;
        info += pr.h_align.transpose() * w * pr.h_align;
        to_ours += pr.h_align.transpose() * w * pr.h_ours;
        to_anchor += pr.h_align.transpose() * w * pr.h_anchor;
        sq += (pt.xy - pr.xy).norm_squared();
    }
    let n_inv = info.try_inverse().ok_or(AlignmentError::Degenerate)?;
    // The fitted alignment absorbs a pose error ξ: δa = −N⁻¹ Σ Hᵀ W (∂xy/∂ξ) ξ
    // (the sign does not matter to the covariance).
    let b_o = n_inv * to_ours;
    let b_a = n_inv * to_anchor;
    let p_anchor = b_a * anchor.cov * b_a.transpose();
    let cov = n_inv + b_o * ours.cov * b_o.transpose() + p_anchor;
    let cov = (cov + cov.transpose()) * 0.5;
    let noise = n_inv + p_anchor;
    let noise_cov = (noise + noise.transpose()) * 0.5;
    if !cov.iter().all(|v| v.is_finite()) || cov.cholesky().is_none() {
        return Err(AlignmentError::Degenerate);
    }
    let alignment = FrameAlignment {
        yaw_rad: yaw,
        t_m: t,
        cov,
    };
    let (ys, ts) = (alignment.yaw_sigma_rad(), alignment.translation_sigma_m());
    if ys > opts.max_yaw_sigma_rad || ts > opts.max_translation_sigma_m {
        return Err(AlignmentError::TooUncertain {
            yaw_sigma_deg: ys.to_degrees(),
            translation_sigma_m: ts,
        });
    }
    Ok(AlignmentMeasurement {
        alignment,
        inliers,
        rms_normalized: (sq / found as f64).sqrt(),
        // At the optimum `H_aᵀ W r = 0`: fitted from our true pose `x̂ ⊞ ξ`
        // the alignment would be `â − N⁻¹ H_aᵀ W H_o ξ`, so its error is
        // `δa = −B_o ξ + n`.
        our_pose_jacobian: -b_o,
        noise_cov,
        anchor_cov: (p_anchor + p_anchor.transpose()) * 0.5,
    })
}

/// The covariance of a point triangulated from cameras `(R_CtoX, p_CinX)` and
/// normalized measurements of noise `sigma`: `(Σ J_iᵀ J_i / σ²)⁻¹` with `J_i`
/// the projection Jacobian w.r.t. the point; `None` when the views do not fix
/// it.
pub fn point_covariance(
    cameras: &[(Matrix3<f64>, Vector3<f64>)],
    p: &Vector3<f64>,
    sigma: f64,
) -> Option<Matrix3<f64>> {
    let mut info = Matrix3::<f64>::zeros();
    for (rot, pos) in cameras {
        let pose = PeerPose {
            t_s: 0.0,
            rot: *rot,
            pos: *pos,
        };
        let proj = project_normalized(&pose, p)?;
        info += proj.h_feature.transpose() * proj.h_feature;
    }
    let cov = (info / (sigma * sigma)).try_inverse()?;
    cov.iter().all(|v| v.is_finite()).then_some(cov)
}

#[cfg(test)]
mod tests;
