//! Fault injection for tests: seeded message loss and a fixed added delay on the
//! receiving side of any transport (this kernel has no `tc netem`).
//!
//! Loss is drawn per received message, so each receiver loses independently, as on
//! a lossy link. The delay holds every message until `delay` after the wrapper first
//! saw it, keeping the order and the throughput (a pipe of fixed latency, not a
//! pause per message).

use super::{PresenceEvent, Received, Transport, TransportError};
use common::messages::MessageKind;
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use std::collections::VecDeque;
use std::time::{Duration, Instant};

/// What to inject.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct FaultSettings {
    /// Probability in `[0, 1]` that a received message is dropped.
    pub loss_probability: f64,
    /// Latency added to every received message.
    pub receive_delay: Duration,
    /// Seed of the loss draws: the same seed and the same arrivals drop the same
    /// messages.
    pub seed: u64,
}

/// A transport with faults injected on receive.
#[derive(Debug)]
pub struct FaultyTransport<T: Transport> {
    inner: T,
    settings: FaultSettings,
    rng: ChaCha8Rng,
    /// Messages that survived the loss draw, with the instant they become due.
    delayed: VecDeque<(Instant, Received)>,
    dropped: u64,
}

impl<T: Transport> FaultyTransport<T> {
    /// Wraps `inner`. The loss probability is clamped to `[0, 1]` (NaN means none).
    pub fn new(inner: T, settings: FaultSettings) -> Self {
        let loss_probability = if settings.loss_probability.is_nan() {
            0.0
        } else {
            settings.loss_probability.clamp(0.0, 1.0)
        };
        Self {
            inner,
            settings: FaultSettings {
                loss_probability,
                ..settings
            },
            rng: ChaCha8Rng::seed_from_u64(settings.seed),
            delayed: VecDeque::new(),
            dropped: 0,
        }
    }

    /// Messages dropped so far.
    pub fn dropped(&self) -> u64 {
        self.dropped
    }

    /// The wrapped transport.
    pub fn inner(&self) -> &T {
        &self.inner
    }

    /// Unwraps the transport; messages still delayed are lost.
    pub fn into_inner(self) -> T {
        self.inner
    }

    /// Passes a message from the inner transport through the loss draw.
    fn admit(&mut self, message: Received) {
        if self.settings.loss_probability > 0.0
            && self.rng.random_bool(self.settings.loss_probability)
        {
            self.dropped += 1;
            return;
        }
        let due = Instant::now() + self.settings.receive_delay;
        self.delayed.push_back((due, message));
    }

    /// Moves everything the inner transport already has into the delay line.
    fn drain_inner(&mut self) -> Result<(), TransportError> {
        while let Some(message) = self.inner.receive(Duration::ZERO)? {
            self.admit(message);
        }
        Ok(())
    }
}

impl<T: Transport> Transport for FaultyTransport<T> {
    fn name(&self) -> &'static str {
        self.inner.name()
    }

    fn publish(&mut self, kind: MessageKind, bytes: &[u8]) -> Result<(), TransportError> {
        self.inner.publish(kind, bytes)
    }

    fn receive(&mut self, timeout: Duration) -> Result<Option<Received>, TransportError> {
        let deadline = Instant::now().checked_add(timeout);
        loop {
            self.drain_inner()?;
            let now = Instant::now();
            if let Some((due, _)) = self.delayed.front() {
                if *due <= now {
                    return Ok(self.delayed.pop_front().map(|(_, message)| message));
                }
            }
            // Wait for the head to become due, a new message, or the deadline.
            let until_deadline =
                deadline.map_or(Duration::MAX, |d| d.saturating_duration_since(now));
            if until_deadline.is_zero() {
                return Ok(None);
            }
            let wait = match self.delayed.front() {
                Some((due, _)) => until_deadline.min(due.saturating_duration_since(now)),
                None => until_deadline,
            };
            if let Some(message) = self.inner.receive(wait)? {
                self.admit(message);
            }
        }
    }

    fn presence(&mut self) -> Vec<PresenceEvent> {
        self.inner.presence()
    }

    fn close(&mut self, timeout: Duration) -> Result<(), TransportError> {
        self.delayed.clear();
        self.inner.close(timeout)
    }
}

#[cfg(test)]
mod tests {
    use super::super::InprocHub;
    use super::*;

    fn pair(
        settings: FaultSettings,
    ) -> Result<(impl Transport, FaultyTransport<impl Transport>), TransportError> {
        let hub = InprocHub::new();
        let sender = hub.endpoint("f", 1)?;
        let receiver = FaultyTransport::new(hub.endpoint("f", 2)?, settings);
        Ok((sender, receiver))
    }

    fn receive_all(t: &mut impl Transport) -> Result<Vec<u8>, TransportError> {
        let mut got = Vec::new();
        while let Some(m) = t.receive(Duration::from_millis(50))? {
            got.push(m.bytes[0]);
        }
        Ok(got)
    }

    #[test]
    fn losses_are_seeded_and_near_the_probability() -> Result<(), TransportError> {
        let settings = FaultSettings {
            loss_probability: 0.3,
            receive_delay: Duration::ZERO,
            seed: 7,
        };
        let mut runs = Vec::new();
        for _ in 0..2 {
            let (mut tx, mut rx) = pair(settings)?;
            for i in 0..200u8 {
                tx.publish(MessageKind::Tracks, &[i])?;
            }
            let got = receive_all(&mut rx)?;
            assert_eq!(got.len() as u64 + rx.dropped(), 200);
            assert!(
                (40..=80).contains(&rx.dropped()),
                "dropped {}",
                rx.dropped()
            );
            assert!(got.windows(2).all(|w| w[0] < w[1]), "order kept");
            runs.push(got);
        }
        assert_eq!(runs[0], runs[1], "same seed, same losses");
        Ok(())
    }

    #[test]
    fn delay_holds_messages_back_but_keeps_them() -> Result<(), TransportError> {
        let delay = Duration::from_millis(60);
        let (mut tx, mut rx) = pair(FaultSettings {
            loss_probability: 0.0,
            receive_delay: delay,
            seed: 0,
        })?;
        tx.publish(MessageKind::Heartbeat, &[1])?;
        assert!(rx.receive(Duration::ZERO)?.is_none(), "not due yet");
        let got = rx.receive(Duration::from_secs(2))?;
        assert_eq!(got.map(|m| m.bytes), Some(vec![1]));
        assert_eq!(rx.dropped(), 0);
        Ok(())
    }
}
