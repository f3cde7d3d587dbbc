//! `sim-fleet paired`: compares two variants of Monte-Carlo studies seed by
//! seed (e.g. `dc-full-history` against `indp-slam` in one study, or one
//! variant before and after a change in two studies with the same seeds). For
//! the robot mean and each robot, and for each scalar key, it prints both means,
//! the mean difference `b − a` with its 95 % t interval and the ratio of the
//! means `b / a` with a seeded bootstrap interval (`montecarlo::stats`).

use crate::montecarlo::aggregate::{Scalars, StudySummary, VariantAggregate};
use crate::montecarlo::stats::{paired, Paired};
use anyhow::{bail, Context, Result};
use serde::Serialize;
use std::fmt::Write as _;
use std::path::{Path, PathBuf};

/// Arguments of `sim-fleet paired`.
#[derive(clap::Args, Debug, Clone)]
pub struct PairedArgs {
    /// The reference, as `VARIANT=STUDY` (a `sim-fleet montecarlo` output folder
    /// or its `summary.json`).
    #[arg(long, value_parser = parse_side)]
    pub a: (String, PathBuf),
    /// The one compared with it, as `VARIANT=STUDY`.
    #[arg(long, value_parser = parse_side)]
    pub b: (String, PathBuf),
    /// Also write the comparison as JSON to this file.
    #[arg(long)]
    pub out: Option<PathBuf>,
}

fn parse_side(s: &str) -> Result<(String, PathBuf), String> {
    let (variant, path) = s
        .split_once('=')
        .ok_or_else(|| format!("expected VARIANT=STUDY, got `{s}`"))?;
    if variant.is_empty() {
        return Err(format!("no variant name in `{s}`"));
    }
    Ok((variant.to_string(), PathBuf::from(path)))
}

/// One row: a robot (or the robot mean) and one scalar key.
#[derive(Clone, Debug, PartialEq, Serialize)]
pub struct PairedRow {
    /// `mean` or the robot's index and name.
    pub robot: String,
    /// The key, as the Monte-Carlo table names it.
    pub metric: &'static str,
    /// The comparison (`None`: no seed has the key on both sides).
    pub stats: Option<Paired>,
}

/// The comparison of two variants over the seeds both studies ran.
#[derive(Clone, Debug, PartialEq, Serialize)]
pub struct PairedReport {
    /// `a` as given.
    pub a: String,
    /// `b` as given.
    pub b: String,
    /// The seeds compared (in `a`'s order).
    pub seeds: Vec<u64>,
    /// The rows: the robot mean first, then each robot.
    pub rows: Vec<PairedRow>,
}

/// Reads a study's `summary.json` (the folder or the file itself).
pub fn read_study(path: &Path) -> Result<StudySummary> {
    let file = if path.is_dir() {
        path.join("summary.json")
    } else {
        path.to_path_buf()
    };
    let text =
        std::fs::read_to_string(&file).with_context(|| format!("reading {}", file.display()))?;
    serde_json::from_str(&text).with_context(|| format!("parsing {}", file.display()))
}

fn variant<'a>(study: &'a StudySummary, name: &str, path: &Path) -> Result<&'a VariantAggregate> {
    match study.variant(name) {
        Some(v) if v.run_means.len() == study.seeds.len() => Ok(v),
        Some(_) => bail!(
            "{}: variant `{name}` has no per-seed values (a summary written before \
             `run_means` existed): run the study again",
            path.display()
        ),
        None => {
            let names: Vec<&str> = study.variants.iter().map(|(n, _)| n.as_str()).collect();
            bail!(
                "{}: no variant `{name}` (it has: {})",
                path.display(),
                names.join(", ")
            )
        }
    }
}

