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

use common::calibration::CameraCalibration;
use common::so3::exp_so3;
use nalgebra::{DMatrix, DVector, Matrix3, Vector3};
use std::collections::BTreeMap;
use thiserror::Error;

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
        }
    }
}

/// Why an EKF operation failed; the state is left unchanged.
#[derive(Debug, Error, PartialEq)]
pub enum StateError {
    /// A Jacobian names a variable that is not in the state.
    #[error("variable {0:?} is not in the state")]
    Missing(Var),
    /// A variable is added twice.
    #[error("variable {0:?} is already in the state")]
    Duplicate(Var),
    /// The innovation covariance is not positive definite.
    #[error("innovation covariance is not positive definite")]
    NotPositiveDefinite,
    /// Jacobian, residual and noise sizes disagree.
    #[error("dimension mismatch: {0}")]
    Dimension(String),
}

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
    /// clone's camera frame (anchored representation), m.
    pub pos: Vector3<f64>,
    /// First estimate (the value at initialization or at the last anchor change).
    pub pos_fej: Vector3<f64>,
    /// The anchor clone of an anchored feature; `None` for a global one.
    pub anchor: Option<u64>,
}

/// The whole filter state: means, first estimates and the joint covariance.
#[derive(Clone, Debug)]
pub struct State {
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
    cov: DMatrix<f64>,
    /// Variables in covariance order with their offsets.
    index: Vec<(Var, usize)>,
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
        let mut s = Self {
            t,
            imu_fej: ImuFej {
                rot: imu.rot,
                pos: imu.pos,
                vel: imu.vel,
            },
            imu,
            calib,
            clones: BTreeMap::new(),
            features: BTreeMap::new(),
            cov: DMatrix::zeros(0, 0),
            index: Vec::new(),
        };
        s.append(Var::Imu, &imu_cov);
        for (v, c) in calib_vars {
            s.append(*v, c);
        }
        s
    }

    fn append(&mut self, var: Var, block: &DMatrix<f64>) {
        let n = self.cov.nrows();
        let k = var.size();
        let mut cov = DMatrix::zeros(n + k, n + k);
        cov.view_mut((0, 0), (n, n)).copy_from(&self.cov);
        cov.view_mut((n, n), (k, k)).copy_from(block);
        self.cov = cov;
        self.index.push((var, n));
    }

    /// Total error-state dimension.
    pub fn dim(&self) -> usize {
        self.cov.nrows()
    }

    /// The joint covariance.
    pub fn cov(&self) -> &DMatrix<f64> {
        &self.cov
    }

    /// Offset of `var` in the covariance.
    pub fn offset(&self, var: Var) -> Option<usize> {
        self.index.iter().find(|(v, _)| *v == var).map(|(_, o)| *o)
    }

    /// Whether `var` is in the state.
    pub fn has(&self, var: Var) -> bool {
        self.offset(var).is_some()
    }

    /// Variables in covariance order.
    pub fn vars(&self) -> impl Iterator<Item = Var> + '_ {
        self.index.iter().map(|(v, _)| *v)
    }

    /// Covariance block of `(a, b)`.
    pub fn block(&self, a: Var, b: Var) -> Option<DMatrix<f64>> {
        let (oa, ob) = (self.offset(a)?, self.offset(b)?);
        Some(self.cov.view((oa, ob), (a.size(), b.size())).into_owned())
    }

    /// Replaces the covariance (propagation writes the whole matrix); must keep size.
    pub fn set_cov(&mut self, cov: DMatrix<f64>) -> Result<(), StateError> {
        if cov.shape() != self.cov.shape() {
            return Err(StateError::Dimension(format!(
                "covariance {:?} != {:?}",
                cov.shape(),
                self.cov.shape()
            )));
        }
        self.cov = cov;
        Ok(())
    }

    /// Mutable access for propagation, which updates the IMU rows and columns.
    pub(crate) fn cov_mut(&mut self) -> &mut DMatrix<f64> {
        &mut self.cov
    }

    fn offsets(&self, vars: &[Var]) -> Result<Vec<(usize, usize)>, StateError> {
        vars.iter()
            .map(|v| {
                self.offset(*v)
                    .map(|o| (o, v.size()))
                    .ok_or(StateError::Missing(*v))
            })
            .collect()
    }

    /// Adds `new` as a linear function of existing variables,
    /// `x_new = Σ J_i x_i + n`, `n ~ N(0, noise)`: the augmentation of clones and
    /// of features. `jac` holds `(var_i, J_i)` with `J_i` of size `new.size() x var_i.size()`.
    pub fn augment(
        &mut self,
        new: Var,
        jac: &[(Var, DMatrix<f64>)],
        noise: &DMatrix<f64>,
    ) -> Result<(), StateError> {
        if self.has(new) {
            return Err(StateError::Duplicate(new));
        }
        let (m, p_nn) = self.linear_map(new.size(), jac)?;
        self.insert_with_cross(new, &(p_nn + noise), &m)
    }

    /// For `x' = Σ J_i x_i` (each `J_i` of `k` rows): `M = Σ J_i P[x_i, :]` (the
    /// cross-covariance of `x'` with the state, `k x dim`) and `P' = Σ M[:, x_i] J_iᵀ`.
    fn linear_map(
        &self,
        k: usize,
        jac: &[(Var, DMatrix<f64>)],
    ) -> Result<(DMatrix<f64>, DMatrix<f64>), StateError> {
        let n = self.dim();
        let mut m = DMatrix::zeros(k, n);
        for (v, j) in jac {
            let o = self.offset(*v).ok_or(StateError::Missing(*v))?;
            if j.shape() != (k, v.size()) {
                return Err(StateError::Dimension(format!("Jacobian for {v:?}")));
            }
            m += j * self.cov.view((o, 0), (v.size(), n));
        }
        let mut p_nn = DMatrix::zeros(k, k);
        for (v, j) in jac {
            let o = self.offset(*v).ok_or(StateError::Missing(*v))?;
            p_nn += m.view((0, o), (k, v.size())) * j.transpose();
        }
        Ok((m, p_nn))
    }

    /// Adds `new` with a given covariance block and cross-covariance with the
    /// existing state (`cross`: `new.size() x dim`), as delayed initialization needs.
    pub fn insert_with_cross(
        &mut self,
        new: Var,
        p_nn: &DMatrix<f64>,
        cross: &DMatrix<f64>,
    ) -> Result<(), StateError> {
        if self.has(new) {
            return Err(StateError::Duplicate(new));
        }
        let n = self.dim();
        let k = new.size();
        if cross.shape() != (k, n) || p_nn.shape() != (k, k) {
            return Err(StateError::Dimension("insert_with_cross".into()));
        }
        let mut cov = DMatrix::zeros(n + k, n + k);
        cov.view_mut((0, 0), (n, n)).copy_from(&self.cov);
        cov.view_mut((n, 0), (k, n)).copy_from(cross);
        cov.view_mut((0, n), (n, k)).copy_from(&cross.transpose());
        cov.view_mut((n, n), (k, k))
            .copy_from(&(0.5 * (p_nn + p_nn.transpose())));
        self.cov = cov;
        self.index.push((new, n));
        Ok(())
    }

    /// Replaces `var` by a linear function of itself and other variables,
    /// `x' = Σ J_i x_i` (the list must include `var` itself): a change of variables,
    /// such as re-anchoring a feature. The mean is the caller's to set.
    pub fn transform(&mut self, var: Var, jac: &[(Var, DMatrix<f64>)]) -> Result<(), StateError> {
        let o = self.offset(var).ok_or(StateError::Missing(var))?;
        let (n, k) = (self.dim(), var.size());
        let (m, p_nn) = self.linear_map(k, jac)?;
        self.cov.view_mut((o, 0), (k, n)).copy_from(&m);
        self.cov.view_mut((0, o), (n, k)).copy_from(&m.transpose());
        self.cov
            .view_mut((o, o), (k, k))
            .copy_from(&(0.5 * (&p_nn + p_nn.transpose())));
        Ok(())
    }

    /// Removes `var` and its rows and columns (marginalization).
    pub fn marginalize(&mut self, var: Var) -> Result<(), StateError> {
        let o = self.offset(var).ok_or(StateError::Missing(var))?;
        let k = var.size();
        let cov = std::mem::replace(&mut self.cov, DMatrix::zeros(0, 0));
        self.cov = cov.remove_rows(o, k).remove_columns(o, k);
        self.index.retain(|(v, _)| *v != var);
        for (_, off) in self.index.iter_mut() {
            if *off > o {
                *off -= k;
            }
        }
        match var {
            Var::Clone(key) => {
                self.clones.remove(&key);
            }
            Var::Feature(id) => {
                self.features.remove(&id);
            }
            _ => {}
        }
        Ok(())
    }

    /// The covariance block of the variables at `offs` (`c x c`).
    fn gather_block(&self, offs: &[(usize, usize)], size: usize) -> DMatrix<f64> {
        let mut out = DMatrix::zeros(size, size);
        let mut c = 0;
        for &(oc, kc) in offs {
            let mut r = 0;
            for &(or, kr) in offs {
                out.view_mut((r, c), (kr, kc))
                    .copy_from(&self.cov.view((or, oc), (kr, kc)));
                r += kr;
            }
            c += kc;
        }
        out
    }

    fn checked_offsets(
        &self,
        vars: &[Var],
        h: &DMatrix<f64>,
        r: &DMatrix<f64>,
    ) -> Result<(Vec<(usize, usize)>, usize), StateError> {
        let offs = self.offsets(vars)?;
        let cols: usize = offs.iter().map(|(_, k)| k).sum();
        if h.ncols() != cols || r.shape() != (h.nrows(), h.nrows()) {
            return Err(StateError::Dimension(format!(
                "H {:?} for {cols} columns, R {:?}",
                h.shape(),
                r.shape()
            )));
        }
        Ok((offs, cols))
    }

    /// `H P Hᵀ + R` and `P Hᵀ` for a sparse Jacobian whose columns are the
    /// variables `vars` in order. Each variable's block of `H` is multiplied with
    /// that variable's columns of `P` only over the rows where the block is not
    /// zero: a SLAM feature's block touches two rows, not the whole stack.
    pub fn innovation(
        &self,
        vars: &[Var],
        h: &DMatrix<f64>,
        r: &DMatrix<f64>,
    ) -> Result<(DMatrix<f64>, DMatrix<f64>), StateError> {
        let (offs, _) = self.checked_offsets(vars, h, r)?;
        let (n, m) = (self.dim(), h.nrows());
        let mut pht = DMatrix::zeros(n, m);
        let mut s = r.clone();
        let mut blocks = Vec::with_capacity(offs.len());
        let mut c = 0;
        for &(o, k) in &offs {
            let hj = h.columns(c, k);
            c += k;
            let rows: Vec<usize> = (0..m)
                .filter(|&i| hj.row(i).iter().any(|v| *v != 0.0))
                .collect();
            if rows.is_empty() {
                continue;
            }
            let p_j = self.cov.columns(o, k);
            if rows.len() == m {
                pht.gemm(1.0, &p_j, &hj.transpose(), 1.0);
                blocks.push((o, k, rows, hj.into_owned()));
            } else {
                let mut hc = DMatrix::zeros(rows.len(), k);
                for (ri, &i) in rows.iter().enumerate() {
                    hc.row_mut(ri).copy_from(&hj.row(i));
                }
                let part = p_j * hc.transpose();
                for (ri, &i) in rows.iter().enumerate() {
                    let mut col = pht.column_mut(i);
                    col += part.column(ri);
                }
                blocks.push((o, k, rows, hc));
            }
        }
        // S = Σ_j H_j (P Hᵀ)[var_j rows] over each block's nonzero rows.
        for (o, k, rows, hc) in &blocks {
            let part = hc * pht.rows(*o, *k);
            if rows.len() == m {
                s += part;
            } else {
                for (ri, &i) in rows.iter().enumerate() {
                    let mut row = s.row_mut(i);
                    row += part.row(ri);
                }
            }
        }
        Ok((s, pht))
    }

    /// Mahalanobis distance `rᵀ S⁻¹ r` of a residual under a sparse Jacobian; only
    /// the covariance block of the involved variables is touched.
    pub fn mahalanobis(
        &self,
        vars: &[Var],
        h: &DMatrix<f64>,
        res: &DVector<f64>,
        r: &DMatrix<f64>,
    ) -> Result<f64, StateError> {
        let (offs, cols) = self.checked_offsets(vars, h, r)?;
        let p_vv = self.gather_block(&offs, cols);
        let s = h * p_vv * h.transpose() + r;
        let chol = s.cholesky().ok_or(StateError::NotPositiveDefinite)?;
        Ok(res.dot(&chol.solve(res)))
    }

    /// EKF update with a sparse Jacobian `h` whose columns are `vars` in order,
    /// residual `res = z - h(x̂)` and noise covariance `r`.
    pub fn ekf_update(
        &mut self,
        vars: &[Var],
        h: &DMatrix<f64>,
        res: &DVector<f64>,
        r: &DMatrix<f64>,
    ) -> Result<(), StateError> {
        if res.len() != h.nrows() {
            return Err(StateError::Dimension("residual length".into()));
        }
        let (s, pht) = self.innovation(vars, h, r)?;
        self.apply_update(s, &pht, res, 1.0)
    }

    /// CI-EKF update (thesis Eqs. 5.15-5.17): this robot's prior covariance is
    /// inflated to `P / ω` and the innovation covariance is
    /// `S = H P Hᵀ / ω + r_others`, where `r_others` already holds the peers'
    /// terms `Σ H_o P_o H_oᵀ / ω_o` and the measurement noise. Only this robot's
    /// state and covariance change: `δx = P Hᵀ S⁻¹ r / ω`,
    /// `P ← P / ω − P Hᵀ S⁻¹ H P / ω²`.
    pub fn ci_update(
        &mut self,
        vars: &[Var],
        h: &DMatrix<f64>,
        res: &DVector<f64>,
        r_others: &DMatrix<f64>,
        omega: f64,
    ) -> Result<(), StateError> {
        if res.len() != h.nrows() {
            return Err(StateError::Dimension("residual length".into()));
        }
        if !(omega > 0.0 && omega <= 1.0) {
            return Err(StateError::Dimension(format!(
                "CI weight {omega} not in (0, 1]"
            )));
        }
        let zero = DMatrix::zeros(h.nrows(), h.nrows());
        let (hph, pht) = self.innovation(vars, h, &zero)?;
        let s = hph / omega + r_others;
        self.apply_update(s, &(pht / omega), res, omega)
    }

    /// The common tail of the updates: with `S = L Lᵀ` and
    /// `W = L⁻¹ (P' Hᵀ)ᵀ` for the prior `P' = P / ω`: `P ← P' − Wᵀ W`,
    /// `δx = Wᵀ L⁻¹ r`. `L⁻¹` is small (m x m); forming it makes `W` one dense
    /// product.
    fn apply_update(
        &mut self,
        s: DMatrix<f64>,
        pht: &DMatrix<f64>,
        res: &DVector<f64>,
        omega: f64,
    ) -> Result<(), StateError> {
        let chol = s.cholesky().ok_or(StateError::NotPositiveDefinite)?;
        let l_inv = lower_triangular_inverse(&chol.l());
        let w = &l_inv * pht.transpose();
        let lr = &l_inv * res;
        let dx = w.tr_mul(&lr);
        if omega != 1.0 {
            self.cov /= omega;
        }
        self.subtract_gram_lower(&w);
        self.cov.fill_upper_triangle_with_lower_triangle();
        self.floor_diagonal();
        self.apply_correction(&dx);
        Ok(())
    }

    /// `P ← P − Wᵀ W` on the lower triangle only (the result is symmetric), in
    /// column blocks so each block is one dense product: about half the work.
    fn subtract_gram_lower(&mut self, w: &DMatrix<f64>) {
        const BLOCK: usize = 32;
        let n = self.dim();
        let w_t = w.transpose();
        let mut j0 = 0;
        while j0 < n {
            let bw = BLOCK.min(n - j0);
            let mut blk = self.cov.view_mut((j0, j0), (n - j0, bw));
            blk.gemm(-1.0, &w_t.rows(j0, n - j0), &w.columns(j0, bw), 1.0);
            j0 += bw;
        }
    }

    /// Keeps the diagonal positive.
    fn floor_diagonal(&mut self) {
        for i in 0..self.dim() {
            if self.cov[(i, i)] < 1e-18 {
                self.cov[(i, i)] = 1e-18;
            }
        }
    }

    /// Adds `new` from an invertible linearized measurement
    /// `r₁ = H_x δx + H_f δx_new + n`, `n ~ N(0, σ² I)` (delayed initialization,
    /// thesis Eqs. 2.41-2.45): `x̂_new += H_f⁻¹ r₁`,
    /// `P_new = H_f⁻¹ (H_x P H_xᵀ + σ² I) H_f⁻ᵀ`, `P_new,x = −H_f⁻¹ H_x P`.
    /// The caller has already stored the variable's mean; the correction `H_f⁻¹ r₁`
    /// is returned for it to apply.
    pub fn initialize_invertible(
        &mut self,
        new: Var,
        vars: &[Var],
        h_x: &DMatrix<f64>,
        h_f: &DMatrix<f64>,
        res: &DVector<f64>,
        sigma2: f64,
    ) -> Result<DVector<f64>, StateError> {
        let k = new.size();
        if h_f.shape() != (k, k) || h_x.nrows() != k || res.len() != k {
            return Err(StateError::Dimension("initialize_invertible".into()));
        }
        let h_inv = h_f
            .clone()
            .try_inverse()
            .ok_or(StateError::NotPositiveDefinite)?;
        let r = DMatrix::identity(k, k) * sigma2;
        let (s, pht) = self.innovation(vars, h_x, &r)?;
        let p_nn = &h_inv * s * h_inv.transpose();
        let cross = -(&h_inv * pht.transpose());
        self.insert_with_cross(new, &p_nn, &cross)?;
        Ok(h_inv * res)
    }

    /// Applies an error-state correction `δx` to every variable (boxplus).
    pub fn apply_correction(&mut self, dx: &DVector<f64>) {
        for &(var, o) in &self.index {
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
            }
        }
    }
}

