//! Tests of the common-VIO update: the two-stage projection's information, exact
//! measurements, wrong associations and loop closures, and Monte-Carlo consistency.

mod cases {
    use super::super::*;
    use crate::estimator::test_scene::scene;
    use rand::{Rng, SeedableRng};
    use rand_chacha::ChaCha8Rng;
    use std::ops::AddAssign;

    fn random_block(rows: usize, cols: usize, rng: &mut ChaCha8Rng) -> Block {
        let mut r = || rng.random_range(-1.0..1.0);
        Block {
            h_x: DMatrix::from_fn(rows, cols, |_, _| r()),
            h_f: DMatrix::from_fn(rows, 3, |_, _| r()),
            res: DVector::from_fn(rows, |_, _| r()),
        }
    }

    /// Eq. 5.19's claim: our nullspace rows, the second-stage rows and the
    /// peer's (dropped) nullspace rows carry exactly the information of one
    /// projection of the whole stack.
    #[test]
    fn two_stage_rows_carry_the_combined_information() {
        let mut rng = ChaCha8Rng::seed_from_u64(5);
        let (ci, cp) = (8, 12);
        let ours = random_block(10, ci, &mut rng);
        let peer = random_block(14, cp, &mut rng);
        let copy = |b: &Block| Block {
            h_x: b.h_x.clone(),
            h_f: b.h_f.clone(),
            res: b.res.clone(),
        };
        let (hc, rc) = stack_and_project(&[copy(&ours), copy(&peer)]).unwrap();
        let info_c = hc.transpose() * &hc;
        let vec_c = hc.transpose() * &rc;

        let mut o = copy(&ours);
        let top = givens_qr_split(&mut o.h_f, &mut o.h_x, &mut o.res);
        let (o_top, o_h, o_r) = split_rows(o, top);
        let mut p = copy(&peer);
        let top = givens_qr_split(&mut p.h_f, &mut p.h_x, &mut p.res);
        let (p_top, p_h, p_r) = split_rows(p, top);
        let (h2, r2) = stack_and_project(&[o_top, p_top]).unwrap();
        let mut info = h2.transpose() * &h2;
        let mut vec = h2.transpose() * &r2;
        info.view_mut((0, 0), (ci, ci))
            .add_assign(&(o_h.transpose() * &o_h));
        vec.rows_mut(0, ci).add_assign(&(o_h.transpose() * &o_r));
        info.view_mut((ci, ci), (cp, cp))
            .add_assign(&(p_h.transpose() * &p_h));
        vec.rows_mut(ci, cp).add_assign(&(p_h.transpose() * &p_r));
        assert!((info - info_c).abs().max() < 1e-10);
        assert!((vec - vec_c).abs().max() < 1e-10);
        // And the CI system is smaller: 3 + 3 - 3 rows instead of 10 + 14 - 3.
        assert_eq!(h2.nrows(), 3);
        assert_eq!(hc.nrows(), 21);
    }

    fn run(
        projection: CommonProjection,
        wrong: bool,
    ) -> (CommonOutcome, crate::estimator::test_scene::Scene, f64) {
        let mut sc = scene(6, 12, 1e-4, 1e-5);
        let tracks: Vec<CommonTrack> = (0..12)
            .map(|l| CommonTrack {
                id: l as u64,
                // With `wrong`, track 3 gets the peer's view of landmark 9.
                peer_obs: sc.peer_obs(if wrong && l == 3 { 9 } else { l }),
            })
            .collect();
        let mut opts = EstimatorOptions::default();
        opts.cooperation.projection = projection;
        let trace_before = sc.state.cov().trace();
        let out = sc.common_update(&tracks, &opts);
        (out, sc, trace_before)
    }

    #[test]
    fn exact_common_measurements_keep_the_truth_and_shrink_the_covariance() {
        for projection in [CommonProjection::TwoStage, CommonProjection::Combined] {
            let truth = scene(6, 12, 1e-4, 1e-5);
            let (out, sc, trace_before) = run(projection, false);
            assert_eq!(out.stats.used, 12, "{projection:?}: {:?}", out.stats);
            assert!(out.fallback.is_empty());
            for (k, c) in &sc.state.clones {
                let t = &truth.state.clones[k];
                assert!((c.pos - t.pos).norm() < 1e-6, "{projection:?} clone {k}");
            }
            assert!(sc.state.cov().trace() < trace_before);
            if projection == CommonProjection::TwoStage {
                assert_eq!(out.stats.ci_rows, 12 * 3);
                assert!(out.stats.own_rows > 0);
            } else {
                assert_eq!(out.stats.own_rows, 0);
                assert!(out.stats.ci_rows > 12 * 3);
            }
        }
    }

