//! The filter state with a type-indexed covariance (thesis Section 2.3.1).
//!
//! Every variable ([`Var`]) knows its offset and size in the covariance. Only this
//! module touches the covariance: augmentation, marginalization and the EKF update
//! with a sparse Jacobian that names the variables it involves.
//!
//! Error state (see `common::conventions`): rotations on the right,
//! `R = R̂ Exp(δθ)`; everything else additive. IMU block order:
//! `[δθ, δp, δv, δb_g, δb_a]`; extrinsic block `[δθ_CtoI, δp_CinI]`; intrinsics
//! `[fx, fy, cx, cy, d0..d3]`; a clone `[δθ, δp]`; a SLAM feature `δp_FinG`.

use super::covariance::{Covariance, StateVar};
use common::calibration::CameraCalibration;
use common::so3::{exp_so3, log_so3};
use nalgebra::{DMatrix, DVector, Matrix3, Vector3};
use std::collections::BTreeMap;
use std::ops::{Deref, DerefMut};

/// A state variable.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, PartialOrd, Ord)]
pub enum Var {
    /// IMU orientation, position, velocity and biases (15).
    Imu,
    /// Camera-IMU time offset (1).
    TimeOffset,
    /// Camera-IMU extrinsics `R_CtoI`, `p_CinI` (6).
    Extrinsic,
    /// Intrinsics and distortion (8).
    Intrinsics,
    /// A stochastic clone of the IMU pose, keyed by image sequence number (6).
    Clone(u64),
    /// A SLAM feature in global 3-D, keyed by track id (3).
    Feature(u64),
    /// Where a peer's world frame is in ours, `[δψ, δt]` (4): peer `peer`'s
    /// frame `epoch` (`cooperation.peer_frame_state_s`, see
    /// `frame_alignment`).
    PeerFrame {
        /// The peer's robot id.
        peer: u32,
        /// Its frame (`StateSnapshot::frame_epoch`).
        epoch: u64,
    },
}

impl Var {
    /// Error-state size of the variable.
    pub fn size(self) -> usize {
        match self {
            Var::Imu => 15,
            Var::TimeOffset => 1,
            Var::Extrinsic | Var::Clone(_) => 6,
            Var::Intrinsics => 8,
            Var::Feature(_) => 3,
            Var::PeerFrame { .. } => 4,
        }
    }
}

pub use super::covariance::StateError;

/// The IMU navigation state. The default is level at the origin, at rest, with
/// zero biases.
#[derive(Clone, Debug, PartialEq)]
pub struct ImuState {
    /// `R_ItoG`.
    pub rot: Matrix3<f64>,
    /// `p_IinG`, m.
    pub pos: Vector3<f64>,
    /// `v_IinG`, m/s.
    pub vel: Vector3<f64>,
    /// Gyroscope bias, rad/s.
    pub bias_gyro: Vector3<f64>,
    /// Accelerometer bias, m/s².
    pub bias_accel: Vector3<f64>,
}

impl Default for ImuState {
    fn default() -> Self {
        Self {
            rot: Matrix3::identity(),
            pos: Vector3::zeros(),
            vel: Vector3::zeros(),
            bias_gyro: Vector3::zeros(),
            bias_accel: Vector3::zeros(),
        }
    }
}

/// First estimates of the IMU pose and velocity: the values propagation last
/// produced, before any update (used by FEJ propagation).
#[derive(Clone, Debug, PartialEq)]
pub struct ImuFej {
    /// First estimate of `R_ItoG`.
    pub rot: Matrix3<f64>,
    /// First estimate of `p_IinG`.
    pub pos: Vector3<f64>,
    /// First estimate of `v_IinG`.
    pub vel: Vector3<f64>,
}

impl ImuFej {
    /// The first estimates taken at `imu`'s current values.
    pub fn of(imu: &ImuState) -> Self {
        Self {
            rot: imu.rot,
            pos: imu.pos,
            vel: imu.vel,
        }
    }
}

/// A cloned IMU pose.
#[derive(Clone, Debug, PartialEq)]
pub struct ClonePose {
    /// IMU time of the clone, s.
    pub t: f64,
    /// Camera time of the image the clone was taken for, s (its IMU time is this
    /// plus the time-offset estimate of that moment).
    pub t_cam: f64,
    /// `R_ItoG`.
    pub rot: Matrix3<f64>,
    /// `p_IinG`, m.
    pub pos: Vector3<f64>,
    /// First estimate of `R_ItoG` (the value when cloned).
    pub rot_fej: Matrix3<f64>,
    /// First estimate of `p_IinG`.
    pub pos_fej: Vector3<f64>,
}

