//! The type-indexed covariance (thesis Section 2.3.1), generic over the variable
//! type: one robot's variables ([`super::state::Var`]) or, in the centralized
//! estimator, every robot's (`(robot, Var)`).
//!
//! Every variable knows its offset and size in the matrix. This is the only code
//! that touches the covariance: augmentation, change of variables,
//! marginalization, and the EKF / CI-EKF updates with a sparse Jacobian that names
//! the variables it involves. Updates return the error-state correction `δx`; the
//! owner of the means applies it (boxplus).

use nalgebra::{DMatrix, DVector};
use std::fmt::Debug;
use thiserror::Error;

/// A state variable as the covariance sees it: a key with an error-state size.
pub trait StateVar: Copy + Eq + Debug {
    /// Error-state size.
    fn size(self) -> usize;
}

/// Why a covariance operation failed; the covariance is left unchanged.
#[derive(Debug, Error, PartialEq)]
pub enum StateError<K: Debug = super::state::Var> {
    /// A Jacobian names a variable that is not in the state.
    #[error("variable {0:?} is not in the state")]
    Missing(K),
    /// A variable is added twice.
    #[error("variable {0:?} is already in the state")]
    Duplicate(K),
    /// The innovation covariance is not positive definite.
    #[error("innovation covariance is not positive definite")]
    NotPositiveDefinite,
    /// Jacobian, residual and noise sizes disagree.
    #[error("dimension mismatch: {0}")]
    Dimension(String),
}

/// `(offset, size)` of each variable of a Jacobian, in column order.
type Offsets = Vec<(usize, usize)>;

/// A joint covariance with its variable index.
#[derive(Clone, Debug)]
pub struct Covariance<K> {
    cov: DMatrix<f64>,
    /// Variables in covariance order with their offsets.
    index: Vec<(K, usize)>,
}

impl<K: StateVar> Default for Covariance<K> {
    fn default() -> Self {
        Self {
            cov: DMatrix::zeros(0, 0),
            index: Vec::new(),
        }
    }
}

