//! iceoryx2: agents that are processes of one machine, over shared memory.
//!
//! * Data: one publish-subscribe service per (fleet, kind), `fleet/<fleet-id>/<kind>`,
//!   with `[u8]` payloads and a `u32` user header holding the sender's robot id. Every
//!   agent has a publisher and a subscriber on each; its own samples are skipped.
//! * Waking: one event service per fleet, `fleet/<fleet-id>/wake`; a publish notifies
//!   it and `receive` sleeps on its listener (no spinning).
//! * Presence: two nodes per agent. The first, `fleet-<fleet-id>-robot-<id>-ports`,
//!   owns every port; the second, `fleet-<fleet-id>-robot-<id>`, is created once the
//!   ports exist, so a peer that sees it appear already reaches its subscribers. The
//!   node list is polled at most every [`PRESENCE_POLL`], and dead nodes' resources
//!   are removed when found (iceoryx2 does not report a dead peer by itself).
//!
//! Delivery policy: no safe overflow; a publisher waits while a subscriber's buffer
//! (`buffer_per_peer` samples) is full, at most [`BLOCK_TIMEOUT`] per sample. A
//! subscriber that makes it wait that long is considered stalled: its samples are
//! dropped (and counted, [`Iceoryx2Transport::dropped`]) for [`STALL_HOLDOFF`], then
//! tried again, so a frozen peer cannot stop the fleet. Order is kept per (sender,
//! kind); kinds are separate services, so their relative order is not.
//!
//! Memory: a publisher's pool holds `2 x buffer_per_peer + 16` samples, each as large
//! as the largest payload sent so far rounded up to a power of two (16 KiB to start,
//! at most `max_message_bytes`). While the peers keep up fewer than
//! `buffer_per_peer + 4` samples are in use; the second half covers one stalled peer.

mod presence;

use super::settings::{Iceoryx2Settings, ICEORYX2_BUILTIN_CONFIG};
use super::{PresenceEvent, Received, Transport, TransportError};
use common::messages::MessageKind;
use iceoryx2::port::listener::Listener;
use iceoryx2::port::notifier::Notifier;
use iceoryx2::port::publisher::Publisher;
use iceoryx2::port::subscriber::Subscriber;
use iceoryx2::port::{BackpressureAction, BackpressureInfo};
use iceoryx2::prelude::*;
use presence::{beacon_name, NodeWatch};
use std::collections::{HashMap, VecDeque};
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

pub use presence::PRESENCE_POLL;

type Ipc = ipc_threadsafe::Service;

const NAME: &str = "iceoryx2";

/// How long a publisher waits for one subscriber with a full buffer.
pub const BLOCK_TIMEOUT: Duration = Duration::from_millis(100);
/// How long a subscriber that made a publisher wait [`BLOCK_TIMEOUT`] is skipped.
pub const STALL_HOLDOFF: Duration = Duration::from_secs(5);
/// The payload size a publisher's samples start with.
const INITIAL_SLICE: usize = 16 * 1024;
/// Samples a subscriber may hold at once (`receive` copies and releases each at once).
const BORROWED: usize = 2;
/// Samples a publisher may loan at once.
const LOANED: usize = 2;

/// An agent's ports in its fleet's iceoryx2 services.
pub struct Iceoryx2Transport {
    fleet_id: String,
    robot_id: u32,
    max_message_bytes: usize,
    /// `None` once closed.
    ports: Option<Ports>,
    /// Peer messages taken out of a subscriber while publishing, served first.
    staged: VecDeque<Received>,
    next_kind: usize,
    watch: NodeWatch,
    dropped: Arc<AtomicU64>,
}

struct Ports {
    /// Declared first so that it is dropped first: peers see this agent vanish before
    /// its ports go.
    beacon: Node<Ipc>,
    kinds: Vec<KindPorts>,
    notifier: Notifier<Ipc>,
    listener: Listener<Ipc>,
    _node: Node<Ipc>,
}

struct KindPorts {
    kind: MessageKind,
    publisher: Publisher<Ipc, [u8], u32>,
    subscriber: Subscriber<Ipc, [u8], u32>,
}

