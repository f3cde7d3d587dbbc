use super::*;
use crate::estimator::peer_window::PeerWindow;
use common::camera::CameraModel;
use common::so3::{exp_so3, log_so3};
use nalgebra::{Matrix6, Vector6};
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;

/// A standard normal sample (Box-Muller).
fn normal(rng: &mut ChaCha8Rng) -> f64 {
    let u1: f64 = rng.random_range(f64::EPSILON..1.0);
    let u2: f64 = rng.random();
    (-2.0 * u1.ln()).sqrt() * (std::f64::consts::TAU * u2).cos()
}

fn sample<const D: usize>(rng: &mut ChaCha8Rng, cov: &SMatrix<f64, D, D>) -> SMatrix<f64, D, 1> {
    let l = cov.cholesky().expect("positive definite").l();
    let n = SMatrix::<f64, D, 1>::from_fn(|_, _| normal(rng));
    l * n
}

/// `R_CtoX` of a camera at `from` looking at `to`.
fn look_at(from: &Vector3<f64>, to: &Vector3<f64>) -> Matrix3<f64> {
    let z = (to - from).normalize();
    let x = Vector3::z().cross(&z).normalize();
    let y = z.cross(&x);
    Matrix3::from_columns(&[x, y, z])
}

fn truth() -> FrameAlignment {
    FrameAlignment {
        yaw_rad: 0.7,
        t_m: Vector3::new(2.0, -1.0, 0.3),
        cov: Matrix4::from_diagonal(&Vector4::new(1e-4, 4e-4, 9e-4, 1e-4)),
    }
}

fn pose_cov(rot_sigma: f64, pos_sigma: f64) -> Matrix6<f64> {
    let mut d = Vector6::from_element(rot_sigma * rot_sigma);
    for k in 3..6 {
        d[k] = pos_sigma * pos_sigma;
    }
    Matrix6::from_diagonal(&d)
}

#[test]
fn the_window_in_our_frame_has_the_jacobians_of_numerical_differentiation() {
    let a = truth();
    let rot = exp_so3(&Vector3::new(0.3, -0.2, 1.1));
    let pos = Vector3::new(1.5, 4.0, -0.7);
    let n = 2;
    let mut cov = DMatrix::<f64>::identity(6 * n, 6 * n) * 1e-3;
    cov[(0, 7)] = 2e-4;
    cov[(7, 0)] = 2e-4;
    let w = PeerWindow {
        peer: 2,
        key: 9,
        poses: vec![
            PeerPose { t_s: 1.0, rot, pos },
            PeerPose {
                t_s: 1.1,
                rot: rot * exp_so3(&Vector3::new(0.0, 0.1, 0.0)),
                pos: pos + Vector3::new(0.1, 0.0, 0.0),
            },
        ],
        cov: Arc::new(cov.clone()),
        camera: CameraModel::default(),
        pixel_sigma_px: 1.0,
        landmarks: vec![PeerLandmark {
            id: 4,
            pos: Vector3::new(3.0, 1.0, 2.0),
            cov: Matrix3::identity() * 1e-2,
        }],
        frame: None,
    };
    let out = window_in_frame(&w, &a);
    // The map from [pose errors in H (12), alignment error (4)] to the pose
    // errors in G, differentiated numerically.
    let in_g = |e: &DVector| -> Vec<(Matrix3<f64>, Vector3<f64>)> {
        let al = FrameAlignment {
            yaw_rad: a.yaw_rad + e[12],
            t_m: a.t_m + Vector3::new(e[13], e[14], e[15]),
            cov: a.cov,
        };
        w.poses
            .iter()
            .enumerate()
            .map(|(i, p)| {
                let r = p.rot * exp_so3(&Vector3::new(e[6 * i], e[6 * i + 1], e[6 * i + 2]));
                let q = p.pos + Vector3::new(e[6 * i + 3], e[6 * i + 4], e[6 * i + 5]);
                (al.rot() * r, al.point(&q))
            })
            .collect()
    };
    type DVector = nalgebra::DVector<f64>;
    let base = in_g(&DVector::zeros(16));
    let mut jac = DMatrix::<f64>::zeros(12, 16);
    let h = 1e-6;
    for k in 0..16 {
        let mut e = DVector::zeros(16);
        e[k] = h;
        let plus = in_g(&e);
        e[k] = -h;
        let minus = in_g(&e);
        for i in 0..n {
            let (b_rot, _) = base[i];
            let dth = (log_so3(&(b_rot.transpose() * plus[i].0))
                - log_so3(&(b_rot.transpose() * minus[i].0)))
                / (2.0 * h);
            let dp = (plus[i].1 - minus[i].1) / (2.0 * h);
            jac.view_mut((6 * i, k), (3, 1)).copy_from(&dth);
            jac.view_mut((6 * i + 3, k), (3, 1)).copy_from(&dp);
        }
    }
    let mut joint = DMatrix::<f64>::zeros(16, 16);
    joint.view_mut((0, 0), (12, 12)).copy_from(&cov);
    joint.view_mut((12, 12), (4, 4)).copy_from(&a.cov);
    let expected = &jac * joint * jac.transpose();
    assert!(
        (&expected - out.cov.as_ref()).abs().max() < 1e-9,
        "{expected}{}",
        out.cov
    );
    for (pose, (rot, pos)) in out.poses.iter().zip(&base) {
        assert!((pose.rot - rot).abs().max() < 1e-12);
        assert!((pose.pos - pos).norm() < 1e-12);
    }
    let l = &out.landmarks[0];
    assert!((l.pos - a.point(&w.landmarks[0].pos)).norm() < 1e-12);
    assert!(l.cov.cholesky().is_some());
}

