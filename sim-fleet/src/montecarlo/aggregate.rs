//! Aggregation of Monte-Carlo runs: the metric keys averaged over the runs
//! (seeds), their spread (smallest and largest run), and divergence counts,
//! per robot and for the robot mean of each run.
//!
//! Every function here is a pure function of its inputs, in their order: the
//! caller sorts the runs (by variant, seed, robot) so that the aggregate does
//! not depend on the order in which the runs finished.

use super::stats::mean_ci95;
use crate::anees::AneesSummary;
use common::summary::{MetricSet, RpeEntry};
use serde::{Deserialize, Serialize};

/// A run whose ATE position RMSE exceeds this (metres), or that has none (a
/// failed run, or NaN), diverged.
pub const DIVERGED_ATE_POS_M: f64 = 10.0;

/// What one robot produced in one run (one seed) of one variant.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct RobotOutcome {
    /// Its metrics (all `None` when the run failed).
    pub metrics: MetricSet,
    /// Why the run failed (an estimator error or panic), if it did.
    pub error: Option<String>,
}

impl RobotOutcome {
    /// A successful run with only its ATE position known (tests of the tables).
    #[cfg(test)]
    pub fn with_ate_pos(ate_pos_m: f64) -> Self {
        RobotOutcome {
            metrics: MetricSet {
                ate_pos_m: Some(ate_pos_m),
                ..MetricSet::default()
            },
            error: None,
        }
    }
}

/// The smallest and the largest value of a metric over runs.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct Range {
    /// Smallest value.
    pub min: f64,
    /// Largest value.
    pub max: f64,
}

/// The spread over runs of the scalar metric keys (the [`MetricSet`] names);
/// `null` for a key no run has.
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct Spread {
    /// ATE orientation RMSE (degrees).
    pub ate_ori_deg: Option<Range>,
    /// ATE position RMSE (m).
    pub ate_pos_m: Option<Range>,
    /// Mean orientation NEES.
    pub nees_ori: Option<Range>,
    /// Mean position NEES.
    pub nees_pos: Option<Range>,
    /// Camera frames processed.
    pub frames: Option<Range>,
    /// Mean processing time per frame (ms).
    pub ms_per_frame_mean: Option<Range>,
    /// 95th percentile of the processing time per frame (ms).
    pub ms_per_frame_p95: Option<Range>,
}

impl Spread {
    /// The field-wise smallest and largest values over `sets`, each field over
    /// the sets that have it. Non-finite values are left out (give the sets
    /// through [`finite_only`] to make that explicit).
    pub fn of(sets: &[MetricSet]) -> Spread {
        let r = |get: fn(&MetricSet) -> Option<f64>| range(sets.iter().filter_map(get));
        Spread {
            ate_ori_deg: r(|s| s.ate_ori_deg),
            ate_pos_m: r(|s| s.ate_pos_m),
            nees_ori: r(|s| s.nees_ori),
            nees_pos: r(|s| s.nees_pos),
            frames: r(|s| s.frames.map(|f| f as f64)),
            ms_per_frame_mean: r(|s| s.ms_per_frame_mean),
            ms_per_frame_p95: r(|s| s.ms_per_frame_p95),
        }
    }
}

/// The range of the finite values, `None` for none.
fn range(values: impl Iterator<Item = f64>) -> Option<Range> {
    values.filter(|v| v.is_finite()).fold(None, |acc, v| {
        Some(match acc {
            None => Range { min: v, max: v },
            Some(r) => Range {
                min: r.min.min(v),
                max: r.max.max(v),
            },
        })
    })
}

/// The scalar accuracy and consistency keys of one run (`null` where the run
/// has none): what paired comparisons of studies match seed by seed.
#[derive(Clone, Copy, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct Scalars {
    /// ATE orientation RMSE (degrees).
    pub ate_ori_deg: Option<f64>,
    /// ATE position RMSE (m).
    pub ate_pos_m: Option<f64>,
    /// Mean orientation NEES.
    pub nees_ori: Option<f64>,
    /// Mean position NEES.
    pub nees_pos: Option<f64>,
    /// ATE orientation RMSE after a position-and-yaw alignment (degrees).
    #[serde(default)]
    pub ate_posyaw_ori_deg: Option<f64>,
    /// ATE position RMSE after a position-and-yaw alignment (m).
    #[serde(default)]
    pub ate_posyaw_pos_m: Option<f64>,
}

