//! The centralized estimator's state (thesis Eqs. 5.6-5.7): every robot's means
//! and one joint covariance with every cross-robot correlation.
//!
//! [`RobotSlot`] is one robot's view of it, implementing [`Filter`], so the
//! single-robot steps (propagation, cloning, MSCKF, SLAM, marginalization) run
//! unchanged and update the whole joint covariance; cross-robot updates use the
//! joint covariance directly.

use crate::estimator::covariance::{Covariance, StateError, StateVar};
use crate::estimator::filter::{transition_rows, Filter, FilterView, ImuMatrix};
use crate::estimator::state::{Means, Var};
use nalgebra::{DMatrix, DVector};

/// A variable of robot `robot` in the joint state.
#[derive(Clone, Copy, Debug, PartialEq, Eq, PartialOrd, Ord, Hash)]
pub struct JointVar {
    /// The robot's slot (its index in the fleet).
    pub robot: u16,
    /// The variable.
    pub var: Var,
}

impl StateVar for JointVar {
    fn size(self) -> usize {
        self.var.size()
    }
}

/// Every robot's means and the joint covariance.
#[derive(Clone, Debug, Default)]
pub struct JointState {
    /// Means by robot slot (`None` until that robot is initialized).
    pub robots: Vec<Option<Means>>,
    /// The joint covariance.
    pub cov: Covariance<JointVar>,
}

fn jv(robot: u16, var: Var) -> JointVar {
    JointVar { robot, var }
}

fn single(e: StateError<JointVar>) -> StateError {
    match e {
        StateError::Missing(v) => StateError::Missing(v.var),
        StateError::Duplicate(v) => StateError::Duplicate(v.var),
        StateError::NotPositiveDefinite => StateError::NotPositiveDefinite,
        StateError::Dimension(s) => StateError::Dimension(s),
    }
}

impl JointState {
    /// Adds robot `robot` with its means and its own prior blocks (IMU first),
    /// uncorrelated with the others.
    pub fn add_robot(&mut self, robot: u16, means: Means, blocks: &[(Var, DMatrix<f64>)]) {
        let i = usize::from(robot);
        if self.robots.len() <= i {
            self.robots.resize(i + 1, None);
        }
        for (v, b) in blocks {
            self.cov.append(jv(robot, *v), b);
        }
        self.robots[i] = Some(means);
    }

    /// The means of robot `robot`, once initialized.
    pub fn means(&self, robot: u16) -> Option<&Means> {
        self.robots.get(usize::from(robot))?.as_ref()
    }

    /// Applies a joint correction to every robot's means.
    pub fn apply_correction(&mut self, dx: &DVector<f64>) {
        for &(v, o) in self.cov.index() {
            if let Some(Some(m)) = self.robots.get_mut(usize::from(v.robot)) {
                m.apply(v.var, o, dx);
            }
        }
    }

    /// EKF update over variables of several robots; the correction is applied
    /// to every robot.
    pub fn ekf_update(
        &mut self,
        vars: &[JointVar],
        h: &DMatrix<f64>,
        res: &DVector<f64>,
        r: &DMatrix<f64>,
    ) -> Result<(), StateError<JointVar>> {
        let dx = self.cov.ekf_update(vars, h, res, r)?;
        self.apply_correction(&dx);
        Ok(())
    }

    /// Gated EKF update of a stack of blocks (see [`Covariance::gated_ekf_update`]);
    /// the accepted blocks' correction goes to every robot's means.
    pub fn gated_ekf_update(
        &mut self,
        vars: &[JointVar],
        h: &DMatrix<f64>,
        res: &DVector<f64>,
        r: &DMatrix<f64>,
        block: usize,
        threshold: f64,
    ) -> Result<Vec<bool>, StateError<JointVar>> {
        let out = self
            .cov
            .gated_ekf_update(vars, h, res, r, block, threshold)?;
        if let Some(dx) = &out.dx {
            self.apply_correction(dx);
        }
        Ok(out.accepted)
    }

