//! `sim-fleet eval --bins-s S`: how a long run evolves. The errors of an
//! evaluated estimate cut into bins of `S` seconds from its first pose (RMS and
//! largest error, mean NEES), and with `--timing`, the agent's per-frame cost
//! in the same bins (from its `timing.csv`). An hour's ATE hides whether the
//! error or the cost grows; its bins do not.

use std::fmt::Write as _;
use std::path::Path;

use serde::Serialize;

use super::{opt, PoseError};

/// Errors and cost of one bin of a run.
#[derive(Clone, Debug, PartialEq, Serialize)]
pub struct Bin {
    /// Start of the bin, s after the first evaluated pose.
    pub from_s: f64,
    /// End of the bin (exclusive), s after the first evaluated pose.
    pub to_s: f64,
    /// Evaluated poses in it.
    pub poses: usize,
    /// RMS orientation error, degrees (`None` without poses).
    pub ori_rms_deg: Option<f64>,
    /// RMS position error, m.
    pub pos_rms_m: Option<f64>,
    /// Largest position error, m.
    pub pos_max_m: Option<f64>,
    /// Mean orientation NEES of the poses that had a covariance.
    pub nees_ori: Option<f64>,
    /// Mean position NEES of the poses that had a covariance.
    pub nees_pos: Option<f64>,
    /// The agent's cost in the bin (with `--timing`).
    pub cost: Option<BinCost>,
}

/// The per-frame cost of one bin, from `timing.csv`.
#[derive(Clone, Debug, PartialEq, Serialize)]
pub struct BinCost {
    /// Camera frames in the bin.
    pub frames: usize,
    /// Mean thread CPU time of a frame, ms (`cpu_ms`).
    pub cpu_ms_mean: f64,
    /// Its 95th percentile, ms.
    pub cpu_ms_p95: f64,
    /// Its largest, ms.
    pub cpu_ms_max: f64,
    /// Mean loop-closure matching time, ms (`matching_ms`).
    pub matching_ms_mean: Option<f64>,
    /// Mean time gathering the peers' evidence, ms (`evidence_ms`; absent
    /// from files written before it was timed).
    pub evidence_ms_mean: Option<f64>,
}

/// The columns of `timing.csv` the bins use: one row per camera frame.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct TimingRows {
    /// Frame time, s (the estimate's clock).
    pub t: Vec<f64>,
    /// Thread CPU time of the frame, ms.
    pub cpu_ms: Vec<f64>,
    /// Loop-closure matching, ms (empty when the file has no such column).
    pub matching_ms: Vec<f64>,
    /// Gathering the evidence, ms (empty when the file has no such column).
    pub evidence_ms: Vec<f64>,
}

/// Why a `timing.csv` could not be read.
#[derive(Debug, thiserror::Error)]
pub enum TimingError {
    /// The file could not be read.
    #[error("reading {path}: {source}")]
    Io {
        /// The file.
        path: String,
        /// Why.
        source: std::io::Error,
    },
    /// The file is not a timing table.
    #[error("{path}: {what}")]
    Bad {
        /// The file.
        path: String,
        /// What is wrong, and on which line.
        what: String,
    },
}

/// Reads the columns [`TimingRows`] holds from an agent's `timing.csv`
/// (columns found by name; a row with a non-finite or missing value is an
/// error naming its line).
pub fn read_timing(path: &Path) -> Result<TimingRows, TimingError> {
    let text = std::fs::read_to_string(path).map_err(|source| TimingError::Io {
        path: path.display().to_string(),
        source,
    })?;
    parse_timing(&text).map_err(|what| TimingError::Bad {
        path: path.display().to_string(),
        what,
    })
}