impl std::fmt::Debug for Iceoryx2Transport {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("Iceoryx2Transport")
            .field("fleet_id", &self.fleet_id)
            .field("robot_id", &self.robot_id)
            .field("open", &self.ports.is_some())
            .field("watch", &self.watch)
            .finish()
    }
}

impl Iceoryx2Transport {
    /// Creates this agent's nodes and opens (or creates) the fleet's services.
    pub fn open(
        fleet_id: &str,
        robot_id: u32,
        settings: &Iceoryx2Settings,
    ) -> Result<Self, TransportError> {
        super::settings::validate_fleet_id(fleet_id)?;
        let config = load_config(settings.config.as_deref())?;
        let dropped = Arc::new(AtomicU64::new(0));
        let node = create_node(
            &config,
            &format!("{}-ports", beacon_name(fleet_id, robot_id)),
        )?;
        let max_peers = settings.max_peers.max(1) as usize;
        let buffer = settings.buffer_per_peer.max(1);
        let stalled = Arc::new(Mutex::new(HashMap::new()));
        let mut kinds = Vec::with_capacity(MessageKind::ALL.len());
        for kind in MessageKind::ALL {
            let service = node
                .service_builder(&service_name(&format!(
                    "fleet/{fleet_id}/{}",
                    kind.as_str()
                ))?)
                .publish_subscribe::<[u8]>()
                .user_header::<u32>()
                .enable_safe_overflow(false)
                .subscriber_max_buffer_size(buffer)
                .subscriber_max_borrowed_samples(BORROWED)
                .history_size(0)
                .max_publishers(max_peers)
                .max_subscribers(max_peers)
                .max_nodes(max_peers)
                .open_or_create()
                .map_err(open_error)?;
            let subscriber = service
                .subscriber_builder()
                .buffer_size(buffer)
                .create()
                .map_err(open_error)?;
            let handler = backpressure_handler(
                subscriber.id().value(),
                Arc::clone(&stalled),
                Arc::clone(&dropped),
            );
            let pool = 2 * buffer + 16;
            let publisher = service
                .publisher_builder()
                .initial_max_slice_len(INITIAL_SLICE.min(settings.max_message_bytes.max(1)))
                .allocation_strategy(AllocationStrategy::PowerOfTwo)
                .backpressure_strategy(BackpressureStrategy::RetryUntilDelivered)
                .max_loaned_samples(LOANED)
                .override_sample_preallocation(move |worst_case| worst_case.min(pool))
                .set_backpressure_handler(handler)
                .create()
                .map_err(open_error)?;
            kinds.push(KindPorts {
                kind,
                publisher,
                subscriber,
            });
        }
        let events = node
            .service_builder(&service_name(&format!("fleet/{fleet_id}/wake"))?)
            .event()
            .max_notifiers(max_peers)
            .max_listeners(max_peers)
            .max_nodes(max_peers)
            .event_id_max_value(255)
            .disable_deadline()
            .disable_notifier_created_event()
            .disable_notifier_dropped_event()
            .disable_notifier_dead_event()
            .open_or_create()
            .map_err(open_error)?;
        let notifier = events.notifier_builder().create().map_err(open_error)?;
        let listener = events.listener_builder().create().map_err(open_error)?;
        let beacon = create_node(&config, &beacon_name(fleet_id, robot_id))?;
        Ok(Self {
            fleet_id: fleet_id.to_owned(),
            robot_id,
            max_message_bytes: settings.max_message_bytes,
            ports: Some(Ports {
                beacon,
                kinds,
                notifier,
                listener,
                _node: node,
            }),
            staged: VecDeque::new(),
            next_kind: 0,
            watch: NodeWatch::new(config, fleet_id, robot_id),
            dropped,
        })
    }

    /// Samples not delivered to a stalled subscriber, since opening.
    pub fn dropped(&self) -> u64 {
        self.dropped.load(Ordering::Relaxed)
    }

    fn ports(&self) -> Result<&Ports, TransportError> {
        self.ports
            .as_ref()
            .ok_or(TransportError::Closed { transport: NAME })
    }

