//! Zenoh in peer mode, no router, through zenoh's synchronous API (`.wait()`).
//!
//! Key expressions are `fleet/<fleet-id>/<robot-id>/<kind>`: one publisher per kind
//! (reliable, blocking congestion control: a slow peer slows the publisher instead of
//! losing messages) and one subscriber on `fleet/<fleet-id>/*/*` that takes the
//! sender's robot id and the kind from the key. Presence is a liveliness token
//! `fleet/<fleet-id>/<robot-id>/alive` and a liveliness subscriber with history, so
//! peers already present are reported too; a killed peer vanishes at once, a frozen
//! or cut-off one after the lease (1 s in the built-in configurations).

use super::own_certificates::{self, Finding};
use super::settings::{ZenohSettings, ZENOH_BUILTIN_CONFIGS};
use super::zenoh_acl::{access_control, AclRole, RobotCertificates};
use super::{PresenceEvent, Received, Transport, TransportError};
use common::messages::MessageKind;
use std::sync::mpsc;
use std::time::{Duration, Instant};
use zenoh::handlers::{FifoChannel, FifoChannelHandler};
use zenoh::liveliness::LivelinessToken;
use zenoh::pubsub::{Publisher, Subscriber};
use zenoh::qos::CongestionControl;
use zenoh::sample::{Locality, Sample, SampleKind};
use zenoh::{Config, Session, Wait};

const NAME: &str = "zenoh";

/// Samples the subscriber queues before zenoh stops reading from the network (it
/// never drops: a full queue pushes back to the publishers). 32 peers x 4 kinds x
/// 10 Hz is 1280 messages a second; this holds several seconds of that.
pub const RECEIVE_QUEUE: usize = 8192;

/// Presence samples queued between two `presence()` calls.
const PRESENCE_QUEUE: usize = 1024;

/// How long dropping an open transport waits for the session to close.
const DROP_CLOSE_TIMEOUT: Duration = Duration::from_secs(2);

/// An agent's Zenoh session in its fleet.
pub struct ZenohTransport {
    fleet_id: String,
    robot_id: u32,
    /// `None` once closed.
    session: Option<Open>,
    malformed: u64,
}

/// What an open session holds; dropped together on close.
struct Open {
    session: Session,
    publishers: Vec<(MessageKind, Publisher<'static>)>,
    subscriber: Subscriber<FifoChannelHandler<Sample>>,
    presence: Subscriber<FifoChannelHandler<Sample>>,
    _token: LivelinessToken,
}

impl std::fmt::Debug for ZenohTransport {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("ZenohTransport")
            .field("fleet_id", &self.fleet_id)
            .field("robot_id", &self.robot_id)
            .field("open", &self.session.is_some())
            .field("malformed", &self.malformed)
            .finish()
    }
}

impl ZenohTransport {
    /// Opens a session with the configuration `settings` names and joins `fleet_id` as
    /// `robot_id`. Declares the subscribers before the liveliness token, so a peer
    /// that sees this agent appear already reaches its subscriber.
    pub fn open(
        fleet_id: &str,
        robot_id: u32,
        settings: &ZenohSettings,
    ) -> Result<Self, TransportError> {
        super::settings::validate_fleet_id(fleet_id)?;
        let mut config = load_config(settings)?;
        if let Some(certs) = &settings.robot_certificates {
            bind_robot_ids(&mut config, settings, fleet_id, robot_id, certs)?;
        }
        check_own_certificates(&config, settings, robot_id)?;
        warn_if_tls_link(&config);
        let session = zenoh::open(config).wait().map_err(open_error)?;
        let mut publishers = Vec::with_capacity(MessageKind::ALL.len());
        for kind in MessageKind::ALL {
            let publisher = session
                .declare_publisher(format!("fleet/{fleet_id}/{robot_id}/{}", kind.as_str()))
                .congestion_control(CongestionControl::Block)
                .wait()
                .map_err(open_error)?;
            publishers.push((kind, publisher));
        }
        let subscriber = session
            .declare_subscriber(format!("fleet/{fleet_id}/*/*"))
            .allowed_origin(Locality::Remote)
            .with(FifoChannel::new(RECEIVE_QUEUE))
            .wait()
            .map_err(open_error)?;
        let presence = session
            .liveliness()
            .declare_subscriber(format!("fleet/{fleet_id}/*/alive"))
            .history(true)
            .with(FifoChannel::new(PRESENCE_QUEUE))
            .wait()
            .map_err(open_error)?;
        let token = session
            .liveliness()
            .declare_token(format!("fleet/{fleet_id}/{robot_id}/alive"))
            .wait()
            .map_err(open_error)?;
        Ok(Self {
            fleet_id: fleet_id.to_owned(),
            robot_id,
            session: Some(Open {
                session,
                publishers,
                subscriber,
                presence,
                _token: token,
            }),
            malformed: 0,
        })
    }