/// A SLAM feature in the state.
#[derive(Clone, Debug, PartialEq)]
pub struct SlamFeature {
    /// `p_FinG` (global representation) or `p_FinA`, the position in the anchor
    /// clone's camera frame (anchored representation), m; with `inverse_depth`,
    /// `(α, β, ρ) = (x/z, y/z, 1/z)` of `p_FinA` (1, 1, 1/m).
    pub pos: Vector3<f64>,
    /// First estimate (the value at initialization or at the last anchor change).
    pub pos_fej: Vector3<f64>,
    /// The anchor clone of an anchored feature; `None` for a global one.
    pub anchor: Option<u64>,
    /// Whether an anchored feature's `pos` is its inverse-depth parameters.
    pub inverse_depth: bool,
}

/// The mean of a peer frame held in the state: `p_G = R_z(ψ) p_H + t`.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct PeerFrameMean {
    /// `ψ`, rad, in `(−π, π]`.
    pub yaw_rad: f64,
    /// `t`, m.
    pub t_m: Vector3<f64>,
    /// Later measurements of the frame used so far (`updater_frame`).
    pub measurements: u32,
}

/// `yaw` wrapped into `(−π, π]`.
pub fn wrap_yaw(yaw: f64) -> f64 {
    let w = yaw.rem_euclid(std::f64::consts::TAU);
    if w > std::f64::consts::PI {
        w - std::f64::consts::TAU
    } else {
        w
    }
}

/// One robot's means: its time, IMU state and first estimates, calibration,
/// clones, SLAM features and peer frames (everything but the covariance).
#[derive(Clone, Debug)]
pub struct Means {
    /// IMU time of the IMU state, s.
    pub t: f64,
    /// The IMU navigation state.
    pub imu: ImuState,
    /// First estimates of the IMU state.
    pub imu_fej: ImuFej,
    /// Current calibration estimate (whether estimated online or fixed).
    pub calib: CameraCalibration,
    /// Clones by image sequence number (oldest first).
    pub clones: BTreeMap<u64, ClonePose>,
    /// SLAM features by track id.
    pub features: BTreeMap<u64, SlamFeature>,
    /// Peers' frames by `(peer, epoch)` (`cooperation.peer_frame_state_s`).
    pub peer_frames: BTreeMap<(u32, u64), PeerFrameMean>,
}

impl Means {
    /// The means at time `t` with no clone and no feature.
    pub fn new(t: f64, imu: ImuState, calib: CameraCalibration) -> Self {
        Self {
            t,
            imu_fej: ImuFej::of(&imu),
            imu,
            calib,
            clones: BTreeMap::new(),
            features: BTreeMap::new(),
            peer_frames: BTreeMap::new(),
        }
    }

    /// Takes the current IMU state and clones as their first estimates (a
    /// filter that starts over its linearization, see
    /// `updater_msckf::rescue`).
    pub fn reset_first_estimates(&mut self) {
        self.imu_fej = ImuFej::of(&self.imu);
        for c in self.clones.values_mut() {
            c.rot_fej = c.rot;
            c.pos_fej = c.pos;
        }
    }

    /// Applies the part of an error-state correction that belongs to `var`, found
    /// at offset `o` of `dx` (boxplus).
    pub fn apply(&mut self, var: Var, o: usize, dx: &DVector<f64>) {
        let d = |i: usize| Vector3::new(dx[o + i], dx[o + i + 1], dx[o + i + 2]);
        match var {
            Var::Imu => {
                self.imu.rot *= exp_so3(&d(0));
                self.imu.pos += d(3);
                self.imu.vel += d(6);
                self.imu.bias_gyro += d(9);
                self.imu.bias_accel += d(12);
            }
            Var::TimeOffset => self.calib.time_offset_s += dx[o],
            Var::Extrinsic => {
                self.calib.rot_c_to_i *= exp_so3(&d(0));
                self.calib.p_c_in_i += d(3);
            }
            Var::Intrinsics => {
                for i in 0..4 {
                    self.calib.camera.intrinsics[i] += dx[o + i];
                    self.calib.camera.distortion[i] += dx[o + 4 + i];
                }
            }
            Var::Clone(key) => {
                if let Some(c) = self.clones.get_mut(&key) {
                    c.rot *= exp_so3(&d(0));
                    c.pos += d(3);
                }
            }
            Var::Feature(id) => {
                if let Some(f) = self.features.get_mut(&id) {
                    f.pos += d(0);
                }
            }
            Var::PeerFrame { peer, epoch } => {
                if let Some(a) = self.peer_frames.get_mut(&(peer, epoch)) {
                    a.yaw_rad = wrap_yaw(a.yaw_rad + dx[o]);
                    a.t_m += d(1);
                }
            }
        }
    }