    /// A peer's measurements are weighed at the pixel noise its window
    /// declares, not at ours: a noisier peer tells us less, a cleaner one more.
    #[test]
    fn a_peer_is_weighed_at_its_own_pixel_noise() {
        let trace_after = |peer_sigma_px: f64| {
            let mut sc = scene(6, 12, 1e-4, 1e-5);
            sc.peer.pixel_sigma_px = peer_sigma_px;
            let tracks: Vec<CommonTrack> = (0..12)
                .map(|l| CommonTrack {
                    id: l as u64,
                    peer_obs: sc.peer_obs(l),
                })
                .collect();
            let before = sc.state.cov().trace();
            let out = sc.common_update(&tracks, &EstimatorOptions::default());
            assert_eq!(out.stats.used, 12, "{peer_sigma_px} px: {:?}", out.stats);
            let after = sc.state.cov().trace();
            assert!(after < before);
            after
        };
        let (clean, same, noisy) = (trace_after(0.5), trace_after(1.0), trace_after(3.0));
        assert!(clean < same && same < noisy, "{clean} {same} {noisy}");
    }

    /// A wrong loop closure: the peer's window saw a rigid copy of our scene
    /// 2 m away (perceptual aliasing), so every match is consistent with one
    /// epipolar geometry but not with the two robots' poses: all are rejected.
    #[test]
    fn a_whole_wrong_loop_closure_is_rejected() {
        let mut sc = scene(6, 12, 1e-4, 1e-5);
        let offset = nalgebra::Vector3::new(2.0, 0.0, 0.3);
        let tracks: Vec<CommonTrack> = (0..12)
            .map(|l| {
                let seen_at = sc.landmarks[l] + offset;
                let peer_obs = sc
                    .peer
                    .poses
                    .iter()
                    .enumerate()
                    .filter_map(|(j, pose)| {
                        let p = crate::estimator::peer_window::project_normalized(pose, &seen_at)?;
                        Some(PeerObservation {
                            participant: 0,
                            pose: j,
                            xy: p.xy,
                        })
                    })
                    .collect();
                CommonTrack {
                    id: l as u64,
                    peer_obs,
                }
            })
            .collect();
        let before = sc.state.clone();
        let out = sc.common_update(&tracks, &EstimatorOptions::default());
        assert_eq!(out.stats.used, 0, "{:?}", out.stats);
        assert_eq!(out.fallback.len(), 12);
        assert_eq!(sc.state.cov(), before.cov());
    }

    /// A CI-EKF update that fails (here: a peer window whose covariance is not
    /// positive, which passes the gate but not the CI system) after our own
    /// rows went in must not send the tracks to the MSCKF: their measurements
    /// would be used twice. Without own rows (combined projection) they fall back.
    /// The fixed peer weight divides the negative covariance by 0.001, which
    /// makes the innovation covariance fail; a searched weight stays where it
    /// does not.
    #[test]
    fn a_failed_ci_update_spends_each_measurement_once() {
        for projection in [CommonProjection::TwoStage, CommonProjection::Combined] {
            let mut sc = scene(6, 12, 1e-4, -1e-8);
            let tracks: Vec<CommonTrack> = (0..12)
                .map(|l| CommonTrack {
                    id: l as u64,
                    peer_obs: sc.peer_obs(l),
                })
                .collect();
            let mut opts = EstimatorOptions::default();
            opts.cooperation.projection = projection;
            opts.cooperation.ci_weighting = common::estimator_options::CiWeighting::FixedPeer;
            let before = sc.state.cov().trace();
            let out = sc.common_update(&tracks, &opts);
            assert_eq!(out.stats.used, 0, "{projection:?}: {:?}", out.stats);
            assert!(out.used.is_empty());
            let after = sc.state.cov().trace();
            if projection == CommonProjection::TwoStage {
                assert!(out.stats.own_rows > 0);
                assert!(after < before, "our own rows were applied");
                assert!(out.fallback.is_empty(), "{:?}", out.fallback);
            } else {
                assert_eq!(after, before);
                assert_eq!(out.fallback.len(), 12);
            }
        }
    }

    #[test]
    fn a_wrong_association_is_gated_out_and_falls_back() {
        let (out, _, _) = run(CommonProjection::TwoStage, true);
        assert_eq!(out.fallback, vec![3]);
        assert_eq!(out.stats.rejected_chi2 + out.stats.failed, 1);
        assert_eq!(out.stats.used, 11);
    }
}