fn parse_timing(text: &str) -> Result<TimingRows, String> {
    let mut lines = text.lines().enumerate();
    let Some((_, header)) = lines.next() else {
        return Err("empty: no header".into());
    };
    let names: Vec<&str> = header.split(',').map(str::trim).collect();
    let col = |name: &str| names.iter().position(|n| *n == name);
    let (Some(t_col), Some(cpu_col)) = (col("t"), col("cpu_ms")) else {
        return Err(format!(
            "the header has no `t` or no `cpu_ms` column: {header:?}"
        ));
    };
    let optional = [col("matching_ms"), col("evidence_ms")];
    let mut rows = TimingRows::default();
    for (i, line) in lines {
        if line.trim().is_empty() {
            continue;
        }
        let fields: Vec<&str> = line.split(',').collect();
        let value = |c: usize| -> Result<f64, String> {
            let field = fields.get(c).ok_or_else(|| {
                format!(
                    "line {}: {} fields, column {c} missing",
                    i + 1,
                    fields.len()
                )
            })?;
            match field.trim().parse::<f64>() {
                Ok(v) if v.is_finite() => Ok(v),
                _ => Err(format!("line {}: {field:?} is not a finite number", i + 1)),
            }
        };
        let t = value(t_col)?;
        if rows.t.last().is_some_and(|&last| t < last) {
            return Err(format!("line {}: time {t} runs backwards", i + 1));
        }
        rows.t.push(t);
        rows.cpu_ms.push(value(cpu_col)?);
        if let Some(c) = optional[0] {
            rows.matching_ms.push(value(c)?);
        }
        if let Some(c) = optional[1] {
            rows.evidence_ms.push(value(c)?);
        }
    }
    Ok(rows)
}

/// Most bins of one evaluation: the files' times are not trusted to be close
/// to each other.
pub const MAX_BINS: usize = 100_000;

/// Cuts `per_pose` (and `timing`, if given) into bins of `bin_s` seconds from
/// the first pose's time. Frames of `timing` before that time go to the first
/// bin, after the last pose's bin to bins of their own. No poses or a width
/// that is not a positive number give no bins; a span of more than
/// [`MAX_BINS`] bins is an error.
pub fn bins(
    per_pose: &[PoseError],
    timing: Option<&TimingRows>,
    bin_s: f64,
) -> Result<Vec<Bin>, String> {
    let Some(first) = per_pose.first() else {
        return Ok(Vec::new());
    };
    if !(bin_s.is_finite() && bin_s > 0.0) {
        return Ok(Vec::new());
    }
    let t0 = first.t;
    let bin_of = |t: f64| ((t - t0) / bin_s).floor().max(0.0);
    let mut last = per_pose.last().map_or(0.0, |p| bin_of(p.t));
    if let Some(t) = timing.and_then(|rows| rows.t.last()) {
        last = last.max(bin_of(*t));
    }
    if last.is_nan() || last >= MAX_BINS as f64 {
        return Err(format!(
            "{last} bins of {bin_s} s from the first pose at {t0} s: at most {MAX_BINS} \
             (a pose or timing row far from the others?)"
        ));
    }
    let n = last as usize + 1;
    let index = |t: f64| bin_of(t) as usize;
    let mut poses: Vec<Vec<&PoseError>> = vec![Vec::new(); n];
    for p in per_pose {
        poses[index(p.t)].push(p);
    }
    let mut frames: Vec<Vec<usize>> = vec![Vec::new(); n];
    if let Some(rows) = timing {
        for (k, &t) in rows.t.iter().enumerate() {
            frames[index(t)].push(k);
        }
    }
    Ok(poses
        .into_iter()
        .zip(frames)
        .enumerate()
        .map(|(i, (ps, fs))| {
            let norm2 = |v: &[f64; 3]| v.iter().map(|x| x * x).sum::<f64>();
            let rms = |f: &dyn Fn(&PoseError) -> f64| {
                (!ps.is_empty())
                    .then(|| (ps.iter().map(|p| f(p)).sum::<f64>() / ps.len() as f64).sqrt())
            };
            let mean_of = |f: &dyn Fn(&PoseError) -> Option<f64>| {
                let v: Vec<f64> = ps.iter().filter_map(|p| f(p)).collect();
                (!v.is_empty()).then(|| v.iter().sum::<f64>() / v.len() as f64)
            };
            Bin {
                from_s: i as f64 * bin_s,
                to_s: (i + 1) as f64 * bin_s,
                poses: ps.len(),
                ori_rms_deg: rms(&|p| norm2(&p.ori_err_deg)),
                pos_rms_m: rms(&|p| norm2(&p.pos_err)),
                pos_max_m: ps.iter().map(|p| norm2(&p.pos_err).sqrt()).reduce(f64::max),
                nees_ori: mean_of(&|p| p.nees_ori),
                nees_pos: mean_of(&|p| p.nees_pos),
                cost: timing.and_then(|rows| cost(rows, &fs)),
            }
        })
        .collect())
}