impl Scalars {
    /// The scalar keys of `m`.
    pub fn of(m: &MetricSet) -> Scalars {
        Scalars {
            ate_ori_deg: m.ate_ori_deg,
            ate_pos_m: m.ate_pos_m,
            nees_ori: m.nees_ori,
            nees_pos: m.nees_pos,
            ate_posyaw_ori_deg: m.ate_posyaw_ori_deg,
            ate_posyaw_pos_m: m.ate_posyaw_pos_m,
        }
    }

    /// Each key with its name, in table order.
    pub fn named(&self) -> [(&'static str, Option<f64>); 6] {
        [
            ("ATE ori deg", self.ate_ori_deg),
            ("ATE pos m", self.ate_pos_m),
            ("NEES ori", self.nees_ori),
            ("NEES pos", self.nees_pos),
            ("aligned ATE ori deg", self.ate_posyaw_ori_deg),
            ("aligned ATE pos m", self.ate_posyaw_pos_m),
        ]
    }

    /// Half-widths of the 95 % intervals of the means of each key over `runs`
    /// (Student t; `null` for fewer than two runs with the key).
    pub fn ci95_of(runs: &[Scalars]) -> Scalars {
        let ci = |get: fn(&Scalars) -> Option<f64>| {
            mean_ci95(runs.iter().filter_map(get)).and_then(|c| c.half_width)
        };
        Scalars {
            ate_ori_deg: ci(|s| s.ate_ori_deg),
            ate_pos_m: ci(|s| s.ate_pos_m),
            nees_ori: ci(|s| s.nees_ori),
            nees_pos: ci(|s| s.nees_pos),
            ate_posyaw_ori_deg: ci(|s| s.ate_posyaw_ori_deg),
            ate_posyaw_pos_m: ci(|s| s.ate_posyaw_pos_m),
        }
    }
}

/// One robot of a variant, aggregated over the runs.
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct RobotAggregate {
    /// Robot index in the scenario.
    pub id: u32,
    /// The robot's name (its trajectory file stem unless the scenario names it).
    pub trajectory: String,
    /// The metric keys averaged over the runs that have them
    /// ([`MetricSet::mean_of`]; RPE averaged per segment length).
    pub metrics: MetricSet,
    /// Smallest and largest run of each scalar key.
    pub spread: Spread,
    /// Half-width of the 95 % interval of each scalar mean ([`Scalars::ci95_of`]).
    #[serde(default)]
    pub ci95: Scalars,
    /// Each run's scalar keys, in seed order (`StudySummary::seeds`; all `null`
    /// for a run without this robot).
    #[serde(default)]
    pub per_run: Vec<Scalars>,
    /// Runs of this robot.
    pub runs: usize,
    /// Runs that diverged (see [`diverged`]), failed runs included.
    pub diverged: usize,
    /// Runs that failed (estimator error or panic; their metrics are `null`).
    pub failed: usize,
    /// The NEES averaged over the runs at each epoch against the band of a
    /// consistent filter ([`crate::anees`]; `null` without runs to read).
    #[serde(default)]
    pub anees: Option<AneesSummary>,
}

/// One variant of the study, aggregated over the runs.
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct VariantAggregate {
    /// The average over the runs of each run's robot mean.
    pub mean: MetricSet,
    /// Smallest and largest robot mean of a run, per scalar key.
    pub mean_spread: Spread,
    /// Half-width of the 95 % interval of each scalar of `mean`, over the runs'
    /// robot means ([`Scalars::ci95_of`]).
    #[serde(default)]
    pub mean_ci95: Scalars,
    /// Each run's robot mean, in seed order (`StudySummary::seeds`).
    #[serde(default)]
    pub run_means: Vec<Scalars>,
    /// Each robot, aggregated over the runs.
    pub robots: Vec<RobotAggregate>,
    /// Runs (seeds) of the variant.
    pub runs: usize,
    /// Robot runs that diverged, over all robots and seeds.
    pub diverged: usize,
    /// Robot runs that failed, over all robots and seeds.
    pub failed: usize,
    /// Agent runs that ended holding whole every keyframe window their peers
    /// published (`null`: no run knows, as in independent or centralized
    /// variants).
    #[serde(default)]
    pub histories_complete: Option<usize>,
}

/// Whether a robot run diverged: its ATE position is missing, NaN, or above
/// [`DIVERGED_ATE_POS_M`].
pub fn diverged(metrics: &MetricSet) -> bool {
    !matches!(metrics.ate_pos_m, Some(v) if v <= DIVERGED_ATE_POS_M)
}

/// `metrics` with every non-finite value (NaN, ±∞) replaced by `None`: JSON
/// has no such numbers (a summary file writes them as `null`), and a mean
/// over them says nothing. The run still counts in [`diverged`].
pub fn finite_only(metrics: &MetricSet) -> MetricSet {
    let f = |v: Option<f64>| v.filter(|x| x.is_finite());
    MetricSet {
        ate_ori_deg: f(metrics.ate_ori_deg),
        ate_pos_m: f(metrics.ate_pos_m),
        ate_posyaw_ori_deg: f(metrics.ate_posyaw_ori_deg),
        ate_posyaw_pos_m: f(metrics.ate_posyaw_pos_m),
        nees_ori: f(metrics.nees_ori),
        nees_pos: f(metrics.nees_pos),
        rpe: metrics.rpe.as_ref().map(|rows| {
            rows.iter()
                .map(|r| RpeEntry {
                    segment_m: r.segment_m,
                    ori_deg_mean: f(r.ori_deg_mean),
                    pos_m_mean: f(r.pos_m_mean),
                    ori_deg_median: f(r.ori_deg_median),
                    pos_m_median: f(r.pos_m_median),
                    count: r.count,
                })
                .collect()
        }),
        ms_per_frame_mean: f(metrics.ms_per_frame_mean),
        ms_per_frame_p95: f(metrics.ms_per_frame_p95),
        ..metrics.clone()
    }
}

/// Aggregates one variant. `robots` lists each robot's `(id, name)`;
/// `runs[k][r]` is robot `r` in run `k` (runs in seed order, robots in the
/// order of `robots`; a run missing a robot just does not count for it).
///
/// A robot's `metrics` are the means over its runs; the variant's `mean` is
/// the mean over the runs of each run's robot mean (the robots that have a
/// value). Means are [`MetricSet::mean_of`] over [`finite_only`] values.
pub fn aggregate_variant(robots: &[(u32, String)], runs: &[Vec<RobotOutcome>]) -> VariantAggregate {
    let robot_aggregates: Vec<RobotAggregate> = robots
        .iter()
        .enumerate()
        .map(|(r, (id, name))| {
            let outcomes: Vec<&RobotOutcome> = runs.iter().filter_map(|run| run.get(r)).collect();
            let sets: Vec<MetricSet> = outcomes.iter().map(|o| finite_only(&o.metrics)).collect();
            // Aligned with the seeds: a run without this robot gives nulls.
            let per_run: Vec<Scalars> = runs
                .iter()
                .map(|run| {
                    run.get(r)
                        .map(|o| Scalars::of(&finite_only(&o.metrics)))
                        .unwrap_or_default()
                })
                .collect();
            RobotAggregate {
                id: *id,
                trajectory: name.clone(),
                metrics: MetricSet::mean_of(&sets),
                spread: Spread::of(&sets),
                ci95: Scalars::ci95_of(&per_run),
                per_run,
                runs: outcomes.len(),
                diverged: outcomes.iter().filter(|o| diverged(&o.metrics)).count(),
                failed: outcomes.iter().filter(|o| o.error.is_some()).count(),
                anees: None,
            }
        })
        .collect();
    let run_means: Vec<MetricSet> = runs
        .iter()
        .map(|run| {
            let sets: Vec<MetricSet> = run.iter().map(|o| finite_only(&o.metrics)).collect();
            MetricSet::mean_of(&sets)
        })
        .collect();
    let scalars: Vec<Scalars> = run_means.iter().map(Scalars::of).collect();
    let owed = runs.iter().flatten().filter_map(|o| {
        let m = &o.metrics;
        m.peer_windows_whole.zip(m.peer_windows_published)
    });
    let histories_complete = owed
        .map(|(whole, published)| usize::from(whole >= published))
        .reduce(|a, b| a + b);
    VariantAggregate {
        histories_complete,
        mean: MetricSet::mean_of(&run_means),
        mean_spread: Spread::of(&run_means),
        mean_ci95: Scalars::ci95_of(&scalars),
        run_means: scalars,
        runs: runs.len(),
        diverged: robot_aggregates.iter().map(|r| r.diverged).sum(),
        failed: robot_aggregates.iter().map(|r| r.failed).sum(),
        robots: robot_aggregates,
    }
}

/// A robot run that failed (estimator error or panic).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct RunFailure {
    /// Variant name.
    pub variant: String,
    /// Seed of the run.
    pub seed: u64,
    /// Robot index.
    pub robot: u32,
    /// What went wrong.
    pub error: String,
}

