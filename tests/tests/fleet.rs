//! Agents as real processes: `sim-fleet run` over Zenoh (loopback, peer mode)
//! and iceoryx2, a killed and restarted agent, an agent killed hard keeping
//! its poses, hostile payloads, and lockstep determinism across runs and
//! transports.
#![allow(clippy::unwrap_used)] // helpers outside #[test] functions

use integration_tests::fleet::{
    configs, kill_and_restart, probe, rows_now, scenario, start_agent, start_agents, wait,
};
use integration_tests::{bin, read_json, sim_fleet_run};

#[path = "../../agent/tests/support/mod.rs"]
mod support;
use serde_json::Value;
use std::path::{Path, PathBuf};
use std::process::{Child, Command};
use std::time::{Duration, Instant};

/// Every agent received every message every peer sent, kind by kind.
fn assert_complete_delivery(out: &Path, robots: usize) {
    let stats: Vec<Value> = (0..robots)
        .map(|i| read_json(&out.join(format!("robot{i}")).join("transport_stats.json")))
        .collect();
    for (me, st) in stats.iter().enumerate() {
        for (peer, pst) in stats.iter().enumerate() {
            if peer == me {
                continue;
            }
            for kind in ["Tracks", "Descriptors", "Snapshot", "Heartbeat"] {
                let sent = pst["net"]["kinds"][kind]["sent"].as_u64().unwrap_or(0);
                let got = st["net"]["received_from"][peer.to_string()][kind]
                    .as_u64()
                    .unwrap_or(0);
                assert!(sent > 0, "robot {peer} sent no {kind}");
                assert_eq!(
                    got, sent,
                    "robot {me} received {got} of the {sent} {kind} messages robot {peer} sent"
                );
            }
        }
        assert_eq!(st["net"]["sequence_gaps"], 0, "robot {me} saw gaps");
    }
}

fn assert_valid_estimates(summary: &Value, robots: usize) {
    let list = summary["robots"].as_array().unwrap();
    assert_eq!(list.len(), robots);
    for r in list {
        assert!(r["frames"].as_u64().unwrap() > 50, "{r}");
        let ate = r["ate_pos_m"].as_f64().unwrap();
        assert!(
            ate.is_finite() && ate < 1.0,
            "robot {}: ATE {ate} m",
            r["id"]
        );
        // Its CPU time, for the real-time share of a core the launcher prints.
        let cpu = r["cpu_s"].as_f64().unwrap_or(-1.0);
        assert!(cpu > 0.0 && cpu < 600.0, "robot {}: cpu_s {cpu}", r["id"]);
    }
}

#[test]
fn three_agents_over_zenoh_on_loopback_receive_everything() {
    let dir = tempfile::tempdir().unwrap();
    let sc = scenario(dir.path(), 20.0);
    let out = dir.path().join("zenoh");
    let summary = sim_fleet_run(&sc, &out, &["--transport", "zenoh", "--seed", "3"]);
    assert_eq!(summary["transport"], "zenoh");
    assert_valid_estimates(&summary, 3);
    assert_complete_delivery(&out, 3);
    for i in 0..3 {
        assert!(out.join(format!("robot{i}/agent.mcap")).is_file());
        let events =
            std::fs::read_to_string(out.join(format!("robot{i}/peer_events.jsonl"))).unwrap();
        assert_eq!(events.matches("\"appeared\"").count(), 2, "{events}");
    }
}

#[test]
fn three_agents_over_iceoryx2_receive_everything() {
    let dir = tempfile::tempdir().unwrap();
    let sc = scenario(dir.path(), 20.0);
    let out = dir.path().join("iox");
    let summary = sim_fleet_run(&sc, &out, &["--transport", "iceoryx2", "--seed", "3"]);
    assert_eq!(summary["transport"], "iceoryx2");
    assert_valid_estimates(&summary, 3);
    assert_complete_delivery(&out, 3);
}

/// The metrics that do not depend on wall-clock timing.
fn deterministic_part(summary: &Value) -> Vec<Value> {
    summary["robots"]
        .as_array()
        .unwrap()
        .iter()
        .map(|r| {
            serde_json::json!([
                r["ate_ori_deg"],
                r["ate_pos_m"],
                r["nees_ori"],
                r["nees_pos"],
                r["rpe"],
                r["frames"],
                r["bytes_sent"],
                r["messages_sent"],
                r["messages_received"],
                // A peer that finishes before us has left, not been lost.
                r["peer_losses"]
            ])
        })
        .collect()
}

