//! The transport part of the agent's configuration, and [`open`] to build the
//! transport it names.
//!
//! In the agent's YAML:
//! ```yaml
//! transport:
//!   fleet_id: euroc
//!   robot_id: 1
//!   kind: zenoh                # zenoh | iceoryx2 | inproc
//!   zenoh:
//!     config: loopback         # a built-in name (see ZENOH_BUILTIN_CONFIGS) or a file path
//!     listen: ["tcp/127.0.0.1:7447"]
//!     connect: ["tcp/127.0.0.1:7448"]
//!     robot_certificates:      # optional, with a mutual-TLS config: robot N may send
//!       robots: [0, 1, 2]      #   only with the certificate named robot{N}
//!       common_name: "robot{id}"
//!   iceoryx2:
//!     config: null             # null: iceoryx2's defaults; "iceoryx2": the built-in file; else a path
//!     max_peers: 64
//!     buffer_per_peer: 256
//!     max_message_bytes: 1048576
//! ```

use super::{
    iceoryx2::Iceoryx2Transport, inproc::InprocHub, zenoh::ZenohTransport,
    zenoh_acl::RobotCertificates, Transport, TransportError,
};
use serde::{Deserialize, Serialize};

/// Which transport an agent uses.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum TransportKind {
    /// Zenoh in peer mode, no router: one machine or many.
    #[default]
    Zenoh,
    /// iceoryx2 shared memory: processes of one machine.
    Iceoryx2,
    /// In-process hub: tests and lockstep simulation.
    Inproc,
}

/// Everything a transport needs to join its fleet.
#[derive(Clone, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct TransportSettings {
    /// The fleet's name: 1 to 64 characters of `A-Z a-z 0-9 _ - .`. Agents of other
    /// fleets on the same network, machine or hub never see each other's messages.
    pub fleet_id: String,
    /// This agent's robot id, unique in the fleet.
    pub robot_id: u32,
    /// Which transport (default `zenoh`).
    #[serde(default)]
    pub kind: TransportKind,
    /// Zenoh settings (used when `kind` is `zenoh`).
    #[serde(default)]
    pub zenoh: ZenohSettings,
    /// iceoryx2 settings (used when `kind` is `iceoryx2`).
    #[serde(default)]
    pub iceoryx2: Iceoryx2Settings,
}

/// The Zenoh session's configuration.
#[derive(Clone, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct ZenohSettings {
    /// A built-in configuration name (`loopback`, `lan`, `explicit-peers`, `tls`, `quic`: the
    /// files of `broker-free-config/`, compiled into the binary) or the path of a json5
    /// Zenoh configuration file. Default `loopback`.
    #[serde(default = "default_zenoh_config")]
    pub config: String,
    /// Endpoints to listen on (e.g. `tcp/127.0.0.1:7447`); when not empty they replace
    /// the file's `listen/endpoints`.
    #[serde(default)]
    pub listen: Vec<String>,
    /// Endpoints to connect to; when not empty they replace the file's
    /// `connect/endpoints`.
    #[serde(default)]
    pub connect: Vec<String>,
    /// Bind robot ids to TLS certificates (needs a configuration with mutual TLS,
    /// such as `tls` or `quic`): robot N's messages and presence are let in only from the peer
    /// whose certificate is named for N. `None` (default): any peer the link lets in
    /// may send under any robot id.
    #[serde(default)]
    pub robot_certificates: Option<RobotCertificates>,
}

impl Default for ZenohSettings {
    fn default() -> Self {
        Self {
            config: default_zenoh_config(),
            listen: Vec::new(),
            connect: Vec::new(),
            robot_certificates: None,
        }
    }
}

fn default_zenoh_config() -> String {
    "loopback".to_owned()
}

/// The iceoryx2 services' settings. Every agent of a fleet must use the same values:
/// the first agent creates the services with them and the others open them.
#[derive(Clone, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Iceoryx2Settings {
    /// iceoryx2's own configuration (root path, file prefix, clean-up policy): `None`
    /// for iceoryx2's defaults, `iceoryx2` for `broker-free-config/iceoryx2.toml`
    /// (compiled in), anything else is the path of a TOML file.
    #[serde(default)]
    pub config: Option<String>,
    /// Agents of one fleet on this machine, at most (publishers, subscribers and
    /// nodes per service).
    #[serde(default = "default_max_peers")]
    pub max_peers: u32,
    /// Messages of one kind a subscriber queues before its publishers wait for it.
    #[serde(default = "default_buffer_per_peer")]
    pub buffer_per_peer: usize,
    /// The largest payload, bytes; larger ones are refused with `TooLarge`.
    #[serde(default = "default_max_message_bytes")]
    pub max_message_bytes: usize,
}

impl Default for Iceoryx2Settings {
    fn default() -> Self {
        Self {
            config: None,
            max_peers: default_max_peers(),
            buffer_per_peer: default_buffer_per_peer(),
            max_message_bytes: default_max_message_bytes(),
        }
    }
}

fn default_max_peers() -> u32 {
    64
}