/// The cost of frames `ks` of `rows` (`None` without frames).
fn cost(rows: &TimingRows, ks: &[usize]) -> Option<BinCost> {
    if ks.is_empty() {
        return None;
    }
    let mean = |col: &[f64]| -> Option<f64> {
        (!col.is_empty()).then(|| ks.iter().map(|&k| col[k]).sum::<f64>() / ks.len() as f64)
    };
    let cpu = || ks.iter().map(|&k| rows.cpu_ms[k]);
    Some(BinCost {
        frames: ks.len(),
        cpu_ms_mean: mean(&rows.cpu_ms).unwrap_or(0.0),
        cpu_ms_p95: common::metrics::percentile(cpu(), 0.95).unwrap_or(0.0),
        cpu_ms_max: cpu().fold(f64::NEG_INFINITY, f64::max),
        matching_ms_mean: mean(&rows.matching_ms),
        evidence_ms_mean: mean(&rows.evidence_ms),
    })
}

/// The bins as a table, one line each.
pub fn table(bins: &[Bin]) -> String {
    let mut s = String::new();
    let _ =
        writeln!(
        s,
        "BINS  {:>8} {:>8} {:>6} {:>9} {:>9} {:>9} {:>8} {:>8} {:>7} {:>7} {:>7} {:>7} {:>8} {:>8}",
        "from_s", "to_s", "poses", "ori_deg", "pos_m", "pos_max", "nees_o", "nees_p", "frames",
        "cpu_ms", "p95_ms", "max_ms", "match_ms", "evid_ms"
    );
    for b in bins {
        let c = b.cost.as_ref();
        let _ = writeln!(
            s,
            "      {:>8.0} {:>8.0} {:>6} {:>9} {:>9} {:>9} {:>8} {:>8} {:>7} {:>7} {:>7} {:>7} {:>8} {:>8}",
            b.from_s,
            b.to_s,
            b.poses,
            opt(b.ori_rms_deg, 3),
            opt(b.pos_rms_m, 4),
            opt(b.pos_max_m, 4),
            opt(b.nees_ori, 2),
            opt(b.nees_pos, 2),
            c.map_or_else(|| "-".to_string(), |c| c.frames.to_string()),
            opt(c.map(|c| c.cpu_ms_mean), 2),
            opt(c.map(|c| c.cpu_ms_p95), 2),
            opt(c.map(|c| c.cpu_ms_max), 2),
            opt(c.and_then(|c| c.matching_ms_mean), 3),
            opt(c.and_then(|c| c.evidence_ms_mean), 3),
        );
    }
    s
}

#[cfg(test)]
mod tests {
    use super::*;

    fn pose(t: f64, dx: f64) -> PoseError {
        PoseError {
            t,
            est_pos: [0.0; 3],
            gt_pos: [0.0; 3],
            pos_err: [dx, 0.0, 0.0],
            ori_err_deg: [0.0, 0.0, 2.0 * dx],
            pos_sigma: None,
            ori_sigma_deg: None,
            nees_ori: None,
            nees_pos: Some(dx),
        }
    }

