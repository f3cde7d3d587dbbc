//! The Markdown table of a Monte-Carlo study (`table.md`, also printed).

use super::aggregate::{Range, Scalars, StudySummary};
use common::summary::MetricSet;
use std::fmt::Write as _;

/// Renders the study as a Markdown table: one row per (variant, robot) and a
/// `mean` row per variant (the average over runs of each run's robot mean).
/// ATE columns show `mean ± h [min-max]` over the runs, `h` the half-width of
/// the mean's 95 % interval (Student t); `runs` counts the robot
/// runs of the row and `diverged` those that diverged (failed ones included,
/// also shown in brackets). `aligned` is the mean ATE after aligning each run by
/// position and yaw (the directions VIO cannot observe), deg / m. `CPU s` is
/// the mean CPU time of one robot's run (simulating its sensors included; see
/// `MetricSet::cpu_s`). Unknown values are `-`.
pub fn render_table(study: &StudySummary) -> String {
    let mut out = String::new();
    let seeds = match (study.seeds.first(), study.seeds.last()) {
        (Some(a), Some(b)) => format!("seeds {a}-{b}"),
        _ => "no seeds".to_string(),
    };
    let _ = writeln!(
        out,
        "Monte-Carlo study of `{}`: {} runs per variant ({seeds}); a run diverged if its ATE position exceeds {} m.\n",
        study.scenario, study.runs, study.diverged_ate_pos_m
    );
    out.push_str(
        "| variant | robot | ATE ori deg | ATE pos m | NEES ori | NEES pos | aligned deg / m | ms/frame | p95 ms | CPU s | runs | diverged |\n",
    );
    out.push_str(
        "| --- | --- | ---: | ---: | ---: | ---: | ---: | ---: | ---: | ---: | ---: | ---: |\n",
    );
    for (name, v) in &study.variants {
        for r in &v.robots {
            row(
                &mut out,
                name,
                &format!("{} {}", r.id, r.trajectory),
                &r.metrics,
                &r.ci95,
                (r.spread.ate_ori_deg, r.spread.ate_pos_m),
                (r.runs, r.diverged, r.failed),
            );
        }
        row(
            &mut out,
            name,
            "mean",
            &v.mean,
            &v.mean_ci95,
            (v.mean_spread.ate_ori_deg, v.mean_spread.ate_pos_m),
            (v.robots.iter().map(|r| r.runs).sum(), v.diverged, v.failed),
        );
    }
    traffic_table(&mut out, study);
    tracks_table(&mut out, study);
    frames_table(&mut out, study);
    anees_table(&mut out, study);
    out
}

/// The NEES averaged over the runs at each camera frame against the band of
/// a consistent filter ([`crate::anees`]), per robot.
fn anees_table(out: &mut String, study: &StudySummary) {
    let rows: Vec<_> = study
        .variants
        .iter()
        .flat_map(|(name, v)| v.robots.iter().map(move |r| (name, r)))
        .filter_map(|(name, r)| Some((name, r, r.anees.as_ref()?)))
        .collect();
    if rows.is_empty() {
        return;
    }
    out.push_str(
        "\nNEES averaged over the runs at each camera frame: its mean, then the share of frames inside / below / above the two-sided 95 % band of a consistent filter, % (tilt: roll and pitch in the world frame, yaw: about gravity; from a start at the truth the unobservable yaw and position sit below it):\n\n",
    );
    out.push_str("| variant | robot | runs | orientation | position | tilt | yaw | velocity | gyro bias | accel bias |\n");
    out.push_str("| --- | --- | ---: | --- | --- | --- | --- | --- | --- | --- |\n");
    for (name, r, a) in rows {
        let cells: Vec<String> = a.shares().into_iter().map(crate::anees::cell).collect();
        let _ = writeln!(
            out,
            "| {name} | {} {} | {} | {} |",
            r.id,
            r.trajectory,
            a.runs,
            cells.join(" | ")
        );
    }
}