    /// One robot's view.
    pub fn slot(&mut self, robot: u16) -> Option<RobotSlot<'_>> {
        self.means(robot)?;
        Some(RobotSlot { joint: self, robot })
    }
}

/// Robot `robot` inside the joint state.
#[derive(Debug)]
pub struct RobotSlot<'a> {
    joint: &'a mut JointState,
    robot: u16,
}

impl RobotSlot<'_> {
    fn map(&self, vars: &[Var]) -> Vec<JointVar> {
        vars.iter().map(|v| jv(self.robot, *v)).collect()
    }
}

/// Read-only view of one robot in the joint state.
#[derive(Clone, Copy, Debug)]
pub struct RobotView<'a> {
    joint: &'a JointState,
    robot: u16,
    means: &'a Means,
}

impl JointState {
    /// A read-only view of robot `robot`, once initialized.
    pub fn view(&self, robot: u16) -> Option<RobotView<'_>> {
        Some(RobotView {
            joint: self,
            robot,
            means: self.means(robot)?,
        })
    }
}

impl FilterView for RobotView<'_> {
    fn means(&self) -> &Means {
        self.means
    }
    fn has(&self, var: Var) -> bool {
        self.joint.cov.has(jv(self.robot, var))
    }
}

impl FilterView for RobotSlot<'_> {
    #[allow(clippy::expect_used)]
    fn means(&self) -> &Means {
        // A slot exists only for an initialized robot (see `JointState::slot`).
        self.joint
            .means(self.robot)
            .expect("a slot's robot is initialized")
    }
    fn has(&self, var: Var) -> bool {
        self.joint.cov.has(jv(self.robot, var))
    }
}