/// The study's `summary.json`.
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct StudySummary {
    /// Scenario name.
    pub scenario: String,
    /// Runs (seeds) per variant.
    pub runs: usize,
    /// The seeds, in order.
    pub seeds: Vec<u64>,
    /// ATE position above which a run counts as diverged (m).
    pub diverged_ate_pos_m: f64,
    /// Wall-clock duration of the whole study (s).
    pub wall_s: Option<f64>,
    /// Each variant by name, in command-line order.
    #[serde(with = "ordered_map")]
    pub variants: Vec<(String, VariantAggregate)>,
    /// Every failed robot run (also counted as diverged).
    pub failures: Vec<RunFailure>,
}

impl StudySummary {
    /// The aggregate of variant `name`.
    pub fn variant(&self, name: &str) -> Option<&VariantAggregate> {
        self.variants
            .iter()
            .find(|(n, _)| n == name)
            .map(|(_, v)| v)
    }
}

/// A list of `(name, value)` pairs as a JSON object that keeps their order.
mod ordered_map {
    use super::VariantAggregate;
    use serde::de::{MapAccess, Visitor};
    use serde::{Deserializer, Serializer};
    use std::fmt;

    pub fn serialize<S: Serializer>(
        entries: &[(String, VariantAggregate)],
        serializer: S,
    ) -> Result<S::Ok, S::Error> {
        serializer.collect_map(entries.iter().map(|(k, v)| (k, v)))
    }