    /// The next peer sample of any kind (kinds taken in turn), own samples skipped.
    fn take_next(&mut self) -> Result<Option<Received>, TransportError> {
        if let Some(message) = self.staged.pop_front() {
            return Ok(Some(message));
        }
        let ports = self.ports()?;
        let n = ports.kinds.len();
        for step in 0..n {
            let index = (self.next_kind + step) % n;
            let kind_ports = &ports.kinds[index];
            if let Some(message) = take_from(kind_ports, self.robot_id)? {
                self.next_kind = (index + 1) % n;
                return Ok(Some(message));
            }
        }
        Ok(None)
    }
}

impl Transport for Iceoryx2Transport {
    fn name(&self) -> &'static str {
        NAME
    }

    fn publish(&mut self, kind: MessageKind, bytes: &[u8]) -> Result<(), TransportError> {
        if bytes.len() > self.max_message_bytes {
            return Err(TransportError::TooLarge {
                len: bytes.len(),
                max: self.max_message_bytes,
            });
        }
        let robot_id = self.robot_id;
        let ports = self
            .ports
            .as_ref()
            .ok_or(TransportError::Closed { transport: NAME })?;
        let publish_error = |reason: String| TransportError::Publish {
            transport: NAME,
            kind,
            reason,
        };
        let Some(kind_ports) = ports.kinds.iter().find(|p| p.kind == kind) else {
            return Err(publish_error("no publisher for this kind".to_owned()));
        };
        // Empty this kind's own subscriber first: it also receives this agent's own
        // samples, which must not fill its buffer and pin the pool.
        while let Some(message) = take_from(kind_ports, robot_id)? {
            self.staged.push_back(message);
        }
        let mut sample = kind_ports
            .publisher
            .loan_slice_uninit(bytes.len())
            .map_err(|e| publish_error(format!("no shared memory for the sample: {e}")))?;
        *sample.user_header_mut() = robot_id;
        let sample = sample.write_from_slice(bytes);
        sample.send().map_err(|e| publish_error(format!("{e:?}")))?;
        ports
            .notifier
            .notify()
            .map_err(|e| publish_error(format!("waking the peers failed: {e:?}")))?;
        Ok(())
    }

    fn receive(&mut self, timeout: Duration) -> Result<Option<Received>, TransportError> {
        if self.ports.is_some() {
            self.watch.poll();
        }
        let deadline = Instant::now().checked_add(timeout);
        loop {
            if let Some(message) = self.take_next()? {
                return Ok(Some(message));
            }
            let remaining = deadline.map_or(Duration::MAX, |d| {
                d.saturating_duration_since(Instant::now())
            });
            if remaining.is_zero() {
                return Ok(None);
            }
            // Notifications that arrived since the last look are kept by the listener,
            // so none is lost between `take_next` and this wait.
            self.ports()?
                .listener
                .timed_wait(|_| {}, remaining)
                .map_err(|e| TransportError::Receive {
                    transport: NAME,
                    reason: format!("waiting for a notification failed: {e:?}"),
                })?;
        }
    }

    fn presence(&mut self) -> Vec<PresenceEvent> {
        if self.ports.is_some() {
            self.watch.poll();
        }
        self.watch.take_events()
    }

    fn close(&mut self, _timeout: Duration) -> Result<(), TransportError> {
        if let Some(ports) = self.ports.take() {
            let Ports {
                beacon,
                kinds,
                notifier,
                listener,
                _node,
            } = ports;
            drop(beacon);
            drop(kinds);
            drop(notifier);
            drop(listener);
            drop(_node);
        }
        self.staged.clear();
        Ok(())
    }
}

impl Drop for Iceoryx2Transport {
    fn drop(&mut self) {
        let _ = self.close(Duration::ZERO);
    }
}

