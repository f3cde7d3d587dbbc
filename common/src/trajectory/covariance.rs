//! The per-pose covariance file written by the agent and read by the evaluation.

use std::path::Path;

use super::parse::{need, number, parse_file, symmetric, write_lines, UPPER};
use super::{StampedCovariance, TrajectoryError};

/// Header and format of the covariance file: one line per pose with the time
/// (s) and the upper triangles, row by row, of the 3x3 orientation block
/// (rad², local-frame error `δθ` of [`crate::conventions`]) and of the 3x3
/// position block (m², global frame). Separators, comments and extra columns
/// are handled as in the trajectory files; timestamps must increase.
pub const COVARIANCE_HEADER: &str =
    "# timestamp ori_xx ori_xy ori_xz ori_yy ori_yz ori_zz pos_xx pos_xy pos_xz pos_yy pos_yz pos_zz";

/// Reads a covariance file (format: [`COVARIANCE_HEADER`]); the blocks are
/// filled symmetrically from their upper triangles.
pub fn read_covariances(path: impl AsRef<Path>) -> Result<Vec<StampedCovariance>, TrajectoryError> {
    parse_file(
        path.as_ref(),
        |f| {
            need(f, 13)?;
            Ok(StampedCovariance {
                t: number(f, 0)?,
                ori: symmetric(f, 1)?,
                pos: symmetric(f, 7)?,
            })
        },
        |c| c.t,
    )
}

/// Writes a covariance file (format: [`COVARIANCE_HEADER`]) that
/// [`read_covariances`] reads back exactly (timestamps with 9 decimals).
pub fn write_covariances(
    path: impl AsRef<Path>,
    covs: &[StampedCovariance],
) -> Result<(), TrajectoryError> {
    write_lines(
        path.as_ref(),
        COVARIANCE_HEADER,
        covs.iter().map(covariance_row),
    )
}

/// One line of [`write_covariances`] (no newline), for writers that append.
pub fn covariance_row(c: &StampedCovariance) -> String {
    let mut row = format!("{:.9}", c.t);
    for block in [&c.ori, &c.pos] {
        for (r, k) in UPPER {
            row.push(' ');
            row.push_str(&block[(r, k)].to_string());
        }
    }
    row
}