    pub fn deserialize<'de, D: Deserializer<'de>>(
        deserializer: D,
    ) -> Result<Vec<(String, VariantAggregate)>, D::Error> {
        struct Entries;
        impl<'de> Visitor<'de> for Entries {
            type Value = Vec<(String, VariantAggregate)>;
            fn expecting(&self, f: &mut fmt::Formatter) -> fmt::Result {
                f.write_str("an object of variant names to aggregates")
            }
            fn visit_map<A: MapAccess<'de>>(self, mut map: A) -> Result<Self::Value, A::Error> {
                let mut out = Vec::new();
                while let Some(entry) = map.next_entry()? {
                    out.push(entry);
                }
                Ok(out)
            }
        }
        deserializer.deserialize_map(Entries)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn set(ate_pos: Option<f64>, ate_ori: Option<f64>, frames: Option<u64>) -> MetricSet {
        MetricSet {
            ate_pos_m: ate_pos,
            ate_ori_deg: ate_ori,
            nees_pos: ate_pos.map(|v| 10.0 * v),
            frames,
            ..MetricSet::default()
        }
    }

    fn ok(metrics: MetricSet) -> RobotOutcome {
        RobotOutcome {
            metrics,
            error: None,
        }
    }

    fn robots(n: u32) -> Vec<(u32, String)> {
        (0..n).map(|i| (i, format!("traj{i}"))).collect()
    }

    #[test]
    fn a_robot_metric_is_the_mean_over_runs_with_the_smallest_and_largest_run() {
        let runs = vec![
            vec![ok(set(Some(0.1), Some(1.0), Some(100)))],
            vec![ok(set(Some(0.3), Some(2.0), Some(101)))],
            vec![ok(set(Some(0.2), Some(6.0), Some(102)))],
        ];
        let v = aggregate_variant(&robots(1), &runs);
        let r = &v.robots[0];
        assert!((r.metrics.ate_pos_m.unwrap() - 0.2).abs() < 1e-12);
        assert!((r.metrics.ate_ori_deg.unwrap() - 3.0).abs() < 1e-12);
        assert_eq!(r.metrics.frames, Some(101));
        assert_eq!(r.spread.ate_pos_m, Some(Range { min: 0.1, max: 0.3 }));
        assert_eq!(r.spread.ate_ori_deg, Some(Range { min: 1.0, max: 6.0 }));
        assert_eq!(
            r.spread.frames,
            Some(Range {
                min: 100.0,
                max: 102.0
            })
        );
        assert_eq!((r.runs, r.diverged, r.failed), (3, 0, 0));
        assert_eq!(r.trajectory, "traj0");
        assert_eq!(v.runs, 3);
    }

