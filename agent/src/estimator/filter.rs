//! [`Filter`]: what the per-robot steps of a frame (propagation, cloning, MSCKF,
//! SLAM, zero-velocity updates, marginalization) need of a filter state: one
//! robot's means, and covariance operations on that robot's variables.
//!
//! [`State`] implements it for the distributed estimator (each robot its own
//! covariance); the centralized estimator implements it with a view of one robot
//! inside the joint state, so the same steps update the full joint covariance
//! with every cross-robot correlation.

use super::covariance::StateError;
use super::state::{Means, State, Var};
use nalgebra::{DMatrix, DVector, SMatrix};

/// The 15x15 IMU error-state transition and noise of one propagation interval.
pub type ImuMatrix = SMatrix<f64, 15, 15>;

/// Read access to one robot in a filter: its means and which of its variables
/// are estimated.
pub trait FilterView {
    /// The robot's means.
    fn means(&self) -> &Means;
    /// Whether the robot's variable `var` is in the state.
    fn has(&self, var: Var) -> bool;
}

/// One robot's filter: its means and the covariance operations on its variables.
/// Updates apply their correction to every mean the covariance couples.
pub trait Filter: FilterView {
    /// The robot's means, for updating in place.
    fn means_mut(&mut self) -> &mut Means;
    /// `rᵀ (H P Hᵀ + R)⁻¹ r` over the variables `vars`.
    fn mahalanobis(
        &self,
        vars: &[Var],
        h: &DMatrix<f64>,
        res: &DVector<f64>,
        r: &DMatrix<f64>,
    ) -> Result<f64, StateError>;
    /// EKF update; the correction is applied to the means.
    fn ekf_update(
        &mut self,
        vars: &[Var],
        h: &DMatrix<f64>,
        res: &DVector<f64>,
        r: &DMatrix<f64>,
    ) -> Result<(), StateError>;
    /// EKF update of a stack of `block`-row blocks with block-diagonal noise,
    /// each block used only if its Mahalanobis distance is at most `threshold`;
    /// the correction is applied to the means. Returns which blocks were used.
    /// The stack's innovation is formed once and gated on its diagonal blocks
    /// (see [`super::gated_update`]).
    fn gated_ekf_update(
        &mut self,
        vars: &[Var],
        h: &DMatrix<f64>,
        res: &DVector<f64>,
        r: &DMatrix<f64>,
        block: usize,
        threshold: f64,
    ) -> Result<Vec<bool>, StateError>;
    /// Delayed initialization of `new` from an invertible system; returns the
    /// mean correction for the caller to apply.
    fn initialize_invertible(
        &mut self,
        new: Var,
        vars: &[Var],
        h_x: &DMatrix<f64>,
        h_f: &DMatrix<f64>,
        res: &DVector<f64>,
        sigma2: f64,
    ) -> Result<DVector<f64>, StateError>;
    /// Adds `new` as a linear function of existing variables plus noise.
    fn augment(
        &mut self,
        new: Var,
        jac: &[(Var, DMatrix<f64>)],
        noise: &DMatrix<f64>,
    ) -> Result<(), StateError>;
    /// Replaces `var` by a linear function of itself and others.
    fn transform(&mut self, var: Var, jac: &[(Var, DMatrix<f64>)]) -> Result<(), StateError>;
    /// Removes `var` from the covariance and the means.
    fn marginalize(&mut self, var: Var) -> Result<(), StateError>;
    /// Propagation's covariance step on the IMU block: `P_II ← Φ P_II Φᵀ + Q`,
    /// `P_Ix ← Φ P_Ix` for every other variable `x` (of any robot).
    fn propagate_covariance(&mut self, phi: &ImuMatrix, q: &ImuMatrix);
    /// A copy of the whole filter (every robot's means and covariance) to
    /// return to: an iterated update restarts from its prior.
    type Saved: Clone;
    /// Saves the filter.
    fn save(&self) -> Self::Saved;
    /// Returns the filter to `saved`.
    fn restore(&mut self, saved: &Self::Saved);
    /// This robot's means in `saved`.
    fn saved_means<'s>(&self, saved: &'s Self::Saved) -> Option<&'s Means>;
}