#[test]
fn the_projection_jacobians_match_numerical_differentiation() {
    let ours = CameraEstimate {
        rot: exp_so3(&Vector3::new(0.2, 0.1, -0.4)) * look_at(&Vector3::zeros(), &Vector3::x()),
        pos: Vector3::new(-1.0, 0.5, 0.2),
        cov: Matrix6::identity(),
    };
    let anchor = CameraEstimate {
        rot: look_at(&Vector3::new(0.0, 0.0, 1.0), &Vector3::new(1.0, 1.0, 0.5)),
        pos: Vector3::new(0.0, 0.0, 1.0),
        cov: Matrix6::identity(),
    };
    let y = Vector3::new(0.3, -0.2, 4.0);
    let (yaw, t) = (0.1, Vector3::new(0.2, 0.1, -0.1));
    let pr = project(yaw, &t, &ours, &anchor, &y).expect("in front");
    let h = 1e-6;
    let num = |f: &dyn Fn(f64) -> Vector2<f64>| (f(h) - f(-h)) / (2.0 * h);
    for k in 0..4 {
        let d = num(&|e| {
            let mut v = Vector4::zeros();
            v[k] = e;
            let tt = t + Vector3::new(v[1], v[2], v[3]);
            project(yaw + v[0], &tt, &ours, &anchor, &y)
                .expect("in front")
                .xy
        });
        assert!((d - pr.h_align.column(k)).norm() < 1e-6, "align {k}");
    }
    let perturb = |c: &CameraEstimate, k: usize, e: f64| {
        let mut v = Vector6::zeros();
        v[k] = e;
        CameraEstimate {
            rot: c.rot * exp_so3(&Vector3::new(v[0], v[1], v[2])),
            pos: c.pos + Vector3::new(v[3], v[4], v[5]),
            cov: c.cov,
        }
    };
    for k in 0..6 {
        let d = num(&|e| {
            project(yaw, &t, &perturb(&ours, k, e), &anchor, &y)
                .expect("in front")
                .xy
        });
        assert!((d - pr.h_ours.column(k)).norm() < 1e-6, "ours {k}");
        let d = num(&|e| {
            project(yaw, &t, &ours, &perturb(&anchor, k, e), &y)
                .expect("in front")
                .xy
        });
        assert!((d - pr.h_anchor.column(k)).norm() < 1e-6, "anchor {k}");
    }
    for k in 0..3 {
        let d = num(&|e| {
            let mut yy = y;
            yy[k] += e;
            project(yaw, &t, &ours, &anchor, &yy).expect("in front").xy
        });
        assert!((d - pr.h_point.column(k)).norm() < 1e-6, "point {k}");
    }
}