/// Compares variant `b` of study `sb` with variant `a` of study `sa` on the
/// seeds both have. Robots are matched by index; the per-robot rows need the
/// same robots on both sides (same count and names), else only the mean is
/// compared.
pub fn compare(
    (a, sa): (&str, &StudySummary),
    (b, sb): (&str, &StudySummary),
    paths: (&Path, &Path),
) -> Result<PairedReport> {
    let va = variant(sa, a, paths.0)?;
    let vb = variant(sb, b, paths.1)?;
    // (index in a, index in b) of each common seed, in a's order.
    let common: Vec<(usize, usize)> = sa
        .seeds
        .iter()
        .enumerate()
        .filter_map(|(i, s)| sb.seeds.iter().position(|t| t == s).map(|j| (i, j)))
        .collect();
    if common.is_empty() {
        bail!(
            "the studies share no seed ({:?} against {:?})",
            sa.seeds,
            sb.seeds
        );
    }
    let mut rows = Vec::new();
    let mut push = |robot: String, ra: &[Scalars], rb: &[Scalars]| {
        for (k, (metric, _)) in Scalars::default().named().iter().enumerate() {
            let pairs: Vec<(f64, f64)> = common
                .iter()
                .filter_map(|&(i, j)| {
                    let x = ra.get(i)?.named()[k].1?;
                    let y = rb.get(j)?.named()[k].1?;
                    Some((x, y))
                })
                .collect();
            rows.push(PairedRow {
                robot: robot.clone(),
                metric,
                stats: paired(&pairs),
            });
        }
    };
    push("mean".to_string(), &va.run_means, &vb.run_means);
    let same_robots = va.robots.len() == vb.robots.len()
        && va
            .robots
            .iter()
            .zip(&vb.robots)
            .all(|(x, y)| x.trajectory == y.trajectory);
    if same_robots {
        for (ra, rb) in va.robots.iter().zip(&vb.robots) {
            push(
                format!("{} {}", ra.id, ra.trajectory),
                &ra.per_run,
                &rb.per_run,
            );
        }
    }
    Ok(PairedReport {
        a: format!("{a}={}", paths.0.display()),
        b: format!("{b}={}", paths.1.display()),
        seeds: common.iter().map(|&(i, _)| sa.seeds[i]).collect(),
        rows,
    })
}

/// The report as a Markdown table.
pub fn render(report: &PairedReport) -> String {
    let mut out = String::new();
    let _ = writeln!(
        out,
        "Paired comparison of b = `{}` with a = `{}` over {} common seeds: means, \
         b − a ± the half-width of its 95 % t interval, b / a with its 95 % \
         bootstrap interval.\n",
        report.b,
        report.a,
        report.seeds.len()
    );
    out.push_str("| robot | metric | seeds | a | b | b − a | b / a |\n");
    out.push_str("| --- | --- | ---: | ---: | ---: | ---: | ---: |\n");
    for r in &report.rows {
        let Some(p) = &r.stats else {
            let _ = writeln!(out, "| {} | {} | 0 | - | - | - | - |", r.robot, r.metric);
            continue;
        };
        let diff = match p.diff_ci95 {
            Some(h) => format!("{:+.4} ± {h:.4}", p.diff),
            None => format!("{:+.4}", p.diff),
        };
        let ratio = ratio_cell(Some(p));
        let _ = writeln!(
            out,
            "| {} | {} | {} | {:.4} | {:.4} | {diff} | {ratio} |",
            r.robot, r.metric, p.n, p.mean_a, p.mean_b
        );
    }
    out
}

/// Every other variant of `study` compared with `baseline`, seed by seed
/// (`sim-fleet montecarlo --baseline`), in the study's variant order.
pub fn against_baseline(study: &StudySummary, baseline: &str) -> Result<BaselineComparison> {
    let here = Path::new("this study");
    let variants = study
        .variants
        .iter()
        .filter(|(n, _)| n != baseline)
        .map(|(name, _)| {
            compare((baseline, study), (name, study), (here, here)).map(|r| (name.clone(), r))
        })
        .collect::<Result<_>>()?;
    Ok(BaselineComparison {
        baseline: baseline.to_string(),
        variants,
    })
}

/// The variants of one study against its baseline (`DIR/baseline.json`).
#[derive(Clone, Debug, PartialEq, Serialize)]
pub struct BaselineComparison {
    /// The baseline variant.
    pub baseline: String,
    /// Each other variant with its comparison (`a` = the baseline).
    pub variants: Vec<(String, PairedReport)>,
}