#[test]
fn lockstep_runs_are_identical_across_runs_and_transports() {
    let dir = tempfile::tempdir().unwrap();
    let sc = scenario(dir.path(), 12.0);
    // Every envelope carries the fleet id, so the byte counts compare only
    // between fleet ids of one length (the default, `fleet-<pid>`, changes
    // length when process ids wrap).
    let a = sim_fleet_run(
        &sc,
        &dir.path().join("a"),
        &["--transport", "zenoh", "--seed", "5", "--fleet-id", "det-a"],
    );
    let b = sim_fleet_run(
        &sc,
        &dir.path().join("b"),
        &["--transport", "zenoh", "--seed", "5", "--fleet-id", "det-b"],
    );
    let c = sim_fleet_run(
        &sc,
        &dir.path().join("c"),
        &[
            "--transport",
            "inproc",
            "--seed",
            "5",
            "--fleet-id",
            "det-c",
        ],
    );
    assert_eq!(deterministic_part(&a), deterministic_part(&b));
    assert_eq!(deterministic_part(&a), deterministic_part(&c));
    assert_same_estimates(&dir.path().join("a"), &dir.path().join("b"), 3);
    assert_same_estimates(&dir.path().join("a"), &dir.path().join("c"), 3);
}

/// The robots' estimates of two runs, bit for bit: poses, and velocities and
/// biases with their truth.
fn assert_same_estimates(a: &Path, b: &Path, robots: usize) {
    for i in 0..robots {
        for file in ["estimate.txt", "imu_state.txt"] {
            let est = |run: &Path| std::fs::read(run.join(format!("robot{i}/{file}"))).unwrap();
            assert!(
                est(a) == est(b),
                "robot {i}: {file} of {} and {} differ",
                a.display(),
                b.display()
            );
        }
    }
}

#[test]
fn a_killed_agent_is_seen_leaving_and_coming_back_and_the_others_finish() {
    let dir = tempfile::tempdir().unwrap();
    let sc = scenario(dir.path(), 24.0);
    let out = dir.path().join("kill");
    // Real time at 4x: 24 s of data take about 6 s, time to kill and restart.
    let cfgs = configs(&sc, &out, &["--transport", "zenoh", "--realtime", "4"]);
    let mut agents = start_agents(&cfgs, &out);
    let mut restarted = kill_and_restart(
        &mut agents[2],
        &cfgs[2],
        &out.join("robot2-again.log"),
        Duration::from_millis(2500),
        Duration::from_millis(1000),
    );
    for (i, a) in agents.iter_mut().take(2).enumerate() {
        assert!(wait(a, Duration::from_secs(120)), "robot {i} failed");
    }
    assert!(
        wait(&mut restarted, Duration::from_secs(120)),
        "restarted robot failed"
    );
    for i in 0..2 {
        let dir = out.join(format!("robot{i}"));
        let events = std::fs::read_to_string(dir.join("peer_events.jsonl")).unwrap();
        let about_2: Vec<&str> = events
            .lines()
            .filter(|l| l.contains("\"peer\":2"))
            .collect();
        let kinds: Vec<&str> = about_2
            .iter()
            .filter_map(|l| {
                ["appeared", "vanished", "reappeared"]
                    .into_iter()
                    .find(|k| l.contains(&format!("\"{k}\"")))
            })
            .collect();
        assert_eq!(
            kinds,
            ["appeared", "vanished", "reappeared"],
            "robot {i}: {events}"
        );
        let s = read_json(&dir.join("summary.json"));
        let r = &s["robots"][0];
        assert!(r["frames"].as_u64().unwrap() > 150, "{r}");
        assert!(r["ate_pos_m"].as_f64().unwrap().is_finite());
        assert!(r["peer_losses"].as_u64().unwrap() >= 1);
    }
    // The restarted agent lost every peer history with its process: history
    // catch-up got the windows its peers made before it came back.
    let stats = |i: usize| read_json(&out.join(format!("robot{i}/transport_stats.json")));
    let again = stats(2);
    for p in 0..2 {
        let made = stats(p)["own_archive_windows"].as_u64().unwrap_or(0);
        let held = again["histories"][p.to_string()]["keyframes"]
            .as_u64()
            .unwrap_or(0);
        assert!(made > 10, "robot {p} made {made} windows");
        assert_eq!(
            held, made,
            "the restarted robot holds {held} of robot {p}'s {made} windows"
        );
    }
    let c = &again["catch_up"];
    assert!(c["windows_stored"].as_u64().unwrap_or(0) > 5, "{c}");
    // What the killed process had written was set aside, not overwritten.
    let aside = out.join("robot2/unfinished-1");
    for f in ["estimate.txt", "timing.csv", "agent.mcap"] {
        assert!(aside.join(f).is_file(), "{f} of the killed run");
    }
    assert!(out.join("robot2/summary.json").is_file());
}