    /// Samples ignored because their key was not `fleet/<fleet-id>/<robot-id>/<kind>`.
    pub fn malformed_keys(&self) -> u64 {
        self.malformed
    }

    fn open_session(&self) -> Result<&Open, TransportError> {
        self.session
            .as_ref()
            .ok_or(TransportError::Closed { transport: NAME })
    }

    /// The robot id and kind of a data key of this fleet, `None` if malformed.
    fn parse_data_key(&self, key: &str) -> Option<(u32, MessageKind)> {
        let rest = key
            .strip_prefix("fleet/")?
            .strip_prefix(self.fleet_id.as_str())?;
        let mut parts = rest.strip_prefix('/')?.split('/');
        let robot = parts.next()?.parse().ok()?;
        let kind = MessageKind::from_segment(parts.next()?)?;
        parts.next().is_none().then_some((robot, kind))
    }
}

impl Transport for ZenohTransport {
    fn name(&self) -> &'static str {
        NAME
    }

    fn publish(&mut self, kind: MessageKind, bytes: &[u8]) -> Result<(), TransportError> {
        let open = self.open_session()?;
        let Some((_, publisher)) = open.publishers.iter().find(|(k, _)| *k == kind) else {
            return Err(TransportError::Publish {
                transport: NAME,
                kind,
                reason: "no publisher for this kind".to_owned(),
            });
        };
        publisher
            .put(bytes)
            .wait()
            .map_err(|e| TransportError::Publish {
                transport: NAME,
                kind,
                reason: e.to_string(),
            })
    }

    fn receive(&mut self, timeout: Duration) -> Result<Option<Received>, TransportError> {
        let deadline = Instant::now().checked_add(timeout);
        loop {
            let open = self.open_session()?;
            let next = match deadline {
                Some(deadline) => open.subscriber.recv_deadline(deadline),
                None => open.subscriber.recv().map(Some),
            };
            let sample = match next {
                Ok(Some(sample)) => sample,
                Ok(None) => return Ok(None),
                Err(e) => {
                    return Err(TransportError::Receive {
                        transport: NAME,
                        reason: e.to_string(),
                    })
                }
            };
            match self.parse_data_key(sample.key_expr().as_str()) {
                Some((robot, _)) if robot == self.robot_id => continue,
                Some((from_robot, kind)) if sample.kind() == SampleKind::Put => {
                    return Ok(Some(Received {
                        from_robot,
                        kind,
                        bytes: sample.payload().to_bytes().into_owned(),
                    }));
                }
                Some(_) => continue, // a delete on a data key carries nothing
                None => self.malformed += 1,
            }
        }
    }

    fn presence(&mut self) -> Vec<PresenceEvent> {
        let Some(open) = self.session.as_ref() else {
            return Vec::new();
        };
        let mut events = Vec::new();
        while let Ok(Some(sample)) = open.presence.try_recv() {
            let robot = sample
                .key_expr()
                .as_str()
                .strip_prefix("fleet/")
                .and_then(|k| k.strip_prefix(self.fleet_id.as_str()))
                .and_then(|k| k.strip_prefix('/'))
                .and_then(|k| k.strip_suffix("/alive"))
                .and_then(|id| id.parse::<u32>().ok());
            match robot {
                Some(robot) if robot == self.robot_id => {}
                Some(robot) => events.push(match sample.kind() {
                    SampleKind::Put => PresenceEvent::Appeared(robot),
                    SampleKind::Delete => PresenceEvent::Vanished(robot),
                }),
                None => self.malformed += 1,
            }
        }
        events
    }

    /// Closes the session on a helper thread and gives up after `timeout` (closing
    /// can hang while a peer is frozen); the session is unusable either way.
    fn close(&mut self, timeout: Duration) -> Result<(), TransportError> {
        let Some(open) = self.session.take() else {
            return Ok(());
        };
        let session = open.session.clone();
        drop(open);
        let (done, finished) = mpsc::channel();
        std::thread::Builder::new()
            .name("zenoh-close".to_owned())
            .spawn(move || {
                let _ = done.send(session.close().wait());
            })
            .map_err(|e| TransportError::Close {
                transport: NAME,
                reason: format!("cannot start the closing thread: {e}"),
            })?;
        match finished.recv_timeout(timeout) {
            Ok(Ok(())) => Ok(()),
            Ok(Err(e)) => Err(TransportError::Close {
                transport: NAME,
                reason: e.to_string(),
            }),
            Err(_) => Err(TransportError::Close {
                transport: NAME,
                reason: format!(
                    "the session did not close within {timeout:?}; left closing in the background"
                ),
            }),
        }
    }
}