impl BaselineComparison {
    /// One row per variant: the ratio of its robot mean to the baseline's for
    /// each scalar key, with the 95 % bootstrap interval.
    pub fn render(&self) -> String {
        let baseline = &self.baseline;
        let mut out = String::new();
        let _ = writeln!(
            out,
            "\nRatio of each variant's mean to `{baseline}`'s, seed by seed (95 % bootstrap \
             interval; below 1: smaller than {baseline}'s):\n"
        );
        let keys = Scalars::default().named();
        let names: Vec<&str> = keys.iter().map(|(n, _)| *n).collect();
        let _ = writeln!(out, "| variant | {} |", names.join(" | "));
        let _ = writeln!(out, "| --- |{}", " ---: |".repeat(names.len()));
        for (name, report) in &self.variants {
            let cells: Vec<String> = report
                .rows
                .iter()
                .filter(|r| r.robot == "mean")
                .map(|r| ratio_cell(r.stats.as_ref()))
                .collect();
            let _ = writeln!(out, "| {name} | {} |", cells.join(" | "));
        }
        out
    }
}

/// `b / a [lo-hi]`, `b / a` without an interval, or `-` without a ratio.
fn ratio_cell(p: Option<&Paired>) -> String {
    match p.and_then(|p| p.ratio.map(|x| (x, p.ratio_ci95))) {
        Some((x, Some((lo, hi)))) => format!("{x:.3} [{lo:.3}-{hi:.3}]"),
        Some((x, None)) => format!("{x:.3}"),
        None => "-".to_string(),
    }
}

