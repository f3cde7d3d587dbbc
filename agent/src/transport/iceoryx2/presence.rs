//! Which robots of the fleet are on this machine: iceoryx2's node list, read at most
//! every [`PRESENCE_POLL`]. An agent's presence node is named by [`beacon_name`]; a
//! node that is gone or dead is a robot that vanished, and a dead node's resources
//! (shared memory, its ports in the services) are removed when it is found.

use super::Ipc;
use crate::transport::PresenceEvent;
use iceoryx2::node::{NodeDetails, NodeView};
use iceoryx2::prelude::*;
use std::collections::BTreeSet;
use std::time::{Duration, Instant};

/// The node list is read at most this often.
pub const PRESENCE_POLL: Duration = Duration::from_millis(100);

/// The name of the node that announces `robot_id` of `fleet_id`.
pub(super) fn beacon_name(fleet_id: &str, robot_id: u32) -> String {
    format!("fleet-{fleet_id}-robot-{robot_id}")
}

/// Watches the node list for one fleet, from one robot's point of view.
#[derive(Debug)]
pub(super) struct NodeWatch {
    config: Config,
    /// `fleet-<fleet-id>-robot-`: a beacon is this and the robot id's digits.
    prefix: String,
    own_robot: u32,
    peers: BTreeSet<u32>,
    events: Vec<PresenceEvent>,
    last_poll: Option<Instant>,
}

impl NodeWatch {
    pub(super) fn new(config: Config, fleet_id: &str, own_robot: u32) -> Self {
        Self {
            config,
            prefix: format!("fleet-{fleet_id}-robot-"),
            own_robot,
            peers: BTreeSet::new(),
            events: Vec::new(),
            last_poll: None,
        }
    }

    /// Events since the last call, appeared and vanished robots in id order per poll.
    pub(super) fn take_events(&mut self) -> Vec<PresenceEvent> {
        std::mem::take(&mut self.events)
    }

    /// Reads the node list unless the last read is younger than [`PRESENCE_POLL`].
    pub(super) fn poll(&mut self) {
        if self.last_poll.is_some_and(|t| t.elapsed() < PRESENCE_POLL) {
            return;
        }
        self.last_poll = Some(Instant::now());
        let mut alive = BTreeSet::new();
        let listed = Node::<Ipc>::list(&self.config, |state| {
            match state {
                NodeState::Alive(view) => {
                    if let Some(robot) = self.robot_of(view.details()) {
                        alive.insert(robot);
                    }
                }
                NodeState::Dead(view) => {
                    if let Err(e) = view.try_remove_stale_resources() {
                        tracing::debug!("iceoryx2: dead node not cleaned up yet: {e:?}");
                    }
                }
                NodeState::Inaccessible(_) | NodeState::Undefined(_) => {}
            }
            CallbackProgression::Continue
        });
        if let Err(e) = listed {
            tracing::warn!("iceoryx2: cannot list nodes: {e:?}");
            return;
        }
        alive.remove(&self.own_robot);
        for gone in self.peers.difference(&alive) {
            self.events.push(PresenceEvent::Vanished(*gone));
        }
        for new in alive.difference(&self.peers) {
            self.events.push(PresenceEvent::Appeared(*new));
        }
        self.peers = alive;
    }

    /// The robot a node announces, if it is a beacon of this fleet.
    fn robot_of(&self, details: &Option<NodeDetails>) -> Option<u32> {
        let rest = details
            .as_ref()?
            .name()
            .as_str()
            .strip_prefix(self.prefix.as_str())?;
        if rest.is_empty() || !rest.bytes().all(|b| b.is_ascii_digit()) {
            return None;
        }
        rest.parse().ok()
    }
}