impl Drop for ZenohTransport {
    fn drop(&mut self) {
        if self.session.is_some() {
            if let Err(e) = self.close(DROP_CLOSE_TIMEOUT) {
                tracing::warn!("{e}");
            }
        }
    }
}

/// The Zenoh configuration `settings` names: a built-in name or a json5 file, with
/// the settings' `listen`/`connect` endpoints in place of the file's when given.
pub fn load_config(settings: &ZenohSettings) -> Result<Config, TransportError> {
    let config_error = |reason: String| TransportError::Config {
        path: settings.config.clone(),
        reason,
    };
    let builtin = ZENOH_BUILTIN_CONFIGS
        .iter()
        .find(|(name, _)| *name == settings.config)
        .map(|(_, text)| *text);
    let text = match builtin {
        Some(text) => text.to_owned(),
        None => std::fs::read_to_string(&settings.config).map_err(|e| {
            config_error(format!(
                "not a built-in name ({}) and not a readable file: {e}",
                builtin_names()
            ))
        })?,
    };
    let mut config = Config::from_json5(&text).map_err(|e| config_error(e.to_string()))?;
    for (key, endpoints) in [
        ("listen/endpoints", &settings.listen),
        ("connect/endpoints", &settings.connect),
    ] {
        if endpoints.is_empty() {
            continue;
        }
        let value = serde_json::to_string(endpoints).map_err(|e| config_error(e.to_string()))?;
        config
            .insert_json5(key, &value)
            .map_err(|e| config_error(format!("{key} = {value}: {e}")))?;
    }
    Ok(config)
}

/// Adds the access control that lets robot N's keys in only from the certificate
/// named for N (`zenoh_acl`). It needs mutual TLS: without the peer's certificate
/// there is no name to check and every message would be refused.
fn bind_robot_ids(
    config: &mut Config,
    settings: &ZenohSettings,
    fleet_id: &str,
    robot_id: u32,
    certs: &RobotCertificates,
) -> Result<(), TransportError> {
    let config_error = |reason: String| TransportError::Config {
        path: settings.config.clone(),
        reason,
    };
    let mtls = config
        .get_json("transport/link/tls/enable_mtls")
        .unwrap_or_default();
    if mtls.trim() != "true" {
        return Err(config_error(
            "robot_certificates needs mutual TLS (transport/link/tls/enable_mtls: true, \
             as in the built-in `tls` configuration): without the peers' certificates \
             there is no name to check"
                .to_owned(),
        ));
    }
    let acl = access_control(fleet_id, certs, AclRole::Agent(robot_id))?;
    config
        .insert_json5("access_control", &acl.to_string())
        .map_err(|e| config_error(format!("access_control: {e}")))
}

/// Says at start what would otherwise fail in silence: this robot's certificate
/// named for another robot (refused), or a certificate outside its validity period
/// by this machine's clock (logged; the links come up once the clock is right).
fn check_own_certificates(
    config: &Config,
    settings: &ZenohSettings,
    robot_id: u32,
) -> Result<(), TransportError> {
    let bind = settings.robot_certificates.as_ref().map(|c| (c, robot_id));
    let findings =
        own_certificates::check(config, bind, std::time::SystemTime::now()).map_err(|reason| {
            TransportError::Config {
                path: settings.config.clone(),
                reason,
            }
        })?;
    for finding in findings {
        match finding {
            Finding::Error(e) => tracing::error!("{e}"),
            Finding::Warning(w) => tracing::warn!("{w}"),
        }
    }
    Ok(())
}

