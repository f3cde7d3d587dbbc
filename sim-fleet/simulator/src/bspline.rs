//! Cubic cumulative SE(3) B-spline (thesis Eqs. 2.104-2.112, App. C).
//!
//! Control poses `T_k = (R_ItoG, p_IinG)` are uniformly spaced by `dt`. For a time
//! `t` in `[t_i, t_{i+1})` the pose is `T(u) = T_{i-1} A_0 A_1 A_2` (Eq. 2.105) with
//! `A_j = Exp(B_j(u) Ω_j)` (Eq. 2.106), `Ω_j = Log(T_{i-1+j}⁻¹ T_{i+j})` (Eq. 2.107)
//! and the cumulative basis of Eqs. 2.108-2.110. Velocity and acceleration come from
//! the analytic time derivatives of that product (App. C), not finite differences.

use common::so3::{exp_so3, log_so3, skew, vee, Se3};
use common::trajectory::StampedPose;
use nalgebra::{Matrix3, Matrix4, Vector3, Vector6};
use thiserror::Error;

/// Why a spline could not be built.
#[derive(Debug, Error)]
pub enum SplineError {
    /// Fewer poses than a cubic spline needs over the requested span.
    #[error("trajectory too short for a cubic B-spline: {0} control points (need at least 4)")]
    TooShort(usize),
    /// The control point spacing is not a positive finite number.
    #[error("invalid control point spacing {0} s")]
    BadSpacing(f64),
}

/// The kinematic state of the spline at one time.
#[derive(Clone, Copy, Debug)]
pub struct SplineState {
    /// Orientation `R_ItoG`.
    pub rot: Matrix3<f64>,
    /// Position `p_IinG` (m).
    pub pos: Vector3<f64>,
    /// Velocity `v_IinG` (m/s), in `G`.
    pub vel: Vector3<f64>,
    /// Angular velocity `ω` (rad/s), in `I` (Eq. 2.111).
    pub omega: Vector3<f64>,
    /// Acceleration of `I` in `G` (m/s²), gravity not included.
    pub acc: Vector3<f64>,
}

/// A uniform cubic cumulative B-spline on SE(3).
#[derive(Clone, Debug)]
pub struct SplineSe3 {
    t0: f64,
    dt: f64,
    ctrl: Vec<Se3>,
    /// `Ω` between consecutive control points, precomputed.
    omega: Vec<Vector6<f64>>,
}

/// The se(3) "hat" of `[ω; v]` as a 4x4 matrix.
fn hat6(xi: &Vector6<f64>) -> Matrix4<f64> {
    let mut m = Matrix4::zeros();
    m.fixed_view_mut::<3, 3>(0, 0)
        .copy_from(&skew(&xi.fixed_rows::<3>(0).into_owned()));
    m.fixed_view_mut::<3, 1>(0, 3)
        .copy_from(&xi.fixed_rows::<3>(3));
    m
}

/// Cumulative basis values and their first and second derivatives w.r.t. `u`
/// (Eqs. 2.108-2.110).
fn basis(u: f64) -> ([f64; 3], [f64; 3], [f64; 3]) {
    let (u2, u3) = (u * u, u * u * u);
    let b = [
        (5.0 + 3.0 * u - 3.0 * u2 + u3) / 6.0,
        (1.0 + 3.0 * u + 3.0 * u2 - 2.0 * u3) / 6.0,
        u3 / 6.0,
    ];
    let db = [
        (3.0 - 6.0 * u + 3.0 * u2) / 6.0,
        (3.0 + 6.0 * u - 6.0 * u2) / 6.0,
        (3.0 * u2) / 6.0,
    ];
    let ddb = [(-6.0 + 6.0 * u) / 6.0, (6.0 - 12.0 * u) / 6.0, u];
    (b, db, ddb)
}

impl SplineSe3 {
    /// Builds the spline from control poses spaced `dt` apart starting at `t0`.
    pub fn from_control_points(t0: f64, dt: f64, ctrl: Vec<Se3>) -> Result<Self, SplineError> {
        if !(dt.is_finite() && dt > 0.0) {
            return Err(SplineError::BadSpacing(dt));
        }
        if ctrl.len() < 4 {
            return Err(SplineError::TooShort(ctrl.len()));
        }
        let omega = ctrl
            .windows(2)
            .map(|w| w[0].inverse().compose(&w[1]).log())
            .collect();
        Ok(Self {
            t0,
            dt,
            ctrl,
            omega,
        })
    }

