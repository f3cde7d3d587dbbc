//! The configurations shipped in `deploy/` load: the example agent configuration
//! with the agent's own loader, the Zenoh router-setup files with Zenoh's.

use agent::config::AgentConfig;
use agent::transport::ZenohSettings;
use std::path::PathBuf;

fn repo(path: &str) -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR"))
        .join("..")
        .join(path)
}

#[test]
fn example_agent_configuration_loads() {
    let cfg = AgentConfig::load(&repo("deploy/config/robot1.yaml")).expect("robot1.yaml");
    assert_eq!(cfg.robot_id, 1);
    assert!(!cfg.clock.peers.contains(&1));
    // The example robot takes from its peers everything the thesis' estimator can.
    assert_eq!(cfg.estimator.variant, "dc-full-history");
}

/// The live robot's example: its own sensors, placed in the fleet's frame,
/// on the sensors' clock.
#[test]
fn example_live_configuration_loads() {
    use agent::config::{ClockMode, InputSource};
    let cfg = AgentConfig::load(&repo("deploy/config/robot1-live.yaml")).expect("robot1-live.yaml");
    assert_eq!(cfg.input.source, InputSource::Live);
    assert_eq!(cfg.clock.mode, ClockMode::Realtime);
    let live = cfg.input.live.expect("the live block");
    assert!(live.calibration.ends_with("deploy/config/kalibr"));
    assert_eq!(live.zenoh.connect, ["tcp/127.0.0.1:7447"]);
    assert_eq!(live.odom_key.as_deref(), Some("vio/odom"));
    assert_eq!(live.body_frame, "imu");
    assert_eq!(
        live.start.heading_axis_i().expect("axis"),
        nalgebra::Vector3::x()
    );
}

#[test]
fn zenoh_router_setup_files_load() {
    for f in [
        "deploy/zenoh/agent-via-router.json5",
        "deploy/zenoh/zenohd-router.json5",
    ] {
        let s = ZenohSettings {
            config: repo(f).display().to_string(),
            listen: Vec::new(),
            connect: Vec::new(),
            robot_certificates: None,
        };
        agent::transport::zenoh::load_config(&s).unwrap_or_else(|e| panic!("{f}: {e}"));
    }
}