    #[test]
    fn the_variant_mean_averages_each_runs_robot_mean_and_spreads_over_those_means() {
        // Run 1: robots 0.1 and 0.3 (mean 0.2); run 2: 0.5 and 0.7 (mean 0.6).
        let runs = vec![
            vec![
                ok(set(Some(0.1), None, None)),
                ok(set(Some(0.3), None, None)),
            ],
            vec![
                ok(set(Some(0.5), None, None)),
                ok(set(Some(0.7), None, None)),
            ],
        ];
        let v = aggregate_variant(&robots(2), &runs);
        assert!((v.mean.ate_pos_m.unwrap() - 0.4).abs() < 1e-12);
        let s = v.mean_spread.ate_pos_m.unwrap();
        assert!((s.min - 0.2).abs() < 1e-12 && (s.max - 0.6).abs() < 1e-12);
        assert!((v.robots[1].metrics.ate_pos_m.unwrap() - 0.5).abs() < 1e-12);
        assert_eq!(v.robots.len(), 2);
    }

    #[test]
    fn each_runs_scalars_stay_in_seed_order_with_the_interval_of_the_mean() {
        // Run 2 lacks robot 1: its slot stays, empty, so seeds still line up.
        let runs = vec![
            vec![
                ok(set(Some(0.1), Some(1.0), None)),
                ok(set(Some(0.3), None, None)),
            ],
            vec![ok(set(Some(0.5), Some(2.0), None))],
            vec![
                ok(set(Some(0.3), Some(3.0), None)),
                ok(set(Some(0.7), None, None)),
            ],
        ];
        let v = aggregate_variant(&robots(2), &runs);
        let pos: Vec<Option<f64>> = v.robots[1].per_run.iter().map(|s| s.ate_pos_m).collect();
        assert_eq!(pos, vec![Some(0.3), None, Some(0.7)]);
        assert_eq!(v.run_means.len(), 3);
        assert!((v.run_means[1].ate_pos_m.unwrap() - 0.5).abs() < 1e-12);
        // Robot 0's orientation: 1, 2, 3 -> s = 1, t(2) = 4.303.
        let h = v.robots[0].ci95.ate_ori_deg.unwrap();
        assert!((h - 4.303 / 3f64.sqrt()).abs() < 1e-12, "{h}");
        assert!(v.robots[1].ci95.ate_pos_m.is_some());
        assert_eq!(v.robots[1].ci95.ate_ori_deg, None);
        assert!(v.mean_ci95.ate_pos_m.is_some());
    }

    #[test]
    fn keys_no_run_has_stay_null_and_missing_values_are_skipped_not_zeroed() {
        let runs = vec![
            vec![ok(set(Some(0.2), None, None))],
            vec![ok(set(Some(0.4), Some(3.0), None))],
        ];
        let v = aggregate_variant(&robots(1), &runs);
        let r = &v.robots[0];
        assert_eq!(r.metrics.ate_ori_deg, Some(3.0));
        assert_eq!(r.spread.ate_ori_deg, Some(Range { min: 3.0, max: 3.0 }));
        assert_eq!(r.metrics.frames, None);
        assert_eq!(r.spread.frames, None);
        assert_eq!(r.metrics.ms_per_frame_p95, None);
        assert_eq!(r.metrics.bytes_sent, None);
        let json = serde_json::to_value(&v).unwrap();
        assert!(json["mean"]["nees_ori"].is_null());
        assert!(json["mean_spread"]["frames"].is_null());
        assert!(json["robots"][0]["spread"]["ms_per_frame_mean"].is_null());
    }

    #[test]
    fn diverged_runs_are_counted_and_kept_in_the_mean_and_the_spread() {
        let runs = vec![
            vec![ok(set(Some(0.2), None, None))],
            vec![ok(set(Some(30.0), None, None))],
            vec![ok(set(Some(10.0), None, None))],
        ];
        let v = aggregate_variant(&robots(1), &runs);
        assert_eq!(v.diverged, 1, "10 m exactly is not diverged, 30 m is");
        assert_eq!(v.robots[0].diverged, 1);
        assert_eq!(v.robots[0].spread.ate_pos_m.unwrap().max, 30.0);
        assert!((v.mean.ate_pos_m.unwrap() - 40.2 / 3.0).abs() < 1e-12);
    }