/// One peer sample of this kind, own samples skipped.
fn take_from(ports: &KindPorts, own_robot: u32) -> Result<Option<Received>, TransportError> {
    loop {
        let sample = ports
            .subscriber
            .receive()
            .map_err(|e| TransportError::Receive {
                transport: NAME,
                reason: format!("{e:?}"),
            })?;
        let Some(sample) = sample else {
            return Ok(None);
        };
        let from_robot = *sample.user_header();
        if from_robot == own_robot {
            continue;
        }
        return Ok(Some(Received {
            from_robot,
            kind: ports.kind,
            bytes: sample.payload().to_vec(),
        }));
    }
}

/// Waits for a full subscriber up to [`BLOCK_TIMEOUT`], then drops for it (counted)
/// for [`STALL_HOLDOFF`]; never waits for this agent's own subscriber.
fn backpressure_handler(
    own_subscriber: u128,
    stalled: Arc<Mutex<HashMap<u128, Instant>>>,
    dropped: Arc<AtomicU64>,
) -> impl Fn(&BackpressureInfo) -> BackpressureAction + Send + 'static {
    move |info: &BackpressureInfo| {
        if info.receiver_port_id == own_subscriber {
            return BackpressureAction::DiscardData;
        }
        let mut stalled = match stalled.lock() {
            Ok(guard) => guard,
            Err(poisoned) => poisoned.into_inner(),
        };
        let now = Instant::now();
        match stalled.get(&info.receiver_port_id) {
            Some(since) if now.duration_since(*since) < STALL_HOLDOFF => {
                dropped.fetch_add(1, Ordering::Relaxed);
                BackpressureAction::DiscardData
            }
            _ if info.elapsed_time >= BLOCK_TIMEOUT => {
                stalled.insert(info.receiver_port_id, now);
                dropped.fetch_add(1, Ordering::Relaxed);
                tracing::warn!(
                    "iceoryx2: a subscriber kept its buffer full for {BLOCK_TIMEOUT:?}; dropping for it for {STALL_HOLDOFF:?}"
                );
                BackpressureAction::DiscardData
            }
            _ => {
                stalled.remove(&info.receiver_port_id);
                BackpressureAction::Retry
            }
        }
    }
}

fn create_node(config: &Config, name: &str) -> Result<Node<Ipc>, TransportError> {
    let name = NodeName::new(name).map_err(|e| TransportError::Open {
        transport: NAME,
        reason: format!("node name {name:?}: {e:?}"),
    })?;
    NodeBuilder::new()
        .name(&name)
        .config(config)
        // The agent handles its own signals; iceoryx2 must not take SIGINT/SIGTERM.
        .signal_handling_mode(SignalHandlingMode::Disabled)
        .create::<Ipc>()
        .map_err(open_error)
}

fn service_name(name: &str) -> Result<ServiceName, TransportError> {
    ServiceName::new(name).map_err(|e| TransportError::Open {
        transport: NAME,
        reason: format!("service name {name:?}: {e:?}"),
    })
}

/// iceoryx2's configuration: its defaults, the built-in file (`iceoryx2`) or a TOML
/// file.
pub fn load_config(name_or_path: Option<&str>) -> Result<Config, TransportError> {
    let text = match name_or_path {
        None => return Ok(Config::default()),
        Some("iceoryx2") => ICEORYX2_BUILTIN_CONFIG.to_owned(),
        Some(path) => std::fs::read_to_string(path).map_err(|e| TransportError::Config {
            path: path.to_owned(),
            reason: format!("not the built-in name \"iceoryx2\" and not a readable file: {e}"),
        })?,
    };
    toml::from_str(&text).map_err(|e| TransportError::Config {
        path: name_or_path.unwrap_or_default().to_owned(),
        reason: e.to_string(),
    })
}

fn open_error(e: impl std::fmt::Debug) -> TransportError {
    TransportError::Open {
        transport: NAME,
        reason: format!("{e:?}"),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_builtin_config_loads() -> Result<(), TransportError> {
        let config = load_config(Some("iceoryx2"))?;
        assert!(config.global.node.cleanup_dead_nodes_on_creation);
        Ok(())
    }

    #[test]
    fn a_missing_config_file_is_a_config_error() {
        assert!(matches!(
            load_config(Some("/nonexistent/iceoryx2.toml")),
            Err(TransportError::Config { .. })
        ));
    }
}
