//! SVG plots of an [`EvalReport`]: trajectory, errors with ±3σ, NEES.
//!
//! Text is written as SVG `<text>` elements, so no font files are needed.

use std::ops::Range;
use std::path::{Path, PathBuf};

use common::metrics::{percentile, CHI2_3DOF_95_HIGH, CHI2_3DOF_95_LOW};
use plotters::coord::types::RangedCoordf64;
use plotters::coord::Shift;
use plotters::prelude::*;

use crate::anees::{band, Epoch, KINDS};
use crate::eval::{EvalReport, PoseError};
use common::trajectory::ImuStateRecord;
use nalgebra::Matrix3;

/// Why a plot could not be written.
#[derive(Debug, thiserror::Error)]
pub enum PlotError {
    /// The output folder could not be created.
    #[error("cannot create the plot folder {}", path.display())]
    Folder {
        /// The folder.
        path: PathBuf,
        /// The I/O error.
        #[source]
        source: std::io::Error,
    },
    /// Drawing or writing an SVG file failed.
    #[error("cannot draw {}", path.display())]
    Draw {
        /// The SVG file.
        path: PathBuf,
        /// The drawing error.
        #[source]
        source: Box<dyn std::error::Error + Send + Sync>,
    },
}

pub(crate) type DrawResult = Result<(), Box<dyn std::error::Error + Send + Sync>>;
type Area<'a> = DrawingArea<SVGBackend<'a>, Shift>;
/// Name, mean and per-pose value of one NEES panel.
type NeesPanel = (&'static str, Option<f64>, fn(&PoseError) -> Option<f64>);

const SIZE: (u32, u32) = (1000, 800);
const AXES: [&str; 3] = ["x", "y", "z"];
const COLORS: [RGBColor; 3] = [
    RGBColor(200, 30, 30),
    RGBColor(30, 140, 30),
    RGBColor(30, 60, 200),
];

/// Writes `trajectory_xy.svg`, `error_pos.svg`, `error_ori.svg` and (when the
/// report has NEES values) `nees.svg` into `dir`, creating it; returns the files.
pub fn write_plots(report: &EvalReport, dir: &Path) -> Result<Vec<PathBuf>, PlotError> {
    std::fs::create_dir_all(dir).map_err(|source| PlotError::Folder {
        path: dir.to_path_buf(),
        source,
    })?;
    let poses = &report.per_pose;
    let t0 = poses.first().map_or(0.0, |p| p.t);
    let mut written = Vec::new();
    let mut draw = |name: &str, size: (u32, u32), f: &dyn Fn(&Area) -> DrawResult| {
        written.push(draw_svg(&dir.join(name), size, f)?);
        Ok::<(), PlotError>(())
    };
    draw("trajectory_xy.svg", (900, 900), &|root| {
        trajectory_xy(root, report)
    })?;
    let at = |p: &PoseError| p.t - t0;
    draw("error_pos.svg", SIZE, &|root| {
        errors(root, poses, at, "position error", "m", |p| {
            (p.pos_err, p.pos_sigma)
        })
    })?;
    draw("error_ori.svg", SIZE, &|root| {
        errors(root, poses, at, "orientation error", "deg", |p| {
            (p.ori_err_deg, p.ori_sigma_deg)
        })
    })?;
    if poses
        .iter()
        .any(|p| p.nees_ori.is_some() || p.nees_pos.is_some())
    {
        draw("nees.svg", SIZE, &|root| nees(root, report, t0))?;
    }
    Ok(written)
}

/// Draws one SVG file with `f`; returns its path.
fn draw_svg(
    path: &Path,
    size: (u32, u32),
    f: &dyn Fn(&Area) -> DrawResult,
) -> Result<PathBuf, PlotError> {
    let result = {
        let root = SVGBackend::new(path, size).into_drawing_area();
        root.fill(&WHITE)
            .map_err(Into::into)
            .and_then(|()| f(&root))
            .and_then(|()| root.present().map_err(Into::into))
    };
    result.map_err(|source| PlotError::Draw {
        path: path.to_path_buf(),
        source,
    })?;
    Ok(path.to_path_buf())
}

/// Writes `error_vel.svg`, `error_bias_gyro.svg` and `error_bias_accel.svg`
/// (each axis's error with ±3σ, from `imu_state.txt`) into `dir`, creating it;
/// returns the files.
pub fn write_imu_plots(records: &[ImuStateRecord], dir: &Path) -> Result<Vec<PathBuf>, PlotError> {
    std::fs::create_dir_all(dir).map_err(|source| PlotError::Folder {
        path: dir.to_path_buf(),
        source,
    })?;
    let t0 = records.first().map_or(0.0, |r| r.estimate.t);
    let at = |r: &ImuStateRecord| r.estimate.t - t0;
    let sigma = |m: &Matrix3<f64>| Some([0, 1, 2].map(|k| m[(k, k)].max(0.0).sqrt()));
    let panels: [(&str, &str, &str, ErrorOf<ImuStateRecord>); 3] = [
        ("error_vel.svg", "velocity error", "m/s", |r| {
            let e = r.truth.vel - r.estimate.vel;
            ([e.x, e.y, e.z], r.estimate.cov_vel)
        }),
        ("error_bias_gyro.svg", "gyro bias error", "rad/s", |r| {
            let e = r.truth.bias_gyro - r.estimate.bias_gyro;
            ([e.x, e.y, e.z], r.estimate.cov_bias_gyro)
        }),
        (
            "error_bias_accel.svg",
            "accelerometer bias error",
            "m/s²",
            |r| {
                let e = r.truth.bias_accel - r.estimate.bias_accel;
                ([e.x, e.y, e.z], r.estimate.cov_bias_accel)
            },
        ),
    ];
    panels
        .into_iter()
        .map(|(name, what, unit, get)| {
            draw_svg(&dir.join(name), SIZE, &|root| {
                errors(root, records, at, what, unit, |r| {
                    let (e, cov) = get(r);
                    (e, sigma(&cov))
                })
            })
        })
        .collect()
}

/// Draws the NEES averaged over `runs` runs at each epoch with its two-sided
/// 95 % band ([`crate::anees`]) into the SVG file `path`: one panel per kind
/// that has values.
pub fn write_anees_plot(path: &Path, epochs: &[Epoch], runs: usize) -> Result<PathBuf, PlotError> {
    if let Some(parent) = path.parent() {
        std::fs::create_dir_all(parent).map_err(|source| PlotError::Folder {
            path: parent.to_path_buf(),
            source,
        })?;
    }
    let kinds: Vec<usize> = (0..KINDS.len())
        .filter(|&k| epochs.iter().any(|e| e.averages[k].is_some()))
        .collect();
    let t0 = epochs.first().map_or(0.0, |e| e.t);
    let height = 60 + 220 * kinds.len().max(1) as u32;
    draw_svg(path, (1000, height), &|root| {
        let panels = root.split_evenly((kinds.len().max(1), 1));
        let t_range = range(epochs.iter().map(|e| e.t - t0));
        for (panel, &k) in panels.iter().zip(&kinds) {
            let (name, dof) = KINDS[k];
            let points: Vec<(f64, f64, f64, f64)> = epochs
                .iter()
                .filter_map(|e| {
                    let a = e.averages[k]?;
                    let (lo, hi) = band(dof, a.runs);
                    Some((e.t - t0, a.value, lo, hi))
                })
                .collect();
            let high = points.iter().map(|p| p.3).fold(0.0, f64::max);
            // Clip rare huge values so the band stays readable.
            let top =
                (1.1 * percentile(points.iter().map(|p| p.1), 0.99).unwrap_or(0.0)).max(1.3 * high);
            let mut chart = nees_chart(
                panel,
                &format!("{name}: NEES averaged over {runs} runs ({dof} DoF) and its 95 % band"),
                t_range.clone(),
                top,
            )?;
            chart
                .draw_series(LineSeries::new(
                    points.iter().map(|p| (p.0, p.1.min(top))),
                    COLORS[2].stroke_width(2),
                ))?
                .label("average")
                .legend(|(x, y)| PathElement::new(vec![(x, y), (x + 20, y)], COLORS[2]));
            chart
                .draw_series(LineSeries::new(
                    points.iter().map(|p| (p.0, p.2)),
                    COLORS[0],
                ))?
                .label("95 % band")
                .legend(|(x, y)| PathElement::new(vec![(x, y), (x + 20, y)], COLORS[0]));
            chart.draw_series(LineSeries::new(
                points.iter().map(|p| (p.0, p.3)),
                COLORS[0],
            ))?;
            chart
                .configure_series_labels()
                .background_style(WHITE.mix(0.8))
                .border_style(BLACK)
                .draw()?;
        }
        Ok(())
    })
}

/// A NEES-over-time chart on `panel`: time on x, NEES from 0 to `top` on y.
fn nees_chart<'a, 'b>(
    panel: &'a Area<'b>,
    caption: &str,
    t_range: Range<f64>,
    top: f64,
) -> Result<NeesChart<'a, 'b>, Box<dyn std::error::Error + Send + Sync>> {
    let mut chart = ChartBuilder::on(panel)
        .caption(caption, ("sans-serif", 18))
        .margin(8)
        .x_label_area_size(35)
        .y_label_area_size(60)
        .build_cartesian_2d(t_range, 0.0..top)?;
    chart
        .configure_mesh()
        .label_style(("sans-serif", 15))
        .x_desc("time [s]")
        .y_desc("NEES")
        .draw()?;
    Ok(chart)
}

/// The chart [`nees_chart`] makes.
type NeesChart<'a, 'b> =
    ChartContext<'a, SVGBackend<'b>, Cartesian2d<RangedCoordf64, RangedCoordf64>>;

/// An item's error per axis and its covariance.
type ErrorOf<T> = fn(&T) -> ([f64; 3], Matrix3<f64>);

/// Top-down view of the aligned estimate and the ground truth, equal axes.
fn trajectory_xy(root: &Area, report: &EvalReport) -> DrawResult {
    let xy = |p: [f64; 3]| (p[0], p[1]);
    let gt = report.per_pose.iter().map(|p| xy(p.gt_pos)).collect();
    let est = report.per_pose.iter().map(|p| xy(p.est_pos)).collect();
    draw_xy(
        root,
        &format!("trajectory x-y (alignment {})", report.align),
        gt,
        vec![("estimate".into(), est, COLORS[2])],
    )
}

/// One estimated path of a top-down chart: legend label, x-y points, colour.
pub(crate) type XyPath = (String, Vec<(f64, f64)>, RGBColor);

/// A top-down chart with equal axes: the ground truth `gt` in black and each
/// path of `estimates` over it, with a legend.
pub(crate) fn draw_xy(
    root: &Area,
    caption: &str,
    gt: Vec<(f64, f64)>,
    estimates: Vec<XyPath>,
) -> DrawResult {
    let all = || gt.iter().chain(estimates.iter().flat_map(|e| &e.1));
    let (xs, ys) = (range(all().map(|p| p.0)), range(all().map(|p| p.1)));
    let half = 0.5 * (xs.end - xs.start).max(ys.end - ys.start);
    let (cx, cy) = (0.5 * (xs.start + xs.end), 0.5 * (ys.start + ys.end));
    let mut chart = ChartBuilder::on(root)
        .caption(caption, ("sans-serif", 24))
        .margin(15)
        .x_label_area_size(45)
        .y_label_area_size(60)
        .build_cartesian_2d(cx - half..cx + half, cy - half..cy + half)?;
    chart
        .configure_mesh()
        .label_style(("sans-serif", 15))
        .x_desc("x [m]")
        .y_desc("y [m]")
        .draw()?;
    chart
        .draw_series(LineSeries::new(gt, BLACK.stroke_width(2)))?
        .label("ground truth")
        .legend(|(x, y)| PathElement::new(vec![(x, y), (x + 20, y)], BLACK));
    for (label, points, c) in estimates {
        chart
            .draw_series(LineSeries::new(points, c.stroke_width(2)))?
            .label(label)
            .legend(move |(x, y)| PathElement::new(vec![(x, y), (x + 20, y)], c));
    }
    chart
        .configure_series_labels()
        .background_style(WHITE.mix(0.8))
        .border_style(BLACK)
        .draw()?;
    Ok(())
}

/// One panel per axis: the error of each item at its time `at` and, where
/// known, ±3σ.
fn errors<T>(
    root: &Area,
    items: &[T],
    at: impl Fn(&T) -> f64,
    what: &str,
    unit: &str,
    get: impl Fn(&T) -> ([f64; 3], Option<[f64; 3]>),
) -> DrawResult {
    let panels = root.split_evenly((3, 1));
    let t_range = range(items.iter().map(&at));
    for (k, panel) in panels.iter().enumerate() {
        let err: Vec<(f64, f64)> = items.iter().map(|p| (at(p), get(p).0[k])).collect();
        let bound: Vec<(f64, f64)> = items
            .iter()
            .filter_map(|p| get(p).1.map(|s| (at(p), 3.0 * s[k])))
            .collect();
        let y = range(
            err.iter()
                .map(|e| e.1)
                .chain(bound.iter().flat_map(|b| [b.1, -b.1])),
        );
        let mut chart = ChartBuilder::on(panel)
            .caption(format!("{what} {}", AXES[k]), ("sans-serif", 18))
            .margin(8)
            .x_label_area_size(35)
            .y_label_area_size(70)
            .build_cartesian_2d(t_range.clone(), y)?;
        chart
            .configure_mesh()
            .label_style(("sans-serif", 15))
            .x_desc("time [s]")
            .y_desc(format!("{} [{unit}]", AXES[k]))
            .draw()?;
        chart
            .draw_series(LineSeries::new(err, COLORS[k].stroke_width(2)))?
            .label("error")
            .legend(move |(x, y)| PathElement::new(vec![(x, y), (x + 20, y)], COLORS[k]));
        if !bound.is_empty() {
            let lower: Vec<(f64, f64)> = bound.iter().map(|&(t, b)| (t, -b)).collect();
            chart
                .draw_series(LineSeries::new(bound, BLACK.mix(0.6)))?
                .label("±3σ")
                .legend(|(x, y)| PathElement::new(vec![(x, y), (x + 20, y)], BLACK.mix(0.6)));
            chart.draw_series(LineSeries::new(lower, BLACK.mix(0.6)))?;
        }
        chart
            .configure_series_labels()
            .background_style(WHITE.mix(0.8))
            .border_style(BLACK)
            .draw()?;
    }
    Ok(())
}

/// NEES of orientation and position over time with the 95 % single-run bounds.
fn nees(root: &Area, report: &EvalReport, t0: f64) -> DrawResult {
    let panels = root.split_evenly((2, 1));
    let t_range = range(report.per_pose.iter().map(|p| p.t - t0));
    let series: [NeesPanel; 2] = [
        ("orientation", report.nees_ori, |p| p.nees_ori),
        ("position", report.nees_pos, |p| p.nees_pos),
    ];
    for (panel, (name, mean, get)) in panels.iter().zip(series) {
        let values: Vec<(f64, f64)> = report
            .per_pose
            .iter()
            .filter_map(|p| get(p).map(|v| (p.t - t0, v)))
            .collect();
        // Clip rare huge values so the bounds stay visible.
        let top = (1.1 * percentile(values.iter().map(|v| v.1), 0.99).unwrap_or(0.0))
            .max(1.2 * CHI2_3DOF_95_HIGH);
        let values: Vec<(f64, f64)> = values.into_iter().map(|(t, v)| (t, v.min(top))).collect();
        let mean_text = mean.map_or_else(|| "-".to_string(), |m| format!("{m:.3}"));
        let mut chart = nees_chart(
            panel,
            &format!("{name} NEES (mean {mean_text}, 3 DoF)"),
            t_range.clone(),
            top,
        )?;
        chart
            .draw_series(LineSeries::new(values, COLORS[2].stroke_width(2)))?
            .label("NEES")
            .legend(|(x, y)| PathElement::new(vec![(x, y), (x + 20, y)], COLORS[2]));
        for (i, level) in [CHI2_3DOF_95_LOW, CHI2_3DOF_95_HIGH]
            .into_iter()
            .enumerate()
        {
            let line = [(t_range.start, level), (t_range.end, level)];
            let series = chart.draw_series(LineSeries::new(line, COLORS[0]))?;
            if i == 0 {
                series
                    .label(format!(
                        "95% bounds {CHI2_3DOF_95_LOW}, {CHI2_3DOF_95_HIGH}"
                    ))
                    .legend(|(x, y)| PathElement::new(vec![(x, y), (x + 20, y)], COLORS[0]));
            }
        }
        chart
            .configure_series_labels()
            .background_style(WHITE.mix(0.8))
            .border_style(BLACK)
            .draw()?;
    }
    Ok(())
}

/// The range of the finite values with 5 % padding (`-1..1` when empty,
/// widened around a single value).
pub(crate) fn range(values: impl Iterator<Item = f64>) -> Range<f64> {
    let (lo, hi) = values
        .filter(|v| v.is_finite())
        .fold((f64::INFINITY, f64::NEG_INFINITY), |(lo, hi), v| {
            (lo.min(v), hi.max(v))
        });
    if lo > hi {
        return -1.0..1.0;
    }
    let pad = if hi - lo > 1e-12 {
        0.05 * (hi - lo)
    } else {
        1e-3_f64.max(0.05 * lo.abs())
    };
    lo - pad..hi + pad
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_band_plot_has_a_panel_per_kind_with_values() {
        use crate::anees::Average;
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("sub/robot0.svg");
        let epochs: Vec<Epoch> = (0..50)
            .map(|i| {
                let mut averages = [None; KINDS.len()];
                averages[0] = Some(Average {
                    value: 3.0 + (i as f64 * 0.3).sin(),
                    runs: 20,
                });
                averages[3] = Some(Average {
                    value: 0.1,
                    runs: 19,
                });
                Epoch {
                    t: 5.0 + 0.1 * i as f64,
                    averages,
                }
            })
            .collect();
        write_anees_plot(&path, &epochs, 20).unwrap();
        let svg = std::fs::read_to_string(&path).unwrap();
        assert!(
            svg.contains("ori: NEES averaged over 20 runs (3 DoF)"),
            "ori panel"
        );
        assert!(
            svg.contains("yaw: NEES averaged over 20 runs (1 DoF)"),
            "yaw panel"
        );
        assert!(!svg.contains("pos: NEES"), "no panel without values");
        write_anees_plot(&dir.path().join("empty.svg"), &[], 0).unwrap();
    }

    #[test]
    fn ranges_pad_the_data_and_survive_empty_or_constant_input() {
        let r = range([0.0, 10.0].into_iter());
        assert!((r.start + 0.5).abs() < 1e-12 && (r.end - 10.5).abs() < 1e-12);
        assert_eq!(range(std::iter::empty()), -1.0..1.0);
        let c = range([2.0, 2.0, f64::NAN].into_iter());
        assert!(c.start < 2.0 && c.end > 2.0);
    }
}