/// `P_II ← Φ P_II Φᵀ + Q`, `P_Ix ← Φ P_Ix` on a joint matrix whose IMU block
/// starts at `o`.
pub(crate) fn transition_rows(cov: &mut DMatrix<f64>, o: usize, phi: &ImuMatrix, q: &ImuMatrix) {
    let n = cov.nrows();
    let rows = cov.view((o, 0), (15, n)).into_owned();
    let new_rows = phi * rows;
    cov.view_mut((o, 0), (15, n)).copy_from(&new_rows);
    let cols = cov.view((0, o), (n, 15)).into_owned();
    let new_cols = cols * phi.transpose();
    cov.view_mut((0, o), (n, 15)).copy_from(&new_cols);
    let mut p_ii = cov.view((o, o), (15, 15)).into_owned();
    p_ii += q;
    let sym = (&p_ii + p_ii.transpose()) * 0.5;
    cov.view_mut((o, o), (15, 15)).copy_from(&sym);
}

impl FilterView for State {
    fn means(&self) -> &Means {
        &self.means
    }
    fn has(&self, var: Var) -> bool {
        State::has(self, var)
    }
}

impl Filter for State {
    fn means_mut(&mut self) -> &mut Means {
        &mut self.means
    }
    fn mahalanobis(
        &self,
        vars: &[Var],
        h: &DMatrix<f64>,
        res: &DVector<f64>,
        r: &DMatrix<f64>,
    ) -> Result<f64, StateError> {
        State::mahalanobis(self, vars, h, res, r)
    }
    fn ekf_update(
        &mut self,
        vars: &[Var],
        h: &DMatrix<f64>,
        res: &DVector<f64>,
        r: &DMatrix<f64>,
    ) -> Result<(), StateError> {
        State::ekf_update(self, vars, h, res, r)
    }
    fn gated_ekf_update(
        &mut self,
        vars: &[Var],
        h: &DMatrix<f64>,
        res: &DVector<f64>,
        r: &DMatrix<f64>,
        block: usize,
        threshold: f64,
    ) -> Result<Vec<bool>, StateError> {
        State::gated_ekf_update(self, vars, h, res, r, block, threshold)
    }
    fn initialize_invertible(
        &mut self,
        new: Var,
        vars: &[Var],
        h_x: &DMatrix<f64>,
        h_f: &DMatrix<f64>,
        res: &DVector<f64>,
        sigma2: f64,
    ) -> Result<DVector<f64>, StateError> {
        State::initialize_invertible(self, new, vars, h_x, h_f, res, sigma2)
    }
    fn augment(
        &mut self,
        new: Var,
        jac: &[(Var, DMatrix<f64>)],
        noise: &DMatrix<f64>,
    ) -> Result<(), StateError> {
        State::augment(self, new, jac, noise)
    }
    fn transform(&mut self, var: Var, jac: &[(Var, DMatrix<f64>)]) -> Result<(), StateError> {
        State::transform(self, var, jac)
    }
    fn marginalize(&mut self, var: Var) -> Result<(), StateError> {
        State::marginalize(self, var)
    }
    fn propagate_covariance(&mut self, phi: &ImuMatrix, q: &ImuMatrix) {
        let o = self.offset(Var::Imu).unwrap_or(0);
        transition_rows(self.cov_mut(), o, phi, q);
    }
    type Saved = State;
    fn save(&self) -> State {
        self.clone()
    }
    fn restore(&mut self, saved: &State) {
        self.clone_from(saved);
    }
    fn saved_means<'s>(&self, saved: &'s State) -> Option<&'s Means> {
        Some(&saved.means)
    }
}