/// `sim-fleet paired`: prints the table (and writes the JSON with `--out`).
pub fn run_paired(args: &PairedArgs) -> Result<()> {
    let (a, pa) = (&args.a.0, args.a.1.as_path());
    let (b, pb) = (&args.b.0, args.b.1.as_path());
    let sa = read_study(pa)?;
    let sb = read_study(pb)?;
    let report = compare((a, &sa), (b, &sb), (pa, pb))?;
    print!("{}", render(&report));
    if let Some(out) = &args.out {
        let text = serde_json::to_string_pretty(&report)?;
        std::fs::write(out, text + "\n").with_context(|| format!("writing {}", out.display()))?;
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::montecarlo::aggregate::{aggregate_variant, RobotOutcome, DIVERGED_ATE_POS_M};

    fn outcome(ate_pos: f64) -> RobotOutcome {
        RobotOutcome::with_ate_pos(ate_pos)
    }

    fn study(seeds: Vec<u64>, variants: Vec<(&str, Vec<Vec<f64>>)>) -> StudySummary {
        let robots = vec![(0, "x".to_string()), (1, "y".to_string())];
        StudySummary {
            scenario: "s".into(),
            runs: seeds.len(),
            seeds,
            diverged_ate_pos_m: DIVERGED_ATE_POS_M,
            wall_s: None,
            variants: variants
                .into_iter()
                .map(|(name, runs)| {
                    let runs: Vec<Vec<RobotOutcome>> = runs
                        .into_iter()
                        .map(|r| r.into_iter().map(outcome).collect())
                        .collect();
                    (name.to_string(), aggregate_variant(&robots, &runs))
                })
                .collect(),
            failures: vec![],
        }
    }

    #[test]
    fn two_variants_of_one_study_are_paired_seed_by_seed() {
        let s = study(
            vec![1, 2, 3],
            vec![
                ("indp", vec![vec![0.1, 0.3], vec![0.4, 0.2], vec![0.2, 0.2]]),
                (
                    "coop",
                    vec![vec![0.05, 0.15], vec![0.2, 0.1], vec![0.1, 0.1]],
                ),
            ],
        );
        let p = Path::new("mc");
        let r = compare(("indp", &s), ("coop", &s), (p, p)).unwrap();
        assert_eq!(r.seeds, vec![1, 2, 3]);
        // The mean and two robots, six keys each (with the aligned ATE).
        assert_eq!(r.rows.len(), 18);
        let pos = r
            .rows
            .iter()
            .find(|row| row.robot == "mean" && row.metric == "ATE pos m")
            .and_then(|row| row.stats)
            .unwrap();
        assert_eq!(pos.n, 3);
        assert!((pos.ratio.unwrap() - 0.5).abs() < 1e-12);
        let (lo, hi) = pos.ratio_ci95.unwrap();
        assert!((lo - 0.5).abs() < 1e-9 && (hi - 0.5).abs() < 1e-9);
        let ori = r
            .rows
            .iter()
            .find(|row| row.metric == "ATE ori deg")
            .unwrap();
        assert!(ori.stats.is_none(), "no run has the key");
        let table = render(&r);
        assert!(
            table.contains("| mean | ATE pos m | 3 | 0.2333 | 0.1167 |"),
            "{table}"
        );
        assert!(table.contains("| 1 y | ATE pos m | 3 |"), "{table}");
        assert!(table.contains("| mean | ATE ori deg | 0 | - |"), "{table}");
    }

    #[test]
    fn every_variant_is_set_against_the_baseline_in_one_row() {
        let s = study(
            vec![1, 2],
            vec![
                ("indp", vec![vec![0.2, 0.2], vec![0.4, 0.4]]),
                ("half", vec![vec![0.1, 0.1], vec![0.2, 0.2]]),
                ("same", vec![vec![0.2, 0.2], vec![0.4, 0.4]]),
            ],
        );
        let c = against_baseline(&s, "indp").unwrap();
        assert_eq!(c.variants.len(), 2);
        let t = c.render();
        assert!(
            t.contains("| half | - | 0.500 [0.500-0.500] | - | - |"),
            "{t}"
        );
        assert!(t.contains("| same | - | 1.000 [1.000-1.000] |"), "{t}");
        assert!(!t.contains("| indp |"), "{t}");
        // Header, rule and rows have as many cells as there are keys (+ name).
        let cells = |l: &str| l.matches('|').count();
        let widths: Vec<usize> = t
            .lines()
            .filter(|l| l.starts_with('|'))
            .map(cells)
            .collect();
        assert_eq!(widths.len(), 4, "{t}");
        assert!(
            widths
                .iter()
                .all(|w| *w == Scalars::default().named().len() + 2),
            "{t}"
        );
    }

    #[test]
    fn only_the_seeds_both_studies_ran_are_compared() {
        let a = study(vec![1, 2, 3], vec![("v", vec![vec![1.0, 1.0]; 3])]);
        let b = study(
            vec![3, 4, 2],
            vec![("v", vec![vec![3.0, 3.0], vec![9.0, 9.0], vec![2.0, 2.0]])],
        );
        let r = compare(("v", &a), ("v", &b), (Path::new("a"), Path::new("b"))).unwrap();
        assert_eq!(r.seeds, vec![2, 3]);
        let p = r.rows[1].stats.unwrap();
        assert_eq!((p.n, p.mean_b), (2, 2.5));
        let none = study(vec![7], vec![("v", vec![vec![1.0, 1.0]])]);
        let err = compare(("v", &a), ("v", &none), (Path::new("a"), Path::new("n")));
        assert!(err.unwrap_err().to_string().contains("share no seed"));
    }

    #[test]
    fn a_missing_variant_names_the_ones_there_are() {
        let s = study(vec![1], vec![("indp", vec![vec![1.0, 1.0]])]);
        let p = Path::new("mc");
        let err = compare(("indp", &s), ("dc", &s), (p, p)).unwrap_err();
        assert!(
            err.to_string().contains("no variant `dc` (it has: indp)"),
            "{err}"
        );
    }

    #[test]
    fn a_summary_without_per_seed_values_asks_for_a_new_study() {
        // A summary.json written before `run_means` existed parses (the keys
        // default to empty) but cannot be paired.
        let mut s = study(vec![1, 2], vec![("indp", vec![vec![1.0, 1.0]; 2])]);
        for (_, v) in &mut s.variants {
            v.run_means.clear();
        }
        let p = Path::new("old");
        let err = compare(("indp", &s), ("indp", &s), (p, p)).unwrap_err();
        assert!(err.to_string().contains("no per-seed values"), "{err}");
        let old = serde_json::to_string(&s)
            .unwrap()
            .replace("\"run_means\":[],", "");
        assert!(!old.contains("run_means"), "{old}");
        let back: StudySummary = serde_json::from_str(&old).expect("an old summary still parses");
        assert!(back.variants[0].1.run_means.is_empty());
    }

    #[test]
    fn sides_are_variant_equals_study() {
        assert_eq!(
            parse_side("dc-full-history=out/mc").unwrap(),
            ("dc-full-history".to_string(), PathBuf::from("out/mc"))
        );
        assert!(parse_side("out/mc").is_err());
        assert!(parse_side("=out/mc").is_err());
    }
}
