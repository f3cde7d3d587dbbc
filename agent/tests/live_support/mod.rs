//! What the live-sensor tests share: the agent binary, waiting for its
//! processes, and a Zenoh session of the test's own.

use std::process::{Child, Command, Output};
use std::time::{Duration, Instant};
use zenoh::Wait;

pub fn agent() -> Command {
    Command::new(env!("CARGO_BIN_EXE_agent"))
}

pub fn succeeded(what: &str, out: &Output) -> String {
    let stdout = String::from_utf8_lossy(&out.stdout).into_owned();
    assert!(
        out.status.success(),
        "{what} failed:\n{stdout}\n{}",
        String::from_utf8_lossy(&out.stderr)
    );
    stdout
}

/// Waits for `child` at most `limit`, killing it past that.
pub fn wait_for(mut child: Child, limit: Duration) -> Output {
    let start = Instant::now();
    while child.try_wait().expect("wait").is_none() {
        if start.elapsed() > limit {
            let _ = child.kill();
            panic!("the process did not end within {limit:?}");
        }
        std::thread::sleep(Duration::from_millis(100));
    }
    child.wait_with_output().expect("output")
}

/// A session of the test's own, connected to the live agent.
pub fn session_to(port: u16) -> zenoh::Session {
    let mut config = zenoh::Config::default();
    config
        .insert_json5("connect/endpoints", &format!("[\"tcp/127.0.0.1:{port}\"]"))
        .expect("connect");
    config
        .insert_json5("scouting/multicast/enabled", "false")
        .expect("scouting");
    zenoh::open(config).wait().expect("session")
}