#[test]
fn malformed_and_foreign_messages_are_dropped_and_counted() {
    let dir = tempfile::tempdir().unwrap();
    let sc = scenario(dir.path(), 16.0);
    let out = dir.path().join("probe");
    let cfgs = configs(&sc, &out, &["--transport", "zenoh", "--realtime", "2"]);
    let mut agents = start_agents(&cfgs, &out);
    probe(
        &cfgs[0],
        &["--malformed", "3", "--foreign-fleet", "someone-else"],
    );
    for (i, a) in agents.iter_mut().enumerate() {
        assert!(wait(a, Duration::from_secs(120)), "robot {i} failed");
    }
    let st = read_json(&out.join("robot0").join("transport_stats.json"));
    assert_eq!(st["net"]["dropped"]["malformed"], 3, "{}", st["net"]);
    assert_eq!(st["net"]["dropped"]["foreign_fleet"], 1, "{}", st["net"]);
    let s = read_json(&out.join("robot0").join("summary.json"));
    assert!(s["robots"][0]["frames"].as_u64().unwrap() > 100);
}

/// Three agents over mutual TLS on the secure `link` (`tls`: TCP, `quic`: UDP;
/// `broker-free-config/zenoh-<link>.json5` with the test's certificates) with their
/// robot ids bound to the certificates: each hears the others' messages of every
/// kind, and a probe holding robot 1's certificate that sends as robot 999 reaches
/// nobody (`malformed_and_foreign_messages_are_dropped_and_counted` is the same probe
/// without TLS, where the payloads arrive and are counted). Not every message: under
/// load Zenoh 1.10.2's TLS link drops and loses some (upstream eclipse-zenoh/zenoh#2557,
/// deploy/README.md), and the tests run in parallel.
fn agents_over_secure_link_with_bound_ids_hear_each_other_and_not_an_impostor(link: &str) {
    let dir = tempfile::tempdir().unwrap();
    let certs = dir.path().join("certs");
    std::fs::create_dir(&certs).unwrap();
    support::make_fleet_certificates(&bin("agent"), &certs, &["robot0", "robot1", "robot2"], link)
        .unwrap();
    let sc = scenario(dir.path(), 16.0);
    let out = dir.path().join(link);
    let cfgs = configs(&sc, &out, &["--transport", "zenoh", "--realtime", "2"]);
    let over_tls = |i: usize, bound: bool| {
        let text = std::fs::read_to_string(&cfgs[i]).unwrap();
        let file = certs.join(format!("robot{i}.json5"));
        let bind = "robot_certificates:\n      robots: [0, 1, 2]";
        let text = text
            .replace("config: loopback", &format!("config: {}", file.display()))
            .replace(
                "robot_certificates: null",
                if bound {
                    bind
                } else {
                    "robot_certificates: null"
                },
            )
            .replace("tcp/127.0.0.1", &format!("{link}/127.0.0.1"));
        assert!(text.contains(&file.display().to_string()), "{text}");
        assert_eq!(text.contains("robots: [0, 1, 2]"), bound, "{text}");
        text
    };
    let impostor = out.join("impostor.yaml");
    std::fs::write(&impostor, over_tls(1, false)).unwrap();
    for (i, cfg) in cfgs.iter().enumerate() {
        std::fs::write(cfg, over_tls(i, true)).unwrap();
    }
    let mut agents = start_agents(&cfgs, &out);
    let said = probe(&impostor, &["--as-robot", "999", "--malformed", "3"]);
    for (i, a) in agents.iter_mut().enumerate() {
        assert!(wait(a, Duration::from_secs(120)), "robot {i} failed");
    }
    for i in 0..3 {
        let st = read_json(&out.join(format!("robot{i}")).join("transport_stats.json"));
        let net = &st["net"];
        for peer in (0..3).filter(|p| *p != i) {
            for kind in ["Tracks", "Descriptors", "Snapshot", "Heartbeat"] {
                let got = net["received_from"][peer.to_string()][kind].as_u64();
                assert!(
                    got.unwrap_or(0) > 0,
                    "robot {i} got no {kind} from {peer}: {net}"
                );
            }
        }
        assert!(
            net["dropped"]["malformed"].as_u64().unwrap_or(0) == 0,
            "{said}{net}"
        );
        assert!(net["received_from"].get("999").is_none(), "{net}");
    }
}

