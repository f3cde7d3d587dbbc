//! The in-process transport: every endpoint of one [`InprocHub`] lives in the same
//! process, for tests and lockstep simulation.
//!
//! Deterministic: a publish appends to each receiver's FIFO under one lock, so every
//! receiver sees the publishes in the order they were made, and presence events come
//! in the order of joins and closes (existing members by robot id on join). The hub
//! is partitioned by fleet id; nothing is delivered back to its sender; queues are
//! unbounded (nothing is ever dropped).

use super::{PresenceEvent, Received, Transport, TransportError};
use common::messages::MessageKind;
use std::collections::{BTreeMap, VecDeque};
use std::sync::{Arc, Condvar, Mutex, MutexGuard};
use std::time::{Duration, Instant};

const NAME: &str = "inproc";

/// The meeting point of in-process endpoints. Cheap to clone: clones share the hub.
#[derive(Clone, Debug, Default)]
pub struct InprocHub {
    state: Arc<Mutex<HubState>>,
}

#[derive(Debug, Default)]
struct HubState {
    next_endpoint: u64,
    /// Open endpoints by their hub-wide id (join order).
    endpoints: BTreeMap<u64, Member>,
}

#[derive(Debug)]
struct Member {
    fleet_id: String,
    robot_id: u32,
    queue: VecDeque<Received>,
    presence: Vec<PresenceEvent>,
    /// Signalled when `queue` grows; waited on with the hub's lock.
    arrived: Arc<Condvar>,
}

impl InprocHub {
    /// A new, empty hub.
    pub fn new() -> Self {
        Self::default()
    }

    /// Joins `fleet_id` as `robot_id`. The new endpoint sees the fleet's present
    /// members appear (by robot id) and they see it appear. Fails if that robot id is
    /// already present in the fleet.
    pub fn endpoint(
        &self,
        fleet_id: &str,
        robot_id: u32,
    ) -> Result<InprocTransport, TransportError> {
        let mut state = lock(&self.state);
        let mut present: Vec<u32> = state
            .endpoints
            .values()
            .filter(|m| m.fleet_id == fleet_id)
            .map(|m| m.robot_id)
            .collect();
        if present.contains(&robot_id) {
            return Err(TransportError::Open {
                transport: NAME,
                reason: format!("robot {robot_id} is already in fleet {fleet_id:?} on this hub"),
            });
        }
        for member in state.endpoints.values_mut() {
            if member.fleet_id == fleet_id {
                member.presence.push(PresenceEvent::Appeared(robot_id));
            }
        }
        present.sort_unstable();
        let id = state.next_endpoint;
        state.next_endpoint += 1;
        let arrived = Arc::new(Condvar::new());
        state.endpoints.insert(
            id,
            Member {
                fleet_id: fleet_id.to_owned(),
                robot_id,
                queue: VecDeque::new(),
                presence: present.into_iter().map(PresenceEvent::Appeared).collect(),
                arrived: Arc::clone(&arrived),
            },
        );
        Ok(InprocTransport {
            hub: self.clone(),
            id,
            robot_id,
            arrived,
            closed: false,
        })
    }
}

/// One endpoint of an [`InprocHub`]. Closes itself when dropped.
#[derive(Debug)]
pub struct InprocTransport {
    hub: InprocHub,
    id: u64,
    robot_id: u32,
    arrived: Arc<Condvar>,
    closed: bool,
}

impl InprocTransport {
    /// This endpoint's robot id.
    pub fn robot_id(&self) -> u32 {
        self.robot_id
    }

    fn check_open(&self) -> Result<(), TransportError> {
        if self.closed {
            return Err(TransportError::Closed { transport: NAME });
        }
        Ok(())
    }
}

impl Transport for InprocTransport {
    fn name(&self) -> &'static str {
        NAME
    }

    fn publish(&mut self, kind: MessageKind, bytes: &[u8]) -> Result<(), TransportError> {
        self.check_open()?;
        let mut state = lock(&self.hub.state);
        let Some(fleet_id) = state.endpoints.get(&self.id).map(|m| m.fleet_id.clone()) else {
            return Err(TransportError::Closed { transport: NAME });
        };
        for (id, member) in state.endpoints.iter_mut() {
            if *id == self.id || member.fleet_id != fleet_id {
                continue;
            }
            member.queue.push_back(Received {
                from_robot: self.robot_id,
                kind,
                bytes: bytes.to_vec(),
            });
            member.arrived.notify_all();
        }
        Ok(())
    }

    fn receive(&mut self, timeout: Duration) -> Result<Option<Received>, TransportError> {
        self.check_open()?;
        let deadline = Instant::now().checked_add(timeout);
        let mut state = lock(&self.hub.state);
        loop {
            let Some(member) = state.endpoints.get_mut(&self.id) else {
                return Err(TransportError::Closed { transport: NAME });
            };
            if let Some(message) = member.queue.pop_front() {
                return Ok(Some(message));
            }
            let remaining = match deadline {
                Some(deadline) => deadline.saturating_duration_since(Instant::now()),
                None => Duration::MAX,
            };
            if remaining.is_zero() {
                return Ok(None);
            }
            state = match self.arrived.wait_timeout(state, remaining) {
                Ok((guard, _)) => guard,
                Err(poisoned) => poisoned.into_inner().0,
            };
        }
    }

    fn presence(&mut self) -> Vec<PresenceEvent> {
        let mut state = lock(&self.hub.state);
        state
            .endpoints
            .get_mut(&self.id)
            .map(|m| std::mem::take(&mut m.presence))
            .unwrap_or_default()
    }

    fn close(&mut self, _timeout: Duration) -> Result<(), TransportError> {
        if self.closed {
            return Ok(());
        }
        self.closed = true;
        let mut state = lock(&self.hub.state);
        if let Some(me) = state.endpoints.remove(&self.id) {
            for member in state.endpoints.values_mut() {
                if member.fleet_id == me.fleet_id {
                    member.presence.push(PresenceEvent::Vanished(me.robot_id));
                }
            }
        }
        Ok(())
    }
}

impl Drop for InprocTransport {
    fn drop(&mut self) {
        let _ = self.close(Duration::ZERO);
    }
}

/// The hub's lock; a panic while holding it leaves consistent queues, so poisoning is
/// ignored.
fn lock(state: &Mutex<HubState>) -> MutexGuard<'_, HubState> {
    match state.lock() {
        Ok(guard) => guard,
        Err(poisoned) => poisoned.into_inner(),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_robot_id_joins_a_fleet_once() -> Result<(), TransportError> {
        let hub = InprocHub::new();
        let _first = hub.endpoint("f", 1)?;
        assert!(hub.endpoint("f", 1).is_err());
        let _other_fleet = hub.endpoint("g", 1)?;
        Ok(())
    }

    #[test]
    fn a_closed_robot_id_can_join_again() -> Result<(), TransportError> {
        let hub = InprocHub::new();
        let mut first = hub.endpoint("f", 1)?;
        first.close(Duration::ZERO)?;
        let _again = hub.endpoint("f", 1)?;
        Ok(())
    }

    #[test]
    fn operations_after_close_are_errors() -> Result<(), TransportError> {
        let hub = InprocHub::new();
        let mut t = hub.endpoint("f", 1)?;
        t.close(Duration::ZERO)?;
        assert!(matches!(
            t.publish(MessageKind::Tracks, b"x"),
            Err(TransportError::Closed { .. })
        ));
        assert!(matches!(
            t.receive(Duration::ZERO),
            Err(TransportError::Closed { .. })
        ));
        assert!(t.close(Duration::ZERO).is_ok());
        Ok(())
    }
}