/// For runs through rendered images: the image frontend's tracks against the
/// rendered truth, the mean error of each robot's tracks averaged over the
/// runs.
fn tracks_table(out: &mut String, study: &StudySummary) {
    let rows: Vec<_> = study
        .variants
        .iter()
        .flat_map(|(name, v)| v.robots.iter().map(move |r| (name, r)))
        .filter(|(_, r)| r.metrics.track_error_px.is_some())
        .collect();
    if rows.is_empty() {
        return;
    }
    out.push_str(
        "\nImage frontend's tracks against the rendered truth (`track_errors.csv` per run):\n\n",
    );
    out.push_str("| variant | robot | mean track error px |\n| --- | --- | ---: |\n");
    for (name, r) in rows {
        let _ = writeln!(
            out,
            "| {name} | {} {} | {} |",
            r.id,
            r.trajectory,
            num(r.metrics.track_error_px, 3)
        );
    }
}

/// For agents that found their peers' frames from loop closures
/// (`start_frame: own`): peers aligned per agent, how soon after its start,
/// and the alignments' errors at the end against the true relative start
/// poses, with their NEES (4 DoF: yaw, translation).
fn frames_table(out: &mut String, study: &StudySummary) {
    let agents: Vec<_> = study
        .variants
        .iter()
        .filter(|(_, v)| v.mean.peer_frames_aligned.is_some())
        .collect();
    if agents.is_empty() {
        return;
    }
    out.push_str(
        "\nPeer frames found from loop closures (means over the runs of each run's robot mean):\n\n",
    );
    out.push_str(
        "| variant | peers aligned | first after s | yaw error deg | position error m | NEES (4 DoF) |\n",
    );
    out.push_str("| --- | ---: | ---: | ---: | ---: | ---: |\n");
    for (name, v) in agents {
        let m = &v.mean;
        let _ = writeln!(
            out,
            "| {name} | {} | {} | {} | {} | {} |",
            m.peer_frames_aligned
                .map_or_else(|| "-".to_string(), |n| n.to_string()),
            num(m.first_peer_frame_s, 1),
            num(m.peer_frame_yaw_err_deg, 3),
            num(m.peer_frame_pos_err_m, 3),
            num(m.peer_frame_nees, 2),
        );
    }
}

/// The traffic of the variants whose robots ran as agents (they sent
/// something), per agent and averaged like the `mean` rows: KB sent per
/// second of fleet time, history replays sent to peers that asked for what
/// they had missed, the peers' keyframe windows held whole at the end against
/// those the peers published (and the agent runs that held all of them), the
/// peak heap of the peers' histories, loop closures and common-feature
/// updates.
fn traffic_table(out: &mut String, study: &StudySummary) {
    let agents: Vec<_> = study
        .variants
        .iter()
        .filter(|(_, v)| v.mean.bytes_per_s_sent.is_some())
        .collect();
    if agents.is_empty() {
        return;
    }
    out.push_str("\nTraffic per agent (means over the runs of each run's robot mean):\n\n");
    out.push_str(
        "| variant | KB/s sent | replayed KB | peer windows held whole | histories complete | peer histories MB | loop closures | common-feature updates |\n",
    );
    out.push_str("| --- | ---: | ---: | ---: | ---: | ---: | ---: | ---: |\n");
    let count = |v: Option<u64>| v.map_or_else(|| "-".to_string(), |v| v.to_string());
    for (name, v) in agents {
        let m = &v.mean;
        let windows = match (m.peer_windows_whole, m.peer_windows_published) {
            (Some(w), Some(p)) => format!("{w} of {p}"),
            _ => "-".to_string(),
        };
        let agent_runs: usize = v.robots.iter().map(|r| r.runs).sum();
        let complete = v
            .histories_complete
            .map_or_else(|| "-".to_string(), |c| format!("{c} of {agent_runs}"));
        let _ = writeln!(
            out,
            "| {name} | {} | {} | {windows} | {complete} | {} | {} | {} |",
            num(m.bytes_per_s_sent.map(|b| b / 1e3), 1),
            num(m.replay_bytes_sent.map(|b| b as f64 / 1e3), 1),
            num(m.history_bytes.map(|b| b as f64 / 1e6), 2),
            count(m.loop_closures),
            count(m.common_feature_updates),
        );
    }
}