/// Over QUIC only. The same agents over `tls` heard each other and not the impostor
/// in every run up to stop 25, but Zenoh 1.10.2's TLS link is unsound under load
/// (eclipse-zenoh/zenoh#2557: it lost messages in every lockstep run, and once
/// aborted a test process with corrupted memory), so a test that loads it would fail
/// at random. The binding over TLS is checked with light traffic in
/// `agent/tests/transport_conformance.rs`.
#[test]
fn agents_over_quic_with_bound_ids_hear_each_other_and_not_an_impostor() {
    agents_over_secure_link_with_bound_ids_hear_each_other_and_not_an_impostor("quic");
}

/// `sim-fleet run --quic`: lockstep over QUIC with mutual TLS and robot ids bound, the
/// load under which Zenoh's TLS link loses messages (deploy/README.md). Every message
/// of every kind arrives, and the estimates are plain TCP's, bit for bit.
#[test]
fn lockstep_over_quic_with_bound_ids_delivers_everything_as_tcp_does() {
    let dir = tempfile::tempdir().unwrap();
    let sc = scenario(dir.path(), 12.0);
    let run = |name: &str, extra: &[&str]| {
        let fleet = format!("det-{name}");
        let mut args = vec!["--transport", "zenoh", "--seed", "5", "--fleet-id", &fleet];
        args.extend(extra);
        sim_fleet_run(&sc, &dir.path().join(name), &args)
    };
    let quic = run("q", &["--quic"]);
    let tcp = run("t", &[]);
    let config = std::fs::read_to_string(dir.path().join("q/robot0/config.yaml")).unwrap();
    assert!(
        config.contains("quic/127.0.0.1") && config.contains("robots:"),
        "{config}"
    );
    assert_complete_delivery(&dir.path().join("q"), 3);
    assert_eq!(deterministic_part(&quic), deterministic_part(&tcp));
    assert_same_estimates(&dir.path().join("q"), &dir.path().join("t"), 3);
}

#[test]
fn a_flooding_peer_neither_stops_an_agent_nor_grows_its_memory() {
    let dir = tempfile::tempdir().unwrap();
    let sc = scenario(dir.path(), 16.0);
    let out = dir.path().join("flood");
    let cfgs = configs(&sc, &out, &["--transport", "zenoh"]);
    // A small memory bound per peer, so the flood reaches it in seconds.
    let mib = 4.0;
    for c in &cfgs {
        let text = std::fs::read_to_string(c).unwrap();
        let text = text.replace(
            "max_mib_per_peer: 64.0",
            &format!("max_mib_per_peer: {mib}"),
        );
        assert!(text.contains(&format!("max_mib_per_peer: {mib}")));
        std::fs::write(c, text).unwrap();
    }
    // Robot 0 starts alone: while it waits for its peers, the probe floods it
    // with valid messages, half stamped for a fleet time that never comes.
    let mut first = start_agent(&cfgs[0], &out.join("robot0.log"));
    let said = probe(&cfgs[0], &["--malformed", "0", "--flood-s", "3"]);
    let mut others: Vec<Child> = (1..3)
        .map(|i| start_agent(&cfgs[i], &out.join(format!("robot{i}.log"))))
        .collect();
    assert!(wait(&mut first, Duration::from_secs(120)), "robot 0 failed");
    for (i, a) in others.iter_mut().enumerate() {
        assert!(wait(a, Duration::from_secs(120)), "robot {} failed", i + 1);
    }
    let st = read_json(&out.join("robot0").join("transport_stats.json"));
    let net = &st["net"];
    let flood_received: u64 = ["Tracks", "Descriptors", "Snapshot"]
        .iter()
        .map(|k| net["received_from"]["999"][k].as_u64().unwrap_or(0))
        .sum();
    assert!(flood_received > 20, "{said}: {net}");
    for reason in ["backlog", "rate_limit"] {
        assert!(
            net["dropped"][reason].as_u64().unwrap_or(0) > 0,
            "{reason}: {said}: {net}"
        );
    }
    let s = read_json(&out.join("robot0").join("summary.json"));
    let r = &s["robots"][0];
    assert!(r["frames"].as_u64().unwrap() > 100, "{r}");
    assert!(r["ate_pos_m"].as_f64().unwrap() < 0.5, "{r}");
    // Three peers (two robots and the probe), each within its bound and the
    // recent frames' and descriptors' shares of it.
    let bound = 3.0 * mib * 1.25 * 1024.0 * 1024.0;
    let held = r["history_bytes"].as_f64().unwrap();
    assert!(held <= bound, "{held} bytes held: {r}");
    // The flood did not cost the peers' data: robot 0 fused theirs.
    assert!(r["common_feature_updates"].as_u64().unwrap_or(0) > 0, "{r}");
}

