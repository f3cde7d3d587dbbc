//! The linearized measurement system of one feature over the window:
//! `r = H_x δx + H_f δp_F + n` (thesis Section 2.3.3.2), shared by the MSCKF
//! update and the delayed initialization of SLAM features.

use super::feature_db::Feature;
use super::filter::FilterView;
use super::projection::{predict, project};
use super::state::{Means, Var};
use super::triangulation::{triangulate, CameraObservation, TriangulationOptions};
use nalgebra::{DMatrix, DVector, Matrix3, Vector3};

/// Column layout of a stacked Jacobian over the window: calibration variables
/// (when estimated) then every clone, oldest first.
#[derive(Clone, Debug)]
pub struct Columns {
    /// The variables in column order.
    pub vars: Vec<Var>,
    offsets: Vec<usize>,
    /// Total number of columns.
    pub dim: usize,
}

impl Columns {
    /// The window layout of `state`.
    pub fn window<F: FilterView + ?Sized>(state: &F) -> Self {
        let mut vars = Vec::with_capacity(2 + state.means().clones.len());
        for v in [Var::Extrinsic, Var::Intrinsics] {
            if state.has(v) {
                vars.push(v);
            }
        }
        vars.extend(state.means().clones.keys().map(|k| Var::Clone(*k)));
        Self::of(vars)
    }

    /// A layout of the given variables.
    pub fn of(vars: Vec<Var>) -> Self {
        let mut offsets = Vec::with_capacity(vars.len());
        let mut dim = 0;
        for v in &vars {
            offsets.push(dim);
            dim += v.size();
        }
        Self { vars, offsets, dim }
    }

    /// Column offset of `var`.
    pub fn col(&self, var: Var) -> Option<usize> {
        self.vars
            .iter()
            .position(|v| *v == var)
            .map(|i| self.offsets[i])
    }
}

/// One feature's stacked system.
#[derive(Clone, Debug)]
pub struct FeatureSystem {
    /// Jacobian w.r.t. the window variables (`2n x cols.dim`).
    pub h_x: DMatrix<f64>,
    /// Jacobian w.r.t. the feature position (`2n x 3`).
    pub h_f: DMatrix<f64>,
    /// Residuals `z − h(x̂)` (`2n`).
    pub res: DVector<f64>,
    /// The triangulated `p_FinG`.
    pub p_f: Vector3<f64>,
}

/// The measurements of `feature` at clones still in the window, as cameras
/// (current estimates) with undistorted normalized coordinates, for
/// triangulation.
///
/// The pixels are undistorted again with the current intrinsics: the
/// normalized coordinates recorded with a measurement hold the intrinsics of
/// its time, and while online calibration converges those move. Near the
/// image's corners a small change in the distortion moves a ray by tens of
/// pixels (rendered V1_01 at 0.3x, seed 2: two held tracks 4-42 px from the
/// corner had their oldest rays 27-30 px (in x) from where the intrinsics one
/// second later put them; their points were triangulated 0.3-0.4 m deep
/// instead of 1.2-1.4 m, and their SLAM initialization moved the velocity by
/// 1.2 cm/s). The recorded
/// coordinates stand in when the pixel cannot be undistorted now.
pub fn camera_observations(state: &Means, feature: &Feature) -> Vec<CameraObservation> {
    let camera = &state.calib.camera;
    feature
        .measurements
        .iter()
        .filter_map(|m| {
            let (r_c_to_g, p_c_in_g) = camera_pose(state, m.clone_key)?;
            Some(CameraObservation {
                r_c_to_g,
                p_c_in_g,
                uvn: camera.undistort(&m.uv).unwrap_or(m.uvn),
            })
        })
        .collect()
}

/// The camera of clone `key` (current estimates): `R_CtoG` and `p_CinG`.
pub fn camera_pose(state: &Means, key: u64) -> Option<(Matrix3<f64>, Vector3<f64>)> {
    let c = state.clones.get(&key)?;
    let calib = &state.calib;
    Some((c.rot * calib.rot_c_to_i, c.pos + c.rot * calib.p_c_in_i))
}