fn row(
    out: &mut String,
    variant: &str,
    robot: &str,
    m: &MetricSet,
    ci: &Scalars,
    (ori_spread, pos_spread): (Option<Range>, Option<Range>),
    (runs, diverged, failed): (usize, usize, usize),
) {
    let diverged = if failed > 0 {
        format!("{diverged} ({failed} failed)")
    } else {
        diverged.to_string()
    };
    let _ = writeln!(
        out,
        "| {variant} | {robot} | {} | {} | {} | {} | {} / {} | {} | {} | {} | {runs} | {diverged} |",
        with_range(m.ate_ori_deg, ci.ate_ori_deg, ori_spread, 3),
        with_range(m.ate_pos_m, ci.ate_pos_m, pos_spread, 3),
        num(m.nees_ori, 2),
        num(m.nees_pos, 2),
        num(m.ate_posyaw_ori_deg, 3),
        num(m.ate_posyaw_pos_m, 3),
        num(m.ms_per_frame_mean, 2),
        num(m.ms_per_frame_p95, 2),
        num(m.cpu_s, 2),
    );
}

fn num(v: Option<f64>, decimals: usize) -> String {
    v.map_or_else(|| "-".to_string(), |v| format!("{v:.decimals$}"))
}

fn with_range(
    mean: Option<f64>,
    ci95: Option<f64>,
    spread: Option<Range>,
    decimals: usize,
) -> String {
    let mut s = num(mean, decimals);
    if let (Some(_), Some(h)) = (mean, ci95) {
        let _ = write!(s, " ± {h:.decimals$}");
    }
    if let Some(r) = spread {
        let _ = write!(s, " [{:.decimals$}-{:.decimals$}]", r.min, r.max);
    }
    s
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::montecarlo::aggregate::{
        aggregate_variant, RobotOutcome, VariantAggregate, DIVERGED_ATE_POS_M,
    };

    fn outcome(ate_pos: f64) -> RobotOutcome {
        let mut o = RobotOutcome::with_ate_pos(ate_pos);
        o.metrics.ate_ori_deg = Some(1.0);
        o.metrics.nees_pos = Some(3.14289);
        o.metrics.cpu_s = Some(1.25);
        o
    }

    /// A study of two seeds over `variants`.
    fn study_of(variants: Vec<(String, VariantAggregate)>) -> StudySummary {
        StudySummary {
            scenario: "loop".into(),
            runs: 2,
            seeds: vec![1, 2],
            diverged_ate_pos_m: DIVERGED_ATE_POS_M,
            wall_s: None,
            variants,
            failures: vec![],
        }
    }

    #[test]
    fn the_table_has_a_row_per_robot_and_a_mean_row_per_variant_with_ranges() {
        let robots = vec![(0, "a".to_string()), (1, "b".to_string())];
        let runs = vec![
            vec![outcome(0.1), outcome(0.2)],
            vec![outcome(0.3), outcome(40.0)],
        ];
        let failed = RobotOutcome {
            metrics: MetricSet::default(),
            error: Some("boom".into()),
        };
        let study = study_of(vec![
            ("indp".into(), aggregate_variant(&robots, &runs)),
            (
                "indp-slam".into(),
                aggregate_variant(&robots[..1], &[vec![failed], vec![outcome(0.5)]]),
            ),
        ]);
        let table = render_table(&study);
        let lines: Vec<&str> = table.lines().filter(|l| l.starts_with("| ")).collect();
        assert_eq!(lines.len(), 2 + 3 + 2, "{table}");
        assert!(
            lines[2].starts_with(
                "| indp | 0 a | 1.000 ± 0.000 [1.000-1.000] | 0.200 ± 1.271 [0.100-0.300] | - | 3.14 |"
            ),
            "{table}"
        );
        assert!(
            lines[2].ends_with("| 1.25 | 2 | 0 |"),
            "CPU s, runs, diverged; {table}"
        );
        assert!(lines[3].ends_with("| 2 | 1 |"), "{table}");
        let cells = |l: &str| l.matches('|').count();
        assert!(lines.iter().all(|l| cells(l) == cells(lines[0])), "{table}");
        assert!(lines[4].starts_with("| indp | mean |"), "{table}");
        assert!(lines[4].ends_with("| 4 | 1 |"), "{table}");
        assert!(
            lines[6]
                .starts_with("| indp-slam | mean | 1.000 [1.000-1.000] | 0.500 [0.500-0.500] |"),
            "one run: no interval; {table}"
        );
        assert!(lines[6].ends_with("| 2 | 1 (1 failed) |"), "{table}");
        assert!(table.contains("seeds 1-2"));
        assert!(
            !table.contains("Traffic"),
            "no agent ran, so no traffic table; {table}"
        );
    }

    #[test]
    fn agent_variants_get_a_traffic_row_with_their_peers_windows() {
        let agent = |whole: u64, replayed: u64| {
            let mut o = outcome(0.1);
            let m = &mut o.metrics;
            m.bytes_per_s_sent = Some(34_600.0);
            m.replay_bytes_sent = Some(replayed);
            m.peer_windows_published = Some(159);
            m.peer_windows_whole = Some(whole);
            m.history_bytes = Some(2_500_000);
            m.loop_closures = Some(100);
            m.common_feature_updates = Some(900);
            o
        };
        let robots = vec![(0, "a".to_string()), (1, "b".to_string())];
        let runs = vec![
            vec![agent(159, 1000), agent(159, 3000)],
            vec![agent(157, 2000), agent(159, 2000)],
        ];
        let study = study_of(vec![
            (
                "indp".into(),
                aggregate_variant(&robots, &[vec![outcome(0.1), outcome(0.2)]]),
            ),
            ("dc-full-history".into(), aggregate_variant(&robots, &runs)),
        ]);
        assert_eq!(study.variants[1].1.histories_complete, Some(3));
        assert_eq!(study.variants[0].1.histories_complete, None);
        let table = render_table(&study);
        let traffic: Vec<&str> = table
            .lines()
            .skip_while(|l| !l.starts_with("Traffic"))
            .filter(|l| l.starts_with("| "))
            .collect();
        assert_eq!(traffic.len(), 3, "header and one agent variant; {table}");
        assert_eq!(
            traffic[2], "| dc-full-history | 34.6 | 2.0 | 159 of 159 | 3 of 4 | 2.50 | 100 | 900 |",
            "{table}"
        );
        assert!(!table.contains("Peer frames"), "{table}");
    }

    #[test]
    fn agents_that_align_their_peers_frames_get_a_row_with_the_errors() {
        let agent = |yaw: f64| {
            let mut o = outcome(0.1);
            let m = &mut o.metrics;
            m.peer_frames_aligned = Some(2);
            m.first_peer_frame_s = Some(2.0);
            m.peer_frame_yaw_err_deg = Some(yaw);
            m.peer_frame_pos_err_m = Some(0.06);
            m.peer_frame_nees = Some(3.0);
            o
        };
        let robots = vec![(0, "a".to_string())];
        let study = study_of(vec![(
            "dc-full-history".into(),
            aggregate_variant(&robots, &[vec![agent(0.2), agent(0.4)]]),
        )]);
        let table = render_table(&study);
        let rows: Vec<&str> = table
            .lines()
            .skip_while(|l| !l.starts_with("Peer frames"))
            .filter(|l| l.starts_with("| "))
            .collect();
        assert_eq!(
            rows.get(2).copied(),
            Some("| dc-full-history | 2 | 2.0 | 0.300 | 0.060 | 3.00 |"),
            "{table}"
        );
    }
    #[test]
    fn robots_with_a_band_test_get_a_row_with_its_shares() {
        use crate::anees::{AneesSummary, BandShare};
        let robots = vec![(0, "a".to_string()), (1, "b".to_string())];
        let mut v = aggregate_variant(&robots, &[vec![outcome(0.1), outcome(0.2)]]);
        let share = |mean: f64, inside: f64, below: f64, above: f64| BandShare {
            mean: Some(mean),
            epochs: 100,
            inside,
            below,
            above,
        };
        v.robots[1].anees = Some(AneesSummary {
            runs: 2,
            bin_s: 0.1,
            ori: share(2.5, 0.9, 0.1, 0.0),
            pos: share(0.3, 0.0, 1.0, 0.0),
            tilt: share(1.9, 0.95, 0.0, 0.05),
            ..Default::default()
        });
        let table = render_table(&study_of(vec![("indp".into(), v)]));
        let rows: Vec<&str> = table
            .lines()
            .skip_while(|l| !l.starts_with("NEES averaged"))
            .filter(|l| l.starts_with("| "))
            .collect();
        // The robot without a test has no row.
        assert_eq!(rows.len(), 3, "{table}");
        assert_eq!(
            rows[2],
            "| indp | 1 b | 2 | 2.50: 90 / 10 / 0 | 0.30: 0 / 100 / 0 | 1.90: 95 / 0 / 5 | - | - | - | - |",
            "{table}"
        );
        let mut none = aggregate_variant(&robots, &[vec![outcome(0.1), outcome(0.2)]]);
        none.robots[0].anees = None;
        assert!(!render_table(&study_of(vec![("indp".into(), none)])).contains("NEES averaged"));
    }
}