/// A lone agent's configuration: no peers, the given input.
fn lone_config(dir: &Path, scenario: &Path, input: &str, clock: &str) -> PathBuf {
    let p = dir.join("lone.yaml");
    std::fs::write(
        &p,
        format!(
            "robot_id: 0\nfleet_id: lone-{}\noutput_dir: lone-out\ntransport:\n  kind: zenoh\n  zenoh:\n    listen: [\"tcp/127.0.0.1:0\"]\ninput:\n  scenario: {}\n{input}clock:\n{clock}",
            std::process::id(),
            scenario.display()
        ),
    )
    .unwrap();
    p
}

#[test]
fn an_agent_replays_an_mcap_recording() {
    let dir = tempfile::tempdir().unwrap();
    let sc = scenario(dir.path(), 16.0);
    let sim = dir.path().join("sim");
    let status = Command::new(bin("sim-fleet"))
        .args(["simulate"])
        .arg(&sc)
        .arg("--out")
        .arg(&sim)
        .status()
        .unwrap();
    assert!(status.success());
    let input = format!(
        "  source: mcap\n  mcap: {}\n",
        sim.join("robot0/measurements.mcap").display()
    );
    let cfg = lone_config(dir.path(), &sc, &input, "  mode: lockstep\n");
    let mut agent = start_agent(&cfg, &dir.path().join("lone.log"));
    assert!(wait(&mut agent, Duration::from_secs(60)), "replay failed");
    let s = read_json(&dir.path().join("lone-out/summary.json"));
    let r = &s["robots"][0];
    assert!(r["frames"].as_u64().unwrap() > 100, "{r}");
    assert!(r["ate_pos_m"].as_f64().unwrap() < 0.5, "{r}");
}

/// A lone agent on a 30 s flight at 1x real time, its outputs in
/// `dir/lone-out`.
fn lone_agent_in_real_time(dir: &Path) -> Child {
    let sc = scenario(dir, 30.0);
    let cfg = lone_config(
        dir,
        &sc,
        "  source: simulator\n",
        "  mode: realtime\n  realtime_rate: 1.0\n",
    );
    start_agent(&cfg, &dir.join("lone.log"))
}

#[test]
fn sigterm_stops_an_agent_with_its_outputs_written() {
    let dir = tempfile::tempdir().unwrap();
    let mut agent = lone_agent_in_real_time(dir.path());
    std::thread::sleep(Duration::from_secs(4));
    let status = Command::new("kill")
        .args(["-TERM", &agent.id().to_string()])
        .status()
        .unwrap();
    assert!(status.success());
    assert!(wait(&mut agent, Duration::from_secs(15)), "no clean exit");
    let out = dir.path().join("lone-out");
    let st = read_json(&out.join("transport_stats.json"));
    assert_eq!(st["interrupted"], true);
    let est = std::fs::read_to_string(out.join("estimate.txt")).unwrap();
    assert!(est.lines().count() > 5, "{est}");
    assert!(
        read_json(&out.join("summary.json"))["robots"][0]["frames"]
            .as_u64()
            .unwrap()
            > 5
    );
    assert!(out.join("agent.mcap").is_file());
}