/// A loop closure of `n` points: the peer's anchor camera in `H`, ours in `G`
/// a metre aside, both looking at a cloud 3-7 m away.
struct Scene {
    truth: FrameAlignment,
    ours: CameraEstimate,
    anchor: CameraEstimate,
    points: Vec<AlignmentPoint>,
}

fn scene(rng: &mut ChaCha8Rng, n: usize, sigma: f64) -> Scene {
    let truth = truth();
    let anchor_pos = Vector3::new(0.5, -0.3, 1.2);
    let center = Vector3::new(5.0, 1.0, 1.0);
    let anchor_rot = look_at(&anchor_pos, &center);
    let ours_h = anchor_pos + Vector3::new(-0.4, 0.9, 0.2);
    let ours_rot_h = look_at(&ours_h, &(center + Vector3::new(0.0, 0.5, 0.0)));
    let ours = CameraEstimate {
        rot: truth.rot() * ours_rot_h,
        pos: truth.point(&ours_h),
        cov: pose_cov(0.002, 0.03),
    };
    let anchor = CameraEstimate {
        rot: anchor_rot,
        pos: anchor_pos,
        cov: pose_cov(0.003, 0.05),
    };
    let points = (0..n)
        .map(|_| {
            let p_h = center
                + Vector3::new(
                    rng.random_range(-2.0..2.0),
                    rng.random_range(-2.5..2.5),
                    rng.random_range(-1.0..1.0),
                );
            let in_anchor = anchor_rot.transpose() * (p_h - anchor_pos);
            let p_c = ours.rot.transpose() * (truth.point(&p_h) - ours.pos);
            let xy = Vector2::new(p_c.x / p_c.z, p_c.y / p_c.z)
                + Vector2::new(normal(rng), normal(rng)) * sigma;
            let depth = in_anchor.z;
            let cov_in_anchor = Matrix3::from_diagonal(&Vector3::new(
                (0.004 * depth).powi(2),
                (0.004 * depth).powi(2),
                (0.03 * depth).powi(2),
            ));
            AlignmentPoint {
                in_anchor,
                cov_in_anchor,
                xy,
            }
        })
        .collect();
    Scene {
        truth,
        ours,
        anchor,
        points,
    }
}

#[test]
fn two_exact_points_give_the_alignment() {
    let mut rng = ChaCha8Rng::seed_from_u64(1);
    let s = scene(&mut rng, 2, 0.0);
    let in_h: Vec<Vector3<f64>> = s
        .points
        .iter()
        .map(|p| s.anchor.rot * p.in_anchor + s.anchor.pos)
        .collect();
    let sols = minimal_solutions(
        &s.ours,
        [(&in_h[0], &s.points[0].xy), (&in_h[1], &s.points[1].xy)],
    );
    assert!(sols
        .iter()
        .any(|(yaw, t)| (yaw - s.truth.yaw_rad).abs() < 1e-8 && (t - s.truth.t_m).norm() < 1e-8));
}

#[test]
fn a_loop_closure_with_outliers_gives_the_alignment() {
    let mut rng = ChaCha8Rng::seed_from_u64(2);
    let sigma = 1.0 / 458.0;
    let mut s = scene(&mut rng, 40, sigma);
    for p in s.points.iter_mut().take(8) {
        p.xy += Vector2::new(0.05, -0.03);
    }
    let opts = AlignmentOptions {
        sigma_normalized: sigma,
        ..AlignmentOptions::default()
    };
    let m = estimate_alignment(&s.ours, &s.anchor, &s.points, &opts).expect("aligned");
    assert!(m.inliers[..8].iter().all(|k| !k), "{:?}", m.inliers);
    assert!(m.inliers[8..].iter().filter(|k| **k).count() >= 30);
    let a = m.alignment;
    assert!((a.yaw_rad - s.truth.yaw_rad).abs() < 3.0 * a.yaw_sigma_rad());
    assert!((a.t_m - s.truth.t_m).norm() < 3.0 * a.translation_sigma_m());
    assert!(m.rms_normalized < 3.0 * sigma);
}

