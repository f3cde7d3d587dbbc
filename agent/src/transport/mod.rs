//! Publish/subscribe between agents behind one trait, with three implementations:
//! Zenoh (peer mode, no router), iceoryx2 (same-host shared memory) and in-process
//! (deterministic, for tests and lockstep simulation).
//!
//! A transport moves opaque byte payloads tagged with the sender's robot id and a
//! [`MessageKind`]; encoding, fleet-id checks and statistics live above it.
//!
//! * [`settings`]: what the agent's configuration says, and [`open`] to build a transport
//!   from it.
//! * [`inproc`]: [`InprocHub`], one process, deterministic.
//! * [`zenoh`]: [`ZenohTransport`], peers over TCP (loopback, LAN, across machines).
//! * [`iceoryx2`]: [`Iceoryx2Transport`], processes of one machine over shared memory.
//! * [`faults`]: [`FaultyTransport`], seeded loss and added delay for fault tests.

pub mod faults;
pub mod fleet_certs;
pub mod iceoryx2;
pub mod inproc;
pub mod own_certificates;
pub mod settings;
pub mod zenoh;
pub mod zenoh_acl;

pub use faults::{FaultSettings, FaultyTransport};
pub use iceoryx2::Iceoryx2Transport;
pub use inproc::{InprocHub, InprocTransport};
pub use settings::{
    open, Iceoryx2Settings, TransportKind, TransportSettings, ZenohSettings, ZENOH_BUILTIN_CONFIGS,
};
pub use zenoh::ZenohTransport;

use common::messages::MessageKind;
use std::time::Duration;
use thiserror::Error;

/// A payload received from a peer.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct Received {
    /// The sender's robot id, as the transport's addressing says (key expression,
    /// service header), not as the payload claims.
    pub from_robot: u32,
    /// What the payload is.
    pub kind: MessageKind,
    /// The encoded message.
    pub bytes: Vec<u8>,
}

/// A peer appearing or disappearing (liveliness / node monitoring).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum PresenceEvent {
    /// The peer is alive (first seen, or back after vanishing).
    Appeared(u32),
    /// The peer died, froze past its lease, or closed.
    Vanished(u32),
}

/// Why a transport operation failed.
#[derive(Debug, Error)]
pub enum TransportError {
    /// Opening the session, node or service failed.
    #[error("cannot open {transport} transport: {reason}")]
    Open {
        /// Which transport.
        transport: &'static str,
        /// What went wrong.
        reason: String,
    },
    /// A configuration file is missing or invalid.
    #[error("transport configuration {path}: {reason}")]
    Config {
        /// The file or name asked for.
        path: String,
        /// What went wrong.
        reason: String,
    },
    /// Publishing failed.
    #[error("{transport}: publishing {kind:?} failed: {reason}")]
    Publish {
        /// Which transport.
        transport: &'static str,
        /// What was being published.
        kind: MessageKind,
        /// What went wrong.
        reason: String,
    },
    /// Receiving failed.
    #[error("{transport}: receiving failed: {reason}")]
    Receive {
        /// Which transport.
        transport: &'static str,
        /// What went wrong.
        reason: String,
    },
    /// Leaving the fleet failed or did not finish in time.
    #[error("{transport}: closing failed: {reason}")]
    Close {
        /// Which transport.
        transport: &'static str,
        /// What went wrong.
        reason: String,
    },
    /// The transport was closed before this call.
    #[error("{transport}: already closed")]
    Closed {
        /// Which transport.
        transport: &'static str,
    },
    /// The payload is larger than the transport accepts.
    #[error("payload of {len} bytes exceeds the limit of {max} bytes")]
    TooLarge {
        /// Payload size.
        len: usize,
        /// The limit.
        max: usize,
    },
}

/// One agent's connection to its fleet.
///
/// Implementations never deliver an agent's own messages back to it, never panic
/// on what peers send, and keep working with no peer at all.
pub trait Transport: Send {
    /// `"zenoh"`, `"iceoryx2"` or `"inproc"`.
    fn name(&self) -> &'static str;
    /// Sends `bytes` to every peer of the fleet under `kind`. Reliable while the
    /// peers keep up (blocking congestion control, no silent drop).
    fn publish(&mut self, kind: MessageKind, bytes: &[u8]) -> Result<(), TransportError>;
    /// The next payload from a peer, waiting at most `timeout`; `Ok(None)` when
    /// nothing arrived in time. `Duration::ZERO` polls.
    fn receive(&mut self, timeout: Duration) -> Result<Option<Received>, TransportError>;
    /// Peer presence changes since the last call, in the order observed.
    fn presence(&mut self) -> Vec<PresenceEvent>;
    /// Leaves the fleet (peers see this agent vanish); waits at most `timeout`.
    fn close(&mut self, timeout: Duration) -> Result<(), TransportError>;
}

/// A boxed transport (what [`open`] returns) is a transport, so wrappers such as
/// [`FaultyTransport`] take it as well as a concrete one.
impl<T: Transport + ?Sized> Transport for Box<T> {
    fn name(&self) -> &'static str {
        (**self).name()
    }
    fn publish(&mut self, kind: MessageKind, bytes: &[u8]) -> Result<(), TransportError> {
        (**self).publish(kind, bytes)
    }
    fn receive(&mut self, timeout: Duration) -> Result<Option<Received>, TransportError> {
        (**self).receive(timeout)
    }
    fn presence(&mut self) -> Vec<PresenceEvent> {
        (**self).presence()
    }
    fn close(&mut self, timeout: Duration) -> Result<(), TransportError> {
        (**self).close(timeout)
    }
}
