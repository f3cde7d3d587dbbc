//! Starting a three-robot fleet of real agent processes, one by one: the
//! scenario, the agents' configurations, the agents, a probe, and waiting.

use crate::{bin, write_loop_trajectory};
use std::path::{Path, PathBuf};
use std::process::{Child, Command, Stdio};
use std::time::{Duration, Instant};

/// A three-robot scenario on a `duration_s` loop (robots start 0, 2 and 4 s
/// apart), written into `dir`; returns its path.
///
/// # Panics
/// If the files cannot be written.
pub fn scenario(dir: &Path, duration_s: f64) -> PathBuf {
    write_loop_trajectory(&dir.join("loop.txt"), duration_s)
        .unwrap_or_else(|e| panic!("writing the loop into {}: {e}", dir.display()));
    let p = dir.join("three.yaml");
    std::fs::write(
        &p,
        "name: three\nrobots:\n  - trajectory: loop.txt\n  - trajectory: loop.txt\n    start_time_s: 2.0\n  - trajectory: loop.txt\n    start_time_s: 4.0\nsensors:\n  camera:\n    max_features: 60\n",
    )
    .unwrap_or_else(|e| panic!("writing {}: {e}", p.display()));
    p
}

/// Writes the agents' configurations (`sim-fleet run --dry-run`) and returns
/// their paths.
///
/// # Panics
/// If `sim-fleet` fails.
pub fn configs(sc: &Path, out: &Path, extra: &[&str]) -> Vec<PathBuf> {
    let output = Command::new(bin("sim-fleet"))
        .arg("run")
        .arg(sc)
        .arg("--out")
        .arg(out)
        .arg("--dry-run")
        .args(extra)
        .output()
        .unwrap_or_else(|e| panic!("starting sim-fleet: {e}"));
    assert!(
        output.status.success(),
        "{}",
        String::from_utf8_lossy(&output.stderr)
    );
    (0..3)
        .map(|i| out.join(format!("robot{i}")).join("config.yaml"))
        .collect()
}

/// Starts one agent per configuration, logging to `out/robot<i>.log`.
pub fn start_agents(cfgs: &[PathBuf], out: &Path) -> Vec<Child> {
    cfgs.iter()
        .enumerate()
        .map(|(i, c)| start_agent(c, &out.join(format!("robot{i}.log"))))
        .collect()
}

/// Runs `agent probe` against the fleet of `config`; returns what it printed.
///
/// # Panics
/// If the probe fails, with what it said.
pub fn probe(config: &Path, args: &[&str]) -> String {
    run_probe(Command::new(bin("agent")), config, args)
}

/// [`probe`] at the lowest CPU priority (`nice -n 19`), as if it flooded from
/// another machine: on one 2-core host a probe flooding as fast as it can
/// otherwise takes a core from the agents it floods.
pub fn probe_from_afar(config: &Path, args: &[&str]) -> String {
    let mut nice = Command::new("nice");
    nice.args(["-n", "19"]).arg(bin("agent"));
    run_probe(nice, config, args)
}

fn run_probe(mut agent: Command, config: &Path, args: &[&str]) -> String {
    let out = agent
        .args(["probe", "--config"])
        .arg(config)
        .args(args)
        .output()
        .unwrap_or_else(|e| panic!("starting agent probe: {e}"));
    let said = String::from_utf8_lossy(&out.stdout).to_string();
    assert!(
        out.status.success(),
        "{said}{}",
        String::from_utf8_lossy(&out.stderr)
    );
    said
}

/// Starts an agent with `config`, its log (stderr) in `log`.
///
/// # Panics
/// If the log cannot be created or the agent started.
pub fn start_agent(config: &Path, log: &Path) -> Child {
    let log_file =
        std::fs::File::create(log).unwrap_or_else(|e| panic!("creating {}: {e}", log.display()));
    Command::new(bin("agent"))
        .arg("--config")
        .arg(config)
        .stdout(Stdio::null())
        .stderr(log_file)
        .spawn()
        .unwrap_or_else(|e| panic!("starting the agent: {e}"))
}

/// Lets `agent` run for `up`, kills it, and after `down` starts it again
/// with `config`, its log in `log`.
///
/// # Panics
/// If the agent cannot be killed or started.
pub fn kill_and_restart(
    agent: &mut Child,
    config: &Path,
    log: &Path,
    up: Duration,
    down: Duration,
) -> Child {
    std::thread::sleep(up);
    agent
        .kill()
        .unwrap_or_else(|e| panic!("killing the agent: {e}"));
    let _ = agent.wait();
    std::thread::sleep(down);
    start_agent(config, log)
}

/// Data rows in a text file now (0 while it does not exist).
pub fn rows_now(path: &Path) -> usize {
    std::fs::read_to_string(path).map_or(0, |s| s.lines().filter(|l| !l.starts_with('#')).count())
}

/// Waits up to `limit` until the running agent's `estimate` (TUM, flushed
/// about once a second) holds `rows` poses; whether it did. Ties a test's
/// kill to how far the agent flew, not to the wall clock: a loaded machine
/// starts agents late (the vocabulary is trained at start).
pub fn wait_for_poses(estimate: &Path, rows: usize, limit: Duration) -> bool {
    let t = Instant::now();
    while t.elapsed() < limit {
        if rows_now(estimate) >= rows {
            return true;
        }
        std::thread::sleep(Duration::from_millis(20));
    }
    false
}

/// Waits up to `limit` for `child` to exit; whether it exited with success
/// (killed, and `false`, at the limit).
pub fn wait(child: &mut Child, limit: Duration) -> bool {
    let t = Instant::now();
    while t.elapsed() < limit {
        if let Ok(Some(status)) = child.try_wait() {
            return status.success();
        }
        std::thread::sleep(Duration::from_millis(50));
    }
    let _ = child.kill();
    false
}