#[test]
fn too_few_points_or_too_little_certainty_give_no_alignment() {
    let mut rng = ChaCha8Rng::seed_from_u64(3);
    let sigma = 1.0 / 458.0;
    let s = scene(&mut rng, 6, sigma);
    let opts = AlignmentOptions {
        sigma_normalized: sigma,
        ..AlignmentOptions::default()
    };
    assert_eq!(
        estimate_alignment(&s.ours, &s.anchor, &s.points, &opts),
        Err(AlignmentError::TooFewInliers {
            found: 6,
            needed: 10
        })
    );
    let s = scene(&mut rng, 30, sigma);
    let strict = AlignmentOptions {
        max_translation_sigma_m: 1e-3,
        ..opts
    };
    assert!(matches!(
        estimate_alignment(&s.ours, &s.anchor, &s.points, &strict),
        Err(AlignmentError::TooUncertain { .. })
    ));
}

/// Draws the errors of both cameras' poses and of the points from their
/// covariances into `s` (estimates = truth minus their errors: `R = R̂
/// Exp(δθ)`, `p = p̂ + δp`); returns our camera's error `ξ`.
fn draw_errors(rng: &mut ChaCha8Rng, s: &mut Scene) -> Vector6<f64> {
    let mut ours = Vector6::zeros();
    for (i, cam) in [&mut s.ours, &mut s.anchor].into_iter().enumerate() {
        let e: Vector6<f64> = sample(rng, &cam.cov);
        cam.rot *= exp_so3(&-Vector3::new(e[0], e[1], e[2]));
        cam.pos -= Vector3::new(e[3], e[4], e[5]);
        if i == 0 {
            ours = e;
        }
    }
    for p in &mut s.points {
        p.in_anchor += sample(rng, &p.cov_in_anchor);
    }
    ours
}

/// EuRoC's pixel noise (normalized) and options that refuse no alignment for
/// its uncertainty (the Monte-Carlo tests must keep every draw).
fn loose_options() -> (f64, AlignmentOptions) {
    let sigma = 1.0 / 458.0;
    let opts = AlignmentOptions {
        sigma_normalized: sigma,
        max_translation_sigma_m: 10.0,
        max_yaw_sigma_rad: 1.0,
        ..AlignmentOptions::default()
    };
    (sigma, opts)
}

/// The covariance is consistent: with both cameras' poses, the points and
/// the pixels drawn from their covariances, the alignment's NEES over 300
/// draws averages its dimension, 4.
#[test]
fn the_alignment_covariance_is_consistent_over_monte_carlo_draws() {
    let (sigma, opts) = loose_options();
    let mut rng = ChaCha8Rng::seed_from_u64(4);
    let (mut sum, mut runs) = (0.0, 0);
    for _ in 0..300 {
        let mut s = scene(&mut rng, 30, sigma);
        draw_errors(&mut rng, &mut s);
        let Ok(m) = estimate_alignment(&s.ours, &s.anchor, &s.points, &opts) else {
            continue;
        };
        let a = m.alignment;
        let d = a.t_m - s.truth.t_m;
        let e = Vector4::new(wrap(a.yaw_rad - s.truth.yaw_rad), d.x, d.y, d.z);
        sum += e.dot(&(a.cov.try_inverse().expect("invertible") * e));
        runs += 1;
    }
    assert!(runs >= 290, "{runs} aligned");
    let nees = sum / f64::from(runs);
    assert!((3.3..5.0).contains(&nees), "NEES {nees}");
}