/// Inverse of a lower-triangular matrix with a positive diagonal, by forward
/// substitution on its columns (`m³/6` multiply-adds, contiguous accesses).
fn lower_triangular_inverse(l: &DMatrix<f64>) -> DMatrix<f64> {
    let m = l.nrows();
    let mut inv = DMatrix::<f64>::zeros(m, m);
    let ls = l.as_slice();
    for (j, x) in inv.as_mut_slice().chunks_exact_mut(m.max(1)).enumerate() {
        // Column j of L⁻¹ solves L x = e_j; x is zero above j.
        x[j] = 1.0;
        for k in j..m {
            let lk = &ls[k * m..(k + 1) * m];
            let xk = x[k] / lk[k];
            x[k] = xk;
            for i in (k + 1)..m {
                x[i] -= lk[i] * xk;
            }
        }
    }
    inv
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
    fn lower_triangular_inverse_is_exact() {
        let a = DMatrix::from_fn(7, 7, |i, j| {
            1.0 / (1.0 + i as f64 + j as f64) + if i == j { 1.0 } else { 0.0 }
        });
        let l = a.cholesky().unwrap().l();
        let inv = lower_triangular_inverse(&l);
        assert!((&l * &inv - DMatrix::identity(7, 7)).norm() < 1e-12);
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
}