    /// The error state `δ` over `vars` (in that order) with `self = base ⊞ δ`
    /// (the inverse of [`Means::apply`]); a variable either lacks is zero.
    pub fn boxminus(&self, base: &Means, vars: &[Var]) -> DVector<f64> {
        let n: usize = vars.iter().map(|v| v.size()).sum();
        let mut d = DVector::zeros(n);
        let mut o = 0;
        for v in vars {
            let mut put = |i: usize, x: Vector3<f64>| d.fixed_rows_mut::<3>(o + i).copy_from(&x);
            match v {
                Var::Imu => {
                    put(0, log_so3(&(base.imu.rot.transpose() * self.imu.rot)));
                    put(3, self.imu.pos - base.imu.pos);
                    put(6, self.imu.vel - base.imu.vel);
                    put(9, self.imu.bias_gyro - base.imu.bias_gyro);
                    put(12, self.imu.bias_accel - base.imu.bias_accel);
                }
                Var::TimeOffset => d[o] = self.calib.time_offset_s - base.calib.time_offset_s,
                Var::Extrinsic => {
                    put(
                        0,
                        log_so3(&(base.calib.rot_c_to_i.transpose() * self.calib.rot_c_to_i)),
                    );
                    put(3, self.calib.p_c_in_i - base.calib.p_c_in_i);
                }
                Var::Intrinsics => {
                    for i in 0..4 {
                        d[o + i] =
                            self.calib.camera.intrinsics[i] - base.calib.camera.intrinsics[i];
                        d[o + 4 + i] =
                            self.calib.camera.distortion[i] - base.calib.camera.distortion[i];
                    }
                }
                Var::Clone(key) => {
                    if let (Some(a), Some(b)) = (self.clones.get(key), base.clones.get(key)) {
                        put(0, log_so3(&(b.rot.transpose() * a.rot)));
                        put(3, a.pos - b.pos);
                    }
                }
                Var::Feature(id) => {
                    if let (Some(a), Some(b)) = (self.features.get(id), base.features.get(id)) {
                        put(0, a.pos - b.pos);
                    }
                }
                Var::PeerFrame { peer, epoch } => {
                    let k = (*peer, *epoch);
                    if let (Some(a), Some(b)) = (self.peer_frames.get(&k), base.peer_frames.get(&k))
                    {
                        put(1, a.t_m - b.t_m);
                        d[o] = wrap_yaw(a.yaw_rad - b.yaw_rad);
                    }
                }
            }
            o += v.size();
        }
        d
    }

    /// Forgets the mean of a marginalized variable.
    pub fn forget(&mut self, var: Var) {
        match var {
            Var::Clone(key) => {
                self.clones.remove(&key);
            }
            Var::Feature(id) => {
                self.features.remove(&id);
            }
            Var::PeerFrame { peer, epoch } => {
                self.peer_frames.remove(&(peer, epoch));
            }
            _ => {}
        }
    }
}

/// One robot's filter state: its means and their joint covariance.
#[derive(Clone, Debug)]
pub struct State {
    /// The means (also reachable directly: `state.imu`, `state.clones`, ...).
    pub means: Means,
    cov: Covariance<Var>,
}

impl Deref for State {
    type Target = Means;
    fn deref(&self) -> &Means {
        &self.means
    }
}

impl DerefMut for State {
    fn deref_mut(&mut self) -> &mut Means {
        &mut self.means
    }
}

impl StateVar for Var {
    fn size(self) -> usize {
        Var::size(self)
    }
}