    #[test]
    fn errors_and_cost_fall_into_the_bins_of_their_time() {
        // 10 Hz for 25 s from t = 100: errors 0.1 m in the first 10 s, 0.2
        // after; cost 1 ms, then 3 ms from 20 s.
        let per_pose: Vec<PoseError> = (0..250)
            .map(|i| {
                let t = 100.0 + 0.1 * f64::from(i);
                pose(t, if t < 110.0 { 0.1 } else { 0.2 })
            })
            .collect();
        let text = std::iter::once("t,total_ms,cpu_ms,matching_ms".to_string())
            .chain(per_pose.iter().map(|p| {
                let c = if p.t < 120.0 { 1.0 } else { 3.0 };
                format!("{},9,{c},0.5", p.t)
            }))
            .collect::<Vec<_>>()
            .join("\n");
        let rows = parse_timing(&text).unwrap();
        assert!(rows.evidence_ms.is_empty());
        let b = bins(&per_pose, Some(&rows), 10.0).unwrap();
        assert_eq!(b.len(), 3);
        assert_eq!(
            b.iter().map(|b| b.poses).collect::<Vec<_>>(),
            [100, 100, 50]
        );
        assert!((b[0].pos_rms_m.unwrap() - 0.1).abs() < 1e-12);
        assert!((b[1].pos_rms_m.unwrap() - 0.2).abs() < 1e-12);
        assert!((b[1].ori_rms_deg.unwrap() - 0.4).abs() < 1e-12);
        assert!((b[2].pos_max_m.unwrap() - 0.2).abs() < 1e-12);
        assert!((b[0].nees_pos.unwrap() - 0.1).abs() < 1e-12);
        assert_eq!(b[0].nees_ori, None);
        let c: Vec<&BinCost> = b.iter().map(|b| b.cost.as_ref().unwrap()).collect();
        assert_eq!((c[1].frames, c[1].cpu_ms_mean), (100, 1.0));
        assert_eq!((c[2].cpu_ms_p95, c[2].cpu_ms_max), (3.0, 3.0));
        assert_eq!(c[0].matching_ms_mean, Some(0.5));
        assert_eq!(c[0].evidence_ms_mean, None);
        assert!(table(&b).lines().count() == 4);
    }

    #[test]
    fn a_bad_timing_file_is_refused_with_its_line() {
        for (text, says) in [
            ("", "no header"),
            ("t,total_ms\n1,2", "no `t` or no `cpu_ms`"),
            ("t,cpu_ms\n1,2\n2,NaN", "line 3"),
            ("t,cpu_ms\n1,2\n2", "line 3"),
            ("t,cpu_ms\n2,2\n1,2", "runs backwards"),
        ] {
            let err = parse_timing(text).unwrap_err();
            assert!(err.contains(says), "{text:?}: {err}");
        }
    }

    #[test]
    fn no_poses_or_a_bad_width_give_no_bins() {
        assert!(bins(&[], None, 10.0).unwrap().is_empty());
        assert!(bins(&[pose(1.0, 0.1)], None, 0.0).unwrap().is_empty());
        assert!(bins(&[pose(1.0, 0.1)], None, f64::NAN).unwrap().is_empty());
    }

    #[test]
    fn a_time_far_from_the_others_is_refused_not_allocated() {
        let poses = [pose(1.0, 0.1), pose(2.0, 0.1)];
        let rows = parse_timing("t,cpu_ms\n1,1\n1e15,1").unwrap();
        let err = bins(&poses, Some(&rows), 1.0).unwrap_err();
        assert!(err.contains("at most 100000"), "{err}");
        let far = [pose(1.0, 0.1), pose(1e300, 0.1)];
        assert!(bins(&far, None, 600.0).is_err());
        assert_eq!(bins(&poses, Some(&rows), 1e14).unwrap().len(), 10);
    }
}