/// The data rows of a TUM file, each checked whole: eight numbers, times
/// increasing, the file ending with a newline.
fn tum_rows(path: &Path) -> Vec<Vec<f64>> {
    let text = std::fs::read_to_string(path).unwrap();
    assert!(text.ends_with('\n'), "{} ends mid-row", path.display());
    let rows: Vec<Vec<f64>> = text
        .lines()
        .filter(|l| !l.starts_with('#'))
        .map(|l| l.split(' ').map(|v| v.parse().unwrap()).collect())
        .collect();
    assert!(rows.iter().all(|r: &Vec<f64>| r.len() == 8));
    assert!(rows.windows(2).all(|w| w[0][0] < w[1][0]));
    rows
}

#[test]
fn an_agent_killed_hard_leaves_its_poses_on_disk() {
    let dir = tempfile::tempdir().unwrap();
    let mut agent = lone_agent_in_real_time(dir.path());
    let out = dir.path().join("lone-out");
    // The poses reach the disk while the agent runs (a second's rows at a time).
    let t = Instant::now();
    while t.elapsed() < Duration::from_secs(60) && rows_now(&out.join("estimate.txt")) < 30 {
        std::thread::sleep(Duration::from_millis(20));
    }
    agent.kill().unwrap(); // SIGKILL: no handler runs, nothing is finished
    agent.wait().unwrap();
    assert!(!out.join("summary.json").exists());
    // Every file ends with a whole row; the one being flushed at the kill may
    // lag the estimate by that flush.
    let est = tum_rows(&out.join("estimate.txt"));
    let gt = tum_rows(&out.join("groundtruth.txt"));
    assert!(est.len() >= 30, "{} poses", est.len());
    assert!(gt.len() >= est.len(), "{} true poses", gt.len());
    let timing = std::fs::read_to_string(out.join("timing.csv")).unwrap();
    assert!(timing.ends_with('\n') && timing.lines().count() > 20);
    let cov = std::fs::read_to_string(out.join("covariance.txt")).unwrap();
    assert!(cov.ends_with('\n') && cov.lines().count() > 20);
    assert!(cov.lines().skip(1).all(|l| l.split(' ').count() == 13));
}

/// Robot 2's configuration of the run in `out`, made to run it alone again
/// (its peers gone) into `again`; `store: false` drops its history store.
fn alone_again(out: &Path, again: &Path, store: bool) -> PathBuf {
    let text = std::fs::read_to_string(out.join("robot2/config.yaml")).unwrap();
    let mut lines: Vec<String> = Vec::new();
    let mut in_peers = false;
    for line in text.lines() {
        if in_peers && line.starts_with("  - ") {
            continue;
        }
        in_peers = false;
        if line.starts_with("output_dir:") {
            lines.push(format!("output_dir: {}", again.display()));
        } else if line == "  peers:" {
            lines.push("  peers: []".into());
            in_peers = true;
        } else if store || !line.starts_with("  store_dir:") {
            lines.push(line.to_owned());
        }
    }
    let p = again.with_extension("yaml");
    std::fs::write(&p, lines.join("\n")).unwrap();
    p
}

/// An agent with history catch-up off keeps no archive of its windows. It
/// answers the requests addressed to it with "found nothing", so its peers
/// close them instead of asking again every `catch_up_retry_s` for the whole
/// run (they sent 74 requests in 145 s before), and still settle at the end.
#[test]
fn a_peer_without_catch_up_says_it_has_nothing_so_nobody_keeps_asking() {
    let dir = tempfile::tempdir().unwrap();
    let sc = scenario(dir.path(), 24.0);
    let out = dir.path().join("mixed");
    let cfgs = configs(&sc, &out, &["--transport", "zenoh"]);
    let text = std::fs::read_to_string(&cfgs[2]).unwrap();
    assert!(text.contains("  catch_up: true"), "{text}");
    std::fs::write(
        &cfgs[2],
        text.replace("  catch_up: true", "  catch_up: false"),
    )
    .unwrap();
    let mut agents = start_agents(&cfgs, &out);
    for (i, a) in agents.iter_mut().enumerate() {
        assert!(wait(a, Duration::from_secs(120)), "robot {i} failed");
    }
    let stats = |i: usize| read_json(&out.join(format!("robot{i}/transport_stats.json")));
    assert!(stats(2)["catch_up"].is_null());
    for i in 0..2 {
        let st = stats(i);
        let c = &st["catch_up"];
        let count = |k: &str| c[k].as_u64().unwrap_or(u64::MAX);
        // A first request to each peer when it is heard, the sweep at the
        // end; the one to robot 2 may find it gone (dropped, not retried).
        assert!(count("requests_sent") <= 6, "robot {i}: {c}");
        assert_eq!(count("requests_retried"), 0, "robot {i}: {c}");
        assert!(count("requests_completed") >= 3, "robot {i}: {c}");
        assert_eq!(
            st["settle"]["complete"], true,
            "robot {i}: {}",
            st["settle"]
        );
    }
}