    /// The same motion seen from another frame: every pose `T` becomes `f ∘ T`.
    /// The increments between control points are relative, so the spline is
    /// exactly the old one's poses moved by `f` (velocities and accelerations
    /// rotated by it).
    pub fn transformed(&self, f: &Se3) -> Self {
        Self {
            t0: self.t0,
            dt: self.dt,
            ctrl: self.ctrl.iter().map(|c| f.compose(c)).collect(),
            omega: self.omega.clone(),
        }
    }

    /// Fits the spline to a trajectory as OpenVINS's simulator does: control points
    /// every `max(mean pose spacing, min_dt)` seconds, each the trajectory's pose
    /// interpolated at that time (slerp on rotation, linear on position).
    pub fn fit(traj: &[StampedPose], min_dt: f64) -> Result<Self, SplineError> {
        if traj.len() < 4 {
            return Err(SplineError::TooShort(traj.len()));
        }
        let first = traj[0].t;
        let last = traj[traj.len() - 1].t;
        let mean_dt = (last - first) / (traj.len() - 1) as f64;
        let dt = mean_dt.max(min_dt);
        if !(dt.is_finite() && dt > 0.0) {
            return Err(SplineError::BadSpacing(dt));
        }
        let mut ctrl = Vec::new();
        let mut j = 0usize;
        let mut k = 0usize;
        loop {
            let t = first + k as f64 * dt;
            if t > last + 1e-9 {
                break;
            }
            while j + 2 < traj.len() && traj[j + 1].t <= t {
                j += 1;
            }
            let (a, b) = (&traj[j], &traj[j + 1]);
            let s = ((t - a.t) / (b.t - a.t)).clamp(0.0, 1.0);
            let dr = log_so3(&(a.rot.transpose() * b.rot));
            ctrl.push(Se3::new(
                a.rot * exp_so3(&(dr * s)),
                a.pos + (b.pos - a.pos) * s,
            ));
            k += 1;
        }
        Self::from_control_points(first, dt, ctrl)
    }

    /// First time the spline is defined (it needs one control point before).
    pub fn start_time(&self) -> f64 {
        self.t0 + self.dt
    }

    /// Last time the spline is defined (it needs two control points after).
    pub fn end_time(&self) -> f64 {
        self.t0 + (self.ctrl.len() - 3) as f64 * self.dt - 1e-9
    }

    /// Control point spacing in seconds.
    pub fn dt(&self) -> f64 {
        self.dt
    }

    /// Index `i` of the segment `[t_i, t_{i+1})` holding `t`, and `u` in [0, 1).
    fn segment(&self, t: f64) -> Option<(usize, f64)> {
        if !t.is_finite() || t < self.start_time() - 1e-12 || t > self.end_time() + 1e-12 {
            return None;
        }
        let s = (t - self.t0) / self.dt;
        let i = (s.floor() as usize).clamp(1, self.ctrl.len() - 3);
        Some((i, s - i as f64))
    }

    /// The pose `(R_ItoG, p_IinG)` at time `t`, or `None` outside the spline's span.
    pub fn pose(&self, t: f64) -> Option<Se3> {
        let (i, u) = self.segment(t)?;
        let (b, _, _) = basis(u);
        let mut pose = self.ctrl[i - 1];
        for (j, bj) in b.iter().enumerate() {
            pose = pose.compose(&Se3::exp(&(self.omega[i - 1 + j] * *bj)));
        }
        Some(pose)
    }