    #[test]
    fn nan_and_failed_runs_count_as_diverged_and_leave_the_means_of_the_others() {
        let failed = RobotOutcome {
            metrics: MetricSet::default(),
            error: Some("estimator panicked".into()),
        };
        let runs = vec![
            vec![ok(set(Some(f64::NAN), Some(f64::INFINITY), Some(50)))],
            vec![failed],
            vec![ok(set(Some(0.5), Some(2.0), Some(150)))],
        ];
        let v = aggregate_variant(&robots(1), &runs);
        let r = &v.robots[0];
        assert_eq!((r.runs, r.diverged, r.failed), (3, 2, 1));
        assert_eq!((v.diverged, v.failed), (2, 1));
        assert_eq!(r.metrics.ate_pos_m, Some(0.5));
        assert_eq!(r.metrics.ate_ori_deg, Some(2.0));
        assert_eq!(r.spread.ate_pos_m, Some(Range { min: 0.5, max: 0.5 }));
        assert_eq!(
            r.metrics.frames,
            Some(100),
            "frames of the NaN run still count"
        );
        assert_eq!(v.mean.ate_pos_m, Some(0.5));
    }

    #[test]
    fn a_run_missing_in_every_seed_gives_null_metrics_and_zero_runs() {
        let runs = vec![vec![ok(set(Some(0.2), None, None))]];
        let v = aggregate_variant(&robots(2), &runs);
        assert_eq!(v.robots[1].runs, 0);
        assert_eq!(v.robots[1].metrics, MetricSet::default());
        assert_eq!(v.robots[1].spread, Spread::default());
    }

    #[test]
    fn rpe_is_averaged_per_segment_length_with_non_finite_statistics_dropped() {
        let row = |seg: f64, pos: f64| RpeEntry {
            segment_m: seg,
            ori_deg_mean: Some(1.0),
            pos_m_mean: Some(pos),
            ori_deg_median: Some(1.0),
            pos_m_median: Some(pos),
            count: 4,
        };
        let with_rpe = |rows: Vec<RpeEntry>| MetricSet {
            rpe: Some(rows),
            ..MetricSet::default()
        };
        let runs = vec![
            vec![ok(with_rpe(vec![row(8.0, 0.1), row(16.0, 0.2)]))],
            vec![ok(with_rpe(vec![row(8.0, 0.3), row(16.0, f64::NAN)]))],
        ];
        let v = aggregate_variant(&robots(1), &runs);
        let rpe = v.robots[0].metrics.rpe.clone().unwrap();
        assert_eq!(rpe.len(), 2);
        assert!((rpe[0].pos_m_mean.unwrap() - 0.2).abs() < 1e-12);
        assert_eq!(rpe[1].pos_m_mean, Some(0.2));
        assert_eq!(rpe[0].count, 8);
        assert_eq!(v.mean.rpe.unwrap()[0].segment_m, 8.0);
    }

    #[test]
    fn the_aggregate_is_bit_identical_for_the_same_sorted_runs() {
        let runs: Vec<Vec<RobotOutcome>> = (0..7)
            .map(|k| {
                let x = 0.1 + 0.37 * k as f64;
                vec![
                    ok(set(Some(x / 3.0), Some(x), Some(k))),
                    ok(set(Some(x / 7.0), Some(x * 1.3), Some(k + 1))),
                ]
            })
            .collect();
        let a = serde_json::to_string(&aggregate_variant(&robots(2), &runs)).unwrap();
        let b = serde_json::to_string(&aggregate_variant(&robots(2), &runs)).unwrap();
        assert_eq!(a, b);
    }

    #[test]
    fn the_study_summary_keeps_the_variant_order_through_json() {
        let study = StudySummary {
            scenario: "loop".into(),
            runs: 1,
            seeds: vec![3],
            diverged_ate_pos_m: DIVERGED_ATE_POS_M,
            wall_s: None,
            variants: vec![
                ("indp-slam".into(), VariantAggregate::default()),
                ("indp".into(), VariantAggregate::default()),
            ],
            failures: vec![],
        };
        let text = serde_json::to_string(&study).unwrap();
        let slam = text.find("\"indp-slam\"").unwrap();
        let indp = text.find("\"indp\"").unwrap();
        assert!(slam < indp, "{text}");
        let back: StudySummary = serde_json::from_str(&text).unwrap();
        assert_eq!(back, study);
        assert!(back.variant("indp").is_some());
        assert!(back.variant("msckf").is_none());
    }
}
