//! Line parsing and writing shared by the trajectory and covariance formats.

use std::io::Write;
use std::path::Path;

use nalgebra::Matrix3;

use super::{LineError, TrajectoryError};
use crate::so3::rot_from_xyzw;

/// Quaternions with a smaller norm are rejected rather than normalized.
const MIN_QUATERNION_NORM: f64 = 1e-6;

/// Reads `path` and parses every data line with `parse`, which gets the
/// line's values (split at spaces, tabs and commas). Blank lines and lines
/// starting with `#` are skipped. Times (`time_of`) must strictly increase.
/// An unfinished last line (no newline after it: the file was cut off while
/// being written) that does not read is dropped with a warning; any other bad
/// line is an error naming it.
pub(super) fn parse_file<T>(
    path: &Path,
    mut parse: impl FnMut(&[&str]) -> Result<T, LineError>,
    time_of: impl Fn(&T) -> f64,
) -> Result<Vec<T>, TrajectoryError> {
    let text = std::fs::read_to_string(path).map_err(|source| TrajectoryError::Read {
        path: path.to_path_buf(),
        source,
    })?;
    let mut out: Vec<T> = Vec::new();
    let lines = text.lines().count();
    let unfinished = !text.ends_with('\n');
    for (index, raw) in text.lines().enumerate() {
        let line = raw.trim();
        if line.is_empty() || line.starts_with('#') {
            continue;
        }
        let fields: Vec<&str> = line
            .split(|c: char| c == ',' || c.is_whitespace())
            .filter(|f| !f.is_empty())
            .collect();
        let wrap = |kind| TrajectoryError::Line {
            path: path.to_path_buf(),
            line: index + 1,
            kind,
        };
        let checked = parse(&fields).and_then(|item| {
            let t = time_of(&item);
            match out.last().map(&time_of) {
                Some(previous) if t <= previous => {
                    Err(LineError::TimeNotIncreasing { t, previous })
                }
                _ => Ok(item),
            }
        });
        match checked {
            Ok(item) => out.push(item),
            Err(kind) if unfinished && index + 1 == lines => {
                tracing::warn!(
                    "{}: the last line ({}) is cut short and dropped: {kind}",
                    path.display(),
                    index + 1
                );
            }
            Err(kind) => return Err(wrap(kind)),
        }
    }
    Ok(out)
}

/// Fails unless the line has at least `expected` values.
pub(super) fn need(fields: &[&str], expected: usize) -> Result<(), LineError> {
    if fields.len() < expected {
        return Err(LineError::TooFewColumns {
            expected,
            found: fields.len(),
        });
    }
    Ok(())
}

/// The finite number in value `index` (0-based) of the line.
pub(super) fn number(fields: &[&str], index: usize) -> Result<f64, LineError> {
    let text = fields.get(index).copied().unwrap_or("");
    let value: f64 = text.parse().map_err(|source| LineError::Number {
        column: index + 1,
        text: text.to_string(),
        source,
    })?;
    if !value.is_finite() {
        return Err(LineError::NotFinite {
            column: index + 1,
            value,
        });
    }
    Ok(value)
}

/// The rotation of a (not necessarily unit) quaternion, rejecting tiny norms.
/// Row/column of the upper-triangle entries of a 3x3 block, in file order.
pub(super) const UPPER: [(usize, usize); 6] = [(0, 0), (0, 1), (0, 2), (1, 1), (1, 2), (2, 2)];

/// The symmetric matrix of the six upper-triangle values starting at `first`.
pub(super) fn symmetric(fields: &[&str], first: usize) -> Result<Matrix3<f64>, LineError> {
    let mut m = Matrix3::zeros();
    for (i, (r, k)) in UPPER.into_iter().enumerate() {
        let v = number(fields, first + i)?;
        m[(r, k)] = v;
        m[(k, r)] = v;
    }
    Ok(m)
}

pub(super) fn rotation(qx: f64, qy: f64, qz: f64, qw: f64) -> Result<Matrix3<f64>, LineError> {
    let norm = (qx * qx + qy * qy + qz * qz + qw * qw).sqrt();
    if !norm.is_finite() || norm < MIN_QUATERNION_NORM {
        return Err(LineError::BadQuaternion { norm });
    }
    Ok(rot_from_xyzw(qx, qy, qz, qw))
}

/// Writes `header` (a comment line) then one line per row to `path`.
pub(super) fn write_lines(
    path: &Path,
    header: &str,
    rows: impl Iterator<Item = String>,
) -> Result<(), TrajectoryError> {
    let wrap = |source| TrajectoryError::Write {
        path: path.to_path_buf(),
        source,
    };
    let file = std::fs::File::create(path).map_err(wrap)?;
    let mut out = std::io::BufWriter::new(file);
    writeln!(out, "{header}").map_err(wrap)?;
    for row in rows {
        writeln!(out, "{row}").map_err(wrap)?;
    }
    out.flush().map_err(wrap)
}