    /// Pose, velocity, angular velocity and acceleration at `t` from the analytic
    /// derivatives of Eq. 2.105 (App. C); `None` outside the span.
    pub fn state(&self, t: f64) -> Option<SplineState> {
        let (i, u) = self.segment(t)?;
        let (b, db, ddb) = basis(u);
        let inv_dt = 1.0 / self.dt;
        let mut a = [Matrix4::zeros(); 3];
        let mut da = [Matrix4::zeros(); 3];
        let mut dda = [Matrix4::zeros(); 3];
        for j in 0..3 {
            let om = self.omega[i - 1 + j];
            let h = hat6(&om);
            a[j] = Se3::exp(&(om * b[j])).matrix();
            // d/dt Exp(B Ω^) = A Ω^ Ḃ ; d²/dt² = Ȧ Ω^ Ḃ + A Ω^ B̈
            let bd = db[j] * inv_dt;
            let bdd = ddb[j] * inv_dt * inv_dt;
            da[j] = a[j] * h * bd;
            dda[j] = da[j] * h * bd + a[j] * h * bdd;
        }
        let t_prev = self.ctrl[i - 1].matrix();
        let pose = t_prev * a[0] * a[1] * a[2];
        let dpose = t_prev * (da[0] * a[1] * a[2] + a[0] * da[1] * a[2] + a[0] * a[1] * da[2]);
        let ddpose = t_prev
            * (dda[0] * a[1] * a[2]
                + a[0] * dda[1] * a[2]
                + a[0] * a[1] * dda[2]
                + (da[0] * da[1] * a[2] + da[0] * a[1] * da[2] + a[0] * da[1] * da[2]) * 2.0);
        let rot = pose.fixed_view::<3, 3>(0, 0).into_owned();
        let drot = dpose.fixed_view::<3, 3>(0, 0).into_owned();
        Some(SplineState {
            rot,
            pos: pose.fixed_view::<3, 1>(0, 3).into_owned(),
            vel: dpose.fixed_view::<3, 1>(0, 3).into_owned(),
            // Eq. 2.111: ω = Vee(Rᵀ Ṙ)
            omega: vee(&(rot.transpose() * drot)),
            acc: ddpose.fixed_view::<3, 1>(0, 3).into_owned(),
        })
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use common::conventions::GRAVITY_MPS2;

    /// A smooth synthetic trajectory: a figure-eight with varying attitude.
    pub(crate) fn synthetic(duration: f64, rate: f64) -> Vec<StampedPose> {
        let n = (duration * rate) as usize;
        (0..=n)
            .map(|k| {
                let t = k as f64 / rate;
                let pos = Vector3::new(
                    3.0 * (0.3 * t).sin(),
                    2.0 * (0.6 * t).sin(),
                    1.0 + 0.3 * (0.5 * t).cos(),
                );
                let rot = exp_so3(&Vector3::new(
                    0.2 * (0.7 * t).sin(),
                    0.15 * (0.4 * t).cos(),
                    0.5 * t,
                ));
                StampedPose { t, rot, pos }
            })
            .collect()
    }

    #[test]
    fn analytic_derivatives_match_finite_differences() {
        let spline = SplineSe3::fit(&synthetic(20.0, 20.0), 0.05).unwrap();
        let h = 1e-5;
        for k in 0..200 {
            let t = spline.start_time() + 0.01 + k as f64 * 0.09;
            if t + h > spline.end_time() {
                break;
            }
            let s = spline.state(t).unwrap();
            let (p, m) = (spline.state(t + h).unwrap(), spline.state(t - h).unwrap());
            let vel_fd = (p.pos - m.pos) / (2.0 * h);
            let acc_fd = (p.vel - m.vel) / (2.0 * h);
            let omega_fd = log_so3(&(m.rot.transpose() * p.rot)) / (2.0 * h);
            assert!((s.vel - vel_fd).norm() < 1e-6, "vel at {t}");
            assert!((s.acc - acc_fd).norm() < 1e-4, "acc at {t}");
            assert!((s.omega - omega_fd).norm() < 1e-6, "omega at {t}");
            let pose = spline.pose(t).unwrap();
            assert!((pose.rot - s.rot).norm() < 1e-12 && (pose.trans - s.pos).norm() < 1e-12);
        }
    }

    #[test]
    fn a_transformed_spline_is_the_moved_motion() {
        let spline = SplineSe3::fit(&synthetic(10.0, 20.0), 0.05).unwrap();
        let f = Se3::new(
            exp_so3(&Vector3::new(0.0, 0.0, 1.2)),
            Vector3::new(3.0, -2.0, 0.5),
        );
        let moved = spline.transformed(&f);
        for k in 0..50 {
            let t = spline.start_time() + 0.05 + k as f64 * 0.17;
            let (a, b) = (spline.state(t).unwrap(), moved.state(t).unwrap());
            assert!((f.rot * a.rot - b.rot).norm() < 1e-9, "rot at {t}");
            assert!(
                (f.transform_point(&a.pos) - b.pos).norm() < 1e-9,
                "pos at {t}"
            );
            assert!((f.rot * a.vel - b.vel).norm() < 1e-9, "vel at {t}");
            assert!((f.rot * a.acc - b.acc).norm() < 1e-7, "acc at {t}");
            assert!((a.omega - b.omega).norm() < 1e-9, "omega at {t}");
        }
    }

    #[test]
    fn spline_passes_close_to_a_smooth_trajectory() {
        let traj = synthetic(20.0, 20.0);
        let spline = SplineSe3::fit(&traj, 0.05).unwrap();
        for p in traj
            .iter()
            .filter(|p| p.t > spline.start_time() && p.t < spline.end_time())
        {
            let s = spline.pose(p.t).unwrap();
            assert!((s.trans - p.pos).norm() < 5e-3);
        }
    }

    #[test]
    fn outside_the_span_there_is_no_state() {
        let spline = SplineSe3::fit(&synthetic(5.0, 20.0), 0.05).unwrap();
        assert!(spline.state(spline.start_time() - 0.01).is_none());
        assert!(spline.state(spline.end_time() + 0.01).is_none());
        assert!(spline.state(f64::NAN).is_none());
        assert!(spline.state(spline.end_time()).is_some());
    }

    /// RK4 integration of the noise-free IMU signals derived from the spline, in the
    /// same (R, p, v) form the estimator uses, at 400 Hz over `seconds`; returns the
    /// final position and orientation errors (m, rad).
    fn rk4_drift(spline: &SplineSe3, seconds: f64) -> (f64, f64) {
        let g = Vector3::new(0.0, 0.0, GRAVITY_MPS2);
        // IMU measurement as the simulator makes it: ω in I, a_m = Rᵀ (a + g).
        let imu = |t: f64| {
            let s = spline.state(t).unwrap();
            (s.omega, s.rot.transpose() * (s.acc + g))
        };
        let dt = 1.0 / 400.0;
        let t_start = spline.start_time();
        let s0 = spline.state(t_start).unwrap();
        let (mut rot, mut pos, mut vel) = (s0.rot, s0.pos, s0.vel);
        let steps = (seconds / dt) as usize;
        let f = |r: &Matrix3<f64>, v: &Vector3<f64>, a: &Vector3<f64>| (*v, r * a - g);
        for k in 0..steps {
            let t = t_start + k as f64 * dt;
            let (w0, a0) = imu(t);
            let (wm, am) = imu(t + dt / 2.0);
            let (w1, a1) = imu(t + dt);
            // RK4 on (p, v); the rotation follows ω through the body frame.
            let rm = rot * exp_so3(&((w0 + wm) * 0.5 * (dt / 2.0)));
            let r1 = rot * exp_so3(&(((w0 + 4.0 * wm + w1) / 6.0) * dt));
            let (k1p, k1v) = f(&rot, &vel, &a0);
            let (k2p, k2v) = f(&rm, &(vel + k1v * dt / 2.0), &am);
            let (k3p, k3v) = f(&rm, &(vel + k2v * dt / 2.0), &am);
            let (k4p, k4v) = f(&r1, &(vel + k3v * dt), &a1);
            pos += (k1p + 2.0 * k2p + 2.0 * k3p + k4p) * (dt / 6.0);
            vel += (k1v + 2.0 * k2v + 2.0 * k3v + k4v) * (dt / 6.0);
            rot = r1;
        }
        let truth = spline.state(t_start + steps as f64 * dt).unwrap();
        (
            (pos - truth.pos).norm(),
            log_so3(&(rot.transpose() * truth.rot)).norm(),
        )
    }

    #[test]
    fn noise_free_imu_integrated_with_rk4_stays_within_a_centimetre_for_60_s() {
        let spline = SplineSe3::fit(&synthetic(70.0, 20.0), 0.05).unwrap();
        let (dp, dr) = rk4_drift(&spline, 60.0);
        assert!(dp < 0.01, "position drift {dp} m after 60 s");
        assert!(dr < 1e-4);
    }

    #[test]
    fn noise_free_imu_of_a_real_flight_integrates_within_a_centimetre_for_60_s() {
        let path = concat!(
            env!("CARGO_MANIFEST_DIR"),
            "/../../../shared/data/trajectories/V1_01_easy.txt"
        );
        let poses = common::trajectory::read_trajectory(path).unwrap();
        let spline = SplineSe3::fit(&poses, 0.05).unwrap();
        let (dp, dr) = rk4_drift(&spline, 60.0);
        assert!(dp < 0.01, "position drift {dp} m after 60 s");
        assert!(dr < 1e-3, "rotation drift {dr} rad");
    }
}