/// With `--history-store` each agent keeps its peers' keyframe windows, and
/// its own, on disk. Started again after its peers have landed and gone
/// (no peer left to catch up from), robot 2 reads them back, holds every
/// window they made, and closes loops on them; without the store it holds
/// none and closes none.
#[test]
fn an_agent_started_again_after_its_peers_are_gone_reads_their_histories_from_disk() {
    let dir = tempfile::tempdir().unwrap();
    let sc = scenario(dir.path(), 24.0);
    let out = dir.path().join("mission");
    let store = dir.path().join("store");
    sim_fleet_run(
        &sc,
        &out,
        &[
            "--transport",
            "zenoh",
            "--variant",
            "dc-full-history",
            "--seed",
            "3",
            "--history-store",
            store.to_str().unwrap(),
        ],
    );
    let stats = |run: &Path| read_json(&run.join("transport_stats.json"));
    let made: Vec<u64> = (0..3)
        .map(|i| {
            stats(&out.join(format!("robot{i}")))["own_archive_windows"]
                .as_u64()
                .unwrap()
        })
        .collect();
    assert!(made.iter().all(|&m| m > 15), "{made:?}");
    // `agent store` shows what robot 2's folder holds: every robot's windows,
    // whole, of this mission, undamaged.
    let shown = Command::new(bin("agent"))
        .args(["store", "--json"])
        .arg(store.join("robot2"))
        .output()
        .unwrap();
    assert!(
        shown.status.success(),
        "{}",
        String::from_utf8_lossy(&shown.stderr)
    );
    let files: Value = serde_json::from_slice(&shown.stdout).unwrap();
    let files = files.as_array().unwrap();
    assert_eq!(files.len(), 3, "{files:?}");
    for (p, f) in files.iter().enumerate() {
        assert_eq!(f["robot"], p, "{f}");
        assert_eq!(f["windows"].as_u64(), Some(made[p]), "{f}");
        assert_eq!(f["whole"], f["windows"], "{f}");
        assert!(f["problem"].is_null(), "{f}");
        assert!(
            f["mission"].as_str().unwrap_or("").ends_with("seed 3"),
            "{f}"
        );
    }
    let run_alone = |name: &str, keep: bool| {
        let again = dir.path().join(name);
        let cfg = alone_again(&out, &again, keep);
        let mut agent = start_agent(&cfg, &dir.path().join(format!("{name}.log")));
        assert!(wait(&mut agent, Duration::from_secs(120)), "{name} failed");
        again
    };
    let again = run_alone("again", true);
    let st = stats(&again);
    let restored = &st["history_store"]["restored_windows"];
    for p in 0..3 {
        assert_eq!(restored[p.to_string()].as_u64(), Some(made[p]), "{st}");
    }
    for p in 0..2 {
        let held = st["histories"][p.to_string()]["keyframes"].as_u64();
        assert_eq!(
            held,
            Some(made[p]),
            "robot 2 holds {held:?} of robot {p}'s windows"
        );
    }
    assert_eq!(st["own_archive_windows"].as_u64(), Some(made[2]));
    let loops = |run: &Path| {
        read_json(&run.join("summary.json"))["robots"][0]["loop_closures"]
            .as_f64()
            .unwrap_or(0.0)
    };
    assert!(loops(&again) > 5.0, "{} loop closures", loops(&again));

    let forgetful = run_alone("forgetful", false);
    assert_eq!(stats(&forgetful)["history_store"], Value::Null);
    assert_eq!(loops(&forgetful), 0.0);
}