mod consistency {
    use super::super::*;
    use crate::estimator::peer_window::project_normalized;
    use crate::estimator::projection::predict;
    use crate::estimator::test_scene::scene;
    use common::so3::exp_so3;
    use nalgebra::{Vector2, Vector3};
    use rand::{Rng, SeedableRng};
    use rand_chacha::ChaCha8Rng;
    /// A standard normal sample (Box-Muller).
    fn gauss(rng: &mut ChaCha8Rng) -> f64 {
        let u1: f64 = rng.random_range(f64::EPSILON..1.0);
        let u2: f64 = rng.random();
        (-2.0 * u1.ln()).sqrt() * (std::f64::consts::TAU * u2).cos()
    }

    /// Monte-Carlo NEES of our clone poses after a common-VIO update: truth
    /// drawn around the estimate from our covariance and the peer's, noisy
    /// measurements of the true scene. CI must not be overconfident.
    #[test]
    fn the_common_update_is_not_overconfident() {
        let mut rng = ChaCha8Rng::seed_from_u64(21);
        let (mut nees, mut trials) = (0.0, 0);
        for _ in 0..200 {
            let mut sc = scene(6, 12, 4e-4, 1e-4);
            // True clone poses: the estimate moved by a draw of our covariance
            // (diagonal in the scene).
            let calib = sc.state.calib.clone();
            let mut true_clones = std::collections::BTreeMap::new();
            for (k, c) in &sc.state.clones {
                let dth = Vector3::from_fn(|_, _| gauss(&mut rng) * 4e-4f64.sqrt());
                let dp = Vector3::from_fn(|_, _| gauss(&mut rng) * 4e-4f64.sqrt());
                true_clones.insert(*k, (c.rot * exp_so3(&dth), c.pos + dp));
            }
            // True peer poses likewise.
            let true_peer: Vec<_> = sc
                .peer
                .poses
                .iter()
                .map(|p| {
                    let dth = Vector3::from_fn(|_, _| gauss(&mut rng) * 1e-4f64.sqrt());
                    let dp = Vector3::from_fn(|_, _| gauss(&mut rng) * 1e-4f64.sqrt());
                    let mut q = *p;
                    q.rot = p.rot * exp_so3(&dth);
                    q.pos = p.pos + dp;
                    q
                })
                .collect();
            // Measurements of the true scene, 1 px noise.
            let mut db = crate::estimator::feature_db::FeatureDb::new();
            let mut tracks = Vec::new();
            for (l, p_f) in sc.landmarks.iter().enumerate() {
                for (k, (rot, pos)) in &true_clones {
                    let Some(uv) = predict(rot, pos, p_f, &calib) else {
                        continue;
                    };
                    let uv = uv + Vector2::new(gauss(&mut rng), gauss(&mut rng));
                    let Ok(uvn) = calib.camera.undistort(&uv) else {
                        continue;
                    };
                    let m = crate::estimator::feature_db::FeatureMeasurement {
                        clone_key: *k,
                        t: *k as f64,
                        uv,
                        uvn,
                    };
                    db.insert(l as u64, m).ok();
                }
                let peer_obs = true_peer
                    .iter()
                    .enumerate()
                    .filter_map(|(j, pose)| {
                        let p = project_normalized(pose, p_f)?;
                        let noise = Vector2::new(gauss(&mut rng), gauss(&mut rng)) / 458.0;
                        Some(PeerObservation {
                            participant: 0,
                            pose: j,
                            xy: p.xy + noise,
                        })
                    })
                    .collect();
                tracks.push(CommonTrack {
                    id: l as u64,
                    peer_obs,
                });
            }
            sc.db = db;
            let out = sc.common_update(&tracks, &EstimatorOptions::default());
            if out.stats.used == 0 {
                continue;
            }
            // NEES of the newest clone's pose.
            let key = *sc.state.clones.keys().next_back().unwrap();
            let c = &sc.state.clones[&key];
            let (tr, tp) = true_clones[&key];
            let mut e = nalgebra::DVector::zeros(6);
            e.rows_mut(0, 3)
                .copy_from(&common::so3::log_so3(&(c.rot.transpose() * tr)));
            e.rows_mut(3, 3).copy_from(&(tp - c.pos));
            let p = sc.state.block(Var::Clone(key), Var::Clone(key)).unwrap();
            nees += e.dot(&p.cholesky().unwrap().solve(&e));
            trials += 1;
        }
        let mean = nees / trials as f64;
        assert!(trials > 150, "{trials} trials used the update");
        assert!(
            mean < 6.0 * 1.15,
            "mean NEES {mean} over {trials} trials (6 dof)"
        );
    }
}