impl State {
    /// A state with the IMU block (covariance `imu_cov`, 15x15) and the calibration
    /// variables listed in `calib_vars` with their prior covariances.
    pub fn new(
        t: f64,
        imu: ImuState,
        imu_cov: DMatrix<f64>,
        calib: CameraCalibration,
        calib_vars: &[(Var, DMatrix<f64>)],
    ) -> Self {
        let mut cov = Covariance::default();
        cov.append(Var::Imu, &imu_cov);
        for (v, c) in calib_vars {
            cov.append(*v, c);
        }
        Self {
            means: Means::new(t, imu, calib),
            cov,
        }
    }

    /// The covariance with its variable index.
    pub fn covariance(&self) -> &Covariance<Var> {
        &self.cov
    }

    /// Total error-state dimension.
    pub fn dim(&self) -> usize {
        self.cov.dim()
    }

    /// The joint covariance matrix.
    pub fn cov(&self) -> &DMatrix<f64> {
        self.cov.matrix()
    }

    /// Offset of `var` in the covariance.
    pub fn offset(&self, var: Var) -> Option<usize> {
        self.cov.offset(var)
    }

    /// Whether `var` is in the state.
    pub fn has(&self, var: Var) -> bool {
        self.cov.has(var)
    }

    /// Variables in covariance order.
    pub fn vars(&self) -> impl Iterator<Item = Var> + '_ {
        self.cov.index().iter().map(|(v, _)| *v)
    }

    /// Covariance block of `(a, b)`.
    pub fn block(&self, a: Var, b: Var) -> Option<DMatrix<f64>> {
        self.cov.block(a, b)
    }

    /// Replaces the covariance; it must keep its size.
    pub fn set_cov(&mut self, cov: DMatrix<f64>) -> Result<(), StateError> {
        self.cov.set(cov)
    }

    /// Mutable access for propagation, which updates the IMU rows and columns.
    pub(crate) fn cov_mut(&mut self) -> &mut DMatrix<f64> {
        self.cov.matrix_mut()
    }

    /// Adds `new` as a linear function of existing variables (see
    /// [`Covariance::augment`]).
    pub fn augment(
        &mut self,
        new: Var,
        jac: &[(Var, DMatrix<f64>)],
        noise: &DMatrix<f64>,
    ) -> Result<(), StateError> {
        self.cov.augment(new, jac, noise)
    }

    /// Adds `new` with a given covariance block and cross-covariance (see
    /// [`Covariance::insert_with_cross`]).
    pub fn insert_with_cross(
        &mut self,
        new: Var,
        p_nn: &DMatrix<f64>,
        cross: &DMatrix<f64>,
    ) -> Result<(), StateError> {
        self.cov.insert_with_cross(new, p_nn, cross)
    }

    /// A change of variables (see [`Covariance::transform`]); the mean is the
    /// caller's to set.
    pub fn transform(&mut self, var: Var, jac: &[(Var, DMatrix<f64>)]) -> Result<(), StateError> {
        self.cov.transform(var, jac)
    }

    /// Removes `var`: its rows and columns and its mean (marginalization).
    pub fn marginalize(&mut self, var: Var) -> Result<(), StateError> {
        self.cov.remove(var)?;
        self.means.forget(var);
        Ok(())
    }

    /// `H P Hᵀ + R` and `P Hᵀ` (see [`Covariance::innovation`]).
    pub fn innovation(
        &self,
        vars: &[Var],
        h: &DMatrix<f64>,
        r: &DMatrix<f64>,
    ) -> Result<(DMatrix<f64>, DMatrix<f64>), StateError> {
        self.cov.innovation(vars, h, r)
    }

    /// Mahalanobis distance of a residual (see [`Covariance::mahalanobis`]).
    pub fn mahalanobis(
        &self,
        vars: &[Var],
        h: &DMatrix<f64>,
        res: &DVector<f64>,
        r: &DMatrix<f64>,
    ) -> Result<f64, StateError> {
        self.cov.mahalanobis(vars, h, res, r)
    }

    /// EKF update with a sparse Jacobian whose columns are `vars` in order,
    /// residual `res = z - h(x̂)` and noise covariance `r`; the correction is
    /// applied to the means.
    pub fn ekf_update(
        &mut self,
        vars: &[Var],
        h: &DMatrix<f64>,
        res: &DVector<f64>,
        r: &DMatrix<f64>,
    ) -> Result<(), StateError> {
        let dx = self.cov.ekf_update(vars, h, res, r)?;
        self.apply_correction(&dx);
        Ok(())
    }

    /// EKF update of independently gated blocks of rows from one innovation (see
    /// [`Covariance::gated_ekf_update`]); the correction is applied to the means.
    /// Returns which blocks were used.
    pub fn gated_ekf_update(
        &mut self,
        vars: &[Var],
        h: &DMatrix<f64>,
        res: &DVector<f64>,
        r: &DMatrix<f64>,
        block: usize,
        threshold: f64,
    ) -> Result<Vec<bool>, StateError> {
        let out = self
            .cov
            .gated_ekf_update(vars, h, res, r, block, threshold)?;
        if let Some(dx) = &out.dx {
            self.apply_correction(dx);
        }
        Ok(out.accepted)
    }

    /// CI-EKF update (thesis Eqs. 5.15-5.17, see [`Covariance::ci_update`]); only
    /// this robot's state and covariance change.
    pub fn ci_update(
        &mut self,
        vars: &[Var],
        h: &DMatrix<f64>,
        res: &DVector<f64>,
        r_others: &DMatrix<f64>,
        omega: f64,
    ) -> Result<(), StateError> {
        let dx = self.cov.ci_update(vars, h, res, r_others, omega)?;
        self.apply_correction(&dx);
        Ok(())
    }

    /// The tail of a CI-EKF update whose pieces are already computed: innovation
    /// covariance `s` (with the `1/ω` inflation) and `P Hᵀ / ω`; with
    /// `unobserved = Some(Bᵀ)`, of the split prior `P / ω − (1/ω − 1) B Bᵀ`.
    pub(crate) fn ci_apply(
        &mut self,
        s: DMatrix<f64>,
        pht_over_omega: &DMatrix<f64>,
        res: &DVector<f64>,
        omega: f64,
        unobserved: Option<&DMatrix<f64>>,
    ) -> Result<(), StateError> {
        let dx = self
            .cov
            .kalman_update(s, pht_over_omega, res, omega, unobserved)?;
        self.apply_correction(&dx);
        Ok(())
    }

    /// EKF update that also returns the correction it applied.
    pub fn ekf_update_dx(
        &mut self,
        vars: &[Var],
        h: &DMatrix<f64>,
        res: &DVector<f64>,
        r: &DMatrix<f64>,
    ) -> Result<DVector<f64>, StateError> {
        let dx = self.cov.ekf_update(vars, h, res, r)?;
        self.apply_correction(&dx);
        Ok(dx)
    }

    /// Adds `new` from an invertible linearized measurement (delayed
    /// initialization, see [`Covariance::initialize_invertible`]); returns the
    /// mean correction for the caller to apply.
    pub fn initialize_invertible(
        &mut self,
        new: Var,
        vars: &[Var],
        h_x: &DMatrix<f64>,
        h_f: &DMatrix<f64>,
        res: &DVector<f64>,
        sigma2: f64,
    ) -> Result<DVector<f64>, StateError> {
        self.cov
            .initialize_invertible(new, vars, h_x, h_f, res, sigma2)
    }

    /// Applies an error-state correction `δx` to every variable (boxplus).
    pub fn apply_correction(&mut self, dx: &DVector<f64>) {
        for &(var, o) in self.cov.index() {
            self.means.apply(var, o, dx);
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn test_state() -> State {
        let imu = ImuState::default();
        let cov = DMatrix::from_fn(
            15,
            15,
            |i, j| if i == j { 0.1 + i as f64 * 0.01 } else { 0.001 },
        );
        State::new(
            0.0,
            imu,
            cov,
            CameraCalibration::euroc_cam0(),
            &[(Var::TimeOffset, DMatrix::from_element(1, 1, 1e-4))],
        )
    }

    #[test]
    fn augmenting_with_a_copy_gives_perfect_correlation() {
        let mut s = test_state();
        let mut j = DMatrix::zeros(6, 15);
        j.view_mut((0, 0), (6, 6)).fill_with_identity();
        s.augment(Var::Clone(1), &[(Var::Imu, j)], &DMatrix::zeros(6, 6))
            .unwrap();
        let pc = s.block(Var::Clone(1), Var::Clone(1)).unwrap();
        let pi = s
            .block(Var::Imu, Var::Imu)
            .unwrap()
            .view((0, 0), (6, 6))
            .into_owned();
        assert!((pc - &pi).norm() < 1e-15);
        let cross = s
            .block(Var::Clone(1), Var::Imu)
            .unwrap()
            .view((0, 0), (6, 6))
            .into_owned();
        assert!((cross - pi).norm() < 1e-15);
        assert_eq!(s.dim(), 22);
    }

    #[test]
    fn marginalizing_removes_rows_and_keeps_other_blocks() {
        let mut s = test_state();
        let j = DMatrix::from_fn(6, 15, |i, k| if i == k { 1.0 } else { 0.0 });
        s.augment(
            Var::Clone(1),
            &[(Var::Imu, j.clone())],
            &DMatrix::identity(6, 6),
        )
        .unwrap();
        s.augment(
            Var::Clone(2),
            &[(Var::Imu, j)],
            &(DMatrix::identity(6, 6) * 2.0),
        )
        .unwrap();
        let before = s.block(Var::Clone(2), Var::Imu).unwrap();
        s.marginalize(Var::Clone(1)).unwrap();
        assert_eq!(s.dim(), 22);
        assert!(!s.has(Var::Clone(1)));
        assert_eq!(s.block(Var::Clone(2), Var::Imu).unwrap(), before);
        assert_eq!(s.offset(Var::Clone(2)), Some(16));
    }

    #[test]
    fn an_update_matches_the_dense_kalman_equations() {
        let mut s = test_state();
        let n = s.dim();
        let mut h_dense = DMatrix::zeros(2, n);
        let h = DMatrix::from_row_slice(2, 3, &[1.0, 0.5, 0.0, 0.0, 1.0, 2.0]);
        h_dense.view_mut((0, 3), (2, 3)).copy_from(&h); // the IMU position block
        let hs = {
            let mut m = DMatrix::zeros(2, 15);
            m.view_mut((0, 3), (2, 3)).copy_from(&h);
            m
        };
        let r = DMatrix::identity(2, 2) * 0.01;
        let res = DVector::from_vec(vec![0.1, -0.2]);
        let p = s.cov().clone();
        let sm = &h_dense * &p * h_dense.transpose() + &r;
        let k = &p * h_dense.transpose() * sm.clone().try_inverse().unwrap();
        let p_expected = &p - &k * &h_dense * &p;
        let dx = &k * &res;
        s.ekf_update(&[Var::Imu], &hs, &res, &r).unwrap();
        assert!((s.cov() - p_expected).norm() < 1e-12);
        assert!((s.imu.pos - Vector3::new(dx[3], dx[4], dx[5])).norm() < 1e-12);
        assert!((s.calib.time_offset_s - dx[15]).abs() < 1e-12);
    }

    #[test]
    fn a_jacobian_naming_an_absent_variable_is_an_error() {
        let mut s = test_state();
        let h = DMatrix::zeros(2, 6);
        let e = s
            .ekf_update(
                &[Var::Clone(9)],
                &h,
                &DVector::zeros(2),
                &DMatrix::identity(2, 2),
            )
            .unwrap_err();
        assert_eq!(e, StateError::Missing(Var::Clone(9)));
    }

    /// `boxminus` undoes `apply`: `(x ⊞ δ) ⊟ x = δ` for every kind of variable.
    #[test]
    fn boxminus_is_the_inverse_of_apply() {
        let mut x = test_state();
        x.augment(Var::Clone(3), &[], &DMatrix::identity(6, 6)).ok();
        x.means.clones.insert(
            3,
            ClonePose {
                t: 0.1,
                t_cam: 0.1,
                rot: exp_so3(&Vector3::new(0.3, -0.2, 1.0)),
                pos: Vector3::new(1.0, 2.0, 3.0),
                rot_fej: Matrix3::identity(),
                pos_fej: Vector3::zeros(),
            },
        );
        let vars: Vec<Var> = x.cov.index().iter().map(|(v, _)| *v).collect();
        let n: usize = vars.iter().map(|v| v.size()).sum();
        let delta = DVector::from_fn(n, |i, _| 0.01 * ((i * 7 % 11) as f64 - 5.0));
        let mut y = x.means.clone();
        for &(var, o) in x.cov.index() {
            y.apply(var, o, &delta);
        }
        let back = y.boxminus(&x.means, &vars);
        assert!((back - delta).abs().max() < 1e-12);
    }
}