/// Triangulates `feature` from the clones still in the window (current estimates)
/// and stacks its measurements. Jacobians use the clones' first estimates when
/// `use_fej`. `None` when the feature cannot be triangulated or projected.
///
/// When the window's views alone fail the limits and the track is older than
/// the window, the point is triangulated again with its retired rays
/// ([`Feature::retired`]) in front: on a slow flight the window's second of
/// views lacks the parallax (V1_01 at half speed: 0.2 m/s, points 5-7 m away,
/// rays about 1 deg apart) while the track's whole life has it. The point is
/// only where the system is linearized: the update still uses the window's
/// measurements alone, and the nullspace projection removes the point's error
/// to first order, so the rays of clones that have left add no information,
/// only a better linearization point.
pub fn build(
    state: &Means,
    feature: &Feature,
    cols: &Columns,
    use_fej: bool,
    tri: &TriangulationOptions,
) -> Option<FeatureSystem> {
    let obs = camera_observations(state, feature);
    if obs.len() < 2 {
        return None;
    }
    let p_f = match triangulate(&obs, tri) {
        Ok(p) => p,
        Err(_) if !feature.retired.is_empty() => {
            let mut longer: Vec<CameraObservation> =
                feature.retired.iter().map(|r| r.view).collect();
            longer.extend_from_slice(&obs);
            let limits = if tri.retired_by_precision {
                // The same depth precision as `obs` at the plain limit
                // (TriangulationOptions::starved).
                let rays = longer.len() as f64 / obs.len() as f64;
                TriangulationOptions {
                    max_condition_number: tri.max_condition_number * rays,
                    ..*tri
                }
            } else {
                *tri
            };
            triangulate(&longer, &limits).ok()?
        }
        Err(_) => return None,
    };
    build_at(state, feature, cols, use_fej, &p_f)
}

/// Stacks the measurements of `feature` at clones in the window, linearized at
/// the feature position `p_f` (e.g. triangulated from several robots' views).
/// `None` when a measurement cannot be projected.
pub fn build_at(
    state: &Means,
    feature: &Feature,
    cols: &Columns,
    use_fej: bool,
    p_f: &Vector3<f64>,
) -> Option<FeatureSystem> {
    let calib = &state.calib;
    let meas: Vec<_> = feature
        .measurements
        .iter()
        .filter_map(|m| state.clones.get(&m.clone_key).map(|c| (m, c)))
        .collect();
    if meas.is_empty() {
        return None;
    }
    let p_f = *p_f;
    let rows = 2 * meas.len();
    let mut h_x = DMatrix::zeros(rows, cols.dim);
    let mut h_f = DMatrix::zeros(rows, 3);
    let mut res = DVector::zeros(rows);
    let ext = cols.col(Var::Extrinsic);
    let intr = cols.col(Var::Intrinsics);
    for (i, (m, c)) in meas.iter().enumerate() {
        let (rot, pos) = if use_fej {
            (&c.rot_fej, &c.pos_fej)
        } else {
            (&c.rot, &c.pos)
        };
        let proj = project(rot, pos, &p_f, calib)?;
        let z_hat = predict(&c.rot, &c.pos, &p_f, calib)?;
        let r = 2 * i;
        let e = m.uv - z_hat;
        res[r] = e.x;
        res[r + 1] = e.y;
        let cc = cols.col(Var::Clone(m.clone_key))?;
        h_x.fixed_view_mut::<2, 6>(r, cc).copy_from(&proj.h_clone);
        if let Some(o) = ext {
            h_x.fixed_view_mut::<2, 6>(r, o)
                .copy_from(&proj.h_extrinsic);
        }
        if let Some(o) = intr {
            h_x.fixed_view_mut::<2, 8>(r, o)
                .copy_from(&proj.h_intrinsics);
        }
        h_f.fixed_view_mut::<2, 3>(r, 0).copy_from(&proj.h_feature);
    }
    Some(FeatureSystem { h_x, h_f, res, p_f })
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::estimator::test_scene::scene;

    #[test]
    fn rays_follow_the_current_intrinsics_not_those_a_measurement_was_recorded_with() {
        let mut s = scene(8, 12, 1e-4, 1e-4);
        // The measurements were recorded while online calibration still held
        // another distortion (the start's perturbation, then a second
        // estimate): their stored normalized coordinates are stale.
        let mut earlier = s.state.means.calib.camera.clone();
        earlier.distortion += nalgebra::Vector4::new(0.02, -0.01, 0.004, 0.007);
        let tri = TriangulationOptions::default();
        let (mut worst_stale, mut worst_now) = (0.0_f64, 0.0_f64);
        for (id, p_true) in s.landmarks.clone().iter().enumerate() {
            let Some(f) = s.db.get_mut(id as u64) else {
                continue;
            };
            for m in &mut f.measurements {
                m.uvn = earlier.undistort(&m.uv).expect("undistorts");
            }
            let f = s.db.get(id as u64).expect("track");
            let stale: Vec<CameraObservation> = camera_observations(&s.state.means, f)
                .into_iter()
                .zip(&f.measurements)
                .map(|(o, m)| CameraObservation { uvn: m.uvn, ..o })
                .collect();
            if let Ok(p) = triangulate(&stale, &tri) {
                worst_stale = worst_stale.max((p - p_true).norm());
            }
            let p = triangulate(&camera_observations(&s.state.means, f), &tri).expect("point");
            worst_now = worst_now.max((p - p_true).norm());
        }
        // Noise-free pixels and true poses: the current intrinsics give the
        // landmarks back; the recorded coordinates miss them by centimetres
        // (8.6 cm here).
        assert!(worst_now < 1e-6, "{worst_now}");
        assert!(worst_stale > 0.05, "{worst_stale}");
    }
}