impl<K: StateVar> Covariance<K> {
    /// Appends `var`, uncorrelated with the rest, with covariance `block`.
    pub fn append(&mut self, var: K, block: &DMatrix<f64>) {
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
    pub fn matrix(&self) -> &DMatrix<f64> {
        &self.cov
    }

    /// Mutable access for propagation, which rewrites the IMU rows and columns.
    pub(crate) fn matrix_mut(&mut self) -> &mut DMatrix<f64> {
        &mut self.cov
    }

    /// Offset of `var` in the covariance.
    pub fn offset(&self, var: K) -> Option<usize> {
        self.index.iter().find(|(v, _)| *v == var).map(|(_, o)| *o)
    }

    /// Whether `var` is in the state.
    pub fn has(&self, var: K) -> bool {
        self.offset(var).is_some()
    }

    /// Variables in covariance order with their offsets.
    pub fn index(&self) -> &[(K, usize)] {
        &self.index
    }

    /// Covariance block of `(a, b)`.
    pub fn block(&self, a: K, b: K) -> Option<DMatrix<f64>> {
        let (oa, ob) = (self.offset(a)?, self.offset(b)?);
        Some(self.cov.view((oa, ob), (a.size(), b.size())).into_owned())
    }

    /// Replaces the matrix; it must keep its size.
    pub fn set(&mut self, cov: DMatrix<f64>) -> Result<(), StateError<K>> {
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

    fn offsets(&self, vars: &[K]) -> Result<Vec<(usize, usize)>, StateError<K>> {
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
        new: K,
        jac: &[(K, DMatrix<f64>)],
        noise: &DMatrix<f64>,
    ) -> Result<(), StateError<K>> {
        if self.has(new) {
            return Err(StateError::Duplicate(new));
        }
        let (m, p_nn) = self.linear_map(new.size(), jac)?;
        self.insert_with_cross(new, &(p_nn + noise), &m)
    }

    /// For `x' = Σ J_i x_i` (each `J_i` of `k` rows): `M = Σ J_i P[x_i, :]` (the
    /// cross-covariance of `x'` with the state, `k x dim`) and `P' = Σ M[:, x_i] J_iᵀ`.
    pub fn linear_map(
        &self,
        k: usize,
        jac: &[(K, DMatrix<f64>)],
    ) -> Result<(DMatrix<f64>, DMatrix<f64>), StateError<K>> {
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
        new: K,
        p_nn: &DMatrix<f64>,
        cross: &DMatrix<f64>,
    ) -> Result<(), StateError<K>> {
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
    pub fn transform(&mut self, var: K, jac: &[(K, DMatrix<f64>)]) -> Result<(), StateError<K>> {
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
    pub fn remove(&mut self, var: K) -> Result<(), StateError<K>> {
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

    /// The joint covariance of `vars`, in that order.
    pub fn gather(&self, vars: &[K]) -> Result<DMatrix<f64>, StateError<K>> {
        let offs = self.offsets(vars)?;
        let size = offs.iter().map(|(_, k)| k).sum();
        Ok(self.gather_block(&offs, size))
    }

    fn checked_offsets(
        &self,
        vars: &[K],
        h: &DMatrix<f64>,
        r: &DMatrix<f64>,
    ) -> Result<(Offsets, usize), StateError<K>> {
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
        vars: &[K],
        h: &DMatrix<f64>,
        r: &DMatrix<f64>,
    ) -> Result<(DMatrix<f64>, DMatrix<f64>), StateError<K>> {
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

    /// `H P_vv Hᵀ` over the covariance block of `vars` only (for gating and CI
    /// weights, where the full `P Hᵀ` is not needed).
    pub fn projected(&self, vars: &[K], h: &DMatrix<f64>) -> Result<DMatrix<f64>, StateError<K>> {
        let zero = DMatrix::zeros(h.nrows(), h.nrows());
        let (offs, cols) = self.checked_offsets(vars, h, &zero)?;
        let p_vv = self.gather_block(&offs, cols);
        Ok(h * p_vv * h.transpose())
    }

    /// Mahalanobis distance `rᵀ S⁻¹ r` of a residual under a sparse Jacobian; only
    /// the covariance block of the involved variables is touched.
    pub fn mahalanobis(
        &self,
        vars: &[K],
        h: &DMatrix<f64>,
        res: &DVector<f64>,
        r: &DMatrix<f64>,
    ) -> Result<f64, StateError<K>> {
        let (offs, cols) = self.checked_offsets(vars, h, r)?;
        let p_vv = self.gather_block(&offs, cols);
        let s = h * p_vv * h.transpose() + r;
        let chol = s.cholesky().ok_or(StateError::NotPositiveDefinite)?;
        Ok(res.dot(&chol.solve(res)))
    }

    /// EKF update with a sparse Jacobian `h` whose columns are `vars` in order,
    /// residual `res = z - h(x̂)` and noise covariance `r`. Returns `δx`.
    pub fn ekf_update(
        &mut self,
        vars: &[K],
        h: &DMatrix<f64>,
        res: &DVector<f64>,
        r: &DMatrix<f64>,
    ) -> Result<DVector<f64>, StateError<K>> {
        if res.len() != h.nrows() {
            return Err(StateError::Dimension("residual length".into()));
        }
        let (s, pht) = self.innovation(vars, h, r)?;
        self.kalman_update(s, &pht, res, 1.0, None)
    }

    /// CI-EKF update (thesis Eqs. 5.15-5.17): the prior covariance is inflated to
    /// `P / ω` and the innovation covariance is `S = H P Hᵀ / ω + r_others`, where
    /// `r_others` already holds the peers' terms `Σ H_o P_o H_oᵀ / ω_o` and the
    /// measurement noise. `δx = P Hᵀ S⁻¹ r / ω`, `P ← P / ω − P Hᵀ S⁻¹ H P / ω²`.
    /// Returns `δx`.
    pub fn ci_update(
        &mut self,
        vars: &[K],
        h: &DMatrix<f64>,
        res: &DVector<f64>,
        r_others: &DMatrix<f64>,
        omega: f64,
    ) -> Result<DVector<f64>, StateError<K>> {
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
        self.kalman_update(s, &(pht / omega), res, omega, None)
    }

    /// The common tail of the updates: with `S = L Lᵀ` and
    /// `W = L⁻¹ (P' Hᵀ)ᵀ` for the prior `P' = P / ω`: `P ← P' − Wᵀ W`,
    /// `δx = Wᵀ L⁻¹ r`. `L⁻¹` is small (m x m); forming it makes `W` one dense
    /// product.
    ///
    /// With `unobserved = Some(Bᵀ)` the prior is `P / ω − (1/ω − 1) B Bᵀ`
    /// instead (split CI, `updater_ci`): the part `B Bᵀ` of `P` is not
    /// inflated. `pht` and `s` must already be that prior's.
    pub(crate) fn kalman_update(
        &mut self,
        s: DMatrix<f64>,
        pht: &DMatrix<f64>,
        res: &DVector<f64>,
        omega: f64,
        unobserved: Option<&DMatrix<f64>>,
    ) -> Result<DVector<f64>, StateError<K>> {
        let chol = s.cholesky().ok_or(StateError::NotPositiveDefinite)?;
        let l_inv = lower_triangular_inverse(&chol.l());
        let w = &l_inv * pht.transpose();
        let lr = &l_inv * res;
        let dx = w.tr_mul(&lr);
        if omega != 1.0 {
            self.cov /= omega;
            if let Some(b_t) = unobserved {
                self.subtract_gram_lower(&(b_t * (1.0 / omega - 1.0).sqrt()));
            }
        }
        self.subtract_gram_lower(&w);
        self.cov.fill_upper_triangle_with_lower_triangle();
        self.floor_diagonal();
        Ok(dx)
    }

    /// `P ← P − Wᵀ W` on the lower triangle ([`subtract_gram_lower`]).
    fn subtract_gram_lower(&mut self, w: &DMatrix<f64>) {
        subtract_gram_lower(&mut self.cov, w);
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
    /// thesis Eqs. 2.41-2.45): `P_new = H_f⁻¹ (H_x P H_xᵀ + σ² I) H_f⁻ᵀ`,
    /// `P_new,x = −H_f⁻¹ H_x P`. Returns the mean correction `H_f⁻¹ r₁` for the
    /// caller, which has already stored the variable's mean, to apply.
    pub fn initialize_invertible(
        &mut self,
        new: K,
        vars: &[K],
        h_x: &DMatrix<f64>,
        h_f: &DMatrix<f64>,
        res: &DVector<f64>,
        sigma2: f64,
    ) -> Result<DVector<f64>, StateError<K>> {
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
}

/// `P ← P − Wᵀ W` (`P` n x n, `W` m x n) on the lower triangle only (the result
/// is symmetric; the caller mirrors it), in column blocks of 32 so each block is
/// one dense product: about half the work of the full product. The covariance
/// update's dense kernel, timed against faer's in `benches/covariance_kernel.rs`.
pub fn subtract_gram_lower(p: &mut DMatrix<f64>, w: &DMatrix<f64>) {
    const BLOCK: usize = 32;
    let n = p.nrows();
    let w_t = w.transpose();
    let mut j0 = 0;
    while j0 < n {
        let bw = BLOCK.min(n - j0);
        let mut blk = p.view_mut((j0, j0), (n - j0, bw));
        blk.gemm(-1.0, &w_t.rows(j0, n - j0), &w.columns(j0, bw), 1.0);
        j0 += bw;
    }
}

/// Inverse of a lower-triangular matrix with a positive diagonal, by forward
/// substitution on its columns (`m³/6` multiply-adds, contiguous accesses).
pub(crate) fn lower_triangular_inverse(l: &DMatrix<f64>) -> DMatrix<f64> {
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
            // An axpy over the rows below k, written with zipped slices so it
            // has no bounds checks and vectorizes.
            for (xi, li) in x[k + 1..].iter_mut().zip(&lk[k + 1..]) {
                *xi -= li * xk;
            }
        }
    }
    inv
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn lower_triangular_inverse_is_exact() {
        let a = DMatrix::from_fn(7, 7, |i, j| {
            1.0 / (1.0 + i as f64 + j as f64) + if i == j { 1.0 } else { 0.0 }
        });
        let l = a.cholesky().unwrap().l();
        let inv = lower_triangular_inverse(&l);
        assert!((&l * &inv - DMatrix::identity(7, 7)).norm() < 1e-12);
    }
}