fn default_buffer_per_peer() -> usize {
    256
}

fn default_max_message_bytes() -> usize {
    1 << 20
}

/// The Zenoh configurations compiled into the binary, by name, so that a deployed
/// agent needs no repository: `(name, json5 text)`.
pub const ZENOH_BUILTIN_CONFIGS: [(&str, &str); 5] = [
    (
        "loopback",
        include_str!("../../../broker-free-config/zenoh-loopback.json5"),
    ),
    (
        "lan",
        include_str!("../../../broker-free-config/zenoh-lan.json5"),
    ),
    (
        "explicit-peers",
        include_str!("../../../broker-free-config/zenoh-explicit-peers.json5"),
    ),
    (
        "tls",
        include_str!("../../../broker-free-config/zenoh-tls.json5"),
    ),
    (
        "quic",
        include_str!("../../../broker-free-config/zenoh-quic.json5"),
    ),
];

/// The iceoryx2 configuration compiled into the binary (name `iceoryx2`).
pub const ICEORYX2_BUILTIN_CONFIG: &str = include_str!("../../../broker-free-config/iceoryx2.toml");

/// Opens the transport `settings` name. `inproc_hub` is required for
/// [`TransportKind::Inproc`] and ignored otherwise.
pub fn open(
    settings: &TransportSettings,
    inproc_hub: Option<&InprocHub>,
) -> Result<Box<dyn Transport>, TransportError> {
    validate_fleet_id(&settings.fleet_id)?;
    Ok(match settings.kind {
        TransportKind::Zenoh => Box::new(ZenohTransport::open(
            &settings.fleet_id,
            settings.robot_id,
            &settings.zenoh,
        )?),
        TransportKind::Iceoryx2 => Box::new(Iceoryx2Transport::open(
            &settings.fleet_id,
            settings.robot_id,
            &settings.iceoryx2,
        )?),
        TransportKind::Inproc => {
            let hub = inproc_hub.ok_or_else(|| TransportError::Open {
                transport: "inproc",
                reason: "the in-process transport needs an InprocHub".to_owned(),
            })?;
            Box::new(hub.endpoint(&settings.fleet_id, settings.robot_id)?)
        }
    })
}

/// Checks that a fleet id can be one segment of a key expression, a service name and
/// a node name: 1 to 64 characters of `A-Z a-z 0-9 _ - .`.
pub fn validate_fleet_id(fleet_id: &str) -> Result<(), TransportError> {
    let valid_char = |c: char| c.is_ascii_alphanumeric() || matches!(c, '_' | '-' | '.');
    if fleet_id.is_empty() || fleet_id.len() > 64 || !fleet_id.chars().all(valid_char) {
        return Err(TransportError::Config {
            path: "fleet_id".to_owned(),
            reason: format!(
                "{fleet_id:?} is not a fleet id: 1 to 64 characters of A-Z a-z 0-9 _ - ."
            ),
        });
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn settings_take_defaults_for_everything_but_the_ids() -> Result<(), serde_json::Error> {
        let settings: TransportSettings =
            serde_json::from_str(r#"{"fleet_id": "f", "robot_id": 3}"#)?;
        assert_eq!(settings.kind, TransportKind::Zenoh);
        assert_eq!(settings.zenoh, ZenohSettings::default());
        assert_eq!(settings.iceoryx2.max_peers, 64);
        assert_eq!(settings.iceoryx2.buffer_per_peer, 256);
        assert_eq!(settings.iceoryx2.max_message_bytes, 1 << 20);
        Ok(())
    }

    #[test]
    fn settings_reject_unknown_keys() {
        let parsed: Result<TransportSettings, _> =
            serde_json::from_str(r#"{"fleet_id": "f", "robot_id": 3, "zenoh": {"lisen": []}}"#);
        assert!(parsed.is_err());
    }

    #[test]
    fn kinds_are_lowercase_names() -> Result<(), serde_json::Error> {
        let settings: TransportSettings =
            serde_json::from_str(r#"{"fleet_id": "f", "robot_id": 3, "kind": "iceoryx2"}"#)?;
        assert_eq!(settings.kind, TransportKind::Iceoryx2);
        Ok(())
    }

    #[test]
    fn fleet_ids_that_would_break_addressing_are_refused() {
        for bad in ["", "a/b", "a*", "with space", &"x".repeat(65)] {
            assert!(validate_fleet_id(bad).is_err(), "{bad:?}");
        }
        for good in ["euroc", "fleet-1", "a.b_c"] {
            assert!(validate_fleet_id(good).is_ok(), "{good:?}");
        }
    }

    #[test]
    fn inproc_without_a_hub_is_an_error() {
        let settings = TransportSettings {
            fleet_id: "f".to_owned(),
            robot_id: 1,
            kind: TransportKind::Inproc,
            zenoh: ZenohSettings::default(),
            iceoryx2: Iceoryx2Settings::default(),
        };
        assert!(matches!(
            open(&settings, None),
            Err(TransportError::Open { .. })
        ));
    }
}
