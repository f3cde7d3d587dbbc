//! One EKF update of a stack of independent measurement blocks, each gated
//! alone (the SLAM update: one 2-row block per feature).
//!
//! Gating a block needs its innovation covariance `S_ii = H_i P H_iᵀ + R_ii`,
//! which is exactly the `i`-th diagonal block of the stacked
//! `S = H P Hᵀ + R` (with `R` block diagonal) that the update computes anyway.
//! So the stack's `S` and `P Hᵀ` are formed once: the gate reads the diagonal
//! blocks, and the update keeps the rows and columns of the accepted blocks.
//! Gating each block against the covariance first and then updating would pass
//! over `P` once per block more.

use super::covariance::{Covariance, StateError, StateVar};
use nalgebra::{DMatrix, DVector};

/// What a gated update did.
#[derive(Clone, Debug, PartialEq)]
pub struct GatedUpdate {
    /// The error-state correction, `None` when no block passed the gate.
    pub dx: Option<DVector<f64>>,
    /// Whether each block passed the gate, in stack order.
    pub accepted: Vec<bool>,
}

impl<K: StateVar> Covariance<K> {
    /// EKF update with the stacked Jacobian `h` (columns: `vars` in order),
    /// residual `res` and block-diagonal noise `r`, whose rows form consecutive
    /// blocks of `block` rows. Block `i` takes part only if its Mahalanobis
    /// distance `r_iᵀ S_ii⁻¹ r_i` is at most `threshold` (and `S_ii` is positive
    /// definite).
    pub fn gated_ekf_update(
        &mut self,
        vars: &[K],
        h: &DMatrix<f64>,
        res: &DVector<f64>,
        r: &DMatrix<f64>,
        block: usize,
        threshold: f64,
    ) -> Result<GatedUpdate, StateError<K>> {
        let m = h.nrows();
        if block == 0 || m % block != 0 || res.len() != m {
            return Err(StateError::Dimension(format!(
                "{m} rows, residual {}, blocks of {block}",
                res.len()
            )));
        }
        let (s, pht) = self.innovation(vars, h, r)?;
        let accepted: Vec<bool> = (0..m / block)
            .map(|i| {
                let o = i * block;
                let s_ii = s.view((o, o), (block, block)).into_owned();
                let r_i = res.rows(o, block);
                s_ii.cholesky()
                    .is_some_and(|c| r_i.dot(&c.solve(&r_i)) <= threshold)
            })
            .collect();
        let rows: Vec<usize> = accepted
            .iter()
            .enumerate()
            .filter(|(_, ok)| **ok)
            .flat_map(|(i, _)| i * block..(i + 1) * block)
            .collect();
        if rows.is_empty() {
            return Ok(GatedUpdate { dx: None, accepted });
        }
        let dx = if rows.len() == m {
            self.kalman_update(s, &pht, res, 1.0, None)?
        } else {
            let s_acc = s.select_rows(&rows).select_columns(&rows);
            let pht_acc = pht.select_columns(&rows);
            let res_acc = res.select_rows(&rows);
            self.kalman_update(s_acc, &pht_acc, &res_acc, 1.0, None)?
        };
        Ok(GatedUpdate {
            dx: Some(dx),
            accepted,
        })
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::estimator::state::Var;

    fn prior() -> Covariance<Var> {
        let mut c = Covariance::default();
        let p = DMatrix::from_fn(15, 15, |i, j| {
            if i == j {
                0.05 + 0.01 * i as f64
            } else {
                0.002
            }
        });
        c.append(Var::Imu, &p);
        c
    }

    /// Three 2-row blocks on the IMU block; the middle one has a residual far
    /// outside its innovation covariance.
    fn system() -> (DMatrix<f64>, DVector<f64>, DMatrix<f64>) {
        let h = DMatrix::from_fn(6, 15, |i, j| ((i * 7 + j * 3) % 5) as f64 * 0.3 - 0.5);
        let res = DVector::from_vec(vec![0.1, -0.2, 40.0, -35.0, 0.05, 0.15]);
        (h, res, DMatrix::identity(6, 6) * 0.01)
    }

    #[test]
    fn the_gate_matches_per_block_mahalanobis_and_the_update_uses_the_accepted_rows() {
        let (h, res, r) = system();
        let vars = [Var::Imu];
        let threshold = 5.99;
        let mut expected = prior();
        let mut ok = Vec::new();
        for i in 0..3 {
            let hi = h.rows(2 * i, 2).into_owned();
            let ri = res.rows(2 * i, 2).into_owned();
            let d2 = expected
                .mahalanobis(&vars, &hi, &ri, &(DMatrix::identity(2, 2) * 0.01))
                .unwrap();
            ok.push(d2 <= threshold);
        }
        assert_eq!(ok, vec![true, false, true]);
        let rows = [0, 1, 4, 5];
        let dx_expected = expected
            .ekf_update(
                &vars,
                &h.select_rows(&rows),
                &res.select_rows(&rows),
                &(DMatrix::identity(4, 4) * 0.01),
            )
            .unwrap();
        let mut gated = prior();
        let out = gated
            .gated_ekf_update(&vars, &h, &res, &r, 2, threshold)
            .unwrap();
        assert_eq!(out.accepted, ok);
        let dx = out.dx.unwrap();
        assert!((dx - dx_expected).norm() < 1e-12);
        assert!((gated.matrix() - expected.matrix()).norm() < 1e-12);
    }

    #[test]
    fn nothing_accepted_leaves_the_covariance_unchanged() {
        let (h, res, r) = system();
        let mut c = prior();
        let before = c.matrix().clone();
        let out = c
            .gated_ekf_update(&[Var::Imu], &h, &res, &r, 2, 0.0)
            .unwrap();
        assert!(out.dx.is_none());
        assert_eq!(out.accepted, vec![false; 3]);
        assert_eq!(c.matrix(), &before);
    }

    #[test]
    fn rows_that_do_not_fill_the_blocks_are_an_error() {
        let (h, res, r) = system();
        let e = prior()
            .gated_ekf_update(&[Var::Imu], &h, &res, &r, 4, 1.0)
            .unwrap_err();
        assert!(matches!(e, StateError::Dimension(_)));
    }
}