/// `our_pose_jacobian` is how the fitted alignment follows our camera's
/// estimate (numerical differentiation of the whole fit on exact points),
/// and `noise_cov` covers what is left once our camera's error is taken out
/// (NEES over Monte-Carlo draws).
#[test]
fn the_alignment_follows_our_pose_by_its_jacobian_and_the_rest_is_its_noise() {
    let (sigma, opts) = loose_options();
    let mut rng = ChaCha8Rng::seed_from_u64(5);
    let s = scene(&mut rng, 30, 0.0);
    let fit = |ours: &CameraEstimate| {
        estimate_alignment(ours, &s.anchor, &s.points, &opts).expect("aligned")
    };
    let d = fit(&s.ours).our_pose_jacobian;
    let h = 1e-6;
    for k in 0..6 {
        let moved = |sign: f64| {
            let mut e = Vector6::zeros();
            e[k] = sign * h;
            let mut o = s.ours;
            o.rot *= exp_so3(&Vector3::new(e[0], e[1], e[2]));
            o.pos += Vector3::new(e[3], e[4], e[5]);
            fit(&o).alignment
        };
        let (plus, minus) = (moved(1.0), moved(-1.0));
        let num = minus.difference(&plus) / (2.0 * h);
        let col: Vector4<f64> = d.column(k).into();
        assert!((num - col).abs().max() < 1e-5, "column {k}: {num} vs {col}");
    }
    let (mut sum, mut runs) = (0.0, 0);
    for _ in 0..300 {
        let mut s = scene(&mut rng, 30, sigma);
        let ours_error = draw_errors(&mut rng, &mut s);
        let Ok(m) = estimate_alignment(&s.ours, &s.anchor, &s.points, &opts) else {
            continue;
        };
        let e = m.alignment.difference(&s.truth) - m.our_pose_jacobian * ours_error;
        sum += e.dot(&(m.noise_cov.try_inverse().expect("invertible") * e));
        runs += 1;
    }
    assert!(runs >= 290, "{runs} aligned");
    let nees = sum / f64::from(runs);
    assert!((3.3..5.0).contains(&nees), "NEES {nees}");
}

#[test]
fn covariance_intersection_of_alignments_never_grows_and_keeps_an_estimate() {
    let a = truth();
    let mut b = a;
    b.yaw_rad += 0.01;
    b.t_m.x += 0.05;
    b.cov = Matrix4::from_diagonal(&Vector4::new(4e-4, 1e-4, 9e-4, 4e-4));
    let f = a.fuse(&b).expect("fused");
    assert!(f.cov.determinant() <= a.cov.determinant() * (1.0 + 1e-9));
    assert!(f.cov.determinant() <= b.cov.determinant() * (1.0 + 1e-9));
    // CI: P⁻¹ = ω A⁻¹ + (1 − ω) B⁻¹ is at least each term's share, so the
    // fused covariance bounds what ω chose: P ≥ (A⁻¹ + B⁻¹)⁻¹ (the
    // independent fusion).
    let independent = (a.cov.try_inverse().expect("inv") + b.cov.try_inverse().expect("inv"))
        .try_inverse()
        .expect("inv");
    assert!((f.cov - independent).symmetric_eigenvalues().min() > -1e-12);
    // The same estimate twice is itself.
    let same = a.fuse(&a).expect("fused");
    assert!((same.cov - a.cov).abs().max() < 1e-12);
    assert!((same.yaw_rad - a.yaw_rad).abs() < 1e-12);
    assert!(a.mahalanobis_sq(&a).expect("gate") < 1e-12);
    assert!(a.mahalanobis_sq(&b).expect("gate") > 1.0);
}

#[test]
fn the_yaw_difference_wraps() {
    let mut a = truth();
    a.yaw_rad = 3.1;
    let mut b = a;
    b.yaw_rad = -3.1;
    let d = a.difference(&b);
    assert!((d[0] - (std::f64::consts::TAU - 6.2)).abs() < 1e-12);
}

#[test]
fn a_point_seen_from_two_places_has_the_covariance_of_its_baseline() {
    let p = Vector3::new(0.0, 0.0, 5.0);
    let cams: Vec<(Matrix3<f64>, Vector3<f64>)> = [-0.5, 0.5]
        .iter()
        .map(|x| {
            let pos = Vector3::new(*x, 0.0, 0.0);
            (look_at(&pos, &p), pos)
        })
        .collect();
    let cov = point_covariance(&cams, &p, 0.002).expect("fixed");
    // Along the rays' bisector (depth) far worse than across.
    assert!(cov[(2, 2)] > 10.0 * cov[(1, 1)]);
    assert!(point_covariance(&cams[..1], &p, 0.002).is_none());
}
