//! Helpers for the integration tests in `tests/tests/`, which start the real
//! binaries. Build them first: `cargo build --release --workspace --bins`.

pub mod fleet;

use serde_json::Value;
use std::path::{Path, PathBuf};
use std::process::Command;

/// Path of a workspace binary built in the same profile as the running test.
///
/// # Panics
/// If the binary is missing, with the command that builds it.
pub fn bin(name: &str) -> PathBuf {
    // target/<profile>/deps/<test-exe>: the binaries sit in target/<profile>/.
    let exe = std::env::current_exe().unwrap_or_default();
    let dir = exe
        .parent()
        .and_then(Path::parent)
        .map(Path::to_path_buf)
        .unwrap_or_default();
    let path = dir.join(name);
    assert!(
        path.is_file(),
        "{} not found: run `cargo build --release --workspace --bins` (same profile as the tests) first",
        path.display()
    );
    path
}

/// The JSON file at `path`.
///
/// # Panics
/// If it cannot be read or parsed, naming the file.
pub fn read_json(path: &Path) -> Value {
    let text =
        std::fs::read_to_string(path).unwrap_or_else(|e| panic!("reading {}: {e}", path.display()));
    serde_json::from_str(&text).unwrap_or_else(|e| panic!("parsing {}: {e}", path.display()))
}

/// Runs `sim-fleet run SCENARIO --out OUT EXTRA...` (real agent processes) and
/// returns the fleet's `summary.json`.
///
/// # Panics
/// If the run fails (with its output) or writes no summary.
pub fn sim_fleet_run(scenario: &Path, out: &Path, extra: &[&str]) -> Value {
    let output = Command::new(bin("sim-fleet"))
        .arg("run")
        .arg(scenario)
        .arg("--out")
        .arg(out)
        .args(extra)
        .output()
        .unwrap_or_else(|e| panic!("starting sim-fleet: {e}"));
    assert!(
        output.status.success(),
        "sim-fleet run failed:\n{}\n{}",
        String::from_utf8_lossy(&output.stdout),
        String::from_utf8_lossy(&output.stderr)
    );
    read_json(&out.join("summary.json"))
}

/// The workspace root.
pub fn workspace_root() -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR"))
        .parent()
        .map(Path::to_path_buf)
        .unwrap_or_default()
}

/// Writes a smooth loop trajectory of `duration_s` (TUM format, 20 Hz) to
/// `path`: a 3 m circle at 0.25 rad/s, heading along it, bobbing 0.2 m.
pub fn write_loop_trajectory(path: &Path, duration_s: f64) -> std::io::Result<()> {
    write_loop_trajectory_from(path, duration_s, 0.0)
}

/// [`write_loop_trajectory`] starting `phase_rad` further along the circle
/// (`PI`: on the opposite side).
pub fn write_loop_trajectory_from(
    path: &Path,
    duration_s: f64,
    phase_rad: f64,
) -> std::io::Result<()> {
    let mut text = String::from("# timestamp tx ty tz qx qy qz qw\n");
    let n = (duration_s * 20.0) as usize;
    for k in 0..=n {
        let s = k as f64 / 20.0;
        let a = 0.25 * s + phase_rad;
        let (x, y, z) = (3.0 * a.cos(), 3.0 * a.sin(), 1.0 + 0.2 * (0.5 * s).sin());
        // Yaw about z following the loop: q = (0, 0, sin(yaw/2), cos(yaw/2)).
        let yaw = a + 1.57;
        let (qz, qw) = ((yaw / 2.0).sin(), (yaw / 2.0).cos());
        text.push_str(&format!(
            "{:.6} {x:.6} {y:.6} {z:.6} 0 0 {qz:.9} {qw:.9}\n",
            100.0 + s
        ));
    }
    std::fs::write(path, text)
}