impl Filter for RobotSlot<'_> {
    #[allow(clippy::expect_used)]
    fn means_mut(&mut self) -> &mut Means {
        self.joint
            .robots
            .get_mut(usize::from(self.robot))
            .and_then(Option::as_mut)
            .expect("a slot's robot is initialized")
    }
    fn mahalanobis(
        &self,
        vars: &[Var],
        h: &DMatrix<f64>,
        res: &DVector<f64>,
        r: &DMatrix<f64>,
    ) -> Result<f64, StateError> {
        self.joint
            .cov
            .mahalanobis(&self.map(vars), h, res, r)
            .map_err(single)
    }
    fn ekf_update(
        &mut self,
        vars: &[Var],
        h: &DMatrix<f64>,
        res: &DVector<f64>,
        r: &DMatrix<f64>,
    ) -> Result<(), StateError> {
        let vars = self.map(vars);
        self.joint.ekf_update(&vars, h, res, r).map_err(single)
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
        let vars = self.map(vars);
        self.joint
            .gated_ekf_update(&vars, h, res, r, block, threshold)
            .map_err(single)
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
        let vars = self.map(vars);
        self.joint
            .cov
            .initialize_invertible(jv(self.robot, new), &vars, h_x, h_f, res, sigma2)
            .map_err(single)
    }
    fn augment(
        &mut self,
        new: Var,
        jac: &[(Var, DMatrix<f64>)],
        noise: &DMatrix<f64>,
    ) -> Result<(), StateError> {
        let jac: Vec<(JointVar, DMatrix<f64>)> = jac
            .iter()
            .map(|(v, j)| (jv(self.robot, *v), j.clone()))
            .collect();
        self.joint
            .cov
            .augment(jv(self.robot, new), &jac, noise)
            .map_err(single)
    }
    fn transform(&mut self, var: Var, jac: &[(Var, DMatrix<f64>)]) -> Result<(), StateError> {
        let jac: Vec<(JointVar, DMatrix<f64>)> = jac
            .iter()
            .map(|(v, j)| (jv(self.robot, *v), j.clone()))
            .collect();
        self.joint
            .cov
            .transform(jv(self.robot, var), &jac)
            .map_err(single)
    }
    fn marginalize(&mut self, var: Var) -> Result<(), StateError> {
        self.joint.cov.remove(jv(self.robot, var)).map_err(single)?;
        self.means_mut().forget(var);
        Ok(())
    }
    fn propagate_covariance(&mut self, phi: &ImuMatrix, q: &ImuMatrix) {
        if let Some(o) = self.joint.cov.offset(jv(self.robot, Var::Imu)) {
            transition_rows(self.joint.cov.matrix_mut(), o, phi, q);
        }
    }
    type Saved = JointState;
    fn save(&self) -> JointState {
        self.joint.clone()
    }
    fn restore(&mut self, saved: &JointState) {
        self.joint.clone_from(saved);
    }
    fn saved_means<'s>(&self, saved: &'s JointState) -> Option<&'s Means> {
        saved.means(self.robot)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::estimator::state::{ImuState, State};
    use common::calibration::CameraCalibration;

    fn prior() -> DMatrix<f64> {
        DMatrix::from_fn(15, 15, |i, j| {
            if i == j {
                0.01 + 0.001 * i as f64
            } else {
                0.0005
            }
        })
    }

    /// A robot alone in the joint state updates exactly as the single-robot state.
    #[test]
    fn a_lone_robot_in_the_joint_state_matches_the_single_robot_state() {
        let calib = CameraCalibration::euroc_cam0();
        let mut single = State::new(0.0, ImuState::default(), prior(), calib.clone(), &[]);
        let mut joint = JointState::default();
        joint.add_robot(
            3,
            Means::new(0.0, ImuState::default(), calib),
            &[(Var::Imu, prior())],
        );
        let h = DMatrix::from_fn(2, 15, |i, j| ((i + 2 * j) % 5) as f64 - 2.0);
        let res = DVector::from_vec(vec![0.1, -0.05]);
        let r = DMatrix::identity(2, 2) * 0.3;
        Filter::ekf_update(&mut single, &[Var::Imu], &h, &res, &r).unwrap();
        let mut slot = joint.slot(3).unwrap();
        Filter::ekf_update(&mut slot, &[Var::Imu], &h, &res, &r).unwrap();
        assert!((joint.cov.matrix() - single.cov()).abs().max() < 1e-14);
        let m = joint.means(3).unwrap();
        assert!((m.imu.pos - single.imu.pos).norm() < 1e-14);
    }

    /// An update of one robot moves a correlated robot too (the cross-robot
    /// correlation a distributed estimator drops).
    #[test]
    fn a_correlated_robot_moves_with_an_update_of_another() {
        let calib = CameraCalibration::euroc_cam0();
        let mut joint = JointState::default();
        for r in 0..2 {
            joint.add_robot(
                r,
                Means::new(0.0, ImuState::default(), calib.clone()),
                &[(Var::Imu, DMatrix::identity(15, 15) * 0.01)],
            );
        }
        // Correlate the two positions.
        let mut p = joint.cov.matrix().clone();
        for i in 0..3 {
            p[(3 + i, 15 + 3 + i)] = 0.009;
            p[(15 + 3 + i, 3 + i)] = 0.009;
        }
        joint.cov.set(p).unwrap();
        let mut h = DMatrix::zeros(3, 15);
        h.view_mut((0, 3), (3, 3)).fill_with_identity();
        let res = DVector::from_vec(vec![0.1, 0.0, 0.0]);
        let mut slot = joint.slot(0).unwrap();
        Filter::ekf_update(
            &mut slot,
            &[Var::Imu],
            &h,
            &res,
            &(DMatrix::identity(3, 3) * 1e-4),
        )
        .unwrap();
        let other = joint.means(1).unwrap();
        assert!(other.imu.pos.x > 0.08, "robot 1 moved {}", other.imu.pos.x);
    }
}