/// Zenoh 1.10.2's TLS link reads and writes one rustls stream from two tasks at
/// once (eclipse-zenoh/zenoh#2557): under load it loses messages, and it has aborted
/// a process with corrupted memory (deploy/README.md, section 5). Said once at start
/// by any agent whose configuration uses it; `quic` carries the same mutual TLS.
fn warn_if_tls_link(config: &Config) {
    if uses_tls_link(config) {
        tracing::warn!(
            "this Zenoh configuration uses TLS links, which in Zenoh 1.10.2 lose messages \
             under load and can corrupt memory (eclipse-zenoh/zenoh#2557); the built-in \
             `quic` configuration carries the same mutual TLS and certificates without \
             that fault (deploy/README.md, section 5)"
        );
    }
}

/// Whether the configuration's endpoints or allowed protocols name the TLS link.
fn uses_tls_link(config: &Config) -> bool {
    const KEYS: [&str; 3] = [
        "listen/endpoints",
        "connect/endpoints",
        "transport/link/protocols",
    ];
    (KEYS.iter())
        .filter_map(|key| config.get_json(key).ok())
        .any(|json| json.contains("tls/") || json.contains("\"tls\""))
}

fn builtin_names() -> String {
    ZENOH_BUILTIN_CONFIGS
        .iter()
        .map(|(name, _)| *name)
        .collect::<Vec<_>>()
        .join(", ")
}

fn open_error(e: zenoh::Error) -> TransportError {
    TransportError::Open {
        transport: NAME,
        reason: e.to_string(),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn every_builtin_config_loads() -> Result<(), TransportError> {
        for (name, _) in ZENOH_BUILTIN_CONFIGS {
            let settings = ZenohSettings {
                config: name.to_owned(),
                ..ZenohSettings::default()
            };
            load_config(&settings)?;
        }
        Ok(())
    }

    #[test]
    fn listen_and_connect_replace_the_files_endpoints(
    ) -> Result<(), Box<dyn std::error::Error + Send + Sync>> {
        let settings = ZenohSettings {
            config: "loopback".to_owned(),
            listen: vec!["tcp/127.0.0.1:17001".to_owned()],
            connect: vec![
                "tcp/127.0.0.1:17002".to_owned(),
                "tcp/127.0.0.1:17003".to_owned(),
            ],
            robot_certificates: None,
        };
        let config = load_config(&settings)?;
        let listen = config.get_json("listen/endpoints")?;
        let connect = config.get_json("connect/endpoints")?;
        assert!(
            listen.contains("17001") && !listen.contains("7447"),
            "{listen}"
        );
        assert!(
            connect.contains("17002") && connect.contains("17003"),
            "{connect}"
        );
        assert!(!connect.contains("7448"), "{connect}");
        Ok(())
    }

    #[test]
    fn only_configurations_with_tls_links_get_the_tls_warning() -> Result<(), TransportError> {
        for (name, tls) in [
            ("loopback", false),
            ("lan", false),
            ("tls", true),
            ("quic", false),
        ] {
            let settings = ZenohSettings {
                config: name.to_owned(),
                ..ZenohSettings::default()
            };
            assert_eq!(uses_tls_link(&load_config(&settings)?), tls, "{name}");
        }
        let over_tls = ZenohSettings {
            connect: vec!["tls/127.0.0.1:17004".to_owned()],
            ..ZenohSettings::default()
        };
        assert!(uses_tls_link(&load_config(&over_tls)?));
        Ok(())
    }

    #[test]
    fn an_unknown_name_that_is_no_file_is_a_config_error() {
        let settings = ZenohSettings {
            config: "/nonexistent/zenoh.json5".to_owned(),
            ..ZenohSettings::default()
        };
        assert!(matches!(
            load_config(&settings),
            Err(TransportError::Config { .. })
        ));
    }

    #[test]
    fn binding_robot_ids_without_mutual_tls_is_refused_before_opening() {
        let settings = ZenohSettings {
            robot_certificates: Some(RobotCertificates {
                robots: vec![1, 2],
                common_name: "robot{id}".to_owned(),
                trusted_routers: Vec::new(),
            }),
            ..ZenohSettings::default()
        };
        match ZenohTransport::open("f", 1, &settings) {
            Err(TransportError::Config { reason, .. }) => {
                assert!(reason.contains("mutual TLS"), "{reason}")
            }
            other => panic!("{other:?}"),
        }
    }
}
